"""Kill exports and trainings at random moments (SIGKILL and SIGINT) and check what they leave.

    nice -n 15 python -m tests.soak.kill_test [--exports 200] [--trainings 50] [--es-trainings 10]
                                                            [--seed 0]

Exports: each publishes a new set over an old complete one and is killed at a random moment: a third
anywhere in the run, a third once its files are staged, a third once the set is committed; the set must be the old complete set
or the new complete set (after the next run's recovery), a present manifest must match its files, no
temporary may be left, and an interrupted run's message must say what it wrote. Trainings (MAGDDPG
`learn train`, ES `learn train-es`): each is killed at a random moment and then resumed; it must resume
from its checkpoint or restart, finish, and end with outputs identical to the uninterrupted run of the
same seed (policy arrays bit-identical, metrics and meta the same but for time taken). Every signal
lands inside a run: a moment at which the run had already ended is drawn again (and counted). Prints
the outcome tables (tests/kill_harness.py); exit 1 if any kill broke a rule.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from tests import kill_harness as kh


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exports", type=int, default=200)
    ap.add_argument("--trainings", type=int, default=50)
    ap.add_argument("--es-trainings", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(np.random.SeedSequence(args.seed))
    bad = 0
    with tempfile.TemporaryDirectory(prefix="kf-kill-") as d:
        root = Path(d)
        if args.exports:
            bad += kh.kill_exports(root / "export", args.exports, rng)
        if args.trainings:
            bad += kh.kill_trainings(root / "train", args.trainings, rng)
        if args.es_trainings:
            bad += kh.kill_trainings(root / "train-es", args.es_trainings, rng, "es")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
