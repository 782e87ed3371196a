"""ES generations per second of this source tree against another one: paired, alternating runs, the ratio.

    python -m tests.bench.bench_es_trees --base /tmp/kiloforge_at_b95249b        # issue 42: a refactor costs nothing
    python -m tests.bench.bench_es_trees --base DIR --rounds 6 --robots 16 --generations 10 --pairs 8

``--base`` is another checkout of the repository (``git worktree add --detach DIR COMMIT``, or ``git archive
COMMIT | tar -x -C DIR``). Each round runs ``python -m learn train-es --robots M --demo-policy none
--generations G --pairs P --seed S`` once in each tree (``PYTHONPATH`` and the working directory set to it), the
order alternating from round to round so a change of load hits both alike. generations/s is each run's
summary.json ``generations`` over ``generation_s`` (wall seconds in generations: start-up, evaluations and
checkpoints excluded; a tree that predates ``generation_s`` gives ``env_steps / env_s``, its seconds in the
generations' member evaluations, turned into generations); the CPU seconds are the run's user + system time. The table gives per tree the median
generations/s and CPU seconds, and the median and range of the per-round ratios (this tree / base). Both trees
must end with the same weights (the script checks ``policy_last.npz`` and says so): the ratio compares equal work.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.bench.bench_es_workers import weights

ROOT = Path(__file__).resolve().parents[2]


def run(args: argparse.Namespace, tree: Path, out: Path) -> tuple[float, float]:
    """One train-es run in ``tree``: (generations/s, CPU seconds)."""
    cmd = [sys.executable, "-m", "learn", "train-es", "--robots", *map(str, args.robots), "--demo-policy", "none",
           "--generations", str(args.generations), "--pairs", str(args.pairs), "--seed", str(args.seed),
           "--quiet", "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    res = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} in {tree} failed:\n{res.stderr[-2000:]}")
    s = json.loads((out / "summary.json").read_text())
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if "generation_s" not in s:  # trees older than generation_s (b95249b): the seconds spent evaluating members
        return args.generations * s["env_steps_per_s"] / s["env_steps"], cpu
    return s["generations"] / s["generation_s"], cpu


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--base", type=Path, required=True, help="the other source tree (the baseline)")
    p.add_argument("--robots", nargs="+", type=int, default=[16])
    p.add_argument("--generations", type=int, default=10)
    p.add_argument("--pairs", type=int, default=8)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--rounds", type=int, default=4)
    args = p.parse_args(argv)
    trees = {"base": args.base.resolve(), "this": ROOT}
    rates: dict[str, list[float]] = {k: [] for k in trees}
    cpus: dict[str, list[float]] = {k: [] for k in trees}
    ratios: list[float] = []
    same = True
    with tempfile.TemporaryDirectory(prefix="bench_es_trees.") as tmp:
        for r in range(args.rounds):
            order = ["base", "this"] if r % 2 == 0 else ["this", "base"]
            for name in order:
                rate, cpu = run(args, trees[name], Path(tmp) / f"r{r}_{name}")
                rates[name].append(rate)
                cpus[name].append(cpu)
                print(f"round {r}, {name}: {rate:.3f} generations/s, {cpu:.1f} CPU s", flush=True)
            ratios.append(rates["this"][-1] / rates["base"][-1])
            same &= all((a == b).all() for a, b in zip(weights(Path(tmp) / f"r{r}_base"),
                                                       weights(Path(tmp) / f"r{r}_this"), strict=True))
    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    print(f"\ntrain-es --robots {' '.join(map(str, args.robots))} --demo-policy none --generations {args.generations} "
          f"--pairs {args.pairs} --seed {args.seed}; {args.rounds} rounds; {os.cpu_count()} CPUs; {load}")
    print(f"{'tree':>4} | {'generations/s':>13} | {'CPU s':>6} | path")
    print("-" * 4 + "-+-" + "-" * 13 + "-+-" + "-" * 6 + "-+-" + "-" * 20)
    for name, tree in trees.items():
        print(f"{name:>4} | {statistics.median(rates[name]):>13.3f} | {statistics.median(cpus[name]):>6.1f} | {tree}")
    print(f"ratio this/base (generations/s): median {statistics.median(ratios):.3f}, "
          f"range {min(ratios):.3f}-{max(ratios):.3f}")
    print(f"policy_last.npz weights equal in every round: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
