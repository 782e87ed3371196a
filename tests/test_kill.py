"""Killed at random moments (a few, CI-sized; tests/bench/kill_test.py runs 200 exports and 50 trainings):
an export leaves the old complete set or the new one, a training resumes or restarts (tests/kill_harness.py)."""
from __future__ import annotations

import signal

import numpy as np
import pytest

import kill_harness as kh


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    return kh.reference_sets(tmp_path_factory.mktemp("ref"))


@pytest.mark.parametrize("sig, moment", [(signal.SIGKILL, "commit"), (signal.SIGINT, "commit"),
                                         (signal.SIGINT, "uniform")])
def test_killed_export_leaves_old_or_new_set(tmp_path, sets, sig, moment):
    """An export killed (SIGKILL) or interrupted (SIGINT) mid-run or mid-publish: old or new complete set, a
    present manifest matches its files, no temporaries after the next run's recovery, an honest message."""
    old, new, duration = sets
    rng = np.random.default_rng(np.random.SeedSequence([sig, len(moment)]))
    r = kh.kill_export(tmp_path / "out", old, new, sig, moment, rng, duration)
    assert r.ok, r
    assert r.after in ("old", "new")
