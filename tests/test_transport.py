"""The transport task (sim/tasks/transport.py): its world, its sensing, cooperation being needed, its metrics."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kiloforge.errors import InputError
from sim.config import preset
from sim.env import SwarmEnv
from sim.light import BODY_SHADE
from sim.radio import light_readings
from sim.rollout import rollout
from sim.tasks import get_task
from sim.tasks.transport import LAMP_PEAK, PUSHERS, START_DISTANCE_MM, TransportMetrics

TASK = get_task("transport")
WORLD = TASK.world(preset("kilobot"))


def test_transport_is_registered_with_its_world():
    """--task transport gives a beacon world with the heavy object, a side lamp and friction between k - 1 and k pushes."""
    assert TASK.name == "transport" and TASK.beacon and WORLD.emitter
    assert WORLD.body_radius_mm > 0 and PUSHERS - 1 < WORLD.body_friction < PUSHERS
    assert WORLD.lamps.startswith("side:") and WORLD.features == ("light", "target", "rbf")
    TASK.check_world(WORLD)
    with pytest.raises(InputError, match="heavy body"):
        TASK.check_world(dataclasses.replace(preset("kilobot"), obs_features=WORLD.obs_features))
    with pytest.raises(InputError, match="needs a world where robot discs collide"):
        TASK.world(preset("thesis"))


def test_readings_behind_the_object_are_in_its_shadow():
    """A robot behind the object (seen from the lamp) reads BODY_SHADE less of the lamp than one beside it."""
    w = dataclasses.replace(WORLD, light_noise=0.0, light_gain_spread=0.0, light_offset_spread=0.0,
                            light_dropout=0.0)
    body = np.array([[-50.0, 0.0]])
    pos = np.array([[[-130.0, 0.0], [-130.0, 70.0]]])  # same x: same lamp light without the object
    lamp = LAMP_PEAK * 0.5 * (1 + (-130.0) / w.arena_half_mm)
    rngs = [np.random.default_rng(0)]
    got = light_readings(pos, w, rngs, body=body)[0]
    np.testing.assert_array_equal(got, np.rint([w.light_floor + (1 - BODY_SHADE) * lamp, w.light_floor + lamp]))
    np.testing.assert_array_equal(light_readings(pos, w, rngs)[0], np.rint([w.light_floor + lamp] * 2))


def test_object_starts_its_start_distance_short_of_the_goal_zone():
    """Every episode's object starts START_DISTANCE_MM short of the goal line (progress 0), inside the arena."""
    env = SwarmEnv(WORLD, 16, 4, seed=3, task=TASK)
    env.reset(seed=3)
    short = TASK.goal_along(WORLD) - env.body_start[:, 0]  # the lamp is at the +x wall
    assert np.all((START_DISTANCE_MM[0] <= short) & (short <= START_DISTANCE_MM[1]))
    assert np.all(np.abs(env.body_start) <= WORLD.arena_half_mm - WORLD.body_radius_mm)
    np.testing.assert_array_equal(TASK.step_info(env)["success"], 0.0)
    with pytest.raises(InputError, match="no room for the object's start"):
        TASK.check_world(dataclasses.replace(WORLD, arena_half_mm=150.0))


@pytest.mark.parametrize("robots", [1, 2])
def test_one_or_two_robots_never_move_the_object(robots):
    """With fewer than k robots the object stays exactly where it started, whatever they do."""
    for policy in ("shadow_pusher", "random"):
        env = SwarmEnv(dataclasses.replace(WORLD, episode_steps=150), 8, robots, seed=0, task=TASK)
        res = rollout(env, TASK.make_baseline(policy, env.cfg), 8, seed=5)
        np.testing.assert_array_equal(res.success, 0.0)
        np.testing.assert_array_equal(env.target, env.body_start)


def test_metrics_report_displacement_and_success_rate():
    """final_displacement is the mean over the last quarter; success_rate counts episodes ending in the goal zone."""
    success = np.array([[0.0, 0.2, 0.6, 1.0], [0.0, 0.1, 0.2, 0.3]])
    m = TASK.episode_metrics(WORLD, 16, np.zeros_like(success), success, None)
    assert isinstance(m, TransportMetrics)
    np.testing.assert_allclose(m.per_episode("final_displacement"), [1.0, 0.3])
    np.testing.assert_allclose(m.per_episode("success_rate"), [1.0, 0.0])
    assert m.summary()["success_rate"].mean == 0.5 and m.to_dict()["per_episode"]["success_rate"] == [1.0, 0.0]
