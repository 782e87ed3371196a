"""Killed at random moments (a few, CI-sized; tests/soak/kill_test.py runs 200 exports and 50 trainings):
an export leaves the old complete set or the new one, a training resumes or restarts and ends with the
uninterrupted run's outputs (tests/kill_harness.py)."""
from __future__ import annotations

import signal

import numpy as np
import pytest

from tests import kill_harness as kh


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


#: episodes after warm-up / ES generations of each case: SIGKILL after the first checkpoint (4: two checkpoints,
#: then the end); SIGINT, which finishes the episode batch it lands in, needs batches left after the first one
CASES = {("magddpg", signal.SIGKILL): 4, ("es", signal.SIGKILL): 4, ("magddpg", signal.SIGINT): 100}


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The short trainings, uninterrupted, run on first use: {(algorithm, length): (duration, episodes, run dir)}."""
    root, runs = tmp_path_factory.mktemp("uninterrupted"), {}

    def get(algorithm: str, length: int):
        if (algorithm, length) not in runs:
            runs[algorithm, length] = kh.uninterrupted_training(root / f"{algorithm}{length}", algorithm, length)
        return runs[algorithm, length]
    return get


@pytest.mark.parametrize("algorithm, sig", list(CASES))
def test_killed_training_resumes_to_the_uninterrupted_outputs(tmp_path, uninterrupted, algorithm, sig):
    """A training SIGKILLed (or SIGINTed) at a random moment after its first checkpoint and resumed ends with the
    uninterrupted run's outputs: policy arrays bit-identical, the same meta and metrics but for time taken."""
    length = CASES[algorithm, sig]
    duration, episodes, ref = uninterrupted(algorithm, length)
    rng = np.random.default_rng(np.random.SeedSequence([7, len(algorithm), sig]))
    r = kh.kill_training(tmp_path / "run", sig, "training", rng, duration, episodes, ref, algorithm, length)
    assert r.ok, r
    assert r.rc == (-signal.SIGKILL if sig == signal.SIGKILL else 130) and r.how == "resumed" and r.identical
    assert r.phase in ("checkpoint write", "between checkpoints")


def test_output_comparison_sees_a_changed_weight(tmp_path, uninterrupted):
    """The identical-output check fails on a policy whose one weight differs by one ulp (it can fail)."""
    import shutil

    _, _, ref = uninterrupted("magddpg", CASES["magddpg", signal.SIGKILL])
    d = tmp_path / "copy"
    shutil.copytree(ref, d)
    assert kh.output_differences(ref, d) == []
    with np.load(d / "policy_last.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["w0"].flat[0] = np.nextafter(arrays["w0"].flat[0], np.float32(np.inf))
    np.savez(d / "policy_last.npz", **arrays)
    assert kh.output_differences(ref, d) == ["policy_last.npz: array w0 differs"]
