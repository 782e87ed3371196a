"""sim.rollout.EpisodeLoop: the one stepping loop records what the env returns, batch by batch."""
from __future__ import annotations

import numpy as np
import pytest

from sim.config import preset
from sim.env import SwarmEnv
from sim.rollout import EpisodeLoop
from sim.tasks import get_task


def _commands(t: int, B: int, M: int) -> np.ndarray:
    return np.stack(np.broadcast_arrays(np.full((B, M), (t % 5) / 4), np.full((B, M), 0.6)), -1)


@pytest.mark.parametrize("task", ["localisation", "aggregation"])
def test_loop_records_rewards_success_and_returns_of_a_hand_stepped_env(task):
    """Two batches through run() equal the same env stepped by hand: rewards, success, returns, hook calls."""
    world = get_task(task).world(preset("kilobot", episode_steps=12))
    B, M, T = 2, 3, 12
    seeds = [4, 9]
    ref = SwarmEnv(world, B, M, seed=0, task=task)
    rewards, success, returns = np.zeros((2 * B, T)), np.zeros((2 * B, T)), np.zeros(2 * B)
    for k, s in enumerate(seeds):
        ref.reset(seed=s)
        for t in range(T):
            _, r, _, truncated, info = ref.step(_commands(t, B, M))
            rewards[k * B:(k + 1) * B, t] = r
            success[k * B:(k + 1) * B, t] = info["success"]
            returns[k * B:(k + 1) * B] += r
        assert np.all(truncated)
    calls = []
    loop = EpisodeLoop(SwarmEnv(world, B, M, seed=0, task=task), batches=2)
    loop.run(lambda t, obs, info: _commands(t, B, M), seeds, begin=lambda k, obs, info: calls.append(("begin", k)),
             observe=lambda t, a, obs, r, info: calls.append(("step", t)), end=lambda k: calls.append(("end", k)))
    np.testing.assert_array_equal(loop.rewards, rewards)
    np.testing.assert_array_equal(loop.success, success)
    np.testing.assert_array_equal(loop.returns, returns)
    batch = [("step", t) for t in range(T)]
    assert calls == [("begin", 0), *batch, ("end", 0), ("begin", 1), *batch, ("end", 1)]


def test_one_row_block_is_reused_and_returns_restart_at_each_batch():
    """batches=1: every batch writes the same rows, and begin() zeroes the running returns."""
    world = preset("kilobot", episode_steps=6)
    act = lambda t, obs, info: _commands(t, 2, 2)  # noqa: E731
    once = EpisodeLoop(SwarmEnv(world, 2, 2, seed=1)).run(act, [3])
    twice = EpisodeLoop(SwarmEnv(world, 2, 2, seed=1)).run(act, [3, 3])
    assert twice.k == 1 and twice.rows == slice(0, 2) and twice.rewards.shape == (2, 6)
    np.testing.assert_array_equal(twice.rewards, once.rewards)
    np.testing.assert_array_equal(twice.returns, once.returns)
    np.testing.assert_array_equal(once.returns, np.add.accumulate(once.rewards, axis=1)[:, -1])
