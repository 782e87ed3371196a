"""The compiled contact loop and radio (sim.compiled) against the NumPy code: bit-identical episodes and messages."""
from __future__ import annotations

import json
import os
from typing import Any

import numpy as np
import pytest

from sim import compiled
from sim.baselines import make_policy
from sim.config import preset
from sim.env import SwarmEnv
from sim.radio import draw_phases, tick_radio
from sim.variants import RANDOMISATIONS, Randomisation

#: per-robot turn rates and pivot points on straight runs: tick_move's closed form with per-robot rotations
UNCURVED = Randomisation(speed=(0.7, 1.3), turn=(0.7, 1.3), speed_spread=0.1, turn_spread=0.1,
                         pivot_offset_mm=(0.0, 16.5), emitter_mobility=(0.0, 1.0))
needs_jit = pytest.mark.skipif(not compiled.available(), reason=f"compiled code unavailable: {compiled.why_not()}")


def _episode(jit: bool, monkeypatch, cfg, B: int, M: int, seed: int, steps: int, policy: str,
             randomise: Randomisation | None = None) -> dict[str, Any]:
    """Positions, headings, beacons, observations and rewards of one batch of episodes, compiled code on or off."""
    monkeypatch.setenv(compiled.ENV_SWITCH, "1" if jit else "0")
    env = SwarmEnv(cfg, B, M, seed=seed, randomise=randomise)
    pol = make_policy(policy, cfg)
    obs, _ = env.reset()
    pol.reset(B, M, np.random.default_rng(seed))
    out: dict[str, list] = {"pos": [], "heading": [], "target": [], "obs": [], "reward": []}
    for _ in range(steps):
        obs, reward, *_ = env.step(pol.act(obs))
        for k, v in (("pos", env.pos), ("heading", env.heading), ("target", env.target), ("obs", obs),
                     ("reward", reward)):
            out[k].append(np.array(v, copy=True))
    return {k: np.stack(v) for k, v in out.items()}


@needs_jit
@pytest.mark.parametrize("M,B,policy,randomise", [
    (4, 8, "baseline", None),
    (16, 4, "baseline", "table"),
    (32, 3, "baseline", "table-free-beacon"),
    (32, 2, "random", None),
    (12, 4, "baseline", "table-free-beacon"),
    (16, 4, "random", "uncurved"),
])
def test_compiled_loop_gives_the_numpy_episode(monkeypatch, M, B, policy, randomise):
    """Whole kilobot-world episodes (jams, walls, pushed beacons, randomised motion) are bit-identical with and without it."""
    cfg = preset("kilobot", episode_steps=120)
    rand = {**RANDOMISATIONS, "uncurved": UNCURVED}[randomise] if randomise else None
    a = _episode(True, monkeypatch, cfg, B, M, 7 + M, 120, policy, rand)
    b = _episode(False, monkeypatch, cfg, B, M, 7 + M, 120, policy, rand)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@needs_jit
@pytest.mark.parametrize("moving_beacon,varied_periods,noise", [(False, False, False), (True, True, True)])
def test_compiled_radio_gives_the_numpy_messages(monkeypatch, moving_beacon, varied_periods, noise):
    """tick_radio's messages (senders, receivers, ticks, distances, per-env loss and noise draws, single) are bit-identical."""
    cfg = preset("kilobot", msg_loss=0.2 if noise else 0.0, dist_noise_mm=3.0 if noise else 0.0)
    rng = np.random.default_rng(5)
    P, B, M = cfg.period_ticks, 6, 24
    start = rng.uniform(-120, 120, (B, M, 2))
    pos = start + np.cumsum(rng.normal(0, 1.5, (P, B, M, 2)), axis=0)  # robots that move during the period
    target = rng.uniform(-60, 60, (B, 2))
    tticks = target + np.cumsum(rng.normal(0, 0.5, (P, B, 2)), axis=0) if moving_beacon else None
    periods = rng.integers(15, 18, (B, M + 1)) if varied_periods else None
    loss = rng.uniform(0.0, 0.3, B) if varied_periods else None  # per-env loss and noise (domain randomisation)
    sigma = rng.uniform(0.0, 4.0, B) if varied_periods else None
    flags = rng.integers(0, 2, (B, M)).astype(np.uint8)
    out = []
    for jit in (True, False):
        monkeypatch.setenv(compiled.ENV_SWITCH, "1" if jit else "0")
        rngs = [np.random.default_rng(100 + e) for e in range(B)]
        phases = draw_phases([np.random.default_rng(e) for e in range(B)], M, cfg, periods)
        out.append(tick_radio(pos, target, phases, 62, flags, cfg, rngs,
                              target_ticks=tticks, msg_period=periods, msg_loss=loss, dist_noise_mm=sigma))
    a, b = out
    assert a.s_env.size > 50 and a.t_env.size > 0
    for f in ("s_env", "s_rx", "s_snd", "s_tick", "s_dist", "s_flag", "t_env", "t_rx", "t_tick", "t_dist"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert a.single == b.single


@needs_jit
@pytest.mark.parametrize("msg_period,table", [(16, 3), (40, 5), (9, 16)])
def test_compiled_messages_give_the_numpy_observation(monkeypatch, msg_period, table):
    """observe_fast's compiled message part (emitter distance, repeat senders, full tables, sensing flags, RBF sums) equals NumPy's."""
    from sim.events import observe
    from sim.radio import observe_fast

    cfg = preset("kilobot", msg_period_ticks=msg_period, neighbour_table_size=table, msg_loss=0.1, dist_noise_mm=3.0)
    rng = np.random.default_rng(msg_period)
    P, B, M = cfg.period_ticks, 5, 24
    pos = rng.uniform(-90, 90, (B, M, 2)) + np.cumsum(rng.normal(0, 1.0, (P, B, M, 2)), axis=0)
    target = rng.uniform(-60, 60, (B, 2))
    flags = rng.integers(0, 2, (B, M)).astype(np.uint8)
    phases = draw_phases([np.random.default_rng(e) for e in range(B)], M, cfg)
    period = tick_radio(pos, target, phases, 31, flags, cfg, [np.random.default_rng(50 + e) for e in range(B)])
    light = rng.choice([-1, 0, 900], (B, M)).astype(np.int16)
    prev_wall = rng.integers(0, 2, (B, M)).astype(np.float32)
    counts = np.bincount(period.s_env * M + period.s_rx, minlength=B * M)
    assert counts.max() > table and period.single == (msg_period > P)  # full tables; repeat senders or not
    out = []
    for jit in (True, False):
        monkeypatch.setenv(compiled.ENV_SWITCH, "1" if jit else "0")
        out.append(observe_fast(period, light, prev_wall, cfg))
    out.append(observe(period.events(), light, prev_wall, cfg))
    for obs, heard in out[1:]:
        np.testing.assert_array_equal(out[0][0], obs)
        np.testing.assert_array_equal(out[0][1], heard)


@needs_jit
def test_compiled_command_bytes_equal_action_to_u8():
    """The compiled check-and-quantise gives action_to_u8's bytes (half steps, the tolerance at both ends) or None."""
    from sim.env import ACTION_TOL
    from sim.motion import action_to_u8

    rng = np.random.default_rng(3)
    edges = np.array([0.0, -0.0, 1.0, -ACTION_TOL, 1.0 + ACTION_TOL, 0.5 / 255, 1.5 / 255, 254.5 / 255, 0.5, 1e-300])
    a = np.concatenate([edges, (np.arange(255) + 0.5) / 255, rng.random(8 * 32 * 2 - edges.size - 255)]).reshape(8, 32, 2)
    lo, hi = -ACTION_TOL, 1.0 + ACTION_TOL
    np.testing.assert_array_equal(compiled.command_bytes(a, a.shape, lo, hi), action_to_u8(np.clip(a, 0.0, 1.0)))
    for bad in (np.nan, np.inf, -2 * ACTION_TOL, 1.0 + 2 * ACTION_TOL):
        b = a.copy()
        b[7, 31, 1] = bad
        assert compiled.command_bytes(b, b.shape, lo, hi) is None
    assert compiled.command_bytes(a.astype(np.float32), a.shape, lo, hi) is None


@needs_jit
def test_compiled_loop_in_a_crowded_small_arena(monkeypatch):
    """A dense jam against the walls of a small arena (many sweeps and pair-list rebuilds) stays bit-identical."""
    cfg = preset("kilobot", arena_half_mm=150.0, episode_steps=80)
    a = _episode(True, monkeypatch, cfg, 3, 20, 3, 80, "random")
    b = _episode(False, monkeypatch, cfg, 3, 20, 3, 80, "random")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_switch_turns_it_off(monkeypatch):
    """KILOFORGE_JIT=0 turns the compiled code off and says so."""
    monkeypatch.setenv(compiled.ENV_SWITCH, "0")
    assert not compiled.available()
    assert compiled.ENV_SWITCH in compiled.why_not()


def test_ci_has_the_compiled_loop():
    """In CI (numba from the test extras) the compiled code runs, so the equality tests above are not skipped."""
    if os.environ.get("CI") != "true":
        pytest.skip("outside CI the compiled loop may be missing (numba not installed)")
    assert compiled.available(), compiled.why_not()


@needs_jit
def test_es_training_learns_the_same_weights(monkeypatch, tmp_path):
    """A short ES training (clone, generations, evaluation) ends with the same weights with and without compiled code."""
    torch = pytest.importorskip("torch")
    from learn.checkpoint import load_checkpoint
    from learn.config import ESConfig
    from learn.es_train import train_es

    tiny = dict(n_robots=(4, 16), t_prev=2, actor_hidden=(8,), episode_steps=40, demo_robot_episodes=6, bc_updates=20,
                bc_batch=64, generations=2, pairs=2, eval_every=2, eval_episodes=2, eval_steps=40, threads=1, seed=4)
    theta, rows = [], []
    calls = {"period_contacts": 0, "straight_period": 0, "radio_messages": 0}
    for name in calls:
        def counted(*a, _f=getattr(compiled, name), _n=name, **k):
            calls[_n] += 1
            return _f(*a, **k)
        monkeypatch.setattr(compiled, name, counted)
    for jit in (True, False):
        monkeypatch.setenv(compiled.ENV_SWITCH, "1" if jit else "0")
        run = train_es(ESConfig(**tiny), tmp_path / f"jit{int(jit)}", progress=False, log=lambda _m: None)
        theta.append(load_checkpoint(run.run_dir / "checkpoint.pt")["theta"])
        summary = json.loads((run.run_dir / "summary.json").read_text())
        assert summary["sim_compiled"] is jit and (summary["sim_compiled_off_because"] is None) is jit
        timing = ("wall_s", "env_steps_per_s", "updates_per_s")  # NaNs compare equal in JSON text
        rows.append(json.dumps([{k: v for k, v in r.items() if k not in timing} for r in run.counters.rows],
                               sort_keys=True))
    assert calls["period_contacts"] + calls["straight_period"] > 0 and calls["radio_messages"] > 0, calls  # compiled
    assert torch.equal(theta[0], theta[1])
    assert rows[0] == rows[1]


@needs_jit
@pytest.mark.parametrize("broken,reason", [("raise", "cannot compile"), ("differ", "|z| differently"),
                                           ("product", "complex products differently")])
def test_a_kernel_that_fails_its_check_is_not_used(monkeypatch, broken, reason):
    """A kernel that fails to compile, or whose |z| or complex product differs from NumPy's, is not used, and
    why_not says why."""
    from sim import compiled_kernels

    def bad(z, out):
        if broken == "raise":
            raise RuntimeError("no compiler")
        out[:] = np.abs(z) * (1 + 1e-15)

    def plain_product(a, b, out):  # without the fused multiply-adds NumPy uses
        out[:] = (a.real * b.real - a.imag * b.imag) + 1j * (a.real * b.imag + a.imag * b.real)

    if broken == "product":
        monkeypatch.setattr(compiled_kernels, "cmul_many", plain_product)
    else:
        monkeypatch.setattr(compiled_kernels, "cabs_many", bad)
    compiled._checked.cache_clear()
    try:
        assert not compiled.available()
        assert reason in compiled.why_not()
        cfg = preset("kilobot", episode_steps=5)
        env = SwarmEnv(cfg, 2, 8, seed=1)
        env.reset()
        env.step(np.full((2, 8, 2), 1.0))  # the NumPy code runs
    finally:
        monkeypatch.undo()
        compiled._checked.cache_clear()
    assert compiled.available()
