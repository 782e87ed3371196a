"""Every generated program sets its whole state in setup(): garbage-filled state, ASan + UBSan, bit-exact.

The host harness (firmware_templates/host/harness.c) gives each robot a freshly malloc'd state filled
with garbage (KF_HOST_FILL), calls the rx callback with 512 messages and asks the tx callback for a
message before setup() (as kilolib may), then replays the event stream; the build runs under
AddressSanitizer and UndefinedBehaviorSanitizer with every finding fatal. CI-sized streams.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

from export.codegen.render import POLICY_FILE, render_firmware
from export.contract import firmware as fwspec
from export.quantize import calibrate, quantize_policy
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import HostBuildError, StreamSpec, build_host, compare, compiler, random_inputs, run_host
from tests.fixtures import TARGET_FILE, synthetic_qpolicy
from kiloforge.actors.gru import random_gru_policy
from kiloforge.actors.lstm import random_lstm_policy
from kiloforge.actors.aggregator import AggregatorPolicy, quantize_aggregator
from kiloforge.actors.searcher import quantize_searcher, searcher_policy
from sim.tasks.aggregation import AggregatorParams
from sim.config import preset

pytestmark = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")

FILLS = ("0xA5", "0x5A", "random:7")
TARGETS = (0, 77)
WORLD = preset("kilobot")


RECURRENT = {"gru": random_gru_policy, "lstm": random_lstm_policy}  #: program kind -> its random float policy


@functools.lru_cache(maxsize=None)
def policy(kind: str):
    """The quantised policy behind each program kind (the beacon program uses the MLP's)."""
    if kind == "searcher":
        return quantize_searcher(searcher_policy(WORLD))
    if kind == "aggregator":  # in localisation's layout: the rule beside a beacon
        return quantize_aggregator(AggregatorPolicy(AggregatorParams(), WORLD))
    if kind in RECURRENT:
        p = RECURRENT[kind](WORLD, 16, seed=4, scale=3.0)
        return quantize_policy(p, calibrate(p, episodes=1, n_robots=(4,), seed=4, steps=40))
    return synthetic_qpolicy(WORLD, 10, (32, 32), ("elu", "elu"), seed=5)


def program(kind: str) -> str:
    """The rendered C of one kind: the MLP, GRU, LSTM, searcher or aggregator program, or the beacon-only program."""
    files = render_firmware(policy(kind), emitter_uids=TARGETS, generator_version="test")
    return files[TARGET_FILE if kind == "beacon" else POLICY_FILE]


def stream(kind: str, seed: int = 0):
    """A random stream (bursts past the rx queue, full tables, foreign types, light -1, beacon uids)."""
    rng = np.random.default_rng(np.random.SeedSequence([11, seed]))
    spec = StreamSpec(n_robots=16, n_steps=20) if kind == "beacon" else StreamSpec(n_robots=32, n_steps=50, rate=0.9)
    return random_inputs(rng, WORLD.period_ticks, TARGETS, spec, comm_radius_mm=WORLD.comm_radius_mm,
                         light_threshold=WORLD.light_threshold)


def emulate(kind: str, inputs):
    """The emulator's bytes for a stream (the beacon program: every robot is a target)."""
    targets = tuple(int(u) for u in inputs.uids) if kind == "beacon" else TARGETS
    return FirmwareEmulator(policy(kind), inputs.uids, inputs.calib, emitter_uids=targets).run(inputs)


@pytest.fixture(scope="module")
def builds(tmp_path_factory):
    return tmp_path_factory.mktemp("sanitized")


@pytest.mark.parametrize("fill", FILLS)
@pytest.mark.parametrize("kind", ("mlp", "gru", "lstm", "searcher", "aggregator", "beacon"))
def test_sanitized_program_on_garbage_state_equals_emulator(kind, fill, builds):
    """ASan/UBSan build, state garbage before setup() and callbacks called before it: 0 findings, bit-exact."""
    exe = build_host(program(kind), builds, name=f"{kind}-asan", sanitize=True)
    inputs = stream(kind, seed=FILLS.index(fill))
    got = run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill=fill)
    want = emulate(kind, inputs)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=f"{kind} {fill}: {compare(want, got)}")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=f"{kind} {fill}: {compare(want, got)}")
    if kind == "beacon":
        assert (want.led == fwspec.rgb(*fwspec.LED_EMITTER)).all()
    else:
        beacon = np.isin(inputs.uids, TARGETS)
        assert beacon.any() and not beacon.all(), "the stream should hold searchers and beacons"
        cmd = want.commands[~beacon]
        if kind in ("searcher", "aggregator"):  # straight, pivot left or right, stop: (0 | 255, 0 | 255)
            assert np.unique(cmd.reshape(-1, 2), axis=0).shape[0] == 4, f"not every {kind} command occurred"
        else:
            assert np.unique(cmd).size > 16, "commands barely vary"


@pytest.mark.parametrize("kind", ("mlp", "gru", "lstm", "searcher", "aggregator", "beacon"))
def test_a_program_relying_on_zeroed_state_is_caught(kind, builds):
    """With setup()'s clearing loop removed a program still passes on zeroed state but not on garbage."""
    loop = "    for (i = 0u; i < (uint16_t)sizeof(kf_state_t); ++i) {\n        p[i] = 0u;\n    }\n"
    text = program(kind)
    assert text.count(loop) == 1
    exe = build_host(text.replace(loop, "    (void)p;\n    (void)i;\n"), builds, name=f"{kind}-noclear",
                     sanitize=True)
    inputs = stream(kind, seed=9)
    want = emulate(kind, inputs)
    assert compare(want, run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill="0")) == ""
    try:
        detail = compare(want, run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill="0xA5"))
    except HostBuildError as e:  # a sanitizer finding (or the harness's own check)
        detail = str(e)
    assert detail, f"{kind}: garbage state went unnoticed"


def test_a_message_offered_before_setup_is_caught(builds):
    """The harness fails a program whose tx callback answers before setup() has run."""
    text = program("mlp")
    guard = "    if (s->ready != KF_READY) {\n        return 0;\n    }\n    return &s->tx.msg"
    assert text.count(guard) == 1
    exe = build_host(text.replace(guard, "    return &s->tx.msg"), builds, name="eager-tx", sanitize=True)
    with pytest.raises(HostBuildError, match="before setup"):
        run_host(exe, stream("mlp"), WORLD.period_ticks, WORLD.obs_dim, fill="0x5A")


def test_bad_fill_is_refused(builds):
    """An unreadable KF_HOST_FILL stops the harness with a message instead of running on some default."""
    exe = build_host(program("beacon"), builds, name="beacon-plain")
    with pytest.raises(HostBuildError, match="KF_HOST_FILL"):
        run_host(exe, stream("beacon"), WORLD.period_ticks, WORLD.obs_dim, fill="lots")
