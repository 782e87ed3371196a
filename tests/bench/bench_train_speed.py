"""Trainer speed of this tree against a git revision: updates/s and env steps/s, alternating runs, ratios.

    python -m tests.bench.bench_train_speed --against 81d913c                 # 4 and 32 robots, 2 rounds of 2 min
    python -m tests.bench.bench_train_speed --against 81d913c --robots 4 --minutes 1 --rounds 3
    python -m tests.bench.bench_train_speed --against HEAD --new-args --update-every 8   # a knob against the tree itself

Each case runs ``python -m learn train --preset fast --world kilobot --robots M --history 20 --n-envs 16
--max-minutes T`` (issue 14's command) in this tree and in the revision (checked out into a temporary
``git worktree``), one after the other, several rounds, alternating which goes first. Each run's
summary.json gives updates per second of update time and env steps per second of env time (what the
trainer itself measures); the table shows the median per tree, the ratio of the medians and the
range of the per-round ratios. On a shared machine the ratios are the honest numbers: absolute rates
move with the load, and both trees see the same load within a round.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Iterator

ROOT = Path(__file__).resolve().parents[2]
COMMAND = ["--preset", "fast", "--world", "kilobot", "--history", "20", "--n-envs", "16", "--quiet"]


@contextlib.contextmanager
def checkout(rev: str, into: Path) -> Iterator[Path]:
    """``rev`` in a detached temporary worktree of this repository (removed afterwards)."""
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(into), rev], check=True,
                   capture_output=True, text=True)
    try:
        yield into
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(into)], capture_output=True)


def run(tree: Path, robots: int, minutes: float, out: Path, extra: list[str]) -> dict:
    """One training run in ``tree``; its summary.json."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "learn", "train", *COMMAND, "--robots", str(robots), "--max-minutes", str(minutes),
           "--out", str(out), *extra]
    res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} in {tree} failed:\n{res.stderr[-2000:]}")
    return json.loads((out / "summary.json").read_text())


def rate(summary: dict, metric: str) -> float:
    """A rate of a run's summary; NaN when the run never did it (no update before the time ran out)."""
    v = summary.get(metric)
    return float("nan") if v is None else float(v)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--against", default="81d913c", help="git revision to compare with (default 81d913c)")
    p.add_argument("--robots", nargs="+", type=int, default=[4, 32])
    p.add_argument("--minutes", type=float, default=2.0, help="--max-minutes of each run")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--tree", type=Path, default=ROOT, help="the tree to measure (default: this one)")
    p.add_argument("--new-args", nargs=argparse.REMAINDER, default=[], help="extra flags for this tree's runs")
    args = p.parse_args(argv)
    metrics = ("updates_per_s", "env_steps_per_s")
    with tempfile.TemporaryDirectory(prefix="bench_train_speed.") as tmp:
        tmp = Path(tmp)
        with checkout(args.against, tmp / "old") as old_tree:
            trees = {"old": (old_tree, []), "new": (args.tree, args.new_args)}
            results: dict = {(M, k): [] for M in args.robots for k in trees}
            for r in range(args.rounds):
                for M in args.robots:
                    order = ["old", "new"] if r % 2 == 0 else ["new", "old"]
                    for k in order:
                        tree, extra = trees[k]
                        s = run(tree, M, args.minutes, tmp / f"run_{k}_{M}_{r}", extra)
                        results[(M, k)].append(s)
                        print(f"round {r + 1} {M:>2} robots {k}: {rate(s, 'updates_per_s'):.1f} updates/s, "
                              f"{rate(s, 'env_steps_per_s'):.0f} env steps/s, {s['updates']} updates, "
                              f"eval share {s.get('eval_share', float('nan'))}", flush=True)
    print(f"\nthis tree vs {args.against}: `python -m learn train {' '.join(COMMAND)} --robots M --max-minutes "
          f"{args.minutes}` {' '.join(args.new_args)}; {args.rounds} rounds, medians")
    print(f"| robots | metric | {args.against} | this tree | ratio | per-round ratios |")
    print("|---:|---|---:|---:|---:|---|")
    for M in args.robots:
        for m in metrics:
            old = [rate(s, m) for s in results[(M, "old")]]
            new = [rate(s, m) for s in results[(M, "new")]]
            ratios = [n / o for n, o in zip(new, old)]
            print(f"| {M} | {m} | {statistics.median(old):.1f} | {statistics.median(new):.1f} | "
                  f"**{statistics.median(new) / statistics.median(old):.2f}x** | "
                  f"{min(ratios):.2f}-{max(ratios):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
