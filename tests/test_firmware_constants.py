"""Each constant of the number format and the firmware contract is defined once, in Python, and the rendered C uses it."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from export.codegen.render import POLICY_FILE
from export.codegen.templates import TEMPLATE_DIR
from export.contract import crc
from export.contract import firmware as fw
from kiloforge import numfmt
from tests.regen_golden import golden_files, golden_policies, render
from tests.fixtures import TARGET_FILE

ROOT = Path(__file__).resolve().parents[1]
KINDS = sorted(golden_policies())


def defines(text: str) -> dict[str, str]:
    """``#define NAME VALUE`` of a C text (comments stripped)."""
    return {m.group(1): m.group(2).strip() for m in re.finditer(r"^#define (KF_\w+) (.+?)(?: /\*.*)?$", text, re.M)}


def c_int(value: str) -> int:
    """An integer literal as the renderer writes it: 8u, 70000UL, -5, ((int8_t)64), (-2147483647L - 1L)."""
    m = re.fullmatch(r"\(\((?:u?int\d+_t)\)(-?\d+[uUlL]*)\)", value)
    v = m.group(1) if m else value
    return int(v.rstrip("uUlL"))


def arrays(text: str) -> dict[str, int]:
    """Name -> length of every ``static const T NAME[n] PROGMEM`` array."""
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"static const \w+ (KF_\w+)\[(\d+)\] PROGMEM", text)}


@pytest.fixture(scope="module", params=KINDS)
def program(request):
    qp = golden_policies()[request.param]
    return qp, render(qp)


CONTRACT = {  # rendered name -> its one definition (in both programs)
    "KF_MSG_VERSION": fw.MSG_VERSION, "KF_READY": fw.STATE_READY,
    "KF_ROLE_BIT": fw.ROLE_BIT, "KF_SENSING_BIT": fw.SENSING_BIT, "KF_MSG_DATA_BYTES": fw.MSG_DATA_BYTES,
    "KF_MSG_USED_BYTES": fw.MSG_USED_BYTES, "KF_MSG_INFO_BYTE": fw.MSG_INFO_BYTE,
    "KF_CRC_POLY": crc.POLY_REFLECTED, "KF_CRC_INIT": crc.INIT, "KF_MSG_TYPE": fw.DEFAULT_MSG_TYPE,
}
#: what a program of a world without a beacon leaves out
BEACON_ONLY = ("KF_ROLE_BIT", "KF_SENSING_BIT", "KF_LED_BEACON", "KF_LED_SENSING", "KF_LED_NBR_SENSING")
LEDS = {"KF_LED_OFF": fw.LED_OFF, "KF_LED_BEACON": fw.LED_EMITTER, "KF_LED_SENSING": fw.LED_SENSING,
        "KF_LED_NBR_SENSING": fw.LED_NBR_SENSING}


def test_beacon_light_constants_are_rendered_from_python():
    """Both programs of a world whose layout reads the beacon's light (object_light) define the message's light byte,
    LIGHT_NONE and the ADC's maximum from export.contract; programs without it (every golden policy) none of them."""
    from export.codegen.render import render_firmware
    from sim.config import preset
    from sim.light import ADC_MAX
    from tests.fixtures import synthetic_qpolicy

    world = dataclasses.replace(preset("kilobot"), obs_features="light,target,object_light,rbf")
    files = render_firmware(synthetic_qpolicy(world, 2, (5,)), generator_version="t")
    for name in (POLICY_FILE, TARGET_FILE):
        d = defines(files[name])
        assert c_int(d["KF_MSG_LIGHT_BYTE"]) == fw.MSG_LIGHT_BYTE and c_int(d["KF_LIGHT_NONE"]) == fw.LIGHT_NONE
        assert c_int(d["KF_ADC_MAX"]) == ADC_MAX
    for qp in golden_policies().values():
        for text in render(qp).values():
            assert "KF_MSG_LIGHT_BYTE" not in text and "kf_beacon_light" not in text


def test_contract_constants_are_rendered_from_python(program):
    """Message layout, queue size, ready value, CRC and LEDs in both programs (one without a beacon, and none of the
    beacon's constants) equal export.contract's."""
    qp, files = program
    beacon = qp.world.emitter
    for name in (POLICY_FILE, TARGET_FILE) if beacon else (POLICY_FILE,):
        d = defines(files[name])
        for key, want in CONTRACT.items():
            if key in BEACON_ONLY and not beacon:
                assert key not in d, (name, key)
            else:
                assert c_int(d[key]) == want, (name, key)
        for key, rgb in LEDS.items():
            if (key in BEACON_ONLY and not beacon) or (key == "KF_LED_NBR_SENSING"
                                                       and not qp.world.has_feature("nbr_sensing")):
                assert key not in d, (name, key)  # that LED shows the nbr_sensing input
            else:
                assert d[key] == "(RGB({}, {}, {}))".format(*rgb), (name, key)
    assert (TARGET_FILE in files) == beacon
    d = defines(files[POLICY_FILE])
    assert c_int(d["KF_RXQ_CAPACITY"]) == fw.RXQ_CAPACITY and c_int(d["KF_ONE"]) == 1 << qp.e_in
    assert c_int(d["KF_TUPLE_DIM"]) == qp.world.tuple_dim and c_int(d["KF_OBS_DIM"]) == qp.world.obs_dim
    if beacon:  # "target not heard"
        assert c_int(d["KF_MINUS_ONE"]) == -(1 << qp.e_in)


def test_number_format_constants_are_rendered_from_python(program):
    """Gate exponent, table sizes and the dense layers' clamps in the program equal kiloforge.numfmt's."""
    qp, files = program
    text = files[POLICY_FILE]
    d = defines(text)
    if "KF_GATE_EXP" in d:
        assert c_int(d["KF_GATE_EXP"]) == numfmt.GATE_EXP
    tables = {k: n for k, n in arrays(text).items() if re.match(r"KF_(ACT|ACTFN\d+|GATE_\w+|TANH\w*)$", k)}
    assert "KF_ACT" in tables and all(n == numfmt.TABLE_SIZE for n in tables.values()), tables
    descs = re.findall(r"static const kf_dense_t \w+ = \{ \w+, \w+, \w+, (\d+)u, (\d+)u, (-?\d+), (-?\d+), [01]u \}", text)
    assert len(descs) == len(qp.layers)
    if qp.layers:  # a rule-based actor (the searcher) has none
        clamps = [(int(lo), int(hi)) for _, _, lo, hi in descs]
        assert clamps[-1] == (0, numfmt.UINT8_MAX)
        assert all(c == (numfmt.INT8_MIN, numfmt.INT8_MAX) for c in clamps[:-1])


def test_hand_written_c_defines_none_of_them():
    """No template or hand-written C file defines a constant the renderer or the build defines (no second copy)."""
    rendered = set(CONTRACT) | set(LEDS) | {"KF_RXQ_CAPACITY", "KF_GATE_EXP", "KF_CELL_MAX", "KF_MARK_STEP_BEGIN", "KF_MARK_STEP_END",
                                            "KF_MARK_FAIL"}
    for text in golden_files().values():  # the generated part only: the inlined hand-written C aside
        rendered |= set(defines(text))
    for path in sorted(TEMPLATE_DIR.rglob("*")):
        if path.suffix in (".h", ".c", ".j2"):
            own = set(re.findall(r"^\s*#\s*define (KF_\w+)", path.read_text(), re.M))
            assert not own & rendered, f"{path.relative_to(ROOT)} defines {sorted(own & rendered)}"


def test_message_payload_matches_the_kilolib_stand_ins():
    """Both kilolib stand-ins declare message_t with export.contract's payload size."""
    for name in ("host/kilolib.h", "avr/kilolib.h"):
        m = re.search(r"uint8_t data\[(\d+)\];", (TEMPLATE_DIR / name).read_text())
        assert m and int(m.group(1)) == fw.MSG_DATA_BYTES, name


@pytest.mark.parametrize("name, home", [
    ("TABLE_ACTIVATIONS", "kiloforge/numfmt.py"), ("ACC32_LIMIT", "kiloforge/numfmt.py"),
    ("ACC24_LIMIT", "kiloforge/numfmt.py"), ("GATE_EXP", "kiloforge/numfmt.py"), ("HIDDEN_EXP", "kiloforge/numfmt.py"),
    ("RXQ_CAPACITY", "export/contract/firmware.py"), ("MSG_BYTES", "export/contract/firmware.py"),
    ("MSG_DATA_BYTES", "export/contract/firmware.py"), ("POLY_REFLECTED", "export/contract/crc.py"),
])
def test_python_constants_are_defined_once(name, home):
    """The constant is assigned in its home module and nowhere else in sim, learn, export or kiloforge."""
    where = [str(p.relative_to(ROOT)) for pkg in ("sim", "learn", "export", "kiloforge") for p in (ROOT / pkg).rglob("*.py")
             if re.search(rf"^\s*{name}\s*(:[^=]+)?=", p.read_text(), re.M)]
    assert where == [home]


def test_no_literal_half_up_constant_or_accumulator_limit():
    """In export and kiloforge, 2^31 and the half-up constant 1 << (s - 1) are written only in kiloforge/numfmt.py
    (cformat's C type ranges aside)."""
    pattern = re.compile(r"2 \*\* 31|2\*\*31|1 << \(s - 1\)|left_shift\(np\.int64\(1\), np\.maximum\(s - 1")
    for pkg in ("export", "kiloforge"):
        for p in (ROOT / pkg).rglob("*.py"):
            if p.name in ("numfmt.py", "cformat.py"):
                continue
            code = "\n".join(ln for ln in p.read_text().splitlines() if not ln.lstrip().startswith("#"))
            code = re.sub(r'"""(?:.|\n)*?"""', "", code)  # docstrings may explain the rule
            assert not pattern.search(code), f"{p.relative_to(ROOT)} writes the constant again"


def test_flashing_checklist_reads_the_leds_the_firmware_sets():
    """docs/flashing.md's LED table names each LED_* colour of the contract with its meaning, and no other colour."""
    colour = {(0, 0, 1): "blue", (0, 1, 0): "green", (1, 1, 0): "yellow", (0, 0, 0): "off"}
    rows = dict(re.findall(r"^\s*\| (blue \(dim\)|green|yellow|off) \| (.+) \|$",
                           (ROOT / "docs" / "flashing.md").read_text(), re.M))
    expected = {fw.LED_EMITTER: "beacon", fw.LED_SENSING: "heard the beacon", fw.LED_NBR_SENSING: "neighbour",
                fw.LED_OFF: "neither"}
    assert len(rows) == len(expected) == 4
    for rgb_value, meaning in expected.items():
        name = next(k for k in rows if k.split()[0] == colour[rgb_value])
        assert meaning in rows[name], (name, rows[name])
