"""One torch across the install: the learn extra's bound (pyproject.toml), the test set-up's pin (tests/run.sh)
and the CPU-only install line of the README and docs/training.md."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
from packaging.requirements import Requirement

tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

ROOT = Path(__file__).resolve().parents[1]
CPU_INDEX = "https://download.pytorch.org/whl/cpu"


def _pin() -> str:
    """The torch version tests/run.sh installs (``TORCH="torch==X.Y.Z"``)."""
    m = re.search(r'^TORCH="torch==(\d+\.\d+\.\d+)"$', (ROOT / "tests" / "run.sh").read_text(), re.M)
    assert m, "tests/run.sh pins no torch==X.Y.Z"
    return m.group(1)


def test_learn_extra_admits_the_tested_torch_and_no_newer_minor():
    """The learn extra's torch bound holds run.sh's torch==X.Y.Z and ends below X.(Y+1), so it never resolves
    a torch the tests did not run."""
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    torch = [Requirement(r) for r in extras["learn"] if Requirement(r).name == "torch"]
    assert len(torch) == 1
    pin = _pin()
    major, minor = map(int, pin.split(".")[:2])
    assert torch[0].specifier.contains(pin)
    assert not torch[0].specifier.contains(f"{major}.{minor + 1}.0")


def test_cpu_install_line_names_the_tested_torch():
    """README and docs/training.md give the CPU-only install of the tested torch from the CPU index run.sh uses."""
    line = f"pip install torch=={_pin()} --index-url {CPU_INDEX}"
    assert CPU_INDEX in (ROOT / "tests" / "run.sh").read_text()
    for doc in ("README.md", "docs/training.md"):
        assert line in (ROOT / doc).read_text(), doc
