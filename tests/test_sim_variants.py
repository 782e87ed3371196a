"""World variants and domain randomisation (sim.variants), and the robustness runner (sim.robustness)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sim.baselines import make_policy
from sim.config import OBS_WALL, preset
from sim.env import SwarmEnv, env_seed_sequences
from sim.robustness import run_suite
from sim.variants import RANDOMISATIONS, Randomisation, robustness_suite


def _free_robot(cfg, randomise=None, heading=0.0, B=1, M=1, seed=0):
    """Env(s) with robots far from everything (no contacts within a period)."""
    env = SwarmEnv(cfg, B, M, seed=seed, randomise=randomise)
    env.reset()
    env.pos[...] = np.stack([np.linspace(-150, 150, M), np.full(M, -100.0)], -1)[None]
    env.heading[...] = heading
    env.target[...] = [150.0, 150.0]
    return env


def _straight_displacement(cfg, randomise=None):
    env = _free_robot(cfg, randomise)
    p0 = env.pos.copy()
    env.step_u8(np.full((1, 1, 2), 255, np.uint8))
    return float(np.linalg.norm(env.pos - p0)), env


def test_nominal_randomisation_is_the_nominal_world():
    """Randomisation() draws nothing: the same arrays as no randomisation, step after step."""
    cfg = preset("kilobot", arena_half_mm=150.0)
    a = SwarmEnv(cfg, 3, 12, seed=4)
    b = SwarmEnv(cfg, 3, 12, seed=4, randomise=RANDOMISATIONS["none"])
    np.testing.assert_array_equal(a.reset()[0], b.reset()[0])
    rng = np.random.default_rng(0)
    for _ in range(4):
        u = rng.random((3, 12, 2))
        o1, r1, *_ = a.step(u)
        o2, r2, *_ = b.step(u)
        np.testing.assert_array_equal(o1, o2)
        np.testing.assert_array_equal(a.pos, b.pos)


@pytest.mark.parametrize("f", [0.7, 1.3])
def test_speed_variant_scales_the_displacement(f):
    """Speed x f (per-env randomisation or the suite's config variant) moves a straight run f x as far."""
    cfg = preset("kilobot")
    nominal, _ = _straight_displacement(cfg)
    drawn, env = _straight_displacement(cfg, Randomisation(speed=(f, f)))
    assert drawn == pytest.approx(f * nominal, rel=1e-9)
    np.testing.assert_allclose(env.world_draw.motion.speed, f)
    suite_cfg, rand = robustness_suite(cfg)[f"speed {f - 1:+.0%}"]
    assert rand is None
    assert _straight_displacement(suite_cfg)[0] == pytest.approx(f * nominal, rel=1e-9)


def test_turn_variant_scales_the_pivot():
    """Turn rate x 0.7 pivots 0.7 x as far in a period of pivoting (both directions)."""
    cfg = preset("kilobot")
    for q in ([255, 0], [0, 255]):
        turned = []
        for rand in (None, Randomisation(turn=(0.7, 0.7))):
            env = _free_robot(cfg, rand)
            env.step_u8(np.array([[q]], np.uint8))
            turned.append(abs(env.heading[0, 0]))
        assert turned[1] == pytest.approx(0.7 * turned[0], rel=1e-9)


def test_calibration_spread_gives_each_robot_its_own_motion():
    """Per-robot spread: speeds, pivot rates and curvatures differ between robots with the asked spread,
    and a curving robot's straight run changes its heading."""
    cfg = preset("kilobot")
    env = _free_robot(cfg, Randomisation(speed_spread=0.1, turn_spread=0.1, curve_deg_s=2.0), B=20, M=10)
    m = env.world_draw.motion
    assert m.speed.shape == (20, 10)
    assert 0.08 < m.speed.std() < 0.12 and 0.08 < m.turn_left.std() < 0.12
    per_s = np.degrees(m.curve / cfg.tick_s)  # deg per second of straight driving
    assert 1.6 < per_s.std() < 2.4
    h0 = env.heading.copy()
    env.step_u8(np.full((20, 10, 2), 255, np.uint8))
    np.testing.assert_allclose(env.heading - h0, 31 * m.curve, atol=1e-12)


def test_graded_motors_follow_each_wheels_drive():
    """Graded motors: straight speed is the mean wheel drive, each pivot its wheel's drive, and a
    stronger left motor curves a straight run counter-clockwise; all-or-nothing motors ignore the wheels."""
    cfg = preset("kilobot")
    env = _free_robot(cfg, Randomisation(motors="graded", wheel_spread=0.1), B=10, M=10)
    m = env.world_draw.motion
    np.testing.assert_allclose(m.speed, (m.turn_left + m.turn_right) / 2, rtol=1e-12)
    want = (m.turn_left - m.turn_right) / 2 * cfg.omega_max_rad_s * cfg.tick_s
    np.testing.assert_allclose(m.curve, want, rtol=1e-12)
    assert (np.sign(m.curve) == np.sign(m.turn_left - m.turn_right)).all()
    binary = _free_robot(cfg, Randomisation(motors="binary", wheel_spread=0.1), B=10, M=10)
    assert binary.world_draw.motion is None  # a running motor gives exactly its calibrated effect


def test_message_period_success_and_noise_variants():
    """Message period 15: each transmitter sends every 15 ticks; success 0.6: 40 % of the messages
    lost; distance noise σ: measured minus true distances scatter by σ."""
    cfg = preset("kilobot", arena_half_mm=120.0, msg_loss=0.0, dist_noise_mm=0.0, dist_integer=False)
    env = SwarmEnv(cfg, 4, 8, seed=1, randomise=Randomisation(msg_period=(15, 15)))
    env.reset()
    sends = []  # (env, receiver, sender, global tick) of everything heard while nobody moves
    for k in range(4):
        *_, info = env.step(np.zeros((4, 8, 2)))
        ev = info["events"]
        sends.append(np.stack([ev.env, ev.rx, ev.sender, k * cfg.period_ticks + ev.tick.astype(np.int64)], -1))
    s = np.concatenate(sends)
    s = s[np.lexsort((s[:, 3], s[:, 2], s[:, 1], s[:, 0]))]
    same = (s[1:, :3] == s[:-1, :3]).all(axis=1)  # consecutive messages of one sender at one receiver
    gaps = np.diff(s[:, 3])[same]
    assert gaps.size > 100 and (gaps == 15).all()

    counts = []
    for rand in (None, Randomisation(msg_success=(0.6, 0.6))):
        env = SwarmEnv(cfg, 4, 8, seed=1, randomise=rand)
        env.reset()
        counts.append(sum(len(env.step(np.zeros((4, 8, 2)))[-1]["events"]) for _ in range(5)))
    assert abs(counts[1] / counts[0] - 0.6) < 0.05

    env = SwarmEnv(cfg, 4, 8, seed=1, randomise=Randomisation(dist_noise_mm=(4.0, 4.0)))
    env.reset()
    *_, info = env.step(np.zeros((4, 8, 2)))
    ev = info["events"]
    s = ev.sender >= 0
    true = np.linalg.norm(env.pos[ev.env[s], ev.rx[s]] - env.pos[ev.env[s], ev.sender[s]], axis=-1)
    err = ev.dist_mm[s] - true
    assert s.sum() > 100 and 3.3 < err[true < 80].std() < 4.7


def test_light_variants_move_the_wall_zone():
    """Dim light halves the wall zone (a robot 30 mm from the wall no longer sees it), bright light
    widens it; uneven light draws a zone per wall."""
    cfg = preset("kilobot", light_dropout=0.0)
    suite = robustness_suite(cfg)
    flags = {}
    for name in ("nominal", "dim light", "bright light"):
        w, _ = suite[name]
        env = _free_robot(w, M=3)
        env.pos[...] = [[[250 - 30, 0.0], [0.0, 250 - 50], [-250 + 15, 0.0]]]
        obs, *_ = env.step_u8(np.zeros((1, 3, 2), np.uint8))
        flags[name] = obs[0, :, OBS_WALL].tolist()
    assert flags == {"nominal": [1, 0, 1], "dim light": [0, 0, 1], "bright light": [1, 1, 1]}
    env = _free_robot(cfg, Randomisation(wall_zone=(0.5, 1.5)), B=50)
    z = env.world_draw.wall_zone_mm
    assert z.shape == (50, 4) and z.min() >= 20 and z.max() <= 60 and z.std() > 5


def test_beacon_mobility_per_env():
    """emitter_mobility (0, 0) tapes every beacon down even in a pushed-beacon world."""
    cfg = preset("kilobot", emitter_mobility=1.0)
    env = SwarmEnv(cfg, 2, 1, seed=0, randomise=Randomisation(emitter_mobility=(0.0, 0.0)))
    env.reset()
    env.pos[...] = [[[-34.0, 0.0]], [[-34.0, 0.0]]]
    env.heading[...] = 0.0
    env.target[...] = 0.0
    env.step_u8(np.full((2, 1, 2), 255, np.uint8))
    np.testing.assert_array_equal(env.target, 0.0)
    np.testing.assert_array_equal(env.world_draw.emitter_mobility, [0.0, 0.0])


def test_free_beacon_randomisation_pushes_every_beacon():
    """The 'table-free-beacon' randomisation is 'table' except that every env's beacon is pushed like a robot."""
    free, table = RANDOMISATIONS["table-free-beacon"], RANDOMISATIONS["table"]
    assert dataclasses.replace(free, emitter_mobility=table.emitter_mobility) == table
    env = SwarmEnv(preset("kilobot"), 2, 1, seed=0, randomise=free)
    env.reset()
    np.testing.assert_array_equal(env.world_draw.emitter_mobility, [1.0, 1.0])
    env.pos[...] = [[[-34.0, 0.0]], [[-34.0, 0.0]]]
    env.heading[...] = 0.0
    env.target[...] = 0.0
    env.step_u8(np.full((2, 1, 2), 255, np.uint8))
    assert np.all(env.target[:, 0] > 0.5)  # pushed along +x by the robot driving into it


def test_pivot_offset_per_robot():
    """pivot_offset_mm draws each robot's pivot distance in the range; a robot drawn 0 pivots in
    place and one drawn 16.5 mm moves its centre along the leg's arc, as in the world of that offset."""
    cfg = preset("kilobot", collisions=False, msg_loss=0.0)
    env = SwarmEnv(cfg, 40, 2, seed=3, randomise=Randomisation(pivot_offset_mm=(0.0, 16.5)))
    env.reset()
    piv = env.world_draw.motion.pivot_mm
    assert piv.shape == (40, 2) and piv.min() >= 0.0 and piv.max() <= 16.5 and piv.std() > 3.0
    env.world_draw.motion.pivot_mm[0] = [0.0, 16.5]
    env.pos[0] = [[-100.0, 0.0], [100.0, 0.0]]
    env.heading[0] = 0.0
    start = env.pos[0].copy()
    env.step_u8(np.tile(np.array([255, 0], np.uint8), (40, 2, 1)))
    np.testing.assert_array_equal(env.pos[0, 0], start[0])
    leg = SwarmEnv(cfg, 1, 1, seed=0)
    leg.reset()
    leg.pos[...], leg.heading[...] = start[1], 0.0
    leg.step_u8(np.array([[[255, 0]]], np.uint8))
    np.testing.assert_allclose(env.pos[0, 1], leg.pos[0, 0], rtol=0, atol=1e-9)
    assert np.linalg.norm(env.pos[0, 1] - start[1]) > 10.0


def test_randomisation_reproducible_and_env_e_equals_single_env():
    """Same seed, same draws and arrays; env e of a batch equals the single env of its seed sequence;
    every reset draws anew; spawns equal the nominal world's."""
    cfg = preset("kilobot", arena_half_mm=200.0)
    table = RANDOMISATIONS["table"]
    B, M = 3, 10
    acts = np.random.default_rng(5).random((4, B, M, 2))
    batch = SwarmEnv(cfg, B, M, seed=7, randomise=table)
    batch.reset()
    nominal = SwarmEnv(cfg, B, M, seed=7)
    nominal.reset()
    np.testing.assert_array_equal(batch.pos, nominal.pos)
    d = batch.world_draw
    rec = [batch.step(a)[0] for a in acts]
    again = SwarmEnv(cfg, B, M, seed=7, randomise=table)
    again.reset()
    np.testing.assert_array_equal(again.world_draw.motion.speed, d.motion.speed)
    np.testing.assert_array_equal(again.world_draw.msg_period, d.msg_period)
    np.testing.assert_array_equal(again.world_draw.motion.pivot_mm, d.motion.pivot_mm)
    assert table.pivot_offset_mm == (0.0, 16.5) and 0.0 <= d.motion.pivot_mm.min() < d.motion.pivot_mm.max() <= 16.5
    for t, a in enumerate(acts):
        np.testing.assert_array_equal(again.step(a)[0], rec[t])
    seqs = env_seed_sequences(7, B)
    for e in range(B):
        single = SwarmEnv(cfg, 1, M, seed=[seqs[e]], randomise=table)
        single.reset()
        np.testing.assert_array_equal(single.world_draw.motion.turn_left[0], d.motion.turn_left[e])
        np.testing.assert_array_equal(single.world_draw.wall_zone_mm[0], d.wall_zone_mm[e])
        for t, a in enumerate(acts):
            np.testing.assert_array_equal(single.step(a[e:e + 1])[0], rec[t][e:e + 1])
    batch.reset()
    assert not np.array_equal(batch.world_draw.motion.speed, d.motion.speed)
    other = SwarmEnv(cfg, B, M, seed=8, randomise=table)
    other.reset()
    assert not np.array_equal(other.world_draw.dist_noise_mm, d.dist_noise_mm)


def test_randomisation_checks():
    """Bad ranges and motion variations in a world without the motor schedule are refused."""
    with pytest.raises(ValueError, match="speed"):
        Randomisation(speed=(1.2, 0.8))
    with pytest.raises(ValueError, match="motors"):
        Randomisation(motors="stepper")
    with pytest.raises(ValueError, match="msg_success"):
        Randomisation(msg_success=(0.0, 1.0))
    with pytest.raises(ValueError, match="tick-level"):
        SwarmEnv(preset("thesis"), 1, 2, randomise=Randomisation(speed=(0.7, 1.3)))
    with pytest.raises(ValueError, match="tick-level"):
        robustness_suite(preset("thesis"))


def test_suite_lists_the_table_variants():
    """The suite holds nominal and every variant the issue names, each a valid world."""
    suite = robustness_suite(preset("kilobot"))
    want = {"nominal", "speed -30%", "speed +30%", "turn rate -30%", "turn rate +30%", "calibration spread",
            "graded motors", "msg period 15", "msg period 17", "msg success 0.6", "msg success 1.0",
            "dist noise 0 mm", "dist noise 6 mm", "dim light", "bright light", "uneven light", "centre pivot",
            "beacon pushed"}
    assert set(suite) == want and next(iter(suite)) == "nominal"
    assert suite["msg period 17"][0].msg_period_ticks == 17
    assert suite["msg success 0.6"][0].msg_loss == pytest.approx(0.4)
    assert suite["beacon pushed"][0].emitter_mobility == 1.0 and suite["centre pivot"][0].pivot_offset_mm == 0.0
    old = robustness_suite(preset("kilobot", emitter_mobility=1.0, pivot_offset_mm=0.0))  # the other way round
    assert old["beacon fixed"][0].emitter_mobility == 0.0 and old["leg pivot"][0].pivot_offset_mm == 16.5
    assert math.isclose(suite["turn rate +30%"][0].omega_max_rad_s, 1.3 * math.pi / 4)


def test_robustness_runner_tiny():
    """The runner evaluates a policy factory in each variant at each robot count: summaries, ratios
    to nominal (1 for nominal itself), a markdown table; the same seed gives the same table."""
    cfg = preset("kilobot", arena_half_mm=150.0)
    full = robustness_suite(cfg)
    suite = {k: full[k] for k in ("nominal", "speed -30%", "graded motors", "msg success 0.6")}
    kw = dict(robots=(2, 3), episodes=2, steps=30, seed=1, suite=suite)
    t = run_suite(lambda w: make_policy("baseline", w), cfg, **kw)
    assert set(t.cells) == set(suite) and all(set(row) == {2, 3} for row in t.cells.values())
    assert t.fraction("nominal", 2) == 1.0 and t.cells["speed -30%"][3].n == 2
    md = t.format()
    assert md.count("\n") == 1 + len(suite) and "graded motors" in md
    d = t.to_dict()
    assert d["final_coverage"]["msg success 0.6"]["2"]["n"] == 2
    again = run_suite(lambda w: make_policy("baseline", w), cfg, **kw)
    assert again.to_dict() == d
    worst, frac = t.worst(2)
    assert worst in suite and (frac is None or frac <= 1.0)
    random = run_suite(lambda w: make_policy("random", w), cfg, **kw)
    assert set(random.cells) == set(suite)
