"""Tests of the neighbour grid, the radio stage, light and the fast observation path."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sim.config import OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL, ROLE_SEARCHER, ROLE_TARGET, preset
from sim.env import SwarmEnv
from sim.events import observe
from sim.grid import pairs_within
from sim.radio import light_readings, observe_fast, target_distance, thesis_radio, tick_radio


def _rngs(n, seed=0):
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]


# --- grid --------------------------------------------------------------------------------------
@pytest.mark.parametrize("B,N,extent,radius", [(3, 70, 100.0, 40.0), (2, 300, 300.0, 25.0), (4, 9, 50.0, 120.0),
                                               (1, 200, 100.0, 7.0)])
@pytest.mark.parametrize("ordered,dtype", [(False, np.float64), (True, np.float64), (True, np.float32)])
def test_grid_equals_dense(B, N, extent, radius, ordered, dtype):
    """Grid and all-pairs search give identical pairs, order and distances (points on cell edges too)."""
    rng = np.random.default_rng(B * N)
    pos = rng.uniform(-extent, extent, (B, N, 2))
    pos[0, :4] = [[-extent, -extent], [extent, extent], [0.0, 0.0], [radius, 0.0]]  # borders, exact radius
    d = pairs_within(pos, radius, extent, "dense", ordered, dtype)
    g = pairs_within(pos, radius, extent, "grid", ordered, dtype)
    for f in ("env", "i", "j", "dist"):
        np.testing.assert_array_equal(getattr(d, f), getattr(g, f))
    brute = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1) <= radius  # (B, N, N)
    brute &= ~np.eye(N, dtype=bool) if ordered else np.triu(np.ones((N, N), bool), 1)
    assert len(d) == brute.sum()
    if ordered:
        np.testing.assert_array_equal(d.udist[d.uidx], d.dist)
        np.testing.assert_array_equal(g.udist[g.uidx], g.dist)


@pytest.mark.parametrize("ordered", [False, True])
def test_chunked_search_equals_unchunked(monkeypatch, ordered):
    """Processing envs in chunks (dense and grid, incl. candidate chunks) changes nothing."""
    import sim.grid as G

    rng = np.random.default_rng(9)
    pos = rng.uniform(-100, 100, (7, 80, 2))
    want = {m: pairs_within(pos, 30.0, 100.0, m, ordered) for m in ("dense", "grid")}
    monkeypatch.setattr(G, "DENSE_CHUNK_PAIRS", 5000)  # 2 envs per dense chunk
    monkeypatch.setattr(G, "GRID_CHUNK_POINTS", 200)  # 2 envs per grid chunk
    monkeypatch.setattr(G, "CHUNK_ENTRIES", 300)  # several candidate chunks
    for m in ("dense", "grid"):
        got = pairs_within(pos, 30.0, 100.0, m, ordered)
        for f in ("env", "i", "j", "dist"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want[m], f))
        if ordered:
            np.testing.assert_array_equal(got.udist[got.uidx], got.dist)


def test_grid_rejects_unknown_method():
    """An unknown neighbour-search method is named in the error."""
    with pytest.raises(ValueError, match="octree"):
        pairs_within(np.zeros((1, 3, 2)), 1.0, 1.0, "octree")


# --- thesis-mode radio -------------------------------------------------------------------------
def _thesis_setup(cfg, B=5, M=12, seed=3):
    rng = np.random.default_rng(seed)
    a = cfg.arena_half_mm
    pos = rng.uniform(-a, a, (B, M, 2))
    target = rng.uniform(-a, a, (B, 2))
    flags = rng.integers(0, 2, (B, M)).astype(np.uint8)
    return pos, target, flags


def test_thesis_radio_everyone_in_range_heard_once():
    """Without loss every ordered pair within the radius is heard exactly once, none beyond; symmetric."""
    cfg = preset("thesis")
    pos, target, flags = _thesis_setup(cfg)
    ev = thesis_radio(pos, target, flags, cfg, _rngs(5)).events()
    s = ev.role == ROLE_SEARCHER
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    want = (d <= cfg.comm_radius_mm) & ~np.eye(pos.shape[1], dtype=bool)
    got = np.zeros_like(want, dtype=int)
    np.add.at(got, (ev.env[s], ev.rx[s], ev.sender[s]), 1)
    np.testing.assert_array_equal(got, want.astype(int))
    np.testing.assert_array_equal(got, got.transpose(0, 2, 1))  # who hears whom is symmetric
    np.testing.assert_allclose(ev.dist_mm[s], d[ev.env[s], ev.rx[s], ev.sender[s]], rtol=1e-12)
    np.testing.assert_array_equal(ev.flag[s], flags[ev.env[s], ev.sender[s]])
    t = ev.role == ROLE_TARGET
    dt = np.linalg.norm(pos - target[:, None], axis=-1)
    assert t.sum() == (dt <= cfg.comm_radius_mm).sum()
    assert (ev.sender[t] == -1).all() and (ev.flag[t] == 0).all() and (ev.tick == 0).all()


def test_thesis_radio_arrival_order():
    """Events are sorted by (env, receiver), target first, then senders ascending."""
    cfg = preset("thesis")
    pos, target, flags = _thesis_setup(cfg, B=3, M=30)
    ev = thesis_radio(pos, target, flags, cfg, _rngs(3)).events()
    key = (ev.env.astype(np.int64) * 30 + ev.rx) * 31 + ev.sender + 1
    assert (np.diff(key) > 0).all()


def test_loss_rate_matches_msg_loss():
    """The fraction of in-range messages lost is msg_loss within 4 binomial standard deviations."""
    p = 0.3
    cfg = preset("thesis", msg_loss=p)
    pos, target, flags = _thesis_setup(cfg, B=40, M=30)
    n_all = len(thesis_radio(pos, target, flags, preset("thesis"), _rngs(40)).events())
    n_got = len(thesis_radio(pos, target, flags, cfg, _rngs(40)).events())
    lost = 1 - n_got / n_all
    assert abs(lost - p) < 4 * math.sqrt(p * (1 - p) / n_all), (lost, n_all)


def test_noise_integer_rounding_and_clip():
    """Measured distances are integers in [33, 255] with the right scatter around the truth."""
    cfg = preset("thesis", dist_noise_mm=3.0, dist_integer=True, dist_min_mm=33.0, comm_radius_mm=85.0)
    pos, target, flags = _thesis_setup(cfg, B=30, M=30)
    per = thesis_radio(pos, target, flags, cfg, _rngs(30))
    ev = per.events()
    assert len(ev) > 1000
    np.testing.assert_array_equal(ev.dist_mm, np.round(ev.dist_mm))
    assert ev.dist_mm.min() >= 33 and ev.dist_mm.max() <= 255
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    s = ev.role == ROLE_SEARCHER
    true = d[ev.env[s], ev.rx[s], ev.sender[s]]
    far = true > 40  # away from the clip
    err = ev.dist_mm[s][far] - true[far]
    assert abs(err.mean()) < 0.2 and 2.8 < err.std() < 3.3  # N(0, 3) plus rounding (σ² + 1/12)


# --- tick-level radio --------------------------------------------------------------------------
def test_tick_radio_rate_order_and_range():
    """Kilobot messages: ≈1.9 per second per robot, arrival order, nobody heard beyond the radius."""
    cfg = preset("kilobot", msg_loss=0.0, dist_noise_mm=0.0, light_dropout=0.0)
    B, M, P = 20, 6, cfg.period_ticks
    rng = np.random.default_rng(5)
    pos = rng.uniform(-60, 60, (B, M, 2))  # some pairs beyond 85 mm
    target = rng.uniform(-60, 60, (B, 2))
    phases = rng.integers(0, cfg.msg_period_ticks, (B, M + 1))
    flags = np.zeros((B, M), np.uint8)
    ticks = np.broadcast_to(pos, (P, B, M, 2))
    n_periods, count = 16, 0
    d = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    for t in range(n_periods):
        ev = tick_radio(ticks, target, phases, t * P, flags, cfg, _rngs(B)).events()
        key = ((ev.env.astype(np.int64) * M + ev.rx) * P + ev.tick) * (M + 1) + ev.sender + 1
        assert (np.diff(key) > 0).all()  # arrival order, target (-1) first at a tick
        s = ev.role == ROLE_SEARCHER
        dd = d[ev.env[s], ev.rx[s], ev.sender[s]]
        assert (dd <= cfg.comm_radius_mm).all()
        # a pair in range hears every transmission: count the sends of each sender once per receiver
        inr = (d <= cfg.comm_radius_mm) & ~np.eye(M, dtype=bool)
        count += s.sum() / inr.sum()
        assert ((ev.tick >= 0) & (ev.tick < P)).all()
    rate = count / (n_periods * cfg.control_period_s)  # messages / s / robot
    assert abs(rate - 31 / 16 / cfg.control_period_s) < 1e-9  # exactly P/T sends per period on average
    assert 1.85 < rate < 1.95


def test_tick_radio_kilobot_distances_are_uint8():
    """With the kilobot preset's noise, every measured distance is an integer in 33..255."""
    env = SwarmEnv(preset("kilobot"), 4, 24, seed=2)
    env.reset()
    rng = np.random.default_rng(0)
    n = 0
    for _ in range(3):
        *_, info = env.step(rng.random((4, 24, 2)))
        ev = info["events"]
        n += len(ev)
        np.testing.assert_array_equal(ev.dist_mm, np.floor(ev.dist_mm))
        assert ((ev.dist_mm >= 33) & (ev.dist_mm <= 255)).all()
    assert n > 0


# --- light -------------------------------------------------------------------------------------
def test_light_near_wall_and_dropout():
    """Light is high within wall_sense_mm of a wall, low elsewhere, -1 at the dropout rate."""
    cfg = preset("thesis", light_dropout=0.2)
    pos = np.array([[[95.0, 0.0], [0.0, -90.0], [0.0, 0.0], [89.0, 89.0]]]).repeat(500, 0)  # (500, 4, 2)
    light = light_readings(pos, cfg, _rngs(500))
    ok = light >= 0
    assert abs((~ok).mean() - 0.2) < 4 * math.sqrt(0.2 * 0.8 / light.size)
    want = np.array([cfg.light_wall, cfg.light_wall, cfg.light_floor, cfg.light_floor])
    assert (np.where(ok, light, want) == want).all()


# --- observation -------------------------------------------------------------------------------
def test_rbf_histogram_matches_direct_formula():
    """The observation's RBF bins equal Σ_m δ(d_m <= R) ψ_k(d_m) / norm from true positions."""
    cfg = preset("thesis")
    env = SwarmEnv(cfg, 3, 10, seed=4)
    env.reset()
    obs, *_ = env.step(np.full((3, 10, 2), 0.5))
    d = np.linalg.norm(env.pos[:, :, None] - env.pos[:, None], axis=-1)
    mu = np.linspace(0, 40, 11)
    want = np.zeros((3, 10, 11))
    for b in range(3):
        for i in range(10):
            for m in range(10):
                if m != i and d[b, i, m] <= 40:
                    want[b, i] += np.exp(-(d[b, i, m] - mu) ** 2 / (2 * 2.5 ** 2)) / 4.0
    np.testing.assert_allclose(obs[..., OBS_RBF:], want, rtol=1e-5, atol=1e-7)
    dt = np.linalg.norm(env.pos - env.target[:, None], axis=-1)
    np.testing.assert_allclose(obs[..., OBS_TARGET], np.where(dt <= 40, dt / 40, -1), rtol=1e-6)


@pytest.mark.parametrize("overrides,M", [({}, 4), ({}, 40), ({"msg_loss": 0.3}, 24),
                                         ({"dist_noise_mm": 2.0, "dist_integer": True}, 24),
                                         ({"neighbour_table_size": 3, "dist_noise_mm": 5.0}, 20),
                                         ({"neighbour_table_size": 2, "arena_half_mm": 50.0}, 30),
                                         ({"light_dropout": 0.3}, 8)])
def test_fast_observe_equals_events_path(overrides, M):
    """The fast thesis-mode observation equals sim.events.observe bit for bit (table overflow too)."""
    cfg = preset("thesis", **overrides)
    fast = SwarmEnv(cfg, 6, M, seed=11, fast_observe=True)
    slow = SwarmEnv(cfg, 6, M, seed=11, fast_observe=False)
    o1, _ = fast.reset()
    o2, _ = slow.reset()
    np.testing.assert_array_equal(o1, o2)
    rng = np.random.default_rng(1)
    most = 0  # most searcher messages one robot received in a period
    for _ in range(8):
        a = rng.random((6, M, 2))
        o1, r1, *_ = fast.step(a)
        o2, r2, *_, info = slow.step(a)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(fast.sensing, slow.sensing)
        ev = info["events"]
        s = ev.role == ROLE_SEARCHER
        most = max(most, np.bincount(ev.env[s] * M + ev.rx[s], minlength=6 * M).max())
    if cfg.neighbour_table_size <= 3:  # these cases must exercise the full-table rule
        assert most > cfg.neighbour_table_size


@pytest.mark.parametrize("overrides", [{}, {"neighbour_table_size": 3}, {"msg_period_ticks": 7, "msg_loss": 0.4},
                                       {"msg_period_ticks": 31, "neighbour_table_size": 3}])
def test_fast_observe_tick_level_equals_events_path(overrides):
    """Tick-level radio, one or several sends per period (latest distance wins, table by first
    arrival, loss and noise): the fast observation equals the events path bit for bit."""
    cfg = preset("kilobot", arena_half_mm=150.0, **overrides)
    fast = SwarmEnv(cfg, 3, 20, seed=6, fast_observe=True)
    slow = SwarmEnv(cfg, 3, 20, seed=6, fast_observe=False)
    np.testing.assert_array_equal(fast.reset()[0], slow.reset()[0])
    rng = np.random.default_rng(9)
    most = repeats = 0
    for _ in range(5):
        a = rng.random((3, 20, 2))
        o1, r1, *_ = fast.step(a)
        o2, r2, *_, info = slow.step(a)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(r1, r2)
        np.testing.assert_array_equal(fast.sensing, slow.sensing)
        ev = info["events"]
        s = ev.role == ROLE_SEARCHER
        pairs = np.unique((ev.env[s].astype(np.int64) * 20 + ev.rx[s]) * 20 + ev.sender[s])
        most = max(most, np.bincount(pairs // 20, minlength=60).max())
        repeats += s.sum() - pairs.size  # messages of a sender already heard this period
    assert (repeats > 0) == (cfg.msg_period_ticks < cfg.period_ticks)
    assert most > cfg.neighbour_table_size or cfg.neighbour_table_size > 3  # small tables overflow


def test_observe_fast_direct_call_matches_observe():
    """observe_fast on a crowded period (table overflow) equals observe on its events."""
    cfg = preset("thesis", neighbour_table_size=4)
    pos, target, flags = _thesis_setup(cfg, B=4, M=60)
    per = thesis_radio(pos, target, flags, cfg, _rngs(4))
    light = np.full((4, 60), 200, np.int16)
    prev = np.zeros((4, 60))
    o1, f1 = observe_fast(per, light, prev, cfg)
    o2, f2 = observe(per.events(), light, prev, cfg)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(f1, f2)
    counts = np.bincount(per.s_env * 60 + per.s_rx, minlength=240)
    assert counts.max() > 4  # overflow happened


def test_message_flags_are_last_step_sensing():
    """A searcher message carries the sender's sensing flag from before the step; the target's is 0."""
    cfg = preset("thesis", comm_radius_mm=120.0, rbf_hi_mm=120.0)
    env = SwarmEnv(cfg, 4, 12, seed=8)
    env.reset()
    rng = np.random.default_rng(3)
    for _ in range(4):
        before = env.sensing.copy()
        *_, info = env.step(rng.random((4, 12, 2)))
        ev = info["events"]
        s = ev.role == ROLE_SEARCHER
        np.testing.assert_array_equal(ev.flag[s], before[ev.env[s], ev.sender[s]])
        assert (ev.flag[~s] == 0).all()
        heard = np.zeros((4, 12), np.uint8)
        heard[ev.env[~s], ev.rx[~s]] = 1
        np.testing.assert_array_equal(env.sensing, heard)


def test_reset_observation_has_no_neighbour_flags():
    """At reset all flags are 0, so no observation reports a sensing neighbour; walls from light."""
    env = SwarmEnv(preset("thesis"), 8, 16, seed=5)
    obs, info = env.reset()
    assert (obs[..., OBS_NBR_SENSING] == 0).all()
    np.testing.assert_array_equal(obs[..., OBS_WALL], (info["light"] >= 500).astype(np.float32))
    dt = target_distance(env.pos, env.target)
    np.testing.assert_array_equal(info["in_range"], dt <= 40)


def test_rbf_fast_bit_identical_to_events_rbf():
    """rbf_fast (in-place passes, folded negation) equals sim.events.rbf bit for bit."""
    from sim.events import rbf
    from sim.radio import rbf_fast

    for cfg in (preset("thesis"), preset("kilobot")):
        d = np.concatenate([np.random.default_rng(0).uniform(0, 120, 5000), [0.0, 33.0, 40.0, 85.0, 85.0001]])
        np.testing.assert_array_equal(rbf_fast(cfg, d), rbf(cfg, d))
