"""The heavy body (sim/body.py): static friction against robots pushing together, and its shadow."""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from sim.body import body_depth, body_move
from sim.config import preset
from sim.env import SwarmEnv
from sim.kinematics import max_overlap
from sim.light import BODY_SHADE, lamp_field, parse_lamps
from sim.tasks.base import BeaconlessTask

K = 3  # robots needed to move the body
WORLD = dataclasses.replace(preset("kilobot"), body_radius_mm=50.0, body_friction=K - 0.5, light_dropout=0.0,
                            msg_loss=0.0, obs_features="target,rbf")


class _Pushers(BeaconlessTask):
    """Robots on the body's -x rim, heading at its centre (the body at the origin)."""

    name = "pushers_test"
    beacon = True
    features = ("target", "rbf")

    def __init__(self, n: int) -> None:
        self.n = n

    def spawn(self, env):
        rim = WORLD.body_radius_mm + WORLD.robot_radius_mm + 0.1
        ang = math.pi + np.radians(30.0) * (np.arange(self.n) - (self.n - 1) / 2)  # 30 degrees apart: no overlaps
        pos = np.stack([rim * np.cos(ang), rim * np.sin(ang)], -1)
        return np.zeros((1, 2)), pos[None].copy(), (ang[None] - math.pi).copy()

    def step_info(self, env):
        return {"success": np.zeros(env.n_envs)}


def _push(n: int, periods: int = 10) -> tuple[np.ndarray, SwarmEnv]:
    env = SwarmEnv(WORLD, 1, n, seed=0, task=_Pushers(n))
    env.reset()
    for _ in range(periods):
        env.step(np.ones((1, n, 2)))
    return env.target[0].copy(), env


def test_k_minus_one_pushers_leave_the_body_in_place():
    """K - 1 robots driving straight into the body for 10 periods do not move it, and stay off it."""
    body, env = _push(K - 1)
    np.testing.assert_array_equal(body, [0.0, 0.0])
    assert body_depth(env.pos, env.target, WORLD)[0].max() == 0.0


def test_k_pushers_move_the_body():
    """K robots pushing the same way move the body forwards (+x), and no discs overlap afterwards."""
    body, env = _push(K)
    assert body[0] > 1.0 and abs(body[1]) < 0.1
    assert body_depth(env.pos, env.target, WORLD)[0].max() == 0.0
    assert max_overlap(env.pos, None, WORLD) < 1e-3


def test_body_move_is_the_excess_over_friction():
    """k aligned full pushes move the body by (1 - friction / k) of their depth; friction or less: not at all."""
    d_full = WORLD.v_max_mm_s * WORLD.control_period_s
    for k in range(1, 7):
        depth = np.full((1, k), d_full)
        normal = np.tile([1.0, 0.0], (1, k, 1))
        move = body_move(depth, normal, WORLD)[0]
        want = max(1.0 - WORLD.body_friction / k, 0.0) * d_full
        np.testing.assert_allclose(move, [want, 0.0], atol=1e-12)


def test_body_shadow_darkens_the_floor_behind_it():
    """Behind the body (seen from a side lamp) the lamp's light drops by BODY_SHADE; beside and before it, not."""
    lamps = parse_lamps("side:0,600", "test")
    body = np.array([[0.0, 0.0]])
    pts = np.array([[[-80.0, 0.0], [-80.0, 60.0], [80.0, 0.0], [-80.0, -49.0]]])
    lit = lamp_field(pts, lamps, 250.0)
    shaded = lamp_field(pts, lamps, 250.0, body=body, body_radius=50.0)
    np.testing.assert_allclose(shaded[0], lit[0] * [1 - BODY_SHADE, 1, 1, 1 - BODY_SHADE])
