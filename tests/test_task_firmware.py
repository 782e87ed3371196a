"""The firmware follows the world's observation layout and beacon (issue 42): aggregation's program has no
beacon parts, and every layout's C equals its emulator on fuzzed streams."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from export.codegen import budget as bud
from export.codegen.render import POLICY_FILE, render_firmware
from export.contract import firmware as fwspec
from export.errors import ExportError
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.actors.mlp import MLP, MLPArch
from kiloforge.policies import save_policy
from sim.config import preset
from sim.tasks import get_task
from tests.fixtures import init_policy, synthetic_qpolicy

AGG_WORLD = get_task("aggregation").world(preset("kilobot", neighbour_table_size=5, period_ticks=12))
#: other layouts a task may choose: features reordered, a beacon without the neighbour flag
LAYOUTS = [AGG_WORLD, dataclasses.replace(AGG_WORLD, obs_features="rbf,wall"),
           dataclasses.replace(AGG_WORLD, emitter=True, obs_features="rbf,target,wall")]
BEACON_PARTS = ("is_beacon", "KF_ROLE_BIT", "KF_SENSING_BIT", "KF_TARGET_UIDS", "KF_TGT", "tgt_heard",
                "KF_LED_BEACON", "KF_OBS_TARGET", "KF_OBS_NBR_SENSING", ".flag")
needs_gcc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")


def test_beaconless_program_has_no_beacon_parts():
    """Aggregation renders one program, without beacon role, target slot, tables, uids or message flags."""
    qp = synthetic_qpolicy(AGG_WORLD, 3, (6,), seed=2)
    files = render_firmware(qp, generator_version="t")
    assert list(files) == [POLICY_FILE]
    c = files[POLICY_FILE]
    assert [p for p in BEACON_PARTS if p in c] == []
    assert "#define KF_OBS_WALL 0u" in c and "#define KF_OBS_RBF 1u" in c and "#define KF_OBS_DIM 12u" in c
    with pytest.raises(ExportError, match="has no emitter: emitter uids do not apply"):
        render_firmware(qp, emitter_uids=(0,), generator_version="t")


def test_aggregation_budget_is_smaller():
    """The same actor in aggregation's layout needs less flash and SRAM than in localisation's."""
    loc = bud.estimate(MLP, preset("kilobot"), MLPArch(10, (32, 32)))
    agg = bud.estimate(MLP, get_task("aggregation").world(preset("kilobot")), MLPArch(10, (32, 32)))
    assert agg.flash_analytic < loc.flash_analytic and agg.sram_analytic < loc.sram_analytic
    assert agg.layer_sizes[0] == 10 * (2 + 12) and loc.layer_sizes[0] == 10 * (2 + 14)


@needs_gcc
@pytest.mark.parametrize("world", LAYOUTS, ids=["aggregation", "rbf-wall", "beacon-rbf-target-wall"])
def test_layout_firmware_equals_emulator_on_fuzzed_streams(world, tmp_path):
    """Each layout's host build equals the emulator byte for byte (queue and table overflow, role-bit senders)."""
    qp = synthetic_qpolicy(world, 4, (8,), seed=7)
    targets = (0, 77) if world.emitter else ()
    files = render_firmware(qp, emitter_uids=targets or None, generator_version="t")
    exe = build_host(files[POLICY_FILE], tmp_path, name="layout")
    rng = np.random.default_rng(np.random.SeedSequence(42))
    inputs = random_inputs(rng, world.period_ticks, targets, StreamSpec(n_robots=64, n_steps=60, rate=0.9),
                           fwspec.DEFAULT_MSG_TYPE, world.comm_radius_mm, world.light_threshold)
    emu = FirmwareEmulator(qp, inputs.uids, inputs.calib, emitter_uids=targets or None)
    want = emu.run(inputs)
    got = run_host(exe, inputs, world.period_ticks, world.obs_dim, fill="random:3")
    np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
    np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
    acc = emu.accepted(inputs.events)
    assert (acc["role"] == 1).sum() > 0 and np.unique(want.commands).size > 32  # the stream reached the rules
    rbf = want.obs[..., world.obs_slice("rbf")]
    assert (rbf > 0).mean() > 0.05 and rbf.max() >= 32  # bins summed over several neighbours
    if not world.emitter:  # role bits are a neighbour's; the LED and message never change
        assert not emu.is_emitter.any() and (want.led == fwspec.rgb(*fwspec.LED_OFF)).all()
        assert (want.messages[..., fwspec.MSG_INFO_BYTE] == 0).all()


@needs_gcc
@pytest.mark.parametrize("verify", ["host", "avr"])
def test_export_of_an_aggregation_policy_verifies_without_a_target_program(verify, tmp_path, capsys):
    """python -m export --task aggregation --verify host|avr passes and writes no kilobot_target.c."""
    from export.cli.main import main
    from export.verify import avr

    if verify == "avr" and avr.missing_tools(simulate=True):
        pytest.skip("avr-gcc or simavr missing")
    world = get_task("aggregation").world(preset("kilobot"))
    p = dataclasses.replace(init_policy(world, 2, (8,)), task=get_task("aggregation").ref)
    path = save_policy(p, tmp_path / "agg.npz")
    out = tmp_path / "fw" / "kilobot_policy.c"
    out.parent.mkdir()
    rc = main(["--task", "aggregation", "--policy", str(path), "--out", str(out), "--verify", verify,
               "--robots-calib", "4", "--calib-steps", "20", "--no-avr", "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0 and "bit-exact" in text and "is the beacon" not in text
    assert sorted(f.name for f in out.parent.iterdir()) == ["kilobot_policy.c", "kilobot_policy.c.manifest.json"]


def test_every_feature_has_a_firmware_block_and_an_emulator_twin():
    """Each registered observation feature has its template partial and its integer twin, and nothing else does."""
    from pathlib import Path

    from export.verify.emulator import INT_FEATURES
    from sim.features import FEATURES

    blocks = Path(__file__).resolve().parent.parent / "firmware_templates" / "features"
    assert {p.name.removesuffix(".c.j2") for p in blocks.glob("*.c.j2")} == set(FEATURES) == set(INT_FEATURES)


def test_emitter_firmware_comes_from_the_task():
    """A task with an emitter names its firmware partials and program file; a missing or bad one is one line."""
    from export.codegen.render import EmitterFirmware
    from sim.tasks.localisation import Localisation

    qp = synthetic_qpolicy(preset("kilobot"), 2, (4,), seed=1)
    for name in ("localisation", "transport"):
        task = get_task(name)
        emitter = EmitterFirmware(task)
        files = render_firmware(qp, generator_version="t", task=task)
        assert list(files) == [POLICY_FILE, task.emitter_program] and emitter.program == "kilobot_target.c"
        assert f"{emitter.uids_table}[2]" not in files[POLICY_FILE] and f"{emitter.uids_table}[1]" in files[POLICY_FILE]
        assert f"#define {emitter.led} " in files[POLICY_FILE] and f"act as {task.beacon_role}" in files[POLICY_FILE]
    bad = {"no partials": {"firmware": ""}, "unknown folder": {"firmware": "nosuchtask"},
           "path in folder": {"firmware": "../features"}, "policy file": {"emitter_program": POLICY_FILE},
           "path in program": {"emitter_program": "../x.c"}}
    for why, attrs in bad.items():
        task = type("Odd", (Localisation,), dict(attrs, name="odd"))()
        with pytest.raises(ExportError) as err:
            render_firmware(qp, generator_version="t", task=task)
        assert "\n" not in str(err.value) and "task 'odd' has an emitter" in str(err.value), why
    with pytest.raises(ExportError, match="^task 'aggregation' has no emitter"):
        EmitterFirmware(get_task("aggregation"))


def test_generic_templates_name_no_task():
    """Outside firmware_templates/tasks/ no template names a task's robot (the beacon) or its uids."""
    import re

    from export.codegen.templates import TEMPLATE_DIR

    generic = [p for p in TEMPLATE_DIR.rglob("*") if p.is_file() and p.suffix in (".j2", ".c", ".h")
               and "tasks" not in p.relative_to(TEMPLATE_DIR).parts]
    assert len(generic) > 20
    assert [p.name for p in generic if re.search(r"beacon|target_uid", p.read_text(), re.I)] == []
