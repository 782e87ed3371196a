"""The hand-written aggregation rule as firmware (actor kind ``aggregator``, ``--task aggregation --policy aggregator``):
its exact thresholds, the integer reference, host and AVR builds, the shipped file, the export CLI."""
from __future__ import annotations

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest

from export.codegen.budget import FLASH_LIMIT_B, SRAM_LIMIT_B, estimate
from export.codegen.render import POLICY_FILE, render_firmware
from export.contract.firmware import EVENT_DTYPE
from kiloforge.shipped import load_task_policy
from export.verify import avr
from export.verify.emulator import FirmwareEmulator, FirmwareInputs
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.actors.aggregator import (AGGREGATOR, PROB_ONE, AggregatorArch, AggregatorPolicy, AggregatorState,
                                         FirmwareDrawAggregator, aggregator_policy, quantize_aggregator)
from kiloforge.actors.registry import KINDS, kind_named
from kiloforge.errors import InputError
from sim.config import preset
from sim.motion import action_to_u8
from sim.tasks import TaskRef, get_task
from sim.tasks.aggregation import NBR_MAX, AggregatorParams, ProbabilisticAggregator, leave_prob, stop_prob
from tests.avr_tools import require_avr
from tests.recorded_loop import record_loop

needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")
WORLD = get_task("aggregation").world(preset("kilobot"))


@functools.lru_cache(maxsize=None)
def shipped():
    """`--task aggregation --policy aggregator` and its integer rule."""
    p = load_task_policy("aggregator", "aggregation")
    return p, quantize_aggregator(p)


@pytest.fixture(scope="module")
def exe(tmp_path_factory):
    """The host build of the shipped aggregator's program."""
    files = render_firmware(shipped()[1], generator_version="test")
    return build_host(files[POLICY_FILE], tmp_path_factory.mktemp("aggregator_host"), name="aggregator")


def _stream(seed: int, n_robots: int = 48, n_steps: int = 80):
    """Fuzzed radio and light (bursts past the rx queue, full tables, light -1), no beacon."""
    rng = np.random.default_rng(np.random.SeedSequence([42, seed]))
    return random_inputs(rng, WORLD.period_ticks, (), StreamSpec(n_robots=n_robots, n_steps=n_steps, rate=0.6),
                         comm_radius_mm=WORLD.comm_radius_mm, light_threshold=WORLD.light_threshold)


# --- the kind and the shipped file --------------------------------------------------------------
def test_aggregator_is_a_registered_kind():
    """The registry maps "aggregator" to its kind, whose partial renders a program of the shipped rule."""
    assert kind_named("aggregator") is AGGREGATOR and KINDS["aggregator"] is AGGREGATOR
    assert AGGREGATOR.template == "actors/aggregator.c.j2" and shipped()[0].kind == "aggregator"
    c = render_firmware(shipped()[1], generator_version="t")[POLICY_FILE]
    assert "KF_STOP_T" in c and "KF_LEAVE_T" in c and "kf_dense" not in c


def test_shipped_policy_is_the_tuned_rule_of_task_aggregation():
    """export/data/aggregator_policy.npz is AggregatorParams() in aggregation's kilobot world, task aggregation v1
    (rewrite it with python -m tools.ship_rules when either changes)."""
    p, qp = shipped()
    assert p.task_ref == TaskRef("aggregation", 1) and p.world == WORLD and p.params == AggregatorParams()
    assert p.hash == aggregator_policy(preset("kilobot")).hash, "aggregator_policy.npz is stale: python -m tools.ship_rules"
    path = Path(__file__).resolve().parents[1] / "export" / "data" / "aggregator_policy.npz"
    with pytest.raises(InputError, match="trained for task aggregation v1"):
        load_task_policy(path, "localisation")


def test_thresholds_are_the_float_rule_exactly():
    """For every int8 RBF sum and every 16-bit draw, the firmware's tables decide as the float rule does on S / 2**e_in."""
    p, qp = shipped()
    float_rule = ProbabilisticAggregator(WORLD, p.params)
    S = np.arange(WORLD.n_rbf * 127 + 1)
    obs = np.zeros((1, S.size, WORLD.obs_dim))
    obs[0, :, WORLD.obs_index("rbf")] = S / (1 << qp.e_in)  # the whole sum in bin 0
    n_float = float_rule.neighbours(obs)[0]
    np.testing.assert_array_equal(qp.neighbours((obs[0] * (1 << qp.e_in)).astype(np.int64)), n_float)
    assert n_float.max() == NBR_MAX and (np.diff(n_float) >= 0).all()
    r = np.arange(PROB_ONE)
    n = np.arange(NBR_MAX + 1)
    for table, prob in ((qp.stop_t, stop_prob(p.params, n)), (qp.leave_t, leave_prob(p.params, n))):
        for k in (0, 1, 3, 5, NBR_MAX):
            np.testing.assert_array_equal(r < int(table[k]), r / PROB_ONE < prob[k])
    assert qp.stop_t[0] == 0 and qp.stop_t[5] == PROB_ONE and qp.leave_t[0] == int(np.ceil(0.7 * PROB_ONE))


@pytest.mark.parametrize("kw", [{"stop_per_nbr": 1.5}, {"leave_decay": -1.0}, {"turn_max_steps": 256},
                                {"run_steps": 0}, {"wall_turn_steps": 2.5}])
def test_bad_parameter_is_one_line(kw):
    """A parameter outside its firmware range (or of the wrong type) is refused in one line naming it."""
    with pytest.raises(InputError) as e:
        AggregatorParams(**kw)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"aggregator parameter {next(iter(kw))} must be"), msg


def test_bad_parameter_in_a_file_is_refused_by_export(tmp_path, capsys):
    """`python -m export` of an aggregator file with stop_per_nbr 2: exit 2, one line naming it, nothing written."""
    from export.cli.main import main
    from tests.bad_inputs import crafted
    p = shipped()[0]
    meta = json.loads(json.dumps(p.meta()))
    meta["params"]["stop_per_nbr"] = 2.0
    path = tmp_path / "bad.npz"
    path.write_bytes(crafted({}, meta))
    rc = main(["--task", "aggregation", "--policy", str(path), "--out", str(tmp_path / "k.c"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "stop_per_nbr must be in [0.0, 1.0]" in err[0], err
    assert not (tmp_path / "k.c").exists()


# --- the integer reference ----------------------------------------------------------------------
def test_integer_rule_is_the_float_rule_on_dequantised_observations():
    """The emulator's commands equal ProbabilisticAggregator fed its int8 observations / 2**e_in and the firmware's draws."""
    p, qp = shipped()
    inputs = _stream(1)
    out = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    obs, cmd = out.obs.astype(np.float64) / (1 << qp.e_in), out.commands
    ref = FirmwareDrawAggregator(p.world, p.params, inputs.uids)
    ref.reset(1, inputs.uids.size)
    got = np.stack([action_to_u8(ref.act(obs[None, :, t])[0]) for t in range(obs.shape[1])], 1)
    np.testing.assert_array_equal(got, cmd)
    kinds = {tuple(c) for c in cmd.reshape(-1, 2).tolist()}
    assert {(255, 255), (255, 0), (0, 255), (0, 0)} <= kinds, f"not every command occurred: {kinds}"


def test_setup_state_seeds_the_generator_only():
    """setup_state gives every field one value per robot: the xorshift32 word from kilo_uid, the rest 0."""
    st = shipped()[1].setup_state(np.array([7, 300, 65535]))
    for f in dataclasses.fields(AggregatorState):
        v = getattr(st, f.name)
        assert v.shape == (3,) and (v.all() if f.name == "rng" else not v.any()), f.name


@needs_cc
def test_host_build_equals_emulator_on_fuzzed_streams(exe):
    """Host build of the shipped aggregator == the emulator byte for byte over 2 x 48 robots x 80 periods of fuzzed streams."""
    for seed in (2, 3):
        inputs = _stream(seed)
        want = FirmwareEmulator(shipped()[1], inputs.uids, inputs.calib).run(inputs)
        got = run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill=f"random:{seed}")
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
        cmd = want.commands
        assert (cmd == 0).all(-1).any() and (cmd == 255).all(-1).any() and (cmd[..., 0] != cmd[..., 1]).any()
        assert (want.obs[..., WORLD.obs_slice("rbf")].sum(-1) >= shipped()[1].nbr_t[2]).any(), "never 3 neighbours"


@needs_cc
def test_host_build_seeds_from_kilo_uid(exe):
    """With no messages, robots of distinct uids turn differently, equal uids alike; a uid-blind emulator is caught."""
    P, S = WORLD.period_ticks, 300
    uids = np.array([5, 6, 5, 999], np.uint16)
    inputs = FirmwareInputs(uids=uids, calib=np.zeros((4, 4), np.uint8), light=np.full((4, S), 900, np.int16),
                            events=np.zeros(0, EVENT_DTYPE), n_ticks=(S + 1) * P)
    want = FirmwareEmulator(shipped()[1], uids, inputs.calib).run(inputs)
    got = run_host(exe, inputs, P, WORLD.obs_dim, fill="0xA5")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
    c = got.commands
    np.testing.assert_array_equal(c[0], c[2])
    assert (c[0] != c[1]).any() and (c[0] != c[3]).any()

    class UidBlind(FirmwareEmulator):
        def reset(self):
            super().reset()
            self.state = self.qp.setup_state(np.zeros_like(self.uids))

    assert compare(UidBlind(shipped()[1], uids, inputs.calib).run(inputs), got) != ""


@needs_cc
def test_firmware_in_the_loop_replays_on_host(exe):
    """SwarmEnv driven by the aggregator's emulator for 120 periods (16 robots): the recorded stream replays bit-exactly."""
    cfg = dataclasses.replace(WORLD, episode_steps=200)
    qp = shipped()[1]
    inputs = record_loop(qp, cfg, 16, 120, seed=3, task="aggregation")
    want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    got = run_host(exe, inputs, cfg.period_ticks, cfg.obs_dim)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps)
    assert (want.commands == 0).all(-1).mean() > 0.1, "no robot rested"


# --- export -------------------------------------------------------------------------------------
@needs_cc
@pytest.mark.parametrize("verify", ["host", "avr"])
def test_export_verify_writes_no_target_program(verify, tmp_path, capsys):
    """`python -m export --task aggregation --policy aggregator --verify host|avr` passes (bit-exact; avr: in simavr)
    and writes one program, no kilobot_target.c."""
    from export.cli.main import main
    if verify == "avr" and avr.missing_tools(simulate=True):
        pytest.skip("avr-gcc or simavr missing")
    out = tmp_path / "fw" / "agg.c"
    out.parent.mkdir()
    rc = main(["--task", "aggregation", "--policy", "aggregator", "--out", str(out), "--verify", verify,
               "--robots-calib", "4", "--calib-steps", "20", "--no-avr", "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0 and "bit-exact" in text
    assert sorted(f.name for f in out.parent.iterdir()) == ["agg.c", "agg.c.manifest.json"]
    manifest = json.loads((out.parent / "agg.c.manifest.json").read_text())
    assert "aggregator" in json.dumps(manifest)


@pytest.mark.avr
def test_avr_build_fits_the_budget():
    """avr-gcc builds the shipped aggregator within the flash and SRAM budget; the estimate is within 10 % of it."""
    require_avr()
    qp = shipped()[1]
    exact = avr.exact_budget(render_firmware(qp), qp, stack_steps=20)
    b = estimate(AGGREGATOR, WORLD, AggregatorArch())
    assert b.with_exact(exact).ok, b.table()
    assert exact["flash"] <= FLASH_LIMIT_B and exact["sram_user"] <= SRAM_LIMIT_B, exact
    assert abs(b.flash_analytic - exact["flash"]) <= 0.1 * exact["flash"], (b.flash_analytic, exact)


def test_policy_in_a_world_without_rbf_is_refused():
    """An aggregator in a world that does not observe the RBF histogram is refused in one line."""
    from kiloforge.errors import PolicyError
    world = dataclasses.replace(WORLD, obs_features="wall")
    with pytest.raises(PolicyError, match="reads wall, rbf"):
        AggregatorPolicy(AggregatorParams(), world)
