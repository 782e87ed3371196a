"""Exact AVR budgets (export.verify.avr.exact_budget) and robot builds against a kilolib checkout."""
from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.avr_tools import require_avr
from export.verify import avr
from export.codegen.budget import FLASH_LIMIT_B, KILOLIB_FLASH_B
from export.codegen.render import POLICY_FILE, render_firmware
from tests.fixtures import TARGET_FILE, synthetic_qpolicy
from sim.config import preset

pytestmark = pytest.mark.avr

WORLD = preset("kilobot", period_ticks=6)


def test_empty_program_costs_exactly_kilolib(tmp_path):
    """The kilolib correction: an empty setup/loop program is kilolib's 7,028 B flash and 0 B user SRAM."""
    require_avr()
    pb = avr.program_budget("empty.c", avr.EMPTY_PROGRAM, tmp_path)
    assert (pb.flash, pb.sram_static) == (KILOLIB_FLASH_B, 0)
    assert pb.sizes == pb.standin


def test_exact_budget_of_a_rendered_policy():
    """Exact figures are consistent (text+data corrected; SRAM = static + stack) and grow with the weights."""
    require_avr()
    small, big = (synthetic_qpolicy(WORLD, 4, (h,), seed=1) for h in (8, 24))
    eb_small = avr.exact_budget(render_firmware(small))
    eb_big = avr.exact_budget(render_firmware(big))
    for eb in (eb_small, eb_big):
        assert KILOLIB_FLASH_B < eb["flash"] <= FLASH_LIMIT_B
        assert eb["sram_user"] == eb["sram_static"] + eb["stack"] and eb["stack_source"] == "estimate"
        assert eb["kilobot_target_flash"] < eb["flash"]
    extra_weights = (24 - 8) * (small.layers[0].w.shape[1] + 2)  # int8 weights only, kernel arrays add more
    assert eb_big["flash"] - eb_small["flash"] > extra_weights
    assert eb_big["sram_static"] - eb_small["sram_static"] < 64  # weights stay in flash (PROGMEM)


def test_exact_budget_measures_the_stack_in_simavr():
    """With the policy given and simavr installed, the stack figure is measured, not estimated."""
    require_avr(simulate=True)
    qp = synthetic_qpolicy(WORLD, 4, (16,), seed=2)
    eb = avr.exact_budget(render_firmware(qp), qp, stack_steps=10)
    assert eb["stack_source"] == "simavr" and 20 < eb["stack"] < 600
    assert eb["sram_user"] == eb["sram_static"] + eb["stack"]


def _fake_kilolib(d):
    """A kilolib checkout look-alike: our stand-in as kilolib.h + build/kilolib.a."""
    (d / "build").mkdir(parents=True)
    (d / "kilolib.h").write_text((avr.STANDIN_DIR / "kilolib.h").read_text())
    obj = d / "build" / "kilolib.o"
    subprocess.run(["avr-gcc", *avr.KILOLIB_CFLAGS, "-c", "-o", str(obj), str(avr.STANDIN_DIR / "kilolib_avr.c")],
                   check=True)
    subprocess.run(["avr-ar", "rcs", str(d / "build" / "kilolib.a"), str(obj)], check=True)
    return d


def test_build_for_robot_writes_elf_and_hex(tmp_path):
    """Against a kilolib checkout: an .elf and an Intel-hex .hex per program, hex bytes = text + data."""
    require_avr()
    files = render_firmware(synthetic_qpolicy(WORLD, 2, (8,), seed=3))
    builds = avr.build_for_robot(files, _fake_kilolib(tmp_path / "kilolib"), tmp_path / "out")
    assert set(builds) == {POLICY_FILE, TARGET_FILE}
    for b in builds.values():
        lines = b.hex.read_text().split()
        assert lines[-1] == ":00000001FF" and all(l.startswith(":") for l in lines)
        data = sum(int(l[1:3], 16) for l in lines if l[7:9] == "00")
        assert data == b.sizes.flash


def test_robot_images_are_the_built_files(tmp_path):
    """robot_images returns the .elf and .hex bytes of both programs (for an atomic write by the CLI)."""
    require_avr()
    files = render_firmware(synthetic_qpolicy(WORLD, 2, (8,), seed=4))
    images, sizes = avr.robot_images(files, _fake_kilolib(tmp_path / "kilolib"))
    assert set(images) == {"kilobot_policy.elf", "kilobot_policy.hex", "kilobot_target.elf", "kilobot_target.hex"}
    assert images["kilobot_policy.elf"][:4] == b"\x7fELF" and images["kilobot_policy.hex"].startswith(b":")
    (tmp_path / "kp.elf").write_bytes(images["kilobot_policy.elf"])
    assert sizes[POLICY_FILE] == avr.sizes(tmp_path / "kp.elf") and set(sizes) == {POLICY_FILE, TARGET_FILE}


def test_find_kilolib_explains_an_unbuilt_checkout(tmp_path):
    """A directory without kilolib.h / build/kilolib.a gets a message that says what to do."""
    with pytest.raises(avr.AvrError, match="make"):
        avr.find_kilolib(tmp_path)


def _kilolibs() -> list:
    """The kilolib checkouts to export against: our stand-in built as one, and a real one in $KILOLIB_DIR."""
    real = os.environ.get("KILOLIB_DIR")
    return ["stand-in", pytest.param(real, marks=pytest.mark.skipif(
        not real, reason="KILOLIB_DIR unset (a kilolib checkout built with make: github.com/acornejo/kilolib)"))]


@pytest.mark.parametrize("kilolib", _kilolibs())
def test_export_with_kilolib_prints_the_elf_flash_and_lists_images(kilolib, tmp_path, capsys):
    """export --kilolib: the printed flash is the built ELF's text + data (avr-size), and the manifest lists the
    .hex/.elf files with their sha256 (verify_manifest checks them)."""
    require_avr()
    from export.cli.main import main
    from export.codegen.manifest import verify_manifest

    kdir = _fake_kilolib(tmp_path / "kilolib") if kilolib == "stand-in" else Path(kilolib)
    out = tmp_path / "kp.c"
    assert main(["--out", str(out), "--kilolib", str(kdir), "--robots-calib", "2", "--calib-steps", "5", "--quiet"]) == 0
    stdout = capsys.readouterr().out
    flash = avr.sizes(tmp_path / "kp.elf").flash
    assert f"FITS: flash {flash:,d} / " in stdout and "flash_source kilolib build" in stdout
    files = json.loads((tmp_path / "kp.c.manifest.json").read_text())["files"]
    assert set(files) == {"kp.c", "kp.elf", "kp.hex", "kilobot_target.c", "kilobot_target.elf", "kilobot_target.hex"}
    assert verify_manifest(tmp_path / "kp.c.manifest.json") == []
