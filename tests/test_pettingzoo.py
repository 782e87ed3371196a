"""Tests of the PettingZoo ParallelEnv wrapper (optional extra: skipped without pettingzoo)."""
from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pettingzoo", reason="pettingzoo not installed (optional extra kiloforge[pettingzoo])")
pytest.importorskip("gymnasium", reason="gymnasium not installed (optional extra kiloforge[pettingzoo])")

from pettingzoo.test import parallel_api_test  # noqa: E402

from sim.config import preset  # noqa: E402
from sim.pettingzoo_env import SwarmParallelEnv, parallel_env  # noqa: E402


def test_parallel_api_test_passes():
    """PettingZoo's own parallel_api_test accepts the wrapper (thesis world, 3 robots, full episodes)."""
    env = parallel_env(preset("thesis", episode_steps=40), n_robots=3, seed=0)
    parallel_api_test(env, num_cycles=100)


def test_parallel_api_test_passes_kilobot():
    """The kilobot world (tick-level motion, lossy radio) passes parallel_api_test too."""
    parallel_api_test(parallel_env(preset("kilobot", episode_steps=15), n_robots=4, seed=0), num_cycles=30)


def test_shared_reward_spaces_state_and_truncation():
    """Every agent gets the same team reward; obs lie in their Box; state is 2+3M wide; truncation ends it."""
    cfg = preset("thesis", episode_steps=5)
    env = SwarmParallelEnv(cfg, n_robots=4, seed=1, render_mode="rgb_array")
    obs, infos = env.reset(seed=3)
    assert env.agents == ["robot_0", "robot_1", "robot_2", "robot_3"]
    assert env.state().shape == (2 + 3 * 4,)
    for t in range(5):
        acts = {a: env.action_space(a).sample() for a in env.agents}
        obs, rew, term, trunc, info = env.step(acts)
        assert len(set(rew.values())) == 1
        assert all(env.observation_space(a).contains(o) for a, o in obs.items())
        assert not any(term.values())
        assert all(trunc.values()) == (t == 4)
        assert set(info["robot_0"]) == {"in_range", "coverage", "success", "robot_success"}
        assert info["robot_0"]["success"] == info["robot_0"]["coverage"]
        assert info["robot_0"]["robot_success"] == info["robot_0"]["in_range"]
    assert env.agents == []
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8


def test_reset_seed_reproduces_episode():
    """reset(seed=s) followed by the same actions gives the same observations."""
    env = parallel_env("thesis", n_robots=2)
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=42)
        traj = [np.concatenate([obs[a] for a in env.agents])]
        for _ in range(10):
            obs, *_ = env.step({a: np.array([1.0, 0.6], np.float32) for a in env.agents})
            traj.append(np.concatenate([obs[a] for a in sorted(obs)]))
        runs.append(np.stack(traj))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_parallel_env_runs_another_task():
    """parallel_env(task="aggregation") plays a beaconless task: its world, state and success in the infos."""
    env = parallel_env("kilobot", n_robots=5, seed=2, render_mode="rgb_array", task="aggregation")
    obs, info = env.reset(seed=2)
    assert env.cfg.emitter is False and env.state().shape == (15,)
    assert set(info["robot_0"]) == {"success", "robot_success"} and obs["robot_0"].shape == (env.cfg.obs_dim,)
    obs, rew, term, trunc, info = env.step({a: env.action_space(a).sample() for a in env.agents})
    assert 0 < info["robot_0"]["success"] <= 1 and env.render().ndim == 3
