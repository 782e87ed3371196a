"""Rungs 2 and 3 for the LSTM actor: the rendered LSTM program (host build and AVR in simavr) equals the emulator."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from tests.avr_tools import require_avr
from export.codegen.budget import estimate
from export.codegen.render import POLICY_FILE, render_firmware
from export.quantize import calibrate
from export.verify import avr
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host, verify_host
from kiloforge.actors.base import HiddenArch
from kiloforge.actors.lstm import CELL_EXP, LSTM, quantize_lstm, random_lstm_policy
from sim.config import preset

needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def qlstm(world, hidden: int, seed: int, scale: float = 2.0, out_scale: float = 1.0, **quant):
    """A quantised random LSTM calibrated on short rollouts of itself (``quant``: quantize_lstm options)."""
    p = random_lstm_policy(world, hidden, seed=seed, scale=scale, out_scale=out_scale)
    return quantize_lstm(p, calibrate(p, episodes=1, n_robots=(4,), seed=seed, steps=min(40, world.episode_steps)),
                         **quant)


#: large weights and narrow ranges (headroom < 1) so that every saturation is reached, and a small case
CASES = [("kilobot-h24", preset("kilobot"), 24, {"scale": 6.0, "out_scale": 4.0, "headroom": 0.6}),
         ("thesis-h8-table3", preset("thesis", period_ticks=4, neighbour_table_size=3), 8,
          {"scale": 3.0, "out_scale": 4.0, "headroom": 0.5})]


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    return tmp_path_factory.mktemp("lstm_host")


def _paths_hit(qp, obs: np.ndarray, commands: np.ndarray) -> dict[str, bool]:
    """Replay the cell over recorded observations and commands: which saturations and extremes occurred."""
    R, S, _ = obs.shape
    H = qp.hidden_size
    s, q_prev = qp.initial_state(R), np.zeros((R, 2), np.int64)
    lo: dict[str, int] = {}
    hi: dict[str, int] = {}
    for t in range(S):
        x = np.concatenate([qp.action_table.astype(np.int64)[q_prev], obs[:, t].astype(np.int64)], 1)
        g = qp.cell.gates(x, s[:, :H], s[:, H:])
        for k in ("a_i", "a_f", "a_g", "a_o", "p", "f", "c", "h"):
            lo[k], hi[k] = min(lo.get(k, 1 << 30), int(g[k].min())), max(hi.get(k, -(1 << 30)), int(g[k].max()))
        s, q_prev = np.concatenate([g["h"], g["c"]], 1), commands[:, t].astype(np.int64)
    return {**{f"{k} saturates": lo[k] == -128 and hi[k] == 127 for k in ("a_i", "a_f", "a_g", "a_o", "p")},
            "forget gate near 0 and 1": lo["f"] < 16 and hi["f"] > 240,
            "cell state beyond +-4": lo["c"] < -(4 << CELL_EXP) and hi["c"] > 4 << CELL_EXP,
            "hidden state spans int8": lo["h"] < -64 and hi["h"] > 64,
            "commands 0 and 255": int(commands.min()) == 0 and int(commands.max()) == 255}


def _bit_exact(builds, specs, fill: str = "random:1") -> int:
    """Host build == emulator over each (case, stream spec); every path exercised; the control steps compared."""
    total, hit_any = 0, {}
    for i, ((name, world, hidden, opts), spec) in enumerate(zip(CASES, specs)):
        qp = qlstm(world, hidden, seed=10 + i, **opts)
        exe = build_host(render_firmware(qp, generator_version="test")[POLICY_FILE], builds, name=f"lstm{i}")
        rng = np.random.default_rng(np.random.SeedSequence(20 + i))
        inputs = random_inputs(rng, world.period_ticks, (world.emitter_uid,), spec,
                               comm_radius_mm=world.comm_radius_mm, light_threshold=world.light_threshold)
        emu = FirmwareEmulator(qp, inputs.uids, inputs.calib)
        want = emu.run(inputs)
        got = run_host(exe, inputs, world.period_ticks, world.obs_dim, fill=fill)
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=f"{name}: {compare(want, got)}")
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=f"{name}: {compare(want, got)}")
        searchers = ~emu.is_emitter
        hit = _paths_hit(qp, want.obs[searchers], want.commands[searchers])
        hit_any = {k: hit_any.get(k, False) or v for k, v in hit.items()}
        total += int(searchers.sum()) * want.steps.shape[1]
    assert all(hit_any.values()), f"never exercised: {[k for k, v in hit_any.items() if not v]}"
    return total


@needs_cc
def test_random_streams_bit_exact(builds):
    """Over 12,000 searcher control steps of random streams (garbage state before setup()): host build == emulator."""
    total = _bit_exact(builds, [StreamSpec(n_robots=64, n_steps=120, rate=0.9),
                                StreamSpec(n_robots=64, n_steps=90, rate=0.6, n_senders=8)])
    assert total >= 12_000, f"only {total} control steps compared"


@pytest.mark.slow
@needs_cc
def test_random_streams_bit_exact_100k(builds):
    """Over 100,000 searcher control steps: host build == emulator (the long run of the CI-sized test above)."""
    total = _bit_exact(builds, [StreamSpec(n_robots=256, n_steps=260, rate=0.9),
                                StreamSpec(n_robots=256, n_steps=200, rate=0.6, n_senders=8)], fill="0x5A")
    assert total >= 100_000, f"only {total} control steps compared"


@needs_cc
def test_a_different_cell_is_detected(builds):
    """The comparison is sensitive: one changed recurrent weight, or a state reset every step, disagrees."""
    world = CASES[0][1]
    qp = qlstm(world, 16, seed=3)
    exe = build_host(render_firmware(qp, generator_version="t")[POLICY_FILE], builds, name="sens")
    rng = np.random.default_rng(np.random.SeedSequence(30))
    inputs = random_inputs(rng, world.period_ticks, (0,), StreamSpec(n_robots=24, n_steps=40, rate=0.9))
    got = run_host(exe, inputs, world.period_ticks, world.obs_dim)
    assert compare(FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs), got) == ""
    w = qp.cell.f.w.copy()
    w[3, -2] = w[3, -2] + 1 if w[3, -2] < 127 else 126  # a weight on the hidden state
    other = replace(qp, cell=replace(qp.cell, f=replace(qp.cell.f, w=w)))
    assert compare(FirmwareEmulator(other, inputs.uids, inputs.calib).run(inputs), got) != ""

    class Forgetful(FirmwareEmulator):
        def control_step(self, light):
            self.state = np.concatenate([self.state[:, :qp.hidden_size], 0 * self.state[:, qp.hidden_size:]], 1)
            return super().control_step(light)  # forgets only the cell state

    assert compare(Forgetful(qp, inputs.uids, inputs.calib).run(inputs), got) != ""


@needs_cc
def test_verify_host_and_beacon_program():
    """verify_host (the CLI's --verify host) passes for an LSTM program and its beacon-only program."""
    qp = qlstm(preset("kilobot"), 6, seed=2)
    result = verify_host(qp, render_firmware(qp, emitter_uids=(0, 9), msg_type=0x11, generator_version="t"),
                         spec=StreamSpec(n_robots=16, n_steps=12))
    assert result.ok and result.control_steps > 0, str(result)


def _simavr(n_robots: int, n_steps: int):
    require_avr(simulate=True)
    world = preset("kilobot", period_ticks=6, neighbour_table_size=4)
    qp = qlstm(world, 32, seed=11, scale=3.0)
    files = render_firmware(qp)
    return world, qp, files, avr.verify_simavr(qp, files, n_robots=n_robots, n_steps=n_steps, seed=4)


@pytest.mark.avr
def test_lstm_is_bit_exact_in_simavr_and_fits():
    """The AVR build of the LSTM program in simavr equals the emulator; cycles per step and the exact budget fit."""
    world, qp, files, check = _simavr(12, 25)
    assert check.ok, str(check)
    assert check.control_steps >= 200 and check.cycles_step.size > 0
    assert check.cycles_step_max < 8_000_000 * 0.05, str(check)  # far below one control period (~1 s)
    b = estimate(LSTM, world, HiddenArch(32)).with_exact(avr.exact_budget(files))
    assert b.ok and b.exact["flash"] < 28_160, b.table()


@pytest.mark.slow
@pytest.mark.avr
def test_lstm_is_bit_exact_in_simavr_2k_steps():
    """Over at least 2,000 control steps the LSTM program in simavr equals the emulator byte for byte."""
    _, _, _, check = _simavr(64, 40)
    assert check.ok, str(check)
    assert check.control_steps >= 2_000, str(check)
