"""The target beacon as a body: taped down (kilobot preset) or pushed by collisions, and the task follows it."""
from __future__ import annotations

import numpy as np
import pytest

from sim.baselines import make_policy
from sim.config import OBS_TARGET, preset
from sim.env import SwarmEnv
from sim.kinematics import OVERLAP_TOL_MM, max_overlap
from sim.radio import tick_radio
from sim.rollout import rollout


def test_presets_choose_the_beacon():
    """The kilobot preset's beacon is taped down, as the thesis target is fixed."""
    assert preset("kilobot").emitter_mobility == 0.0
    assert preset("thesis").emitter_mobility == 0.0
    with pytest.raises(ValueError, match="emitter_mobility"):
        preset("kilobot", emitter_mobility=1.5)


def test_world_dicts_of_older_artifacts_are_unchanged():
    """A fixed beacon and a centre pivot are not serialised (older artifacts' worlds and hashes stay
    the same, and load as taped beacon + centre pivot); a pushable beacon and a leg pivot are, and
    every world round-trips."""
    from sim.config import WorldConfig

    old = preset("kilobot", emitter_mobility=0.0, pivot_offset_mm=0.0)  # the world older artifacts hold
    d = old.to_dict()
    assert not {"beacon_mobility", "pivot_offset_mm", "pivot_angle_deg"} & set(d)  # world-JSON keys (sim.compat)
    assert WorldConfig.from_dict(d).emitter_mobility == 0.0 and WorldConfig.from_dict(d).pivot_offset_mm == 0.0
    new, pushed = preset("kilobot"), preset("kilobot", emitter_mobility=1.0)
    assert "beacon_mobility" not in new.to_dict() and new.to_dict()["pivot_offset_mm"] == 16.5
    assert pushed.to_dict()["beacon_mobility"] == 1.0
    for w in (old, new, pushed, preset("kilobot", pivot_angle_deg=90.0)):
        assert WorldConfig.from_dict(w.to_dict()) == w


def _pusher(mobility):
    """A robot driving straight at the beacon from 34 mm; a second robot just outside its range."""
    cfg = preset("kilobot", emitter_mobility=mobility, msg_loss=0.0, dist_noise_mm=0.0, light_dropout=0.0)
    env = SwarmEnv(cfg, 1, 2, seed=0)
    env.reset()
    env.pos[...] = [[[-34.0, 0.0], [86.0, 0.0]]]
    env.heading[...] = 0.0
    env.target[...] = [[0.0, 0.0]]
    return cfg, env


@pytest.mark.parametrize("mobility", [0.0, 1.0])
def test_pushed_beacon_moves_fixed_beacon_stays(mobility):
    """Driving into the beacon pushes it ahead at half the pusher's speed when it is mobile, not at
    all when fixed; no discs overlap either way."""
    cfg, env = _pusher(mobility)
    q = np.array([[[255, 255], [0, 0]]], np.uint8)
    for _ in range(3):
        env.step_u8(q)
        assert max_overlap(env.pos, env.target, cfg) <= OVERLAP_TOL_MM
    travel = 3 * 31 * cfg.v_max_mm_s * cfg.tick_s  # 30.5 mm, contact from the first tick
    if mobility == 0.0:
        np.testing.assert_array_equal(env.target, [[0.0, 0.0]])
        assert env.pos[0, 0, 0] <= -33.0 + OVERLAP_TOL_MM  # the pusher is held back
    else:
        assert travel / 2 - 1.0 < env.target[0, 0] < travel / 2 + 1.0
        assert abs(env.target[0, 1]) < 1e-9
        assert env.target[0, 0] - env.pos[0, 0, 0] >= 33.0 - OVERLAP_TOL_MM


def test_task_observations_and_state_follow_the_pushed_beacon():
    """After the beacon is pushed towards robot 1, robot 1 is in range, hears the beacon at its new
    distance, coverage and reward count it, and the critic state holds the new position."""
    cfg, env = _pusher(1.0)
    obs, r, *_, info = env.step_u8(np.array([[[255, 255], [0, 0]]], np.uint8))
    bx = env.target[0, 0]
    assert 86.0 - bx < cfg.comm_radius_mm < 86.0  # robot 1 was out of range before the push
    np.testing.assert_array_equal(info["in_range"], [[True, True]])
    assert info["coverage"][0] == 1.0
    assert r[0] == pytest.approx(cfg.reward_scale * (1.0 - cfg.action_penalty * (2 / 2)), rel=1e-6)
    ev = info["events"]
    heard = (ev.sender == -1) & (ev.rx == 1)
    assert heard.any()
    assert obs[0, 1, OBS_TARGET] >= 0  # heard this period, at the beacon's distance when it sent
    assert abs(obs[0, 1, OBS_TARGET] * cfg.comm_radius_mm - (86.0 - bx)) <= 4.0  # moved <= 3.3 mm this period
    np.testing.assert_allclose(env.state()[0, :2], env.target[0] / cfg.arena_half_mm, rtol=1e-6)

    cfg, fixed = _pusher(0.0)
    _, _, *_, info = fixed.step_u8(np.array([[[255, 255], [0, 0]]], np.uint8))
    np.testing.assert_array_equal(info["in_range"], [[True, False]])


def test_tick_radio_uses_the_beacon_position_at_the_send_tick():
    """Target messages are measured from where the beacon was at the tick it sent."""
    cfg = preset("kilobot", msg_loss=0.0, dist_noise_mm=0.0, msg_period_ticks=5)
    P = cfg.period_ticks
    pos = np.zeros((P, 1, 1, 2))  # one receiver at the origin
    track = np.zeros((P, 1, 2))
    track[:, 0, 0] = 40.0 + np.arange(P)  # the beacon moves 1 mm per tick
    per = tick_radio(pos, track[-1], np.zeros((1, 2), np.int64), 0, np.zeros((1, 1), np.uint8), cfg,
                     [np.random.default_rng(0)], target_ticks=track)
    np.testing.assert_array_equal(per.t_tick, [0, 5, 10, 15, 20, 25, 30])
    np.testing.assert_array_equal(per.t_dist, 40.0 + per.t_tick)


def test_rollout_records_the_beacon_track():
    """A rollout of the searcher in the kilobot world with an untaped beacon records the pushed
    beacon's positions, and its in-range flags are measured from them."""
    cfg = preset("kilobot", episode_steps=120, arena_half_mm=150.0, emitter_mobility=1.0)
    res = rollout(SwarmEnv(cfg, 2, 12, seed=1), make_policy("baseline", cfg), 2, seed=3, record=True)
    tr = res.trajectories
    assert tr.target.shape == (2, 121, 2)
    moved = np.linalg.norm(tr.target[:, -1] - tr.target[:, 0], axis=-1)
    assert moved.max() > 1.0  # searchers crowding the beacon pushed it
    d = np.linalg.norm(tr.positions - tr.target[:, :, None, :], axis=-1)
    clear = np.abs(d - cfg.comm_radius_mm) > 1e-3
    np.testing.assert_array_equal(tr.in_range[clear], (d <= cfg.comm_radius_mm)[clear])
