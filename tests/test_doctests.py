"""Run the doctests of every module in sim/, kiloforge/ and export/ (number-formatting helpers document themselves)."""
from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import export
import kiloforge
import sim

MODULES = sorted(m.name for pkg in (sim, kiloforge, export)
                 for m in pkgutil.walk_packages(pkg.__path__, prefix=f"{pkg.__name__}.")
                 if not m.name.rsplit(".", 1)[-1].startswith("__"))


@pytest.mark.parametrize("name", MODULES)
def test_module_doctests(name):
    """The module's doctests pass (modules needing an optional package skip when it is missing)."""
    try:
        mod = importlib.import_module(name)
    except ImportError as e:  # e.g. sim.pettingzoo_env without pettingzoo
        pytest.skip(f"{name} needs an optional package: {e}")
    result = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.failed == 0, f"{result.failed} doctest(s) failed in {name}"
