"""Tests of the Kilobot period motion: closed form vs a per-tick reference, contacts, pushes, batching."""
from __future__ import annotations

import math

import numpy as np
import pytest

from sim.config import preset
from sim.env import SwarmEnv, env_seed_sequences
from sim.kinematics import (OVERLAP_TOL_MM, Collider, MotionParams, max_overlap, tick_move,
                            wrap_angle)
from sim.motion import MODE_LEFT, MODE_RIGHT, MODE_STRAIGHT, mode_at_tick, schedule


def _reference(pos, heading, q, cfg, motion=None):
    """Collision-free reference: step every robot tick by tick (pivot about the leg, straight, walls
    each tick).

    A pivot tick finds the leg from the pose, turns, and puts the centre back at R from the leg.
    Returns the (P, B, M, 2) positions after each tick; pos and heading are updated in place.
    """
    P = cfg.period_ticks
    turn, mode, straight = schedule(q[..., 0], q[..., 1], P)
    dphi, dl = cfg.omega_max_rad_s * cfg.tick_s, cfg.v_max_mm_s * cfg.tick_s
    one = np.ones(heading.shape)
    sp, tl, tr = (one, one, one) if motion is None else (motion.speed, motion.turn_left, motion.turn_right)
    curve = np.zeros(heading.shape) if motion is None or motion.curve is None else motion.curve
    R = cfg.pivot_offset_mm if motion is None or motion.pivot_mm is None else motion.pivot_mm
    alpha = math.radians(cfg.pivot_angle_deg)
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    rec = np.empty((P,) + pos.shape)
    for k in range(P):
        m = mode_at_tick(turn, mode, straight, k)
        for pivot, sign, rate in ((MODE_LEFT, 1.0, tl), (MODE_RIGHT, -1.0, tr)):
            on = m == pivot
            beta = sign * alpha
            leg_x, leg_y = pos[..., 0] + R * np.cos(heading + beta), pos[..., 1] + R * np.sin(heading + beta)
            heading += np.where(on, sign * dphi * rate, 0.0)
            pos[..., 0] = np.where(on, leg_x - R * np.cos(heading + beta), pos[..., 0])
            pos[..., 1] = np.where(on, leg_y - R * np.sin(heading + beta), pos[..., 1])
        st = m == MODE_STRAIGHT
        heading += np.where(st, curve, 0.0)
        step = np.where(st, dl * sp, 0.0)
        pos[..., 0] += step * np.cos(heading)
        pos[..., 1] += step * np.sin(heading)
        np.clip(pos, -lim, lim, out=pos)
        rec[k] = pos
    heading[...] = wrap_angle(heading)
    return rec


def _random_case(rng, B, M, cfg, near_walls=False):
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    pos = rng.uniform(-lim, lim, (B, M, 2))
    if near_walls:  # half of the robots within 8 mm of a wall, heading for it or along it
        side = rng.random((B, M)) < 0.5
        pos[..., 0] = np.where(side, np.sign(pos[..., 0]) * (lim - rng.uniform(0, 8, (B, M))), pos[..., 0])
    heading = rng.uniform(-math.pi, math.pi, (B, M))
    q = rng.integers(0, 256, (B, M, 2)).astype(np.uint8)
    q[:, ::3] = 255  # some full straight runs
    return pos, heading, q


PIVOTS = {"leg": {}, "centre": {"pivot_offset_mm": 0.0}, "leg 90 deg": {"pivot_angle_deg": 90.0}}


@pytest.mark.parametrize("pivot", list(PIVOTS))
@pytest.mark.parametrize("near_walls", [False, True])
def test_closed_form_equals_per_tick_reference(near_walls, pivot):
    """Without collisions the closed-form period equals stepping tick by tick (every tick, 1e-9 mm),
    for leg and centre pivots."""
    cfg = preset("kilobot", collisions=False, **PIVOTS[pivot])
    rng = np.random.default_rng(3)
    pos, heading, q = _random_case(rng, 6, 40, cfg, near_walls)
    p_ref, h_ref = pos.copy(), heading.copy()
    want = _reference(p_ref, h_ref, q, cfg)
    rec = np.empty_like(want)
    tick_move(pos, heading, q, cfg, None, None, rec)
    np.testing.assert_allclose(rec, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(pos, p_ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.cos(heading - h_ref), 1.0, atol=1e-12)
    if near_walls:
        assert (np.abs(pos) == cfg.arena_half_mm - cfg.robot_radius_mm).any()  # the walls did clip


@pytest.mark.parametrize("pivot", ["world", "per robot"])
def test_per_robot_motion_and_curvature_equal_reference(pivot):
    """Per-robot speed, turn rates, curved straights and pivot offsets (arcs, also along walls)
    match the per-tick reference."""
    cfg = preset("kilobot", collisions=False)
    rng = np.random.default_rng(8)
    B, M = 5, 30
    pos, heading, q = _random_case(rng, B, M, cfg, near_walls=True)
    motion = MotionParams(speed=rng.uniform(0.7, 1.3, (B, M)), turn_left=rng.uniform(0.7, 1.3, (B, M)),
                          turn_right=rng.uniform(0.7, 1.3, (B, M)), curve=rng.normal(0, 0.02, (B, M)),
                          pivot_mm=rng.uniform(0.0, 16.5, (B, M)) if pivot == "per robot" else None)
    for _ in range(6):  # several periods: robots meet walls at all angles
        p_ref, h_ref = pos.copy(), heading.copy()
        want = _reference(p_ref, h_ref, q, cfg, motion)
        rec = np.empty_like(want)
        tick_move(pos, heading, q, cfg, None, None, rec, motion=motion)
        np.testing.assert_allclose(rec, want, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.cos(heading - h_ref), 1.0, atol=1e-12)
        q = rng.integers(0, 256, (B, M, 2)).astype(np.uint8)


@pytest.mark.parametrize("side", ["left", "right"])
def test_leg_pivot_moves_the_centre_along_the_arc(side):
    """31 ticks of a left (right) pivot turn the heading by +(-)31 dphi about the leg at 16.5 mm and
    heading +(-)125.5 deg: the leg stays put, the centre stays 16.5 mm from it, and it ends at the
    hand-computed point, ahead and on the side of the turn."""
    cfg = preset("kilobot", collisions=False)
    assert cfg.pivot_offset_mm == 16.5 and cfg.pivot_angle_deg == 125.5
    sign = 1.0 if side == "left" else -1.0
    q = np.array([[[255, 0]]] if side == "left" else [[[0, 255]]], np.uint8)
    pos, heading = np.zeros((1, 1, 2)), np.zeros((1, 1))
    rec = np.empty((31, 1, 1, 2))
    tick_move(pos, heading, q, cfg, None, None, rec)
    dphi = cfg.omega_max_rad_s * cfg.tick_s
    turn = 31 * dphi  # 0.7978 rad = 45.7 deg
    a = math.radians(125.5)
    leg = 16.5 * np.array([math.cos(a), sign * math.sin(a)])  # (-9.582, ±13.432)
    want = leg - 16.5 * np.array([math.cos(a + turn), sign * math.sin(a + turn)])
    np.testing.assert_allclose(want, [6.7245, sign * 10.9108], atol=1e-3)  # by hand: 16.5 (cos a - cos(a + 45.7°)), ...
    np.testing.assert_allclose(heading, [[sign * turn]], atol=1e-12)
    np.testing.assert_allclose(pos[0, 0], want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(rec[:, 0, 0] - leg, axis=1), 16.5, rtol=0, atol=1e-9)
    chord = np.linalg.norm(np.diff(np.concatenate([np.zeros((1, 2)), rec[:, 0, 0]]), axis=0), axis=1)
    np.testing.assert_allclose(chord, 2 * 16.5 * math.sin(dphi / 2), rtol=1e-9)  # 13.3 mm/s along the arc
    first = rec[0, 0, 0] / np.linalg.norm(rec[0, 0, 0])  # first tick: heading ± 35.5 deg (+ dphi / 2)
    np.testing.assert_allclose(first, [math.cos(math.radians(35.5) + dphi / 2),
                                       sign * math.sin(math.radians(35.5) + dphi / 2)], atol=1e-9)


def test_arc_that_meets_a_wall_and_turns_back():
    """A left pivot next to the right wall moves the centre into the wall, then away from it: the
    closed form equals clipping every tick (not clipping the free arc once)."""
    cfg = preset("kilobot", collisions=False)
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    pos = np.array([[[lim - 0.3, 0.0]]])
    heading = np.array([[math.radians(90.0 - 35.5 - 20.0)]])  # the arc heads at 70 deg, ends at 116 deg
    q = np.array([[[255, 0]]], np.uint8)
    p_ref, h_ref = pos.copy(), heading.copy()
    want = _reference(p_ref, h_ref, q, cfg)
    free = _reference(pos.copy(), heading.copy(), q, preset("kilobot", collisions=False, arena_half_mm=1e4))
    once = np.minimum(free, lim)  # the free arc, clipped afterwards
    assert (want[:, 0, 0, 0] == lim).any() and np.abs(once - want).max() > 0.1
    rec = np.empty_like(want)
    tick_move(pos, heading, q, cfg, None, None, rec)
    np.testing.assert_allclose(rec, want, rtol=0, atol=1e-9)


def test_leg_pivot_then_straight_and_centre_pivot():
    """A pivot then straight period: the straight run starts where the arc ends, along the new
    heading; with pivot_offset_mm = 0 the pivot leaves the centre in place."""
    q = np.array([[[200, 100]]], np.uint8)  # 12 left pivot ticks, then 18 straight ticks
    dphi = math.pi / 4 / 30.52
    dl = 10.0 / 30.52
    a, h = math.radians(125.5), 12 * dphi
    arc_end = 16.5 * np.array([math.cos(a) - math.cos(a + h), math.sin(a) - math.sin(a + h)])
    for R, start in ((16.5, arc_end), (0.0, np.zeros(2))):
        cfg = preset("kilobot", collisions=False, pivot_offset_mm=R)
        pos, heading = np.zeros((1, 1, 2)), np.zeros((1, 1))
        rec = np.empty((31, 1, 1, 2))
        tick_move(pos, heading, q, cfg, None, None, rec)
        np.testing.assert_allclose(rec[11, 0, 0], start, rtol=0, atol=1e-9)
        np.testing.assert_allclose(pos[0, 0], start + 18 * dl * np.array([math.cos(h), math.sin(h)]), rtol=0, atol=1e-9)
        if R == 0.0:
            assert (rec[:12] == 0).all()


def test_contact_free_envs_take_the_closed_form_and_contacts_push():
    """In a batch, the env without contacts equals the collision-free reference; in the env where a
    robot drives into a resting one, the resting one is pushed ahead and no discs overlap."""
    cfg = preset("kilobot")
    dl = cfg.v_max_mm_s * cfg.tick_s
    pos = np.array([[[0.0, 0.0], [34.0, 0.0]], [[0.0, 0.0], [0.0, 100.0]]])
    heading = np.zeros((2, 2))
    q = np.array([[[255, 255], [0, 0]], [[255, 255], [0, 0]]], np.uint8)
    target = np.array([[-150.0, -150.0], [-150.0, -150.0]])
    p_ref, h_ref = pos.copy(), heading.copy()
    want = _reference(p_ref, h_ref, q, cfg)
    rec = np.empty_like(want)
    tick_move(pos, heading, q, cfg, Collider(cfg), target, rec)
    np.testing.assert_allclose(rec[:, 1], want[:, 1], rtol=0, atol=1e-9)  # env 1: no contact
    travel = 31 * dl  # the pusher's own travel; contact after 1 mm
    pushed = pos[0, 1, 0] - 34.0
    assert (travel - 1.0) / 2 - 0.3 < pushed < (travel - 1.0) / 2 + 0.3  # the pair moves on at half speed
    assert pos[0, 1, 0] - pos[0, 0, 0] >= 33.0 - OVERLAP_TOL_MM
    assert max_overlap(pos, target, cfg) <= OVERLAP_TOL_MM


def _crowd(seed, B=3, M=22, a=140.0):
    cfg = preset("kilobot", arena_half_mm=a)
    return cfg, SwarmEnv(cfg, B, M, seed=seed)


def test_crowded_periods_no_overlap_and_soft_contacts_inside():
    """Robots driven into a crowd: no overlap beyond OVERLAP_TOL_MM at the end of every period, and
    less than 1 mm at any tick inside it (soft contacts, see sim.kinematics)."""
    cfg, env = _crowd(1)
    env.reset()
    rng = np.random.default_rng(0)
    inside = 0.0
    for _ in range(10):
        a = rng.random((3, 22, 2)) * [0.2, 0.2] + 0.8  # mostly straight
        env.step(a)
        assert max_overlap(env.pos, env.target, cfg) <= OVERLAP_TOL_MM
        rec = np.empty((cfg.period_ticks, 3, 22, 2))
        p, h = env.pos.copy(), env.heading.copy()
        tick_move(p, h, (a * 255).astype(np.uint8), cfg, Collider(cfg), env.target.copy(), rec)
        inside = max(inside, max(max_overlap(r, None, cfg) for r in rec))
    assert 0.0 < inside < 1.0


def test_crowded_batch_equals_single_env_runs():
    """With collisions every period, env e of a batch equals the single env of its seed sequence."""
    B, M, steps = 3, 22, 6
    cfg, batch = _crowd(4, B, M)
    acts = np.random.default_rng(2).random((steps, B, M, 2)) * 0.3 + 0.7
    batch.reset()
    rec = []
    for t in range(steps):
        obs, r, *_ = batch.step(acts[t])
        rec.append((obs, r, batch.pos.copy(), batch.target.copy()))
    seqs = env_seed_sequences(4, B)
    for e in range(B):
        single = SwarmEnv(cfg, 1, M, seed=[seqs[e]])
        single.reset()
        for t in range(steps):
            obs, r, *_ = single.step(acts[t, e:e + 1])
            np.testing.assert_array_equal(obs, rec[t][0][e:e + 1])
            np.testing.assert_array_equal(r, rec[t][1][e:e + 1])
            np.testing.assert_array_equal(single.pos, rec[t][2][e:e + 1])
