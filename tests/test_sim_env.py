"""Tests of SwarmEnv: kinematics, walls, collisions, reward, seeding, batching and input checks."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sim.config import preset
from sim.env import SwarmEnv, env_seed_sequences
from sim.kinematics import RELAX_MARGIN_MM, RELAX_OMEGA, Collider, max_overlap, thesis_move, tick_move, wrap_angle
from sim.motion import action_to_u8


def _place(env, pos, heading, target=None):
    """Teleport robots of a reset env (B, M, 2) / (B, M); optional target (B, 2)."""
    env.pos[...] = pos
    env.heading[...] = heading
    if target is not None:
        env.target[...] = target


# --- kinematics --------------------------------------------------------------------------------
def test_thesis_kinematics_hand_computed():
    """Turn first, then move along the new heading: φ' = φ + k_ang ω ΔT, p' = p + k_lin v ΔT (cos φ', sin φ')."""
    cfg = preset("thesis")
    env = SwarmEnv(cfg, 1, 3, seed=0)
    env.reset()
    _place(env, [[[0, 0], [10, 20], [-30, 5]]], [[0.0, 1.0, 3.0]])
    env.step(np.array([[[1.0, 0.0], [0.2, 0.6], [1.0, 0.5]]]))
    want_h = [math.pi / 4, 1.0 - 0.4 * math.pi / 4, 3.0 + 0.5 * math.pi / 4 - 2 * math.pi]  # last one wraps
    np.testing.assert_allclose(env.heading[0], want_h, rtol=0, atol=1e-12)
    want_p = [[5 * math.cos(want_h[0]), 5 * math.sin(want_h[0])],
              [10 + 4 * math.cos(want_h[1]), 20 + 4 * math.sin(want_h[1])],
              [-30 + 7.5 * math.cos(want_h[2]), 5 + 7.5 * math.sin(want_h[2])]]
    np.testing.assert_allclose(env.pos[0], want_p, rtol=0, atol=1e-5)


def test_wrap_angle_range():
    """Headings are wrapped to (-π, π]; in-range angles are unchanged bit for bit."""
    x = np.array([math.pi, -math.pi, 3 * math.pi, -2.5, 7.0, 1e-300, -100.0])
    w = wrap_angle(x)
    assert ((w > -math.pi) & (w <= math.pi)).all()
    np.testing.assert_allclose(np.cos(w), np.cos(x), atol=1e-12)
    assert w[0] == math.pi and w[1] == math.pi and w[3] == -2.5 and w[5] == 1e-300


def test_walls_clip_centres():
    """Robot centres stop at a - r: 100 mm for thesis points, 233.5 mm for Kilobot discs."""
    cfg = preset("thesis")
    pos, head = np.array([[[99.0, 0.0], [0.0, -95.0]]]), np.array([[0.0, -math.pi / 2]])
    thesis_move(pos, head, np.ones((1, 2, 2)), cfg)
    np.testing.assert_allclose(pos, [[[100.0, 0.0], [0.0, -100.0]]], atol=1e-6)
    kb = preset("kilobot", collisions=False)
    pos, head = np.array([[[230.0, 0.0]]]), np.array([[0.0]])
    tick_move(pos, head, np.full((1, 1, 2), 255, np.uint8), kb, None, None)
    assert pos[0, 0, 0] == 250.0 - 16.5


def test_kilobot_tick_schedule_hand_computed():
    """Pivot ticks then straight ticks, per the uint8 motor schedule (centre pivot)."""
    cfg = preset("kilobot", collisions=False, pivot_offset_mm=0.0)
    env = SwarmEnv(cfg, 1, 3, seed=0)
    env.reset()
    start = np.array([[[0.0, 0.0], [50.0, 0.0], [-50.0, 0.0]]])
    _place(env, start, [[0.5, 0.5, 0.5]])
    q = np.array([[[255, 0], [128, 128], [200, 100]]], np.uint8)  # (31 L, 0) (0, 16 S) (12 L, 18 S)
    env.step_u8(q)
    dphi, dl = cfg.omega_max_rad_s * cfg.tick_s, cfg.v_max_mm_s * cfg.tick_s
    np.testing.assert_allclose(env.heading[0], [0.5 + 31 * dphi, 0.5, 0.5 + 12 * dphi], atol=1e-12)
    h2 = 0.5 + 12 * dphi
    want = [[0.0, 0.0], [50 + 16 * dl * math.cos(0.5), 16 * dl * math.sin(0.5)],
            [-50 + 18 * dl * math.cos(h2), 18 * dl * math.sin(h2)]]
    np.testing.assert_allclose(env.pos[0], want, atol=1e-5)


def test_tick_move_records_every_tick():
    """The per-tick record shows pivoting first (position fixed: centre pivot), then the straight run."""
    cfg = preset("kilobot", collisions=False, pivot_offset_mm=0.0)
    pos, head = np.zeros((1, 1, 2)), np.zeros((1, 1))
    rec = np.empty((31, 1, 1, 2))
    tick_move(pos, head, np.array([[[200, 100]]], np.uint8), cfg, None, None, rec)
    assert (rec[:12] == 0).all()
    steps = np.linalg.norm(np.diff(rec[11:31, 0, 0], axis=0), axis=1)
    np.testing.assert_allclose(steps[:18], cfg.v_max_mm_s * cfg.tick_s, rtol=1e-6)
    assert (steps[18:] == 0).all()


# --- collisions --------------------------------------------------------------------------------
def test_collider_pushes_symmetrically_and_target_is_fixed():
    """Overlapping discs are pushed apart symmetrically along the centre line (over-relaxed:
    separated by RELAX_OMEGA x (overlap + margin)); a disc on the target takes the whole push."""
    cfg = preset("kilobot")
    col = Collider(cfg)
    pos = np.array([[[0.0, 0.0], [20.0, 0.0], [100.0, 100.0]]])
    target = np.array([[100.0, 120.0]])
    assert col.resolve(pos, target) == 1
    half = (13.0 + RELAX_MARGIN_MM) * RELAX_OMEGA / 2  # overlap 33 - 20 = 13 mm
    np.testing.assert_allclose(pos[0, :2], [[-half, 0.0], [20.0 + half, 0.0]], atol=1e-9)
    np.testing.assert_allclose(pos[0, 2], [100.0, 100.0 - 2 * half], atol=1e-9)
    np.testing.assert_array_equal(target, [[100.0, 120.0]])


def test_no_overlap_after_reset_and_steps():
    """In a crowded Kilobot world no discs (nor the target) overlap after reset or any step."""
    cfg = preset("kilobot", arena_half_mm=160.0)
    env = SwarmEnv(cfg, 3, 30, seed=6)
    env.reset()
    assert max_overlap(env.pos, env.target, cfg) <= 0.0
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(8):
        env.step(rng.random((3, 30, 2)) * [1.0, 0.3] + [0.0, 0.7])  # mostly straight: pile-ups
        worst = max(worst, max_overlap(env.pos, env.target, cfg))
        assert np.abs(env.pos).max() <= 160.0 - 16.5
    assert worst <= 1e-6


def test_jam_in_corner_resolves():
    """Robots driven into a corner end the period without overlaps beyond the tolerance."""
    cfg = preset("kilobot", arena_half_mm=120.0)
    env = SwarmEnv(cfg, 1, 12, seed=1)
    env.reset()
    toward = np.arctan2(103.5 - env.pos[0, :, 1], 103.5 - env.pos[0, :, 0])  # face the corner
    env.heading[0] = toward
    for _ in range(6):
        env.step_u8(np.full((1, 12, 2), 255, np.uint8))
    assert max_overlap(env.pos, env.target, cfg) <= 1e-6


def test_spawn_too_dense_is_refused():
    """A world too small for M discs is refused with the arena size that would fit."""
    with pytest.raises(ValueError, match="arena_half_mm >="):
        SwarmEnv(preset("kilobot"), 1, 400, seed=0)


# --- reward ------------------------------------------------------------------------------------
def test_reward_hand_computed():
    """R = 5 ((Σδ/M)² - (1/M) Σ 0.01 ||a||²) with δ after the move."""
    env = SwarmEnv(preset("thesis"), 1, 4, seed=0)
    env.reset()
    _place(env, [[[10, 0], [-20, 0], [60, 0], [0, -70]]], [[math.pi / 2, 0, math.pi, 0]], target=[[0, 0]])
    a = np.array([[[1.0, 1.0], [0.0, 0.0], [0.5, 0.0], [0.0, 0.0]]])
    _, r, term, trunc, info = env.step(a)
    np.testing.assert_array_equal(info["in_range"], [[True, True, False, False]])
    assert r.shape == (1,) and r.dtype == np.float32
    assert r[0] == pytest.approx(5 * ((2 / 4) ** 2 - 0.01 * (2 + 0 + 0.25 + 0) / 4), rel=1e-6)
    assert info["coverage"][0] == 0.5 and not term.any() and not trunc.any()


def test_reward_uses_applied_u8_command():
    """In tick-level worlds the penalty uses q/255 of the quantised command actually applied."""
    env = SwarmEnv(preset("kilobot"), 1, 2, seed=0)
    env.reset()
    a = np.array([[[0.3, 0.7], [0.001, 0.999]]])
    _, r, *_ , info = env.step(a)
    u = action_to_u8(a) / 255.0
    cover = info["in_range"].mean()
    assert r[0] == pytest.approx(5 * (cover ** 2 - 0.01 * np.mean(np.sum(u * u, -1))), rel=1e-6)


# --- episodes, state, info ---------------------------------------------------------------------
def test_truncation_and_reset():
    """truncated is all-True after episode_steps; stepping on raises until reset."""
    env = SwarmEnv(preset("thesis", episode_steps=3), 2, 2, seed=0)
    env.reset()
    for k in range(3):
        _, _, term, trunc, _ = env.step(np.zeros((2, 2, 2)))
        assert trunc.tolist() == [k == 2] * 2 and not term.any()
    assert env.t == 3
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((2, 2, 2)))
    env.reset()
    assert env.t == 0


def test_state_layout_and_info():
    """state() is target xy then (x, y, φ) per robot, normalised; info has the documented keys."""
    env = SwarmEnv(preset("thesis"), 2, 3, seed=1)
    obs, info = env.reset()
    s = env.state()
    assert s.shape == (2, 11) and s.dtype == np.float32
    np.testing.assert_allclose(s[:, :2], env.target / 100, rtol=1e-6)
    np.testing.assert_allclose(s[:, 2:].reshape(2, 3, 3)[..., :2], env.pos / 100, rtol=1e-6)
    np.testing.assert_allclose(s[:, 2:].reshape(2, 3, 3)[..., 2], env.heading / math.pi, rtol=1e-6)
    assert obs.shape == (2, 3, 14) and obs.dtype == np.float32
    assert set(info) == {"in_range", "events", "light", "coverage", "success", "robot_success"}
    assert info["success"] is info["coverage"]  # localisation's success signal is its coverage
    assert "events" in info and info["light"].dtype == np.int16 and info["light"].shape == (2, 3)
    np.testing.assert_array_equal(info["coverage"], info["in_range"].mean(1))
    assert len(dict(info)["events"]) == len(info["events"])


def test_step_and_step_u8_agree():
    """Tick-level step() equals step_u8(action_to_u8(a)); thesis step_u8(q) equals step(q/255)."""
    rng = np.random.default_rng(2)
    for name in ("kilobot", "thesis"):
        e1, e2 = (SwarmEnv(preset(name), 2, 5, seed=3) for _ in range(2))
        e1.reset()
        e2.reset()
        for _ in range(3):
            a = rng.random((2, 5, 2))
            q = action_to_u8(a)
            o1, r1, *_ = e1.step(a if name == "kilobot" else q / 255.0)
            o2, r2, *_ = e2.step_u8(q)
            np.testing.assert_array_equal(o1, o2)
            np.testing.assert_array_equal(r1, r2)
            np.testing.assert_array_equal(e1.pos, e2.pos)


# --- seeding and batching ----------------------------------------------------------------------
def _run(env, steps=4, act_seed=0):
    out = []
    obs, info = env.reset()
    out += [obs, env.pos.copy(), info["events"].dist_mm]
    rng = np.random.default_rng(act_seed)
    for _ in range(steps):
        obs, r, _, _, info = env.step(rng.random((env.n_envs, env.n_robots, 2)))
        out += [obs, r, env.pos.copy(), env.heading.copy(), info["light"], info["events"].dist_mm]
    return out


@pytest.mark.parametrize("name", ["thesis", "kilobot"])
def test_same_seed_same_arrays_whatever_global_rng(name):
    """Same seed → identical arrays, whatever np.random's global state; another seed differs."""
    saved = np.random.get_state()  # the test perturbs the global RNG on purpose; leave it as found
    try:
        np.random.seed(0)
        a = _run(SwarmEnv(preset(name), 3, 8, seed=42))
        np.random.seed(999)
        np.random.random(10)
        b = _run(SwarmEnv(preset(name), 3, 8, seed=42))
    finally:
        np.random.set_state(saved)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    c = _run(SwarmEnv(preset(name), 3, 8, seed=43))
    assert not np.array_equal(a[1], c[1])


@pytest.mark.parametrize("name,overrides", [
    ("thesis", {"msg_loss": 0.2, "dist_noise_mm": 1.0, "light_dropout": 0.1}),
    ("kilobot", {}),
])
def test_batch_equals_single_env_runs(name, overrides):
    """Env e of a batch behaves exactly like a single env seeded with env_seed_sequences(seed, B)[e]."""
    cfg = preset(name, **overrides)
    B, M, steps = 3, 10, 4
    rng = np.random.default_rng(7)
    acts = rng.random((steps, B, M, 2))
    batch = SwarmEnv(cfg, B, M, seed=5)
    obs_b, info_b = batch.reset()
    rec_b = [(obs_b, info_b["events"])]
    for t in range(steps):
        obs, r, _, _, info = batch.step(acts[t])
        rec_b.append((obs, info["events"], r, batch.pos.copy()))
    seqs = env_seed_sequences(5, B)
    for e in range(B):
        single = SwarmEnv(cfg, 1, M, seed=[seqs[e]])
        obs_s, info_s = single.reset()
        rec_s = [(obs_s, info_s["events"])]
        for t in range(steps):
            obs, r, _, _, info = single.step(acts[t, e:e + 1])
            rec_s.append((obs, info["events"], r, single.pos.copy()))
        for rb, rs in zip(rec_b, rec_s):
            np.testing.assert_array_equal(rb[0][e], rs[0][0])
            evb, evs = rb[1], rs[1]
            sel = evb.env == e
            for f in ("rx", "sender", "tick", "dist_mm", "role", "flag"):
                np.testing.assert_array_equal(getattr(evb, f)[sel], getattr(evs, f))
            if len(rb) > 2:
                assert rb[2][e] == rs[2][0]
                np.testing.assert_array_equal(rb[3][e], rs[3][0])


def test_reset_with_seed_reproduces():
    """reset(seed=s) restarts the same episode."""
    env = SwarmEnv(preset("kilobot"), 2, 6, seed=1)
    o1, _ = env.reset(seed=9)
    p1 = env.pos.copy()
    env.reset()
    assert not np.array_equal(env.pos, p1)
    o2, _ = env.reset(seed=9)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(env.pos, p1)


# --- bad input ---------------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs,word", [
    ({"n_envs": 0}, "n_envs"), ({"n_robots": 0}, "n_robots"), ({"n_robots": 2.5}, "n_robots"),
    ({"seed": -1}, "seed"), ({"seed": "abc"}, "seed"), ({"cfg": "thesis"}, "WorldConfig"),
])
def test_constructor_rejects_bad_input(kwargs, word):
    """Bad constructor arguments raise ValueError naming the problem."""
    args = {"cfg": preset("thesis"), "n_envs": 2, "n_robots": 3, **kwargs}
    with pytest.raises(ValueError, match=word):
        SwarmEnv(**args)


def test_unknown_preset_is_named():
    """An unknown preset name is rejected by sim.config.preset with the choices."""
    with pytest.raises(ValueError, match="unknown preset 'kilobots'"):
        SwarmEnv(preset("kilobots"), 1, 1)


@pytest.mark.parametrize("bad,word", [
    (np.zeros((2, 3)), "shape"), (np.zeros((2, 3, 3)), "shape"), (np.full((2, 3, 2), np.nan), "NaN"),
    (np.full((2, 3, 2), np.inf), "NaN/inf"), (np.full((2, 3, 2), 1.01), r"\[0, 1\]"),
    (np.full((2, 3, 2), -0.2), r"\[0, 1\]"), (np.full((2, 3, 2), "a"), "dtype"),
])
def test_step_rejects_bad_actions(bad, word):
    """Wrong shapes, NaN/inf and out-of-range actions raise ValueError naming the problem."""
    env = SwarmEnv(preset("thesis"), 2, 3, seed=0)
    env.reset()
    with pytest.raises(ValueError, match=word):
        env.step(bad)


def test_step_tolerates_tiny_excursions_and_u8_checks():
    """Actions within 1e-6 of [0, 1] are clipped; step_u8 rejects floats, bad shapes and out-of-range ints."""
    env = SwarmEnv(preset("thesis"), 1, 2, seed=0)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros((1, 2, 2)))
    env.reset()
    env.step(np.array([[[1 + 5e-7, -5e-7], [0.5, 0.5]]]))
    with pytest.raises(ValueError, match="uint8"):
        env.step_u8(np.zeros((1, 2, 2)))
    with pytest.raises(ValueError, match="shape"):
        env.step_u8(np.zeros((1, 2), np.uint8))
    with pytest.raises(ValueError, match="0..255"):
        env.step_u8(np.full((1, 2, 2), 256, np.int32))
