"""The hand-written transport baseline as firmware (actor kind ``shadow_pusher``, ``--task transport --policy
shadow_pusher``): exact distance thresholds, the integer reference, the host build, the shipped file, the export CLI."""
from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from export.codegen.render import POLICY_FILE, render_firmware
from kiloforge.shipped import load_task_policy
from export.verify.emulator import FirmwareEmulator, FirmwareInputs
from export.verify.hostbuild import StreamSpec, build_host, compare, compiler, random_inputs, run_host
from kiloforge.actors.registry import kind_named
from kiloforge.actors.shadow_pusher import SHADOW_PUSHER, distance_thresholds, shadow_pusher_policy
from sim.config import preset
from sim.motion import action_to_u8
from sim.tasks import TaskRef, get_task
from sim.tasks.transport import ShadowPusherParams

needs_cc = pytest.mark.skipif(compiler() is None, reason="no host C compiler (gcc) installed")
WORLD = get_task("transport").world(preset("kilobot"))


@functools.lru_cache(maxsize=None)
def shipped():
    """`--task transport --policy shadow_pusher` and its integer rule."""
    p = load_task_policy("shadow_pusher", "transport")
    return p, SHADOW_PUSHER.quantize_rule(p, None)


def _stream(seed: int, n_robots: int = 48, n_steps: int = 80) -> FirmwareInputs:
    """Fuzzed radio (a third of the messages the object robot's, at distances 0..255) and light (near the dark
    threshold, drifting, -1, 0, 1023); no robot is the object's."""
    rng = np.random.default_rng(np.random.SeedSequence([44, seed]))
    spec = StreamSpec(n_robots=n_robots, n_steps=n_steps, rate=0.4, target_p=0.3, emitter_p=0.0)
    inputs = random_inputs(rng, WORLD.period_ticks, (WORLD.emitter_uid,), spec, comm_radius_mm=WORLD.comm_radius_mm,
                           light_threshold=shipped()[0].params.dark)
    light = inputs.light.astype(np.int64)
    drift = np.clip(550 + np.cumsum(rng.integers(-30, 31, light.shape), 1), 0, 1023)
    light = np.where(rng.random(light.shape) < 0.5, drift, light)
    light[inputs.light < 0] = -1
    return dataclasses.replace(inputs, light=light.astype(np.int16))


def test_kind_is_registered_and_shipped_for_task_transport():
    """The registry maps the name to its kind; export/data/shadow_pusher_policy.npz is the tuned rule in transport's
    kilobot world (rewrite it with python -m tools.ship_rules when either changes)."""
    p, qp = shipped()
    assert kind_named("shadow_pusher") is SHADOW_PUSHER and p.kind == "shadow_pusher"
    assert p.task_ref == TaskRef("transport", 2) and p.world == WORLD and p.params == ShadowPusherParams()
    assert p.hash == shadow_pusher_policy(preset("kilobot")).hash, "stale: python -m tools.ship_rules"
    c = render_firmware(qp, generator_version="t")[POLICY_FILE]
    assert "KF_TOUCH_T" in c and "KF_BACK_T" in c and "kf_dense" not in c


@pytest.mark.parametrize("e_in", [6, 4])
def test_distance_thresholds_decide_as_the_float_rule(e_in):
    """For every pair of heard int8 targets, the integer thresholds decide touching and "farther" as the float
    rule's distances tq / ONE * comm radius do, at several parameters."""
    one, k = 1 << e_in, np.arange(0, 128)
    for touch, back in ((72.0, 4.0), (66.5, 0.0), (80.0, 10.5)):
        p = ShadowPusherParams(touch_mm=touch, back_mm=back)
        touch_t, back_t = distance_thresholds(p, WORLD.comm_radius_mm, one)
        d = k / one * WORLD.comm_radius_mm
        np.testing.assert_array_equal(k <= touch_t, d <= touch)
        np.testing.assert_array_equal(k[:, None] - k[None, :] > back_t, d[:, None] > d[None, :] + back)


def test_integer_rule_is_the_float_rule_on_dequantised_observations():
    """The emulator's commands equal sim.tasks.transport's ShadowPusher fed its int8 observations / 2**e_in and the
    firmware's draws; straight runs and both pivots occur."""
    p, qp = shipped()
    inputs = _stream(1)
    out = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
    obs, cmd = out.obs.astype(np.float64) / (1 << qp.e_in), out.commands
    ref = SHADOW_PUSHER.draw_reference(p, inputs.uids)
    ref.reset(1, inputs.uids.size)
    got = np.stack([action_to_u8(ref.act(obs[None, :, t])[0]) for t in range(obs.shape[1])], 1)
    np.testing.assert_array_equal(got, cmd)
    assert {tuple(c) for c in cmd.reshape(-1, 2).tolist()} == {(255, 255), (255, 0), (0, 255)}
    t = obs[..., WORLD.obs_index("target")]
    assert ((t >= 0) & (t * WORLD.comm_radius_mm <= p.params.touch_mm)).any()  # robots touching the object


@needs_cc
def test_host_build_equals_emulator_on_fuzzed_streams(tmp_path):
    """Host build of the shipped rule == the emulator byte for byte over 48 robots x 80 periods of fuzzed streams."""
    qp = shipped()[1]
    exe = build_host(render_firmware(qp, generator_version="test")[POLICY_FILE], tmp_path, name="shadow_pusher")
    for seed in (2, 3):
        inputs = _stream(seed)
        want = FirmwareEmulator(qp, inputs.uids, inputs.calib).run(inputs)
        got = run_host(exe, inputs, WORLD.period_ticks, WORLD.obs_dim, fill=f"random:{seed}")
        np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
        np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))


@needs_cc
def test_export_writes_both_programs_and_verifies(tmp_path, capsys):
    """`python -m export --task transport --policy shadow_pusher --verify avr` (host where avr-gcc or simavr is
    missing): exit 0, bit-exact, the searchers' program and the object robot's kilobot_target.c written."""
    from export.cli.main import main
    from export.verify import avr

    mode = "host" if avr.missing_tools(simulate=True) else "avr"
    rc = main(["--task", "transport", "--policy", "shadow_pusher", "--out", str(tmp_path / "t.c"), "--verify", mode,
               "--robots-calib", "4", "--calib-steps", "20"])
    text = capsys.readouterr().out
    assert rc == 0 and "bit-exact" in text, text
    assert (tmp_path / "t.c").is_file() and (tmp_path / "kilobot_target.c").is_file()
    assert "kf_forward" in (tmp_path / "t.c").read_text()


@pytest.mark.avr
def test_avr_build_fits_the_budget():
    """avr-gcc builds the shipped rule within the flash and SRAM budget; the estimate is within 10 % of it."""
    from export.codegen.budget import FLASH_LIMIT_B, SRAM_LIMIT_B, estimate
    from export.verify import avr
    from kiloforge.actors.light_rules import LightRuleArch
    from tests.avr_tools import require_avr

    require_avr()
    qp = shipped()[1]
    exact = avr.exact_budget(render_firmware(qp), qp, stack_steps=20)
    b = estimate(SHADOW_PUSHER, WORLD, LightRuleArch())
    assert b.with_exact(exact).ok, b.table()
    assert exact["flash"] <= FLASH_LIMIT_B and exact["sram_user"] <= SRAM_LIMIT_B, exact
    assert abs(b.flash_analytic - exact["flash"]) <= 0.1 * exact["flash"], (b.flash_analytic, exact)
