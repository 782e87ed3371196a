"""The compiled per-tick contact loop (sim.contacts_jit) against the NumPy loop: bit-identical episodes."""
from __future__ import annotations

import os
from typing import Any

import numpy as np
import pytest

from sim import contacts_jit
from sim.baselines import make_policy
from sim.config import preset
from sim.env import SwarmEnv
from sim.variants import RANDOMISATIONS, Randomisation

needs_jit = pytest.mark.skipif(not contacts_jit.available(), reason=f"compiled loop unavailable: {contacts_jit.why_not()}")


def _episode(jit: bool, monkeypatch, cfg, B: int, M: int, seed: int, steps: int, policy: str,
             randomise: Randomisation | None = None) -> dict[str, Any]:
    """Positions, headings, beacons, observations and rewards of one batch of episodes, compiled loop on or off."""
    monkeypatch.setenv(contacts_jit.ENV_SWITCH, "1" if jit else "0")
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
])
def test_compiled_loop_gives_the_numpy_episode(monkeypatch, M, B, policy, randomise):
    """Whole kilobot-world episodes (jams, walls, pushed beacons, randomised motion) are bit-identical with and without it."""
    cfg = preset("kilobot", episode_steps=120)
    rand = RANDOMISATIONS[randomise] if randomise else None
    a = _episode(True, monkeypatch, cfg, B, M, 7 + M, 120, policy, rand)
    b = _episode(False, monkeypatch, cfg, B, M, 7 + M, 120, policy, rand)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@needs_jit
def test_compiled_loop_in_a_crowded_small_arena(monkeypatch):
    """A dense jam against the walls of a small arena (many sweeps and pair-list rebuilds) stays bit-identical."""
    cfg = preset("kilobot", arena_half_mm=150.0, episode_steps=80)
    a = _episode(True, monkeypatch, cfg, 3, 20, 3, 80, "random")
    b = _episode(False, monkeypatch, cfg, 3, 20, 3, 80, "random")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_switch_turns_it_off(monkeypatch):
    """KILOFORGE_JIT=0 turns the compiled loop off and says so."""
    monkeypatch.setenv(contacts_jit.ENV_SWITCH, "0")
    assert not contacts_jit.available()
    assert contacts_jit.ENV_SWITCH in contacts_jit.why_not()


def test_ci_has_the_compiled_loop():
    """In CI (numba from the test extras) the compiled loop runs, so the equality tests above are not skipped."""
    if os.environ.get("CI") != "true":
        pytest.skip("outside CI the compiled loop may be missing (numba not installed)")
    assert contacts_jit.available(), contacts_jit.why_not()
