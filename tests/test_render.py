"""The firmware renderer: golden files, template coverage, banner, escaping, constants, argument checks."""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from export.codegen.cformat import c_comment, clamp_index_table, nonzero_windows
from export.codegen.render import POLICY_FILE, render_firmware
from export.codegen.templates import TEMPLATE_DIR, templates_loaded
from export.contract import firmware as fwspec
from export.errors import ExportError
from tests.fixtures import synthetic_qpolicy
from kiloforge import numfmt
from kiloforge.actors.gru import quantize_gru, random_gru_policy
from kiloforge.actors.recurrent import calibration_from_sequences
from tests.regen_golden import GOLDEN_DIR, GOLDEN_VERSION, TARGET_GOLDEN, golden_files, golden_mlp, golden_policies, render
from sim.config import preset
from sim.motion import schedule_constants


def _define(text: str, name: str) -> str:
    m = re.search(rf"^#define {name} (.+?)(?: /\*.*)?$", text, re.M)
    assert m, f"{name} is not defined"
    return m.group(1).strip()


def _code_only(c: str) -> str:
    """C text without comments, string literals (inline asm) and #include lines."""
    c = re.sub(r"/\*.*?\*/", " ", c, flags=re.S)
    c = re.sub(r'"(?:[^"\\\n]|\\.)*"', '""', c)
    return re.sub(r"^\s*#\s*include.*$", "", c, flags=re.M)


def test_golden_files_match_byte_for_byte():
    """Each kind's fixed golden policy renders, hand-written C aside, exactly to the committed tests/golden/<kind>.c."""
    from kiloforge.actors.registry import KINDS

    files = golden_files()
    assert set(files) == {f"{k}.c" for k in KINDS} | {TARGET_GOLDEN}
    assert {p.name for p in GOLDEN_DIR.iterdir()} == set(files), "stale or missing golden files"
    for name, text in files.items():
        want = (GOLDEN_DIR / name).read_text(encoding="utf-8")
        assert text == want, (f"{name} differs from tests/golden/{name}; if the change is intended run "
                              f"`python -m tests.regen_golden` and review the diff")


def test_every_template_is_rendered():
    """Every *.j2 in firmware_templates/ is loaded by some render (here: the golden and a wide policy)."""
    golden_files()  # every kind's partial
    render_firmware(synthetic_qpolicy(preset("kilobot"), 2, (5, 3), ("relu", "tanh")), generator_version="t")
    light = dataclasses.replace(preset("kilobot"), emitter=False, obs_features="light,rbf,random")  # light and random
    render_firmware(synthetic_qpolicy(light, 2, (5,)), generator_version="t")
    obj = dataclasses.replace(preset("kilobot"), obs_features="light,target,object_light,rbf")  # the beacon's light
    render_firmware(synthetic_qpolicy(obj, 2, (5,)), generator_version="t")
    gru = random_gru_policy(preset("kilobot"), 4)
    render_firmware(quantize_gru(gru, calibration_from_sequences(gru, np.zeros((1, 2, gru.in_dim)))),
                    generator_version="t")
    on_disk = {p.relative_to(TEMPLATE_DIR).as_posix() for p in TEMPLATE_DIR.rglob("*.j2")}
    assert on_disk, "no templates found"
    assert on_disk <= templates_loaded(), f"never rendered: {sorted(on_disk - templates_loaded())}"


def test_render_is_deterministic_and_pure():
    """Rendering twice gives identical text; the policy object is not modified."""
    qp = golden_mlp()
    w0 = qp.layers[0].w.copy()
    assert render(qp) == render(qp)
    np.testing.assert_array_equal(qp.layers[0].w, w0)


def test_banner_names_version_hash_and_format():
    """The do-not-edit banner carries the generator version, the policy hash and the number format."""
    for qp in golden_policies().values():
        for text in render(qp).values():
            head = text.split("*/", 1)[0]
            assert "DO NOT EDIT" in head
            assert f"kiloforge {GOLDEN_VERSION}" in head
            assert qp.policy_hash in head
            assert numfmt.FORMAT_NAME in head and numfmt.ROUNDING in head


def test_world_name_is_comment_safe():
    """Free text from the policy (the world name) cannot end the banner comment or inject code."""
    w = dataclasses.replace(preset("thesis"), name="evil */ int pwned; /* \u00e9 ??=")  # newlines: refused by WorldConfig
    qp = synthetic_qpolicy(w, 1, (3,))
    text = render_firmware(qp, generator_version="x */ y")[POLICY_FILE]
    banner, rest = text.split("*/", 1)
    assert "pwned" in banner and "pwned" not in rest
    assert "x * / y" in banner
    assert "??=" not in text


def test_defines_follow_config_and_motion():
    """Rendered constants equal the world config, sim.motion's schedule constants and fwspec."""
    w = preset("kilobot")
    qp = synthetic_qpolicy(w, 4, (6,))
    text = render_firmware(qp, generator_version="t", msg_type=0x33)[POLICY_FILE]
    k_turn, k_straight = schedule_constants(w.period_ticks)
    assert _define(text, "KF_K_TURN") == f"{k_turn}u"
    assert _define(text, "KF_K_STRAIGHT") == f"{k_straight}u"
    assert _define(text, "KF_PERIOD_TICKS") == f"{w.period_ticks}u"
    assert _define(text, "KF_NBR_CAPACITY") == f"{w.neighbour_table_size}u"
    assert _define(text, "KF_RXQ_CAPACITY") == f"{fwspec.RXQ_CAPACITY}u"
    assert _define(text, "KF_MSG_TYPE") == "51u"
    assert _define(text, "KF_MSG_VERSION") == f"{fwspec.MSG_VERSION}u"
    assert _define(text, "KF_T_PREV") == "4u"
    assert _define(text, "KF_ONE") == f"((int8_t){1 << qp.e_in})"
    assert _define(text, "KF_LIGHT_THRESHOLD") == f"((int16_t){w.light_threshold})"


def test_generated_c_has_no_float_or_division_in_code():
    """Outside comments the programs use no float types, no float literals and no division."""
    for text in (t for qp in golden_policies().values() for t in render(qp).values()):
        code = _code_only(text)
        assert not re.search(r"\b(float|double)\b", code)
        assert not re.search(r"\d\.\d", code), "a float literal reached the C"
        assert not re.search(r"[^/*]/[^/*=]", code), "a division operator reached the C"
        assert not re.search(r"\bmalloc\b", code)
        assert re.search(r"PROGMEM", code)


def test_trimmed_tables_are_exact():
    """The clamped target table and the windowed RBF table reproduce numfmt's full 256-entry tables."""
    for w in (preset("thesis"), preset("kilobot"), preset("kilobot", comm_radius_mm=255.0, rbf_sigma_mm=40.0)):
        tgt = numfmt.target_table(w.comm_radius_mm, 6)
        prefix, last = clamp_index_table(tgt)
        d = np.arange(256)
        np.testing.assert_array_equal(prefix[np.minimum(d, last)], tgt)
        rbf = numfmt.rbf_table(w.rbf_centres_mm, w.rbf_sigma_mm, w.rbf_norm, w.comm_radius_mm, 6)
        lo, n, off, packed = nonzero_windows(rbf)
        rebuilt = np.zeros_like(rbf)
        for k in range(rbf.shape[0]):
            j = (d - lo[k]) % 256  # the C's uint8 wrap-around
            inside = j < n[k]
            rebuilt[k, inside] = packed[off[k] + j[inside]]
        np.testing.assert_array_equal(rebuilt, rbf)


@pytest.mark.parametrize("kwargs, match", [
    ({"msg_type": 1}, "GPS"),
    ({"msg_type": 0x80}, "user type"),
    ({"emitter_uids": ()}, "emitter uids"),
    ({"emitter_uids": (70000,)}, "65535"),
    ({"emitter_uids": ("a",)}, "integers"),
])
def test_bad_arguments_give_one_line_errors(kwargs, match):
    """Bad message types and target uids raise ExportError with a one-line message."""
    with pytest.raises(ExportError, match=match) as err:
        render_firmware(golden_mlp(), generator_version="t", **kwargs)
    assert "\n" not in str(err.value)


def test_bad_policy_hash_is_rejected():
    """A policy hash that is not hex never reaches the banner."""
    qp = dataclasses.replace(golden_mlp(), policy_hash="abc */ x")
    with pytest.raises(ExportError, match="hex"):
        render_firmware(qp, generator_version="t")


def test_target_uids_reach_the_table():
    """The configured target uids are the entries of KF_TARGET_UIDS (duplicates dropped)."""
    text = render_firmware(golden_mlp(), emitter_uids=(5, 300, 5), generator_version="t")[POLICY_FILE]
    m = re.search(r"KF_TARGET_UIDS\[(\d+)\] PROGMEM = \{\s*([^}]*)\}", text)
    assert m and m.group(1) == "2"
    assert [v.strip() for v in m.group(2).split(",")] == ["5u", "300u"]


def test_comment_helper_breaks_terminators():
    """c_comment never lets '*/' or '/*' through, whatever the input."""
    for s in ("*/", "/*", "**//**", "a*/*/b", "*" * 5 + "/" * 5):
        out = c_comment(s)
        assert "*/" not in out and "/*" not in out


def test_doctests_of_the_firmware_helpers():
    """The doctests of the C formatting, CRC, firmware-constant and emulator modules pass."""
    import doctest

    from export.codegen import cformat
    from export.contract import crc
    from export.contract import firmware as fw
    from export.verify import emulator

    for mod in (cformat, crc, fw, emulator):
        res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS)
        assert res.attempted > 0 and res.failed == 0, f"{mod.__name__}: {res}"
