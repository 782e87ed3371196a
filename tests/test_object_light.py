"""The object_light feature: the beacon's own light reading in its messages, in the simulator (float reference, fast
path), the firmware (both programs, host build) and the emulator (bit-exact twin)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from export.codegen.render import render_firmware
from export.contract import firmware as fw
from export.verify.emulator import FirmwareEmulator, events_from_sim
from export.verify import avr
from export.verify.hostbuild import StreamSpec, compiler, random_inputs, verify_host
from sim.config import preset
from sim.env import SwarmEnv
from sim.events import HeardEvents
from sim.tasks.transport import LAMP_PEAK, Transport
from tests.avr_tools import require_avr
from tests.fixtures import synthetic_qpolicy



class TransportObjectLight(Transport):
    """Transport with the object's broadcast reading in the observation."""

    features = ("light", "target", "object_light", "rbf")


TASK = TransportObjectLight()
WORLD = TASK.world(preset("kilobot"))
needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def _run(fast: bool, steps: int = 40, seed: int = 5) -> list[np.ndarray]:
    env = SwarmEnv(WORLD, 2, 16, seed=seed, task=TASK, fast_observe=fast)
    obs, _ = env.reset()
    rng = np.random.default_rng(1)
    out = [obs]
    for _ in range(steps):
        obs, *_ = env.step(rng.random((2, 16, 2)))
        out.append(obs)
    return out


def test_fast_path_equals_the_event_reference():
    """observe_fast gives the object_light feature (and every other input) bit for bit as sim.events.observe does."""
    for a, b in zip(_run(True), _run(False)):
        np.testing.assert_array_equal(a, b)


def test_beacon_reads_the_unshaded_light_at_the_body_centre():
    """Without noise or spreads the beacon's reading is the floor plus the side lamp at the object's centre (it rides
    on top of the object, so its own shadow does not darken it)."""
    w = dataclasses.replace(WORLD, light_noise=0.0, light_gain_spread=0.0, light_offset_spread=0.0, light_dropout=0.0)
    env = SwarmEnv(w, 3, 4, seed=2, task=TASK)
    env.reset()
    want = np.rint(w.light_floor + LAMP_PEAK * 0.5 * (1 + env.target[:, 0] / w.arena_half_mm))
    np.testing.assert_array_equal(env._emitter_reading(), want)


def test_events_carry_the_beacons_reading():
    """events_from_sim writes a target message's reading (LIGHT_NONE before the beacon's first) and 0 in searchers'."""
    ev = HeardEvents(env=np.zeros(3, np.int32), rx=np.array([0, 1, 2], np.int32), sender=np.array([-1, -1, 0], np.int32),
                     tick=np.zeros(3, np.int16), dist_mm=np.full(3, 40.0), role=np.array([1, 1, 0], np.uint8),
                     flag=np.zeros(3, np.uint8), light=np.array([517, -1, -1]))
    assert events_from_sim(ev, 0, WORLD, 3)["light"].tolist() == [517, fw.LIGHT_NONE, 0]


def test_firmware_in_the_loop_matches_the_float_reference():
    """Driving the simulator with the emulator: the int8 object_light input is (L · ONE) >> 10 of the float L / 1024
    (-ONE where the float is -1) at every step, and robots do hear the beacon's reading."""
    M, P = 16, WORLD.period_ticks
    qp = synthetic_qpolicy(WORLD, 2, (8,), ("relu",), seed=3)
    one, i = int(qp.one_q), WORLD.obs_index("object_light")
    env = SwarmEnv(WORLD, 1, M, seed=11, task=TASK)
    obs_f, info = env.reset()
    emu = FirmwareEmulator(qp, np.arange(1, M + 1))
    emu.tick_outputs(P)
    emu.deliver(events_from_sim(info["events"], 0, WORLD, M))
    held = 0
    for k in range(1, 60):
        q, obs_i = emu.control_step(info["light"][0])
        f = obs_f[0, :, i].astype(np.float64)
        want = np.where(f >= 0, np.floor(np.maximum(f, 0) * 1024).astype(np.int64) * one >> 10, -one)
        np.testing.assert_array_equal(obs_i[:, i], want)
        held += int((f >= 0).sum())
        obs_f, _, _, _, info = env.step_u8(q[None])
        emu.tick_outputs(P)
        emu.deliver(events_from_sim(info["events"], k, WORLD, M))
    assert held > 0, "no robot ever held the beacon's reading; pick another seed"


@needs_cc
def test_host_build_equals_emulator_on_fuzzed_streams():
    """Both programs of an object_light world (the beacon program with every robot a beacon) equal the emulator byte
    for byte on fuzzed streams whose messages carry readings, LIGHT_NONE and out-of-range values."""
    qp = synthetic_qpolicy(WORLD, 2, (8,), ("relu",), seed=4)
    files = render_firmware(qp, generator_version="t")
    for seed in (0, 1):
        check = verify_host(qp, files, seed=seed, spec=StreamSpec(n_robots=24, n_steps=30, target_p=0.3))
        assert check.ok, check.detail


def test_policy_program_is_bit_exact_in_simavr():
    """The policy program of an object_light world (beacon role included) replays a fuzzed stream on the AVR under
    simavr exactly as the emulator does."""
    require_avr(simulate=True)
    qp = synthetic_qpolicy(WORLD, 2, (8,), ("relu",), seed=4)
    rng = np.random.default_rng(np.random.SeedSequence(6))
    inputs = random_inputs(rng, WORLD.period_ticks, (WORLD.emitter_uid,), StreamSpec(n_robots=16, n_steps=20,
                                                                                        target_p=0.3),
                           fw.DEFAULT_MSG_TYPE, WORLD.comm_radius_mm, WORLD.light_threshold)
    check = avr.verify_simavr(qp, render_firmware(qp, generator_version="t"), inputs=inputs)
    assert check.ok, check.detail
