"""The hand-written searcher as firmware (``--policy searcher`` and ``pusher``): its draws, the integer reference, host and AVR builds, closed loop."""
from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import pytest

from tests.avr_tools import require_avr
from export.cli.common import load
from export.codegen.budget import FLASH_LIMIT_B, SRAM_LIMIT_B, estimate
from export.codegen.render import POLICY_FILE, render_firmware
from export.verify import avr
from export.verify.closed_loop import run_firmware, run_float
from export.contract.firmware import EVENT_DTYPE
from export.verify.emulator import FirmwareEmulator, FirmwareInputs
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.actors.searcher import (SEARCHER, FirmwareDrawSearcher, SearcherArch, SearcherState,
                                       draw_bytes, firmware_draws, pusher_policy, quantize_searcher, rng_seed,
                                       run_table, searcher_policy, xorshift32)
from tests.recorded_loop import record_loop
from sim.baselines import PUSHER, TUNED, SearcherParams
from sim.config import preset
from sim.motion import action_to_u8

needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")
WORLD = preset("kilobot")
TARGETS = (0,)
NAMES = ("searcher", "pusher")  #: the shipped searchers


@functools.lru_cache(maxsize=None)
def shipped(name: str = "searcher"):
    """A shipped searcher (``--policy searcher`` or ``pusher``) and its integer searcher."""
    p = load(Path(name))
    return p, quantize_searcher(p)


@pytest.fixture(scope="module", params=NAMES)
def name(request):
    """Each shipped searcher in turn."""
    return request.param


@pytest.fixture(scope="module")
def exe(name, tmp_path_factory):
    """The host build of that shipped searcher's program."""
    files = render_firmware(shipped(name)[1], emitter_uids=TARGETS, generator_version="test")
    return build_host(files[POLICY_FILE], tmp_path_factory.mktemp(f"{name}_host"), name=name)


# --- the draws ---------------------------------------------------------------------------------
def test_shipped_policy_is_the_tuned_kilobot_searcher():
    """`--policy searcher` loads sim.baselines' TUNED["kilobot"] searcher in today's kilobot world (rewrite it when the preset changes)."""
    p, qp = shipped()
    assert p.kind == "searcher" and p.world == WORLD and p.params == TUNED["kilobot"]
    assert p.hash == searcher_policy(WORLD).hash, "export/data/searcher_policy.npz is stale: see kiloforge/actors/searcher.py"
    assert qp.speed_q == 255 and qp.stop_q == int(np.floor(TUNED["kilobot"].stop_dist * 64)) and qp.margin_q == 0


def test_shipped_pusher_is_the_tuned_searcher_with_pusher():
    """`--policy pusher` loads TUNED["kilobot"] with sim.baselines.PUSHER; its margin is floor(0.05 * 64) = 3 obs units."""
    p, qp = shipped("pusher")
    assert p.params == dataclasses.replace(TUNED["kilobot"], **PUSHER)
    assert p.hash == pusher_policy(WORLD).hash, "export/data/pusher_policy.npz is stale: see kiloforge/actors/searcher.py"
    assert qp.stop_q == 60 and qp.margin_q == 3


@pytest.mark.parametrize("params", [TUNED["kilobot"], SearcherParams(), SearcherParams(run_alpha=0.0, run_min_steps=7,
                                                                                        run_max_steps=90)])
def test_draw_bytes_follow_the_float_distributions(params):
    """Over all 256 byte values: each uniform integer draw is within 1/256 of its float probability, the run CDF within 1/512."""
    b = np.arange(256)
    _, tumble, wall, runs = firmware_draws(params, np.stack([b] * 4, -1))
    for lo, hi, got in ((1, params.tumble_max_steps, tumble), (params.wall_turn_min, params.wall_turn_max, wall)):
        freq = np.bincount(got - lo, minlength=hi - lo + 1) / 256
        assert freq.size == hi - lo + 1 and np.abs(freq - 1 / (hi - lo + 1)).max() <= 1 / 256
    np.testing.assert_array_equal(runs, run_table(params).astype(np.int64))
    r = np.arange(1, params.run_max_steps)
    if params.run_alpha > 0:
        cdf = np.clip(1 - (params.run_min_steps / r) ** params.run_alpha, 0, None)  # P(ceil(Pareto) <= r)
    else:
        cdf = 1 - np.exp(-r / params.run_min_steps)
    fw = (runs[:, None] <= r).mean(0)
    assert np.abs(fw - cdf).max() <= 1 / 512 + 1e-12
    if params.run_alpha > 0:  # the Pareto tail reaches the cut; an exponential of mean 7 never does
        assert (runs == params.run_max_steps).any() and runs.min() >= np.ceil(params.run_min_steps)


def test_uids_seed_different_streams():
    """Distinct kilo_uids give distinct, never-zero xorshift32 words and different draw streams; equal uids draw alike."""
    uids = np.arange(0, 1 << 16)
    seed = rng_seed(uids)
    assert np.unique(seed).size == uids.size and (seed != 0).all()
    w = rng_seed(np.array([1, 2, 3, 1]))
    bytes_ = []
    for _ in range(64):
        w = xorshift32(w)
        bytes_.append(draw_bytes(w))
    s = np.stack(bytes_, 1)  # (4, 64, 4)
    np.testing.assert_array_equal(s[0], s[3])
    for i, j in ((0, 1), (0, 2), (1, 2)):
        assert (s[i, :, 0] < 128).tolist() != (s[j, :, 0] < 128).tolist(), f"uids {i + 1}, {j + 1} turn alike"


def test_setup_state_sets_every_field():
    """setup_state gives every SearcherState field one value per robot, the generator seeded from kilo_uid, the rest 0."""
    uids = np.array([7, 300, 65535])
    st = shipped()[1].setup_state(uids)
    for f in dataclasses.fields(SearcherState):
        v = getattr(st, f.name)
        assert v.shape == (3,), f.name
        if f.name == "rng":
            np.testing.assert_array_equal(v, rng_seed(uids))
        else:
            assert not v.any(), f.name


# --- the integer reference -----------------------------------------------------------------------
def _stream(seed: int, n_robots: int = 48, n_steps: int = 80):
    rng = np.random.default_rng(np.random.SeedSequence([16, seed]))
    return random_inputs(rng, WORLD.period_ticks, TARGETS, StreamSpec(n_robots=n_robots, n_steps=n_steps, rate=0.6),
                         comm_radius_mm=WORLD.comm_radius_mm, light_threshold=WORLD.light_threshold)


@pytest.mark.parametrize("name", NAMES)
def test_integer_searcher_is_the_float_rules_on_dequantised_observations(name):
    """The emulator's commands equal sim.baselines' float rules fed its int8 observations / 2**e_in and the same draws."""
    p, qp = shipped(name)
    inputs = _stream(1)
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=TARGETS)
    out = emu.run(inputs)
    s = ~emu.is_emitter
    obs, cmd = out.obs[s].astype(np.float64) / (1 << qp.e_in), out.commands[s]
    ref = FirmwareDrawSearcher(p.world, p.params, inputs.uids[s])
    ref.reset(1, int(s.sum()))
    got = np.stack([action_to_u8(ref.act(obs[None, :, t])[0]) for t in range(obs.shape[1])], 1)
    np.testing.assert_array_equal(got, cmd)
    kinds = {tuple(c) for c in cmd.reshape(-1, 2).tolist()}
    assert {(255, 255), (255, 0), (0, 255), (0, 0)} <= kinds, f"not every command occurred: {kinds}"
    if name == "pusher":  # the stream exercises the pusher's own rules: the plain searcher answers it differently
        plain = FirmwareDrawSearcher(p.world, TUNED["kilobot"], inputs.uids[s])
        plain.reset(1, int(s.sum()))
        other = np.stack([action_to_u8(plain.act(obs[None, :, t])[0]) for t in range(obs.shape[1])], 1)
        assert (other != cmd).any(-1).mean() > 0.05


@needs_cc
def test_host_build_equals_emulator_on_random_streams(name, exe):
    """Host build of `--policy searcher` / `pusher` == the emulator byte for byte over 2 x 48 robots x 80 control steps of random streams."""
    total = 0
    for seed in (2, 3):
        inputs = _stream(seed)
        emu = FirmwareEmulator(shipped(name)[1], inputs.uids, inputs.calib, emitter_uids=TARGETS)
        want = emu.run(inputs)
        got = run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill=f"random:{seed}")
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
        cmd = want.commands[~emu.is_emitter]
        assert (cmd == 0).all(-1).any() and (cmd == 255).all(-1).any() and (cmd[..., 0] != cmd[..., 1]).any()
        total += int((~emu.is_emitter).sum()) * want.steps.shape[1]
    assert total >= 5_000, f"only {total} control steps compared"


@needs_cc
def test_host_build_seeds_from_kilo_uid(name, exe):
    """With no messages, robots of distinct uids tumble differently, equal uids alike; a uid-blind emulator is caught."""
    P, S = WORLD.period_ticks, 300
    uids = np.array([5, 6, 5, 999], np.uint16)
    light = np.full((4, S), 900, np.int16)  # bright: never the wall flag
    inputs = FirmwareInputs(uids=uids, calib=np.zeros((4, 4), np.uint8), light=light,
                            events=np.zeros(0, EVENT_DTYPE), n_ticks=(S + 1) * P)
    want = FirmwareEmulator(shipped(name)[1], uids, inputs.calib, emitter_uids=TARGETS).run(inputs)
    got = run_host(exe, inputs, P, WORLD.obs_dim, fill="0xA5")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    c = got.commands
    np.testing.assert_array_equal(c[0], c[2])
    assert (c[0] != c[1]).any() and (c[0] != c[3]).any() and (c[1] != c[3]).any()
    assert ((c[0, :, 0] == 255) & (c[0, :, 1] == 0)).any() and ((c[0, :, 0] == 0) & (c[0, :, 1] == 255)).any()

    class UidBlind(FirmwareEmulator):
        def reset(self):
            super().reset()
            self.state = self.qp.setup_state(np.zeros_like(self.uids))

    assert compare(UidBlind(shipped(name)[1], uids, inputs.calib, emitter_uids=TARGETS).run(inputs), got) != ""


@needs_cc
def test_firmware_in_the_loop_replays_on_host(name, exe):
    """SwarmEnv driven by the searcher emulator for 120 steps (16 robots): the recorded stream replays bit-exactly on host."""
    cfg = dataclasses.replace(WORLD, episode_steps=200)
    M, P, K = 16, cfg.period_ticks, 120
    qp = shipped(name)[1]
    inputs = record_loop(qp, cfg, M, K, seed=3)
    want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    got = run_host(exe, inputs, P, cfg.obs_dim)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps)
    obs = want.obs
    assert (obs[..., 1] >= 0).any(), "no robot heard the target"


# --- AVR ---------------------------------------------------------------------------------------
@pytest.mark.avr
@pytest.mark.parametrize("name", NAMES)
def test_avr_build_fits_the_budget(name):
    """avr-gcc builds `--policy searcher` and `pusher` within the flash and SRAM budget (stack measured in simavr when installed)."""
    require_avr()
    qp = shipped(name)[1]
    exact = avr.exact_budget(render_firmware(qp), qp, stack_steps=20)
    b = estimate(SEARCHER, WORLD, SearcherArch()).with_exact(exact)
    assert b.ok, b.table()
    assert exact["flash"] <= FLASH_LIMIT_B and exact["sram_user"] <= SRAM_LIMIT_B, exact


# --- closed loop -------------------------------------------------------------------------------
def _coverage(n_robots: int, episodes: int, steps: int, seed: int) -> tuple[float, float]:
    p, qp = shipped()
    f = run_float(p, n_robots, episodes, seed, steps=steps, n_envs=episodes)
    q = run_firmware(qp, n_robots, episodes, seed, steps=steps, n_envs=episodes)
    return float(f.metrics().final_coverage.mean()), float(q.metrics().final_coverage.mean())


# Measured (16 robots, 300 steps, 32 episodes, seed 0): final coverage float 0.812, firmware 0.829 (sd 0.14
# per episode); paired per-episode difference +0.017, sd 0.064, so sd 0.022 for a mean over 8 episodes; the four
# 8-episode blocks differ by +0.003, +0.048, -0.010, +0.027. At 4 episodes x 100 steps (seeds 0-9) the difference
# of the means has sd 0.063. The tolerances are 3 sd: the draws differ (NumPy vs xorshift32), not the rules.
@pytest.mark.slow
def test_closed_loop_coverage_matches_the_float_searcher():
    """16 robots, 8 episodes x 300 steps, kilobot world: firmware final coverage within 0.07 (3 sd) of the float searcher's."""
    f, q = _coverage(16, 8, 300, seed=0)
    assert f > 0.6, f"the float searcher covers only {f:.3f}"
    assert abs(q - f) <= 0.07, f"final coverage float {f:.4f} vs firmware {q:.4f} (measured: 0.787 vs 0.789)"


def test_closed_loop_coverage_matches_the_float_searcher_short():
    """16 robots, 4 episodes x 100 steps (CI size): firmware final coverage within 0.19 (3 sd) of the float searcher's."""
    f, q = _coverage(16, 4, 100, seed=0)
    assert f > 0.3, f"the float searcher covers only {f:.3f}"
    assert abs(q - f) <= 0.19, f"final coverage float {f:.4f} vs firmware {q:.4f} (measured: 0.605 vs 0.664)"


def test_export_cli_renders_the_searcher(tmp_path, capsys):
    """`python -m export --policy searcher` writes the searcher program, its manifest and the error report."""
    import json

    from export.cli.main import main

    out = tmp_path / "kilobot_policy.c"
    assert main(["--policy", "searcher", "--out", str(out), "--robots-calib", "4", "--calib-steps", "20",
                 "--quiet"]) == 0
    assert "searcher quantisation error" in capsys.readouterr().out
    c = out.read_text()
    assert "kf_forward" in c and f"#define KF_STOP_Q {shipped()[1].stop_q}u" in c and "KF_RUN" in c
    man = json.loads((tmp_path / "kilobot_policy.c.manifest.json").read_text())
    assert man["quantization"]["kind"] == "searcher" and man["error"]["kind"] == "searcher"
