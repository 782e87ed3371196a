"""Rungs 2 and 3 for the recurrent policy: the rendered GRU program (host build and AVR in simavr) equals the emulator."""
from __future__ import annotations

import dataclasses
from dataclasses import replace

import numpy as np
import pytest

from tests.avr_tools import require_avr
from export.codegen.budget import estimate
from export.codegen.render import POLICY_FILE, render_firmware
from export.contract import firmware as fwspec
from export.quantize import calibrate
from export.verify import avr
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host, verify_host
from kiloforge import numfmt
from kiloforge.actors.base import HiddenArch
from kiloforge.actors.gru import GRU, quantize_gru, random_gru_policy
from tests.recorded_loop import record_loop
from sim.config import preset

needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def qgru(world, hidden: int, seed: int, scale: float = 2.0, out_scale: float = 1.0, nx_shift: int | None = None,
         **quant):
    """A quantised random GRU calibrated on short rollouts of itself (``quant``: quantize_gru options;
    ``nx_shift`` forces the candidate's input shift, moving the tanh table to a finer exponent)."""
    p = random_gru_policy(world, hidden, seed=seed, scale=scale, out_scale=out_scale)
    cal = calibrate(p, episodes=1, n_robots=(4,), seed=seed, steps=min(40, world.episode_steps))
    qp = quantize_gru(p, cal, **quant)
    if nx_shift is not None:
        c = qp.cell
        e_n = c.nx.e_out + nx_shift
        qp = replace(qp, cell=replace(c, nx_shift=nx_shift, rn_shift=numfmt.GATE_EXP + c.nh.e_out - e_n,
                                      n_table=numfmt.act_table("tanh", e_n, numfmt.HIDDEN_EXP)))
    return qp


CASES = [  # (name, world, hidden, stream, qgru options): large weights and narrow ranges so that every
    # saturation is reached (case 0: gate exponents capped at 4, the tables' saturating range), and
    # finer exponents (case 1)
    ("kilobot-h32", preset("kilobot"), 32, StreamSpec(n_robots=96, n_steps=170, rate=0.9),
     {"scale": 6.0, "out_scale": 4.0, "headroom": 0.7, "gate_exp_max": 4}),
    ("thesis-h8-table3", preset("thesis", period_ticks=4, neighbour_table_size=3), 8,
     StreamSpec(n_robots=128, n_steps=90, rate=0.6, n_senders=8),
     {"scale": 3.0, "out_scale": 4.0, "headroom": 0.5, "nx_shift": 1}),
]


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    return tmp_path_factory.mktemp("gru_host")


def test_render_is_deterministic_and_keeps_the_state_in_sram():
    """The GRU program renders the same text twice, holds x and h instead of a history, and names its exponents."""
    qp = qgru(preset("kilobot"), 16, seed=1)
    a = render_firmware(qp, generator_version="t")[POLICY_FILE]
    assert a == render_firmware(qp, generator_version="t")[POLICY_FILE]
    assert "int8_t h[KF_HIDDEN];" in a and "s->hist" not in a and "#define KF_HIDDEN 16u" in a
    assert f"#define KF_RN_SHIFT {qp.cell.rn_shift}u" in a and "kf_gru_update(" in a
    assert "GRU: input 16" in a and f"e_r {qp.cell.r.e_out}" in a
    for name in ("KF_LR", "KF_LZ", "KF_LNX", "KF_LNH", "KF_LOUT", "KF_GATE_R", "KF_GATE_K", "KF_TANH"):
        assert name in a, name


def _paths_hit(qp, obs: np.ndarray, commands: np.ndarray) -> dict[str, bool]:
    """Replay the cell over the recorded observations and commands: which saturations and extremes occurred."""
    R, S, _ = obs.shape
    h, q_prev = qp.initial_state(R), np.zeros((R, 2), np.int64)
    seen: dict[str, list] = {}
    for t in range(S):
        x = np.concatenate([qp.action_table.astype(np.int64)[q_prev], obs[:, t].astype(np.int64)], 1)
        g = qp.cell.gates(x, h)
        for k in ("a_r", "a_z", "nx", "nh", "pre_n", "k", "h"):
            seen.setdefault(k, []).append((int(g[k].min()), int(g[k].max())))
        h, q_prev = g["h"], commands[:, t].astype(np.int64)
    lo = {k: min(a for a, _ in v) for k, v in seen.items()}
    hi = {k: max(b for _, b in v) for k, v in seen.items()}
    return {"a_r saturates": lo["a_r"] == -128 and hi["a_r"] == 127, "a_z saturates": lo["a_z"] == -128 and hi["a_z"] == 127,
            "candidate saturates": lo["pre_n"] == -128 and hi["pre_n"] == 127,
            "keep gate 0 and 255": lo["k"] == 0 and hi["k"] == 255, "state spans int8": lo["h"] < -64 and hi["h"] > 64,
            "commands 0 and 255": int(commands.min()) == 0 and int(commands.max()) == 255}


@needs_cc
def test_random_streams_bit_exact(builds):
    """Over 20,000 searcher control steps of random streams (garbage state before setup()): host build == emulator."""
    total, hit_any = 0, {}
    for i, (name, world, hidden, spec, opts) in enumerate(CASES):
        qp = qgru(world, hidden, seed=10 + i, **opts)
        files = render_firmware(qp, generator_version="test")
        exe = build_host(files[POLICY_FILE], builds, name=f"gru{i}")
        rng = np.random.default_rng(np.random.SeedSequence(20 + i))
        inputs = random_inputs(rng, world.period_ticks, (world.emitter_uid,), spec,
                               comm_radius_mm=world.comm_radius_mm, light_threshold=world.light_threshold)
        emu = FirmwareEmulator(qp, inputs.uids, inputs.calib)
        want = emu.run(inputs)
        got = run_host(exe, inputs, world.period_ticks, world.obs_dim, fill=f"random:{i}")
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=f"{name}: {compare(want, got)}")
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=f"{name}: {compare(want, got)}")
        searchers = ~emu.is_emitter
        assert np.unique(want.commands[searchers]).size > 64, f"{name}: commands barely vary"
        hit = _paths_hit(qp, want.obs[searchers], want.commands[searchers])
        assert hit["state spans int8"], f"{name}: the hidden state hardly moves"
        hit_any = {k: hit_any.get(k, False) or v for k, v in hit.items()}
        total += int(searchers.sum()) * want.steps.shape[1]
    assert all(hit_any.values()), f"never exercised: {[k for k, v in hit_any.items() if not v]}"
    assert total >= 20_000, f"only {total} control steps compared"


@needs_cc
def test_a_different_cell_is_detected(builds):
    """The comparison is sensitive: one changed recurrent weight, or a state reset every step, disagrees."""
    world, hidden, spec = CASES[0][1], 16, StreamSpec(n_robots=24, n_steps=40, rate=0.9)
    qp = qgru(world, hidden, seed=3)
    exe = build_host(render_firmware(qp, generator_version="t")[POLICY_FILE], builds, name="sens")
    rng = np.random.default_rng(np.random.SeedSequence(30))
    inputs = random_inputs(rng, world.period_ticks, (0,), spec)
    got = run_host(exe, inputs, world.period_ticks, world.obs_dim)
    assert compare(FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs), got) == ""
    w = qp.cell.nh.w.copy()
    w[3, 5] = w[3, 5] + 1 if w[3, 5] < 127 else 126
    other = replace(qp, cell=replace(qp.cell, nh=replace(qp.cell.nh, w=w)))
    assert compare(FirmwareEmulator(other, inputs.uids, inputs.calib).run(inputs), got) != ""

    class Forgetful(FirmwareEmulator):
        def control_step(self, light):
            self.state = self.qp.initial_state(self.R)
            return super().control_step(light)

    assert compare(Forgetful(qp, inputs.uids, inputs.calib).run(inputs), got) != ""


@needs_cc
def test_firmware_in_the_loop_replays_on_host(builds):
    """SwarmEnv driven by the GRU emulator: the recorded stream replays bit-exactly through the host build."""
    cfg = preset("kilobot", episode_steps=20, arena_half_mm=120.0)
    M, P, K = 8, cfg.period_ticks, 15
    qp = qgru(cfg, 12, seed=9)
    inputs = record_loop(qp, cfg, M, K, seed=6)
    want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    got = run_host(build_host(render_firmware(qp, generator_version="t")[POLICY_FILE], builds, name="loop"),
                   inputs, P, cfg.obs_dim)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps)


@needs_cc
def test_verify_host_and_beacon_program():
    """verify_host (the CLI's --verify host) passes for a GRU program and its beacon-only program."""
    qp = qgru(preset("kilobot"), 6, seed=2)
    result = verify_host(qp, render_firmware(qp, emitter_uids=(0, 9), msg_type=0x11, generator_version="t"),
                         spec=StreamSpec(n_robots=16, n_steps=12))
    assert result.ok and result.control_steps > 0, str(result)


@pytest.mark.avr
def test_gru_is_bit_exact_in_simavr_and_fits():
    """The AVR build of the GRU program in simavr equals the emulator; cycles per step and the exact budget fit."""
    require_avr(simulate=True)
    world = preset("kilobot", period_ticks=6, neighbour_table_size=4)
    qp = qgru(world, 32, seed=11, scale=3.0)
    files = render_firmware(qp)
    check = avr.verify_simavr(qp, files, n_robots=12, n_steps=25, seed=4)
    assert check.ok, str(check)
    assert check.control_steps >= 200 and check.cycles_step.size > 0
    assert check.cycles_step_max < 8_000_000 * 0.05, str(check)  # far below one control period (~1 s)
    exact = avr.exact_budget(files)
    b = estimate(GRU, world, HiddenArch(32)).with_exact(exact)
    assert b.ok and exact["flash"] < 28_160, b.table()


def test_same_seed_same_program():
    """The quantised GRU depends only on its seeds (calibration rollouts included)."""
    a, b = qgru(preset("thesis"), 8, seed=4), qgru(preset("thesis"), 8, seed=4)
    for la, lb in zip(a.layers, b.layers):
        for f in ("w", "b", "shift"):
            np.testing.assert_array_equal(getattr(la, f), getattr(lb, f))
    assert dataclasses.replace(a, policy_hash="x").policy_hash == "x" and fwspec.MSG_BYTES == 12


def test_export_cli_writes_a_gru_program(tmp_path, capsys):
    """`python -m export --policy gru.npz` calibrates, quantises, checks the budget and writes C + manifest."""
    import json

    from kiloforge.policies import save_policy
    from export.cli.main import main

    p = random_gru_policy(preset("kilobot"), 10, seed=6, scale=2.0)
    path = save_policy(p, tmp_path / "gru.npz")
    out = tmp_path / "kilobot_policy.c"
    assert main(["--policy", str(path), "--out", str(out), "--robots-calib", "3", "--calib-steps", "20",
                 "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "GRU quantisation error" in text and "GRU actor" in text and "free-running" in text
    c = out.read_text()
    assert "#define KF_HIDDEN 10u" in c and f"policy sha256   {p.hash}" in c
    man = json.loads((tmp_path / "kilobot_policy.c.manifest.json").read_text())
    assert man["quantization"]["kind"] == "gru" and man["layer_sizes"] == [16, 10, 2]
    assert man["budget"]["kind"] == "gru" and man["error"]["kind"] == "gru"
    assert (tmp_path / "kilobot_target.c").is_file()
