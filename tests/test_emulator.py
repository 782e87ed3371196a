"""The firmware emulator: receive rules, queue, observation, history, schedule, beacon, sim timing."""
from __future__ import annotations

import numpy as np
import pytest

from export.contract import firmware as fwspec
from export.contract.crc import crc16_mcrf4xx
from export.verify.emulator import FirmwareEmulator, FirmwareInputs, events_from_sim, n_control_steps
from export.contract.firmware import EVENT_DTYPE
from tests.fixtures import synthetic_qpolicy
from sim.config import ACTION_DIM, OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL, preset
from sim.events import HeardEvents
from sim.motion import MODE_LEFT, MODE_RIGHT, MODE_STRAIGHT, mode_at_tick, schedule

WORLD = preset("kilobot", period_ticks=8, neighbour_table_size=4)


def _events(rows) -> np.ndarray:
    """EVENT_DTYPE array from (robot, tick, uid, role, flag, dist[, type, version]) tuples."""
    ev = np.zeros(len(rows), EVENT_DTYPE)
    for i, r in enumerate(rows):
        robot, tick, uid, role, flag, dist = r[:6]
        typ, ver = (r[6], r[7]) if len(r) > 6 else (fwspec.DEFAULT_MSG_TYPE, fwspec.MSG_VERSION)
        ev[i] = (robot, tick, uid, role, flag, typ, ver, dist, 0)
    return ev


def _emu(qp, uids=(1, 2, 3), **kw) -> FirmwareEmulator:
    return FirmwareEmulator(qp, np.array(uids), **kw)


@pytest.fixture(scope="module")
def qp():
    return synthetic_qpolicy(WORLD, 3, (8,), ("elu",), seed=5)


def test_queue_keeps_the_first_messages_of_a_tick(qp):
    """Of the messages of ours in one tick only the first RXQ_CAPACITY are queued; foreign ones take no slot."""
    cap = fwspec.RXQ_CAPACITY
    rows = [(0, 3, 100 + i, 0, 0, 50, 0x05, 1) for i in range(3)]  # foreign type first
    rows += [(0, 3, 200 + i, 0, 0, 50) for i in range(cap + 4)]  # then more than the queue holds
    rows += [(0, 3, 300, 0, 0, 50, fwspec.DEFAULT_MSG_TYPE, 7)]  # malformed version byte
    rows += [(0, 4, 400, 0, 0, 50)]  # the next tick has room again
    acc = _emu(qp).accepted(_events(rows))
    assert acc["uid"].tolist() == [200 + i for i in range(cap)] + [400]


def test_beacons_ignore_messages(qp):
    """A robot whose uid is a target uid queues nothing."""
    emu = _emu(qp, uids=(WORLD.emitter_uid, 5))
    acc = emu.accepted(_events([(0, 1, 9, 0, 0, 40), (1, 1, 9, 0, 0, 40)]))
    assert acc["robot"].tolist() == [1]


def _run_one_period(qp, rows, light=600):
    """Deliver rows during the listening period, run control step 1; returns (q, obs, emulator)."""
    emu = _emu(qp, uids=(1,))
    emu.tick_outputs(WORLD.period_ticks)
    emu.deliver(_events(rows))
    q, obs = emu.control_step(np.array([light]))
    return q, obs, emu


def test_neighbour_table_rules(qp):
    """First arrivals get entries up to the table size; later messages of known senders overwrite."""
    rbf = qp.rbf_table.astype(np.int64)
    # senders 11..15 in order; the table holds 4: sender 15 is dropped; 12 is heard again later
    rows = [(0, t, 10 + t, 0, 0, 40 + t) for t in range(1, 6)] + [(0, 7, 12, 0, 1, 60)]
    q, obs, _ = _run_one_period(qp, rows)
    dists = [41, 60, 43, 44]  # 11, 12 (latest), 13, 14
    want = np.minimum(rbf[:, dists].sum(1), 127)
    np.testing.assert_array_equal(obs[0, OBS_RBF:], want)
    assert obs[0, OBS_NBR_SENSING] == qp.one_q  # sender 12's latest flag is set
    assert obs[0, OBS_WALL] == qp.one_q  # light 600 >= threshold 500


def test_target_slot_latest_wins_and_sets_sensing(qp):
    """The target's latest distance is observed; the robot's next message says it senses the target."""
    rows = [(0, 1, 0, 1, 0, 20), (0, 5, 999, 1, 0, 70)]  # role bit matters, not the uid
    q, obs, emu = _run_one_period(qp, rows)
    assert obs[0, OBS_TARGET] == qp.target_table[70]
    assert emu.msg[0, 3] == fwspec.SENSING_BIT
    assert emu.led[0] == fwspec.rgb(*fwspec.LED_SENSING)
    q, obs, emu = _run_one_period(qp, [])
    assert obs[0, OBS_TARGET] == -qp.one_q and emu.msg[0, 3] == 0
    assert emu.led[0] == fwspec.rgb(*fwspec.LED_OFF)


def test_history_is_algorithm_4_oldest_first(qp):
    """Each step's command is the integer actor on [ACT[q_prev], obs] tuples, oldest first, o_1 repeated at start."""
    rng = np.random.default_rng(np.random.SeedSequence(11))
    R, P, steps = 5, WORLD.period_ticks, 7
    T = (steps + 1) * P
    ev = np.zeros(300, EVENT_DTYPE)
    ev["robot"] = rng.integers(0, R, 300)
    ev["tick"] = rng.integers(0, T, 300)
    ev["uid"] = rng.integers(1, 9, 300)
    ev["role"] = rng.random(300) < 0.2
    ev["flag"] = rng.random(300) < 0.5
    ev["type"], ev["version"] = fwspec.DEFAULT_MSG_TYPE, fwspec.MSG_VERSION
    ev["dist"] = rng.integers(30, 90, 300)
    inputs = FirmwareInputs(uids=np.arange(1, R + 1), calib=np.tile(fwspec.DEFAULT_CALIB, (R, 1)),
                            light=rng.integers(-1, 1024, (R, steps)), events=ev, n_ticks=T)
    out = _emu(qp, uids=range(1, R + 1)).run(inputs)
    q, obs = out.commands.astype(np.int64), out.obs.astype(np.int64)  # (R, steps, 2), (R, steps, D)
    act = qp.action_table.astype(np.int64)
    for k in range(steps):
        tuples = []
        for j in range(k - qp.t_prev + 1, k + 1):  # oldest first
            jj = max(j, 0)  # before the first step: the first tuple repeated
            a = act[q[:, jj - 1]] if jj > 0 else np.zeros((R, ACTION_DIM), np.int64)
            tuples.append(np.concatenate([a, obs[:, jj]], 1))
        flat = np.concatenate(tuples, 1)  # (R, in_dim)
        np.testing.assert_array_equal(qp.forward_int(flat), out.commands[:, k])


def test_motor_schedule_tick_by_tick(qp):
    """Per-tick duties follow sim.motion's schedule; spinup exactly when a motor starts from rest."""
    rng = np.random.default_rng(np.random.SeedSequence(12))
    R, P = 40, WORLD.period_ticks
    calib = rng.integers(0, 256, (R, 4)).astype(np.uint8)
    calib[::5] = 0  # some robots with zero duties
    emu = FirmwareEmulator(qp, np.arange(1, R + 1), calib)
    emu.tick_outputs(P)
    prev = np.zeros((R, 2), np.uint8)
    for _ in range(6):
        emu.deliver(np.zeros(0, EVENT_DTYPE))
        q, _ = emu.control_step(rng.integers(0, 1024, R))
        out = emu.tick_outputs(P)
        turn, mode, straight = schedule(q[:, 0], q[:, 1], P)
        for t in range(P):
            m = mode_at_tick(turn, mode, straight, t)
            want = np.zeros((R, 2), np.uint8)
            want[m == MODE_STRAIGHT] = calib[m == MODE_STRAIGHT, 0:2]
            want[m == MODE_LEFT, 0] = calib[m == MODE_LEFT, 2]
            want[m == MODE_RIGHT, 1] = calib[m == MODE_RIGHT, 3]
            np.testing.assert_array_equal(out[:, t, 0:2], want)
            spin = ((want != 0) & (prev == 0)).any(1)
            np.testing.assert_array_equal(out[:, t, 2], spin)
            prev = want


def test_beacon_outputs_are_constant(qp):
    """Beacon robots never move, show blue, send role 1 with a valid CRC and run no control step."""
    uids = np.array([WORLD.emitter_uid, 77, 3])
    R, T = 3, 5 * WORLD.period_ticks + 3
    ev = _events([(0, 2, 3, 0, 1, 40), (1, 9, 1, 1, 0, 40)])
    inputs = FirmwareInputs(uids=uids, calib=np.full((R, 4), 80), light=np.full((R, n_control_steps(T, 8)), 900),
                            events=ev, n_ticks=T)
    out = FirmwareEmulator(qp, uids, np.full((R, 4), 80), emitter_uids=(WORLD.emitter_uid, 77)).run(inputs)
    for r in (0, 1):
        assert not out.duties[r].any() and not out.spinup[r].any() and not out.steps[r].any()
        assert (out.led[r] == fwspec.rgb(*fwspec.LED_EMITTER)).all()
        msg = out.messages[r, 0]
        assert (out.messages[r] == msg).all() and msg[3] == fwspec.ROLE_BIT
        assert int(msg[10]) | int(msg[11]) << 8 == crc16_mcrf4xx(msg[:10].tobytes())
    assert out.duties[2].any(), "the searcher should move at some point"


def test_listening_period_before_first_step(qp):
    """During the first period the searcher stands still with LED off and sensing 0; step 1 comes at tick P."""
    P = WORLD.period_ticks
    inputs = FirmwareInputs(uids=[4], calib=[[90, 90, 90, 90]], light=[[0, 0]], events=np.zeros(0, EVENT_DTYPE),
                            n_ticks=3 * P)
    out = _emu(qp, uids=(4,), calib=np.array([[90, 90, 90, 90]])).run(inputs)
    assert out.steps.shape[1] == 2
    assert not out.duties[0, :P].any() and (out.led[0, :P] == 0).all() and (out.messages[0, :P, 3] == 0).all()


def test_events_from_sim_conversion():
    """Sim events become firmware events: receiver index, uids, global ticks, uint8 distances, order."""
    cfg = preset("kilobot")
    ev = HeardEvents(env=np.array([1, 0, 0], np.int32), rx=np.array([2, 1, 1], np.int32),
                     sender=np.array([-1, 0, 4], np.int32), tick=np.array([3, 9, 2], np.int16),
                     dist_mm=np.array([40.5, 300.0, 33.4]), role=np.array([1, 0, 0], np.uint8),
                     flag=np.array([0, 1, 0], np.uint8))
    out = events_from_sim(ev, 5, cfg, n_robots=3)
    assert out["robot"].tolist() == [1, 1, 5]  # (env 0, rx 1) twice, sorted by tick, then (env 1, rx 2)
    assert out["tick"].tolist() == [5 * cfg.period_ticks + 2, 5 * cfg.period_ticks + 9, 5 * cfg.period_ticks + 3]
    assert out["uid"].tolist() == [5, 1, cfg.emitter_uid]
    assert out["dist"].tolist() == [33, 255, 41]
    assert out["role"].tolist() == [0, 0, 1] and out["flag"].tolist() == [0, 1, 0]
    assert (out["type"] == fwspec.DEFAULT_MSG_TYPE).all() and (out["version"] == fwspec.MSG_VERSION).all()


def test_firmware_in_the_loop_matches_simulator_observations():
    """Driving SwarmEnv with the emulator: int8 observations equal the simulator's float ones up to rounding."""
    from sim.env import SwarmEnv

    cfg = preset("kilobot", episode_steps=30, arena_half_mm=120.0)
    M, P = 8, cfg.period_ticks
    qp = synthetic_qpolicy(cfg, 2, (8,), ("relu",), seed=2)
    env = SwarmEnv(cfg, 1, M, seed=4)
    obs_f, info = env.reset()
    emu = FirmwareEmulator(qp, np.arange(1, M + 1))
    emu.tick_outputs(P)
    emu.deliver(events_from_sim(info["events"], 0, cfg, M))
    scale = 2.0 ** -qp.e_in
    seen_target = 0
    for k in range(1, 25):
        q, obs_i = emu.control_step(info["light"][0])
        o = obs_i.astype(np.float64) * scale  # (M, D)
        f = obs_f[0].astype(np.float64)
        np.testing.assert_array_equal(o[:, OBS_WALL], f[:, OBS_WALL])
        np.testing.assert_array_equal(o[:, OBS_NBR_SENSING], f[:, OBS_NBR_SENSING])
        np.testing.assert_allclose(o[:, OBS_TARGET], f[:, OBS_TARGET], atol=0.5 * scale + 1e-9)
        np.testing.assert_allclose(o[:, OBS_RBF:], f[:, OBS_RBF:], atol=M * 0.5 * scale + 1e-9)
        np.testing.assert_array_equal(emu.msg[:, 3] >> 1, env.sensing[0])  # same sensing flags
        seen_target += int((f[:, OBS_TARGET] >= 0).sum())
        obs_f, _, _, _, info = env.step_u8(q[None])
        emu.tick_outputs(P)
        emu.deliver(events_from_sim(info["events"], k, cfg, M))
    assert seen_target > 0, "the episode never had a robot hear the target; pick another seed"
