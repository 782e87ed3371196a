"""Replay memory: shapes, histories as sim.history.History builds them, uniform sampling, wrap-around."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from learn.replay import EpisodeReplay  # noqa: E402
from sim.history import History  # noqa: E402

M, D, S, TP = 3, 5, 7, 4  # robots, tuple width (2 actions + 3 obs), state width, t_prev


def as_numpy(batch) -> SimpleNamespace:
    """A sampled minibatch's tensors as NumPy arrays."""
    return SimpleNamespace(**{f.name: None if getattr(batch, f.name) is None else getattr(batch, f.name).numpy()
                              for f in dataclasses.fields(batch)})


def _fill(rp: EpisodeReplay, B: int, steps: int, rng: np.random.Generator, start_id: float = 0.0):
    """Run B synchronised episodes of ``steps`` random steps; returns what History saw at each step."""
    obs = rng.random((B, M, D - 2), dtype=np.float32)
    hist = History(TP, D - 2)
    h = hist.reset(obs)
    s = np.full((B, S), start_id, np.float32)
    rp.begin(hist.buf[:, :, 0], s)
    seen = [h]
    for t in range(steps):
        a = rng.random((B, M, 2), dtype=np.float32)
        obs = rng.random((B, M, D - 2), dtype=np.float32)
        h = hist.push(a, obs)
        s = np.full((B, S), start_id + t + 1, np.float32)
        rp.add(np.concatenate([a, obs], -1), s, np.full(B, start_id + t, np.float32))
        seen.append(h)
    return seen


def test_shapes_and_histories_match_history_buffer():
    """Every stored transition rebuilds h and h' exactly as History held them (Algorithm 4 initialisation included)."""
    rng = np.random.default_rng(0)
    T, B = 9, 2
    rp = EpisodeReplay(capacity=100, episode_steps=T, n_robots=M, tuple_dim=D, state_dim=S, t_prev=TP)
    seen = _fill(rp, B, T, rng)
    assert len(rp) == B * T
    for slot in range(B):
        e = np.full(T, rp.active[slot])
        t = np.arange(T)
        b = as_numpy(rp.gather(e, t))
        assert b.s.shape == (T, S) and b.h.shape == (T, M, TP * D) and b.a.shape == (T, M, 2)
        assert b.r.shape == (T,) and b.s2.shape == (T, S) and b.h2.shape == (T, M, TP * D)
        for k in range(T):
            np.testing.assert_array_equal(b.h[k], seen[k][slot])
            np.testing.assert_array_equal(b.h2[k], seen[k + 1][slot])
            np.testing.assert_array_equal(b.a[k], seen[k + 1][slot][:, -D:-D + 2])  # newest tuple's action
        np.testing.assert_array_equal(b.r, np.arange(T))
        np.testing.assert_array_equal(b.s[:, 0], np.arange(T))
        np.testing.assert_array_equal(b.s2[:, 0], np.arange(1, T + 1))


def test_sampling_is_uniform_over_stored_transitions():
    """Counts of sampled transitions, including those of unfinished episodes, are uniform (chi-square bound)."""
    rng = np.random.default_rng(1)
    T = 5
    rp = EpisodeReplay(capacity=40, episode_steps=T, n_robots=M, tuple_dim=D, state_dim=S, t_prev=TP)
    _fill(rp, 4, T, rng)
    _fill(rp, 2, 3, rng, start_id=100.0)  # two unfinished episodes of 3 steps
    n_stored = 4 * T + 2 * 3
    assert len(rp) == n_stored
    n = 52_000
    b = as_numpy(rp.sample(n, np.random.default_rng(2)))
    # identify each transition by (state id, first coordinate of h) — unique here
    keys = np.round(b.s[:, 0]).astype(int) * 10_000 + np.floor(b.h[:, 0, -1] * 9999).astype(int)
    _, counts = np.unique(keys, return_counts=True)
    assert counts.size == n_stored, "every stored transition must be reachable, nothing else"
    expected = n / n_stored
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert chi2 < 60, f"chi-square {chi2:.1f} with {n_stored - 1} dof is far from uniform"
    assert (b.s[:, 0] >= 100).mean() > 0.15  # the unfinished episodes are sampled (6/26 ≈ 0.23)


def test_wrap_around_overwrites_oldest_episodes():
    """With room for 3 episodes, the 4th and 5th replace the 1st and 2nd; samples come only from stored ones."""
    rng = np.random.default_rng(3)
    T = 4
    rp = EpisodeReplay(capacity=3 * T + 2, episode_steps=T, n_robots=M, tuple_dim=D, state_dim=S, t_prev=TP)
    assert rp.n_slots == 3 and rp.capacity == 12
    for k in range(5):
        _fill(rp, 1, T, rng, start_id=1000.0 * k)
    assert len(rp) == 3 * T
    b = as_numpy(rp.sample(2000, np.random.default_rng(4)))
    episode_of = np.floor(b.s[:, 0] / 1000).astype(int)
    assert set(np.unique(episode_of)) == {2, 3, 4}
    # a batch of parallel episodes that wraps past the end of the ring
    _fill(rp, 2, T, rng, start_id=9000.0)
    assert sorted(rp.active.tolist()) == [0, 2] and rp.next_slot == 1
    b = as_numpy(rp.sample(2000, np.random.default_rng(5)))
    assert set(np.unique(np.floor(b.s[:, 0] / 1000).astype(int))) == {4, 9}


def test_state_dict_round_trip():
    """A replay restored from its state_dict samples exactly what the original samples."""
    rng = np.random.default_rng(6)
    T = 4
    rp = EpisodeReplay(capacity=40, episode_steps=T, n_robots=M, tuple_dim=D, state_dim=S, t_prev=TP)
    _fill(rp, 3, T, rng)
    rp2 = EpisodeReplay(capacity=40, episode_steps=T, n_robots=M, tuple_dim=D, state_dim=S, t_prev=TP)
    rp2.load_state_dict(rp.state_dict())
    a, b = as_numpy(rp.sample(64, np.random.default_rng(7))), as_numpy(rp2.sample(64, np.random.default_rng(7)))
    for name in ("s", "h", "a", "r", "s2", "h2"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert rp.state_dict()["tuples"].shape[0] == 3  # only the used slots are saved


def test_one_gather_histories_are_overlapping_views_of_one_buffer():
    """h and h' of a sample share one gathered window (h' is h shifted by one tuple); repeated samples reuse it."""
    rng = np.random.default_rng(8)
    rp = EpisodeReplay(capacity=60, episode_steps=6, n_robots=M, tuple_dim=D, state_dim=S, t_prev=TP)
    _fill(rp, 3, 6, rng)
    b = rp.sample(32, np.random.default_rng(9))
    assert b.h.untyped_storage().data_ptr() == b.h2.untyped_storage().data_ptr()
    torch.testing.assert_close(b.h[..., D:], b.h2[..., :-D], rtol=0, atol=0)  # t_prev - 1 shared tuples
    torch.testing.assert_close(b.a, b.h2[..., -D:-D + 2], rtol=0, atol=0)  # a_t is the newest tuple's action
    ptr = b.h.data_ptr()
    assert rp.sample(32, np.random.default_rng(10)).h.data_ptr() == ptr  # no new allocation per minibatch


def test_windows_and_blocks_round_trip():
    """Windows cut from a replay restored block by block equal the original's; only written blocks are dirty."""
    rng = np.random.default_rng(11)
    rp = EpisodeReplay(capacity=200, episode_steps=5, n_robots=M, tuple_dim=D, state_dim=S)
    rp.block_slots = 3  # small blocks for the test
    rp.dirty = np.zeros(rp.n_blocks, bool)
    _fill(rp, 4, 5, rng)
    assert rp.dirty.tolist() == [True, True] + [False] * (rp.n_blocks - 2) and rp.used_blocks() == [0, 1]
    rp2 = EpisodeReplay(capacity=200, episode_steps=5, n_robots=M, tuple_dim=D, state_dim=S)
    rp2.block_slots = 3
    rp2.dirty = np.zeros(rp2.n_blocks, bool)
    rp2.load_meta(rp.meta())
    for k in rp.used_blocks():
        rp2.load_block(k, rp.block(k))
    w1, w2 = rp.sample_windows(20, 2, 2, np.random.default_rng(12)), rp2.sample_windows(20, 2, 2, np.random.default_rng(12))
    for f in ("x", "off", "s", "a", "r", "s2"):
        torch.testing.assert_close(getattr(w1, f), getattr(w2, f), rtol=0, atol=0)


def test_per_robot_rewards_are_sampled_per_robot():
    """per_robot_rewards: the replay stores (B, M) rewards and returns each transition's row of them, (N, M) and windows (N, U, M)."""
    T, M, D = 6, 3, 4
    rep = EpisodeReplay(4 * T, T, M, D, 2 + 3 * M, t_prev=2, per_robot_rewards=True)
    rep.begin(np.zeros((2, M, D), np.float32), np.zeros((2, 2 + 3 * M), np.float32))
    for t in range(T):
        r = (100 * np.arange(2)[:, None] + 10 * t + np.arange(M)).astype(np.float32)  # env, step, robot
        rep.add(np.full((2, M, D), t, np.float32), np.full((2, 2 + 3 * M), t + 1, np.float32), r)  # s_{t+1} holds t + 1
    b = rep.sample(16, np.random.default_rng(0))
    assert b.r.shape == (16, M)
    t = b.s[:, 0].numpy()  # the state holds its step
    np.testing.assert_array_equal(b.r.numpy() % 100, 10 * t[:, None] + np.arange(M))
    w = rep.sample_windows(5, burn_in=1, unroll=2, rng=np.random.default_rng(1))
    assert w.r.shape == (5, 2, M)
    np.testing.assert_array_equal(w.r.numpy() % 100, 10 * w.s[:, :, 0].numpy()[..., None] + np.arange(M))
