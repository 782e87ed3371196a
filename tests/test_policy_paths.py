"""kiloforge.policies.policy_paths: every policy a benchmark or an experiment compares gets its own column label."""
from __future__ import annotations

from pathlib import Path

import pytest

from kiloforge.policies import policy_paths


def test_labels_are_short_and_unique():
    """Run dirs by name, files by stem, grown to more of the path where two collide; a repeat is a ValueError."""
    assert policy_paths(["runs/a", "x/default_policy.npz"]) == {
        "a": Path("runs/a/policy_best.npz"), "default_policy": Path("x/default_policy.npz")}
    got = policy_paths(["r/s1/policy_best.npz", "r/s2/policy_best.npz", "runs/s3"])
    assert list(got) == ["s1/policy_best", "s2/policy_best", "s3"]
    assert got["s3"] == Path("runs/s3/policy_best.npz")
    got = policy_paths(["a/r1/generations/gen_060.npz", "a/r2/generations/gen_060.npz", "a/r2/generations/gen_055.npz"])
    assert list(got) == ["r1/generations/gen_060", "r2/generations/gen_060", "gen_055"]
    with pytest.raises(ValueError, match="'r/s1/policy_best' is given twice"):
        policy_paths(["r/s1/policy_best.npz", "r/s1/policy_best.npz"])
