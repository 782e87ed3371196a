"""Rung 2 of the verification ladder: the generated C, built for the host, equals the emulator byte for byte.

Also runs the C unit tests of the hand-written runtime (tests/c/test_runtime.c).
"""
from __future__ import annotations

import dataclasses
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from export.codegen.render import POLICY_FILE, emitter_firmware, render_firmware
from export.contract import firmware as fwspec
from export.verify.emulator import FirmwareEmulator, FirmwareInputs
from export.verify.hostbuild import (HOST_CFLAGS, HostBuildError, StreamSpec, build_host, compare, compiler,
                                     random_inputs, rendered_params, run_host, runtime_flags, verify_host)
from tests.fixtures import TARGET_FILE, synthetic_qpolicy
from kiloforge import numfmt
from tests.recorded_loop import record_loop
from sim.config import preset

pytestmark = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")

TESTS = Path(__file__).resolve().parent
TEMPLATES = TESTS.parent / "firmware_templates"


@dataclass(frozen=True)
class Case:
    name: str
    world: object
    t_prev: int
    hidden: tuple
    acts: tuple
    spec: StreamSpec
    msg_type: int = fwspec.DEFAULT_MSG_TYPE
    targets: tuple = (0,)


CASES = [
    Case("kilobot-elu-32x32", preset("kilobot"), 10, (32, 32), ("elu", "elu"),
         StreamSpec(n_robots=128, n_steps=300, rate=0.9)),
    Case("thesis-relu-table3", preset("thesis", period_ticks=4, neighbour_table_size=3), 4, (16,), ("relu",),
         StreamSpec(n_robots=256, n_steps=260, rate=0.6, n_senders=8, burst_p=0.03), msg_type=0x05,
         targets=(0, 77)),
    Case("kilobot-tanh-sigmoid-identity", preset("kilobot", period_ticks=12, neighbour_table_size=5), 20,
         (8, 8, 8), ("tanh", "sigmoid", "identity"), StreamSpec(n_robots=64, n_steps=120)),
    Case("thesis-one-layer", preset("thesis", period_ticks=3, neighbour_table_size=2), 1, (), (),
         StreamSpec(n_robots=64, n_steps=100)),
]


def _coverage(emu: FirmwareEmulator, inputs: FirmwareInputs) -> dict[str, int]:
    """How often the stream hit each rule (so the comparison cannot pass on easy streams only)."""
    ev, P, cap = inputs.events, emu.P, emu.rxq_capacity
    ours = (ev["type"] == emu.msg_type) & (ev["version"] == fwspec.MSG_VERSION) & ~emu.is_emitter[ev["robot"]]
    _, per_tick = np.unique(ev[ours]["robot"].astype(np.int64) << 32 | ev[ours]["tick"], return_counts=True)
    acc = emu.accepted(ev)
    nbr = acc[acc["role"] == 0]
    period = nbr["robot"].astype(np.int64) << 32 | (nbr["tick"] // P)
    pairs = np.unique(np.stack([period, nbr["uid"].astype(np.int64)], 1), axis=0, return_counts=True)
    _, senders = np.unique(pairs[0][:, 0], return_counts=True)
    return {
        "queue_full": int((per_tick > cap).sum()),
        "table_full": int((senders > emu.world.neighbour_table_size).sum()),
        "duplicates": int((pairs[1] > 1).sum()),
        "foreign": int((ev["type"] != emu.msg_type).sum()),
        "bad_version": int((ev["version"] != fwspec.MSG_VERSION).sum()),
        "light_busy": int((inputs.light < 0).sum()),
        "beacons": int(emu.is_emitter.sum()),
        "near": int((acc["dist"] < 33).sum()),
        "beyond_radius": int((acc["dist"] > emu.world.comm_radius_mm).sum()),
        "target_msgs": int((acc["role"] == 1).sum()),
    }


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    return tmp_path_factory.mktemp("hostbuild")


def test_runtime_c_unit_tests(tmp_path):
    """tests/c/test_runtime.c passes (the CRC with export/contract/crc.py's constants), and its rounding shift
    equals numfmt.rshift_round on a grid."""
    exe = tmp_path / "test_runtime"
    res = subprocess.run([*compiler(), *HOST_CFLAGS, *runtime_flags(), "-I", str(TEMPLATES), "-o", str(exe),
                          str(TESTS / "c" / "test_runtime.c")], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    run = subprocess.run([str(exe), "grid"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    grid = np.array([ln.split() for ln in run.stdout.split("\n") if ln], np.int64)  # (n, 3): a, s, result
    assert grid.shape[0] >= 300 * 31
    np.testing.assert_array_equal(grid[:, 2], numfmt.rshift_round(grid[:, 0], grid[:, 1]))


def test_random_streams_bit_exact(builds):
    """Over 100,000 control steps of random streams (garbage state before setup()): every byte equals the emulator."""
    total_steps = 0
    for i, case in enumerate(CASES):
        qp = synthetic_qpolicy(case.world, case.t_prev, case.hidden, case.acts, seed=100 + i)
        files = render_firmware(qp, emitter_uids=case.targets, msg_type=case.msg_type, generator_version="test")
        exe = build_host(files[POLICY_FILE], builds, name=f"case{i}")
        rng = np.random.default_rng(np.random.SeedSequence(200 + i))
        inputs = random_inputs(rng, case.world.period_ticks, case.targets, case.spec, case.msg_type,
                               case.world.comm_radius_mm, case.world.light_threshold)
        emu = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=case.targets, msg_type=case.msg_type)
        want = emu.run(inputs)
        got = run_host(exe, inputs, case.world.period_ticks, case.world.obs_dim, fill=f"random:{i}")
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=f"{case.name}: {compare(want, got)}")
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=f"{case.name}: {compare(want, got)}")
        cov = _coverage(emu, inputs)
        for rule, n in cov.items():
            if rule == "table_full" and case.world.neighbour_table_size >= case.spec.n_senders:
                continue
            assert n > 0, f"{case.name}: the stream never exercised '{rule}' ({cov})"
        searchers = ~emu.is_emitter
        leds = set(np.unique(want.led).tolist())
        assert leds == {fwspec.rgb(*c) for c in (fwspec.LED_OFF, fwspec.LED_EMITTER, fwspec.LED_SENSING,
                                                 fwspec.LED_NBR_SENSING)}, f"{case.name}: LEDs {leds}"
        assert want.spinup.any(), f"{case.name}: no motor ever started"
        assert np.unique(want.commands[searchers]).size > 32, f"{case.name}: commands barely vary"
        total_steps += int(searchers.sum()) * want.steps.shape[1]
    assert total_steps >= 100_000, f"only {total_steps} control steps compared"


def test_target_program_equals_beacon_emulation(builds):
    """kilobot_target.c behaves like the beacon role of the policy program, whatever the uid."""
    case = CASES[0]
    qp = synthetic_qpolicy(case.world, 2, (4,), seed=3)
    files = render_firmware(qp, generator_version="test")
    exe = build_host(files[TARGET_FILE], builds, name="target")
    rng = np.random.default_rng(np.random.SeedSequence(300))
    inputs = random_inputs(rng, case.world.period_ticks, (0,), StreamSpec(n_robots=16, n_steps=20))
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=tuple(int(u) for u in inputs.uids))
    want = emu.run(inputs)
    got = run_host(exe, inputs, case.world.period_ticks, case.world.obs_dim)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps)
    assert (want.led == fwspec.rgb(*fwspec.LED_EMITTER)).all()


def test_a_different_firmware_is_detected(builds):
    """The comparison is sensitive: an emulator with a smaller rx queue or neighbour table disagrees."""
    case = CASES[0]
    qp = synthetic_qpolicy(case.world, 2, (8,), ("relu",), seed=7)
    files = render_firmware(qp, emitter_uids=case.targets, msg_type=case.msg_type, generator_version="test")
    exe = build_host(files[POLICY_FILE], builds, name="sensitive")
    rng = np.random.default_rng(np.random.SeedSequence(400))
    inputs = random_inputs(rng, case.world.period_ticks, case.targets,
                           StreamSpec(n_robots=32, n_steps=40, rate=0.9, burst_p=0.05))
    got = run_host(exe, inputs, case.world.period_ticks, case.world.obs_dim)
    same = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=case.targets, msg_type=case.msg_type)
    assert compare(same.run(inputs), got) == ""
    small_queue = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=case.targets,
                                   msg_type=case.msg_type, rxq_capacity=fwspec.RXQ_CAPACITY - 1)
    assert compare(small_queue.run(inputs), got) != ""
    qp_small = dataclasses.replace(qp, world=dataclasses.replace(case.world, neighbour_table_size=15))
    small_table = FirmwareEmulator(qp_small, inputs.uids, inputs.calib, emitter_uids=case.targets,
                                   msg_type=case.msg_type)
    assert compare(small_table.run(inputs), got) != ""


def test_firmware_in_the_loop_stream_replays_on_host(builds):
    """A stream recorded from SwarmEnv driven by the emulator replays bit-exactly through the host build."""
    cfg = preset("kilobot", episode_steps=20, arena_half_mm=120.0)
    M, P, K = 8, cfg.period_ticks, 15
    qp = synthetic_qpolicy(cfg, 3, (8,), ("elu",), seed=9)
    inputs = record_loop(qp, cfg, M, K, seed=6)
    assert inputs.events.size > 100
    want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    files = render_firmware(qp, generator_version="test")
    got = run_host(build_host(files[POLICY_FILE], builds, name="loop"), inputs, P, cfg.obs_dim)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps)


def test_verify_host_reports_ok():
    """verify_host (the CLI's --verify host) checks both programs with the rendered uids and type."""
    qp = synthetic_qpolicy(preset("kilobot"), 2, (6,), seed=1)
    files = render_firmware(qp, emitter_uids=(9, 0), msg_type=0x11, generator_version="t")
    assert rendered_params(files[POLICY_FILE], emitter_firmware(qp.world).uids_table) == ((9, 0), 0x11)
    result = verify_host(qp, files, spec=StreamSpec(n_robots=16, n_steps=10))
    assert result.ok and result.control_steps > 0, str(result)
    assert "bit-exact" in str(result)


EDGE_WORLDS = [
    preset("kilobot", comm_radius_mm=255.0, rbf_hi_mm=255.0, rbf_sigma_mm=60.0, period_ticks=1),
    preset("thesis", n_rbf=1, neighbour_table_size=1, period_ticks=255),
    preset("thesis", neighbour_table_size=64, period_ticks=2),
    preset("thesis", comm_radius_mm=1.0, rbf_lo_mm=0.0, rbf_hi_mm=0.0, n_rbf=2),
]


@pytest.mark.parametrize("world, t_prev, hidden", [(EDGE_WORLDS[0], 2, (3,)), (EDGE_WORLDS[1], 1, ()),
                                                    (EDGE_WORLDS[2], 40, (4,)), (EDGE_WORLDS[3], 3, (2,))])
def test_edge_configurations(world, t_prev, hidden):
    """Extreme worlds (radius 255, period 1 and 255, tables of 1 and 64, a 40-tuple ring) build warning-free and match."""
    qp = synthetic_qpolicy(world, t_prev, hidden, seed=3)
    result = verify_host(qp, render_firmware(qp, generator_version="t"), spec=StreamSpec(n_robots=8, n_steps=6))
    assert result.ok, str(result)


def test_build_errors_name_the_problem(builds):
    """A program that does not compile raises HostBuildError carrying the compiler's message."""
    with pytest.raises(HostBuildError, match="undeclared|error"):
        build_host("int main(void) { return missing_symbol; }\n", builds, name="broken")


def test_harness_rejects_a_bad_stream(builds):
    """The harness exits non-zero with a message on a stream that is not ours."""
    qp = synthetic_qpolicy(preset("thesis"), 1, (3,), seed=1)
    exe = build_host(render_firmware(qp, generator_version="t")[POLICY_FILE], builds, name="badstream")
    res = subprocess.run([str(exe)], input=b"NOPE" + bytes(12), capture_output=True)
    assert res.returncode == 2 and b"bad magic" in res.stderr
    res = subprocess.run([str(exe)], input=b"KFS1" + bytes(4), capture_output=True)
    assert res.returncode == 2 and b"ended early" in res.stderr
