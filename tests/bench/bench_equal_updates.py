"""What is learned at equal updates: this tree (optionally with extra flags) against a revision, over seeds.

    python -m tests.bench.bench_equal_updates --against 81d913c --seeds 1 2 3
    python -m tests.bench.bench_equal_updates --against HEAD --robots 16 --new-args --actor-robots 4

Both trees train ``python -m learn train --preset fast --world W --robots M --episodes E --seed S``
(a fixed episode budget, so both make the same number of updates), then each run's last actor is
evaluated on the same fresh episodes (seed 777, never used in training) and the table prints per seed
the final coverage and return of both, and their means and standard deviations. A change that keeps
what is learned shows differences within the seed-to-seed spread.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.bench.bench_train_speed import ROOT, checkout

EVAL = """
import json, sys
from kiloforge.policies import load_policy
from kiloforge.policies import swarm_policy
from sim.env import SwarmEnv
from sim.rollout import rollout
p = load_policy(sys.argv[1])
m = rollout(SwarmEnv(p.world, 50, int(sys.argv[2]), seed=777), swarm_policy(p), int(sys.argv[3]), seed=777).metrics()
print(json.dumps({"coverage": float(m.final_coverage.mean()), "return": float(m.returns.mean())}))
"""


def run(tree: Path, args, seed: int, out: Path, extra: list[str]) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "learn", "train", "--preset", "fast", "--world", args.world, "--robots",
           str(args.robots), "--episodes", str(args.episodes), "--seed", str(seed), "--quiet", "--out", str(out), *extra]
    res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
    summary = json.loads((out / "summary.json").read_text())
    ev = subprocess.run([sys.executable, "-c", EVAL, str(out / "policy_last.npz"), str(args.robots), str(args.eval_episodes)],
                        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, check=True)
    return {**json.loads(ev.stdout), "updates": summary["updates"], "wall_s": summary["wall_s"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--against", default="81d913c")
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    p.add_argument("--world", default="thesis")
    p.add_argument("--robots", type=int, default=2)
    p.add_argument("--episodes", type=int, default=352, help="learning episodes (after the 32 warm-up ones)")
    p.add_argument("--eval-episodes", type=int, default=100)
    p.add_argument("--tree", type=Path, default=ROOT, help="the tree to measure (default: this one)")
    p.add_argument("--new-args", nargs=argparse.REMAINDER, default=[])
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_equal_updates.") as tmp:
        tmp = Path(tmp)
        with checkout(args.against, tmp / "old") as old_tree:
            for s in args.seeds:
                old = run(old_tree, args, s, tmp / f"old_{s}", [])
                new = run(args.tree, args, s, tmp / f"new_{s}", args.new_args)
                rows.append((s, old, new))
                print(f"seed {s}: {args.against} coverage {old['coverage']:.3f} return {old['return']:.1f} "
                      f"({old['updates']} updates, {old['wall_s']:.0f} s) | this tree coverage {new['coverage']:.3f} "
                      f"return {new['return']:.1f} ({new['updates']} updates, {new['wall_s']:.0f} s)", flush=True)
    print(f"\n{args.world} world, {args.robots} robots, --preset fast --episodes {args.episodes} "
          f"{' '.join(args.new_args)}; last actor on {args.eval_episodes} fresh episodes (seed 777)")
    print(f"| seed | updates | {args.against} final coverage | this tree | {args.against} return | this tree |")
    print("|---:|---:|---:|---:|---:|---:|")
    for s, o, n in rows:
        print(f"| {s} | {o['updates']} / {n['updates']} | {o['coverage']:.3f} | {n['coverage']:.3f} | "
              f"{o['return']:.1f} | {n['return']:.1f} |")
    if len(rows) > 1:
        def ms(k, i):
            v = [r[i][k] for r in rows]
            return f"{statistics.mean(v):.3f} ± {statistics.stdev(v):.3f}" if k == "coverage" else \
                f"{statistics.mean(v):.1f} ± {statistics.stdev(v):.1f}"
        print(f"| mean ± std | | {ms('coverage', 1)} | {ms('coverage', 2)} | {ms('return', 1)} | {ms('return', 2)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
