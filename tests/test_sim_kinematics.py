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
    """Collision-free reference: step every robot tick by tick (pivot, straight, walls each tick).

    Returns the (P, B, M, 2) positions after each tick; pos and heading are updated in place.
    """
    P = cfg.period_ticks
    turn, mode, straight = schedule(q[..., 0], q[..., 1], P)
    dphi, dl = cfg.omega_max_rad_s * cfg.tick_s, cfg.v_max_mm_s * cfg.tick_s
    one = np.ones(heading.shape)
    sp, tl, tr = (one, one, one) if motion is None else (motion.speed, motion.turn_left, motion.turn_right)
    curve = np.zeros(heading.shape) if motion is None or motion.curve is None else motion.curve
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    rec = np.empty((P,) + pos.shape)
    for k in range(P):
        m = mode_at_tick(turn, mode, straight, k)
        st = m == MODE_STRAIGHT
        heading += np.where(m == MODE_LEFT, dphi * tl, 0.0) - np.where(m == MODE_RIGHT, dphi * tr, 0.0)
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


@pytest.mark.parametrize("near_walls", [False, True])
def test_closed_form_equals_per_tick_reference(near_walls):
    """Without collisions the closed-form period equals stepping tick by tick (every tick, 1e-9 mm)."""
    cfg = preset("kilobot", collisions=False)
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


def test_per_robot_motion_and_curvature_equal_reference():
    """Per-robot speed, turn rates and curved straights (arcs, also along walls) match the per-tick reference."""
    cfg = preset("kilobot", collisions=False)
    rng = np.random.default_rng(8)
    B, M = 5, 30
    pos, heading, q = _random_case(rng, B, M, cfg, near_walls=True)
    motion = MotionParams(speed=rng.uniform(0.7, 1.3, (B, M)), turn_left=rng.uniform(0.7, 1.3, (B, M)),
                          turn_right=rng.uniform(0.7, 1.3, (B, M)), curve=rng.normal(0, 0.02, (B, M)))
    for _ in range(6):  # several periods: robots meet walls at all angles
        p_ref, h_ref = pos.copy(), heading.copy()
        want = _reference(p_ref, h_ref, q, cfg, motion)
        rec = np.empty_like(want)
        tick_move(pos, heading, q, cfg, None, None, rec, motion=motion)
        np.testing.assert_allclose(rec, want, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.cos(heading - h_ref), 1.0, atol=1e-12)
        q = rng.integers(0, 256, (B, M, 2)).astype(np.uint8)


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
