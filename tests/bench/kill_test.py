"""Kill exports and trainings at random moments (SIGKILL and SIGINT) and check what they leave.

    PYTHONPATH=. nice -n 15 python tests/bench/kill_test.py [--exports 200] [--trainings 50] [--seed 0]

Exports: each publishes a new set over an old complete one and is killed at a random moment: a third
anywhere in the run, a third once its files are staged, a third once the set is committed; the set must be the old complete set
or the new complete set (after the next run's recovery), a present manifest must match its files, no
temporary may be left, and an interrupted run's message must say what it wrote. Trainings: each is
killed at a random moment and then resumed; it must resume from its checkpoint or restart, and finish
(tests/kill_harness.py). Prints the outcome table; exit 1 if any kill broke a rule.
"""
from __future__ import annotations

import argparse
import collections
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import kill_harness as kh  # noqa: E402


def said(r: kh.KillResult) -> str:
    """What the killed run's last line said, in short."""
    if r.signal == "SIGKILL" or r.rc == 0:
        return "-"
    for key in ("nothing written", "interrupted after writing", "interpreter start-up or exit"):
        if key in r.message:
            return key
    return r.message[:40]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exports", type=int, default=200)
    ap.add_argument("--trainings", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = np.random.default_rng(np.random.SeedSequence(args.seed))
    bad = 0
    with tempfile.TemporaryDirectory(prefix="kf-kill-") as d:
        root = Path(d)
        if args.exports:
            old, new, duration = kh.reference_sets(root)
            print(f"one export takes {duration:.2f} s; killing {args.exports}")
            table: collections.Counter = collections.Counter()
            t0 = time.perf_counter()
            for i in range(args.exports):
                sig = (signal.SIGKILL, signal.SIGINT)[i % 2]
                moment = ("uniform", "publish", "commit")[(i // 2) % 3]
                r = kh.kill_export(root / f"e{i}", old, new, sig, moment, rng, duration)
                table[(r.signal, r.moment, r.before, r.after, r.rc, said(r))] += 1
                if not r.ok:
                    bad += 1
                    print(f"export {i}: {r}")
            print(f"\n{args.exports} killed exports in {time.perf_counter() - t0:.0f} s\n")
            print("| signal | moment | set right after the kill | after recovery | exit status | message | runs |")
            print("|---|---|---|---|---:|---|---:|")
            for (s, m, b, a, rc, msg), n in sorted(table.items(), key=lambda kv: (kv[0][0], kv[0][1], -kv[1])):
                print(f"| {s} | {m} | {b} | {a} | {rc} | {msg} | {n} |")
            print(f"\nexports that broke a rule: {bad}")
        if args.trainings:
            tbad = kh.kill_trainings(root / "train", args.trainings, rng)
            bad += tbad
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
