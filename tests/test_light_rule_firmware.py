"""The hand-written phototaxis baselines as firmware (actor kinds ``stop_in_light`` and ``run_and_tumble``,
``--task phototaxis --policy stop_in_light|run_and_tumble``): exact thresholds, the integer reference, host and AVR
builds, the shipped files, the export CLI."""
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
from kiloforge.actors.light_rules import LightRuleArch, fall_threshold, level_threshold
from kiloforge.actors.registry import KINDS, kind_named
from kiloforge.actors.run_and_tumble import RUN_AND_TUMBLE, run_and_tumble_policy
from kiloforge.actors.stop_in_light import STOP_IN_LIGHT, StopInLightPolicy, stop_in_light_policy
from kiloforge.errors import InputError, PolicyError
from sim.config import preset
from sim.light import ADC_MAX
from sim.motion import action_to_u8
from sim.tasks import TaskRef, get_task
from sim.tasks.phototaxis import RunAndTumbleParams, StopInLightParams, falls, stops
from tests.avr_tools import require_avr
from tests.recorded_loop import record_loop

needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")
TASK = get_task("phototaxis")
WORLD = TASK.world(preset("kilobot"))
RULES = {"stop_in_light": (STOP_IN_LIGHT, stop_in_light_policy, StopInLightParams),
         "run_and_tumble": (RUN_AND_TUMBLE, run_and_tumble_policy, RunAndTumbleParams)}
NAMES = sorted(RULES)


@functools.lru_cache(maxsize=None)
def shipped(name: str):
    """`--task phototaxis --policy NAME` and its integer rule."""
    p = load_task_policy(name, "phototaxis")
    return p, RULES[name][0].quantize_rule(p, None)


@pytest.fixture(scope="module")
def exes(tmp_path_factory):
    """Host builds of both shipped rules' programs."""
    return {n: build_host(render_firmware(shipped(n)[1], generator_version="test")[POLICY_FILE],
                          tmp_path_factory.mktemp(n), name=n) for n in NAMES}


def _stream(seed: int, threshold: int, n_robots: int = 48, n_steps: int = 80) -> FirmwareInputs:
    """Fuzzed radio and light: readings uniform, near ``threshold``, -1 (receiving), 0 and 1023, and slow drifts
    (runs that rise or hold), no beacon."""
    rng = np.random.default_rng(np.random.SeedSequence([43, seed]))
    inputs = random_inputs(rng, WORLD.period_ticks, (), StreamSpec(n_robots=n_robots, n_steps=n_steps, rate=0.6),
                           comm_radius_mm=WORLD.comm_radius_mm, light_threshold=threshold)
    light = inputs.light.astype(np.int64)
    drift = np.clip(300 + np.cumsum(rng.integers(-20, 21, light.shape), 1), 0, ADC_MAX)
    pick = rng.random(light.shape)
    light = np.where(pick < 0.4, drift, light)
    light = np.where((pick >= 0.4) & (pick < 0.45), 0, np.where((pick >= 0.45) & (pick < 0.5), ADC_MAX, light))
    light[inputs.light < 0] = -1
    return dataclasses.replace(inputs, light=light.astype(np.int16))


def _threshold(name: str) -> int:
    p = shipped(name)[0].params
    return p.threshold if name == "stop_in_light" else 500


# --- the kinds and the shipped files ------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_rule_is_a_registered_kind(name):
    """The registry maps the name to its kind, whose partial renders a program of the shipped rule without dense kernels."""
    kind = RULES[name][0]
    assert kind_named(name) is kind and KINDS[name] is kind and kind.template == f"actors/{name}.c.j2"
    c = render_firmware(shipped(name)[1], generator_version="t")[POLICY_FILE]
    assert "KF_TUMBLE_T" in c and "kf_dense" not in c
    assert ("KF_LEVEL_T" in c) == (name == "stop_in_light") and ("KF_FALL_T" in c) == (name == "run_and_tumble")


@pytest.mark.parametrize("name", NAMES)
def test_shipped_policy_is_the_tuned_rule_of_task_phototaxis(name):
    """export/data/<name>_policy.npz is the tuned parameters in phototaxis's kilobot world, task phototaxis v1
    (rewrite it with python -m tools.ship_rules when either changes); another task refuses it."""
    kind, make, params = RULES[name]
    p, _ = shipped(name)
    assert p.kind == name and p.task_ref == TaskRef("phototaxis", 1) and p.world == WORLD and p.params == params()
    assert p.hash == make(preset("kilobot")).hash, f"{name}_policy.npz is stale: python -m tools.ship_rules"
    path = Path(__file__).resolve().parents[1] / "export" / "data" / f"{name}_policy.npz"
    with pytest.raises(InputError, match="trained for task phototaxis v1"):
        load_task_policy(path, "aggregation")


@pytest.mark.parametrize("e_in", [6, 4, 0])
def test_thresholds_are_the_float_rule_exactly(e_in):
    """For every int8 level and change, the integer thresholds decide as the float rule does on lq / ONE * 1024 counts,
    at several thresholds and input exponents."""
    q = np.arange(-128, 128)
    counts = q * 1024.0 / (1 << e_in)
    for t in (0, 1, 12, 15, 16, 17, 550, 560, 1000, ADC_MAX):
        np.testing.assert_array_equal(q >= level_threshold(t, 1 << e_in), stops(StopInLightParams(threshold=t), counts))
        np.testing.assert_array_equal(q < fall_threshold(t, 1 << e_in), falls(RunAndTumbleParams(fall=t), counts))
    assert level_threshold(550, 64) == 35 and fall_threshold(12, 64) == 0 and fall_threshold(16, 64) == -1


@pytest.mark.parametrize("name,kw", [("stop_in_light", {"threshold": 1024}), ("stop_in_light", {"run_steps": 0}),
                                     ("run_and_tumble", {"fall": -1}), ("run_and_tumble", {"turn_max_steps": 256}),
                                     ("run_and_tumble", {"fall": 2.5})])
def test_bad_parameter_is_one_line(name, kw):
    """A parameter outside its firmware range (or of the wrong type) is refused in one line naming it."""
    with pytest.raises(InputError) as e:
        RULES[name][2](**kw)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{name} parameter {next(iter(kw))} must be"), msg


def test_bad_parameter_in_a_file_is_refused_by_export(tmp_path, capsys):
    """`python -m export` of a stop_in_light file with threshold 2000: exit 2, one line naming it, nothing written."""
    from export.cli.main import main
    from tests.bad_inputs import crafted
    meta = json.loads(json.dumps(shipped("stop_in_light")[0].meta()))
    meta["params"]["threshold"] = 2000
    path = tmp_path / "bad.npz"
    path.write_bytes(crafted({}, meta))
    rc = main(["--task", "phototaxis", "--policy", str(path), "--out", str(tmp_path / "k.c"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "threshold must be in [0, 1023]" in err[0], err
    assert not (tmp_path / "k.c").exists()


def test_policy_in_a_world_without_light_is_refused():
    """A light rule in a world that does not observe the light feature is refused in one line."""
    with pytest.raises(PolicyError, match="reads the light feature"):
        StopInLightPolicy(StopInLightParams(), dataclasses.replace(WORLD, obs_features="rbf"))


# --- the integer reference ----------------------------------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_integer_rule_is_the_float_rule_on_dequantised_observations(name):
    """The emulator's commands equal the sim.tasks.phototaxis rule fed its int8 observations / 2**e_in and the
    firmware's draws; every command (straight, both pivots, and for stop_in_light standing) occurs."""
    p, qp = shipped(name)
    inputs = _stream(1, _threshold(name))
    out = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    obs, cmd = out.obs.astype(np.float64) / (1 << qp.e_in), out.commands
    ref = RULES[name][0].draw_reference(p, inputs.uids)
    ref.reset(1, inputs.uids.size)
    got = np.stack([action_to_u8(ref.act(obs[None, :, t])[0]) for t in range(obs.shape[1])], 1)
    np.testing.assert_array_equal(got, cmd)
    kinds = {tuple(c) for c in cmd.reshape(-1, 2).tolist()}
    want = {(255, 255), (255, 0), (0, 255)} | ({(0, 0)} if name == "stop_in_light" else set())
    assert kinds == want, f"commands seen: {kinds}"


@pytest.mark.parametrize("name", NAMES)
def test_setup_state_seeds_the_generator_only(name):
    """setup_state gives the xorshift32 word from kilo_uid (distinct per uid) and zero turn fields."""
    st = shipped(name)[1].setup_state(np.array([7, 300, 65535]))
    assert len(set(st.rng.tolist())) == 3 and st.rng.all() and not st.turn_left.any() and not st.turn_dir.any()


# --- host and AVR builds ------------------------------------------------------------------------
@needs_cc
@pytest.mark.parametrize("name", NAMES)
def test_host_build_equals_emulator_on_fuzzed_streams(name, exes):
    """Host build of the shipped rule == the emulator byte for byte over 2 x 48 robots x 80 periods of fuzzed streams
    (light -1, 0, 1023, near the threshold, drifting)."""
    for seed in (2, 3):
        inputs = _stream(seed, _threshold(name))
        want = FirmwareEmulator(shipped(name)[1], inputs.uids, inputs.calib).run(inputs)
        got = run_host(exes[name], inputs, WORLD.period_ticks, WORLD.obs_dim, fill=f"random:{seed}")
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
        cmd = want.commands
        assert (cmd == 255).all(-1).any() and (cmd[..., 0] != cmd[..., 1]).any()
        assert (cmd == 0).all(-1).any() == (name == "stop_in_light")


@needs_cc
@pytest.mark.parametrize("name", NAMES)
def test_host_build_seeds_from_kilo_uid(name, exes):
    """In the dark with no messages, robots of distinct uids turn differently, equal uids alike; a uid-blind emulator
    is caught."""
    P, S = WORLD.period_ticks, 300
    uids = np.array([5, 6, 5, 999], np.uint16)
    inputs = FirmwareInputs(uids=uids, calib=np.zeros((4, 4), np.uint8), light=np.full((4, S), 100, np.int16),
                            events=np.zeros(0, EVENT_DTYPE), n_ticks=(S + 1) * P)
    qp = shipped(name)[1]
    got = run_host(exes[name], inputs, P, WORLD.obs_dim, fill="0xA5")
    np.testing.assert_array_equal(got.steps, FirmwareEmulator(qp, uids, inputs.calib).run(inputs).steps)
    c = got.commands
    np.testing.assert_array_equal(c[0], c[2])
    assert (c[0] != c[1]).any() and (c[0] != c[3]).any()

    class UidBlind(FirmwareEmulator):
        def reset(self):
            super().reset()
            self.state = self.qp.setup_state(np.zeros_like(self.uids))

    assert compare(UidBlind(qp, uids, inputs.calib).run(inputs), got) != ""


@needs_cc
@pytest.mark.parametrize("name", NAMES)
def test_firmware_in_the_loop_replays_on_host(name, exes):
    """SwarmEnv (phototaxis, 16 robots) driven by the rule's emulator for 120 periods: the recorded stream replays
    bit-exactly on the host build; stop_in_light robots stand in the light."""
    cfg = dataclasses.replace(WORLD, episode_steps=200)
    qp = shipped(name)[1]
    inputs = record_loop(qp, cfg, 16, 120, seed=3, task="phototaxis")
    want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    got = run_host(exes[name], inputs, cfg.period_ticks, cfg.obs_dim)
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps)
    if name == "stop_in_light":
        assert (want.commands == 0).all(-1).mean() > 0.05, "no robot stood in the light"


@needs_cc
@pytest.mark.parametrize("name", NAMES)
def test_export_verify_avr_writes_one_program(name, tmp_path, capsys):
    """`python -m export --task phototaxis --policy NAME --verify avr` passes (bit-exact in simavr) and writes one
    program and its manifest, no kilobot_target.c."""
    from export.cli.main import main
    if avr.missing_tools(simulate=True):
        pytest.skip("avr-gcc or simavr missing")
    out = tmp_path / "fw" / "photo.c"
    out.parent.mkdir()
    rc = main(["--task", "phototaxis", "--policy", name, "--out", str(out), "--verify", "avr",
               "--robots-calib", "4", "--calib-steps", "20", "--no-avr", "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0 and "bit-exact" in text
    assert sorted(f.name for f in out.parent.iterdir()) == ["photo.c", "photo.c.manifest.json"]
    assert json.loads((out.parent / "photo.c.manifest.json").read_text())["quantization"]["kind"] == name


@pytest.mark.avr
@pytest.mark.parametrize("name", NAMES)
def test_avr_build_fits_the_budget(name):
    """avr-gcc builds the shipped rule within the flash and SRAM budget; the estimate is within 10 % of it."""
    require_avr()
    qp = shipped(name)[1]
    exact = avr.exact_budget(render_firmware(qp), qp, stack_steps=20)
    b = estimate(RULES[name][0], WORLD, LightRuleArch())
    assert b.with_exact(exact).ok, b.table()
    assert exact["flash"] <= FLASH_LIMIT_B and exact["sram_user"] <= SRAM_LIMIT_B, exact
    assert abs(b.flash_analytic - exact["flash"]) <= 0.1 * exact["flash"], (b.flash_analytic, exact)


@needs_cc
@pytest.mark.parametrize("name", NAMES)
def test_sanitized_build_on_garbage_state_equals_emulator(name, tmp_path):
    """ASan/UBSan host build, state filled with garbage before setup(): no finding and bit-exact on a fuzzed stream."""
    exe = build_host(render_firmware(shipped(name)[1], generator_version="test")[POLICY_FILE], tmp_path,
                     name=f"{name}-asan", sanitize=True)
    inputs = _stream(4, _threshold(name), n_robots=24, n_steps=40)
    want = FirmwareEmulator(shipped(name)[1], inputs.uids, inputs.calib).run(inputs)
    got = run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill="0xA5")
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
