"""Fuzzing, a CI-sized slice (tests/soak/fuzz_all.py runs the same targets on >= 10,000 inputs): policy files,
world JSON, ONNX graphs and command lines either work or fail with one clean line; never a traceback, a
partial output or an accepted corrupt file (the targets and the property: tests/fuzz_targets.py)."""
from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from hypothesis import example, given

from tests import fuzz_commands as fc
from tests import fuzz_targets as ft

pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def work():
    with tempfile.TemporaryDirectory(prefix="kf-fuzz-") as d:
        root = Path(d)
        yield root, ft.Fixtures(root / "fixtures")


def _ok(outcome: tuple[str, str]) -> None:
    kind, detail = outcome
    assert kind in ("accepted", "rejected"), f"{kind}: {detail}"


@ft.fuzz_settings(40)
@given(case=ft.policy_byte_mutation())
def test_fuzz_policy_bytes(work, case):
    """Byte-level damage to a valid policy file of every kind: refused in one line, or still the same policy."""
    data, original = case
    _ok(ft.check_policy_file(data, work[0], original))


@ft.fuzz_settings(60)
@given(case=ft.policy_meta_mutation())
def test_fuzz_policy_meta(work, case):
    """Any JSON field of a policy's meta set to any value or literal, re-hashed or not: refused, or valid."""
    data, original = case
    _ok(ft.check_policy_file(data, work[0], original))


@ft.fuzz_settings(40)
@given(case=ft.policy_array_mutation())
def test_fuzz_policy_arrays(work, case):
    """Arrays reshaped, retyped, poisoned, pickled, renamed; zip layouts varied: refused, or valid."""
    data, original = case
    _ok(ft.check_policy_file(data, work[0], original))


@ft.fuzz_settings(60)
@given(text=ft.world_json_text())
@example(text='{"world": "kilobot"}')  # no t_prev: the model's input width gives it
def test_fuzz_world_json(work, text):
    """--world-json documents and random text: refused in one line, or a world holding exactly what was given."""
    _ok(ft.check_world_json(text, work[0], work[1].onnx_bare))


@ft.fuzz_settings(40)
@given(data=ft.onnx_mutation())
def test_fuzz_onnx(work, data):
    """Mutated ONNX actors: refused in one line, or imported computing what onnxruntime computes."""
    pytest.importorskip("onnxruntime")
    _ok(ft.check_onnx(data, work[0]))


@ft.fuzz_settings(40)
@given(data=ft.st.data())
def test_fuzz_export_cli(work, data):
    """Random `python -m export` argv (all sub-commands, sometimes over an old set): exit 0 with a verified set,
    or 1/2 with one line and the output directory as it was."""
    _ok(ft.cli_case("export", data, work[1], work[0] / "export_out"))


@ft.fuzz_settings(6)
@given(data=ft.st.data())
def test_fuzz_sim_cli(work, data):
    """Random `python -m sim` argv: all four outputs, or one line and nothing written."""
    _ok(ft.cli_case("sim", data, work[1], work[0] / "sim_out"))


# --- issue 47: every command through the kiloforge entry machinery (tests/fuzz_commands.py) -------------------
@pytest.fixture(scope="module")
def names_fx(work):
    return fc.NameFixtures(work[0] / "name_fixtures")


@pytest.mark.parametrize("target,n", [("names", 6), ("run_folders", 20), ("stdout", 10), ("disk_full", 3),
                                      ("weights", 4), ("part_a", 8)])
def test_fuzz_issue_47_targets(work, names_fx, target, n):
    """Hostile names, run folders, standard outputs, full disks, huge weights and part A's causes through the
    kiloforge command: a success with every output, or one clean line with nothing written; never a hang."""
    check = {"names": lambda d: fc.names_case(d, names_fx, work[0]),
             "run_folders": lambda d: fc.run_folder_case(d, work[0]),
             "stdout": lambda d: fc.stdout_case(d, names_fx, work[0]),
             "disk_full": lambda d: fc.disk_full_case(d, names_fx, work[0]),
             "weights": lambda d: fc.weights_case(d, work[0]),
             "part_a": lambda d: fc.part_a_case(d, names_fx, work[0])}[target]

    @ft.fuzz_settings(n)
    @given(data=ft.st.data())
    def run(data):
        _ok(check(data))
    run()
