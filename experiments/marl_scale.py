"""Can MAGDDPG learn localisation at 16 robots from scratch (issue 45 item 3)?

    python -m experiments.marl_scale train --variant linear --seeds 1 2 3 --minutes 50 --out runs/marl
    python -m experiments.marl_scale train --variant local --seeds 1 2 3 --minutes 20 --out runs/marl
    python -m experiments.marl_scale evaluate runs/marl/linear_s1 runs/marl/linear_s2 runs/marl/linear_s3 --out runs/marl/eval
    python -m experiments.marl_scale plot runs/marl/linear_s1 runs/marl/linear_s2 runs/marl/linear_s3 --out curves.png

``train`` runs ``python -m learn train`` (MAGDDPG, ``--preset fast``, 16 robots, the kilobot world, random initial
weights, no demonstrations) with one of the :data:`VARIANTS` for every seed, all seeds at once (one process each),
into ``OUT/VARIANT_sSEED``; each stops after ``--minutes`` of wall clock (``--max-minutes``), so how far it gets
depends on the machine and what else runs on it (its ``summary.json`` records the updates made).

``evaluate`` plays every run's result (``policy_best.npz``, selected on the run's own evaluation episodes) with
``python -m learn evaluate`` on held-out episodes (``sim.config.HELD_OUT_SEED``, never used for training or
selection; 16 robots, 500 steps) beside the random walk and the hand-written searchers, and prints the per-seed
table with each run's final coverage as a multiple of the random walk's.
``plot`` draws the runs' learning curves, one per variant (mean ± 2 std over seeds).
Results: docs/results/marl.md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from sim.config import HELD_OUT_SEED

ROBOTS = 16
COMMON = ["--preset", "fast", "--robots", str(ROBOTS), "--world", "kilobot", "--eval-every", "25600",
          "--eval-episodes", "20", "--quiet"]
#: variant -> the flags it adds to COMMON
VARIANTS: dict[str, list[str]] = {
    "concat": ["--critic", "concat"],  # the thesis's critic and squared team reward (fast's defaults)
    "team": ["--critic", "mean"],  # the thesis's squared team reward, the mean-embedding critic
    "linear": ["--critic", "mean", "--reward", "linear"],  # the team's coverage, not squared
    # each robot's own success, one value per robot; the head runs once per robot, so it is narrower (64, 64)
    "local": ["--critic", "robot", "--reward", "local", "--critic-hidden", "64", "64"],
}
EPISODES = 50


def train(variant: str, seeds: list[int], minutes: float, out: Path) -> None:
    procs = []
    for seed in seeds:
        run = out / f"{variant}_s{seed}"
        cmd = [sys.executable, "-m", "learn", "train", *COMMON, *VARIANTS[variant], "--max-minutes", str(minutes),
               "--seed", str(seed), "--out", str(run)]
        print(" ".join(cmd[1:]), flush=True)
        procs.append(subprocess.Popen(cmd))
    codes = [p.wait() for p in procs]
    if any(codes):
        sys.exit(f"marl_scale: error: training exited with {codes}")


def evaluate(runs: list[Path], out: Path) -> None:
    policies = [str(r / "policy_best.npz") for r in runs]
    subprocess.run([sys.executable, "-m", "learn", "evaluate", "--policy", *policies, "--robots", str(ROBOTS),
                    "--episodes", str(EPISODES), "--steps", "500", "--seed", str(HELD_OUT_SEED), "--no-gif", "--quiet",
                    "--out", str(out)], check=True)
    res = json.loads((out / "evaluation.json").read_text())["robots"][str(ROBOTS)]["metrics"]

    def final(name: str) -> tuple[float, float]:
        s = res[name]["summary"]["final_coverage"]
        return s["mean"], s["ci95"]

    walk = final("random")[0]
    print(f"\n| run | updates | final coverage (held out, {EPISODES} episodes, ± 95 % CI) | × random walk |")
    print("|---|---:|---:|---:|")
    for run in runs:
        name = next(n for n in res if n.startswith(run.name))
        m, ci = final(name)
        updates = json.loads((run / "summary.json").read_text()).get("updates")
        print(f"| {run.name} | {updates} | {m:.3f} ± {ci:.3f} | {m / walk:.1f} |")
    for name in ("random", "hand-written", "hand-written pusher"):
        m, ci = final(name)
        print(f"| {name} | | {m:.3f} ± {ci:.3f} | {m / walk:.1f} |")


def plot(runs: list[str], out: str) -> None:
    """One curve (mean ± 2 std over seeds) per variant: the run directory's name without ``_sSEED``.
    (``python -m learn plot`` separates the variants as well, labelling each by the config fields in which they
    differ, ``reward=linear, critic=mean``; this one labels each curve by its variant name and flags, and titles the
    figure with the experiment.)"""
    from learn.evaluate import success_panel
    from learn.plots import plot_learning_curves
    from learn.runfiles import read_metrics
    from sim.tasks import get_task

    groups: dict[str, list] = {}
    for run in runs:
        variant = Path(run).name.rsplit("_s", 1)[0]
        label = f"{variant}: {' '.join(VARIANTS.get(variant, []))}"
        groups.setdefault(label, []).append(read_metrics(run))
    plot_learning_curves(groups, out, success=success_panel(get_task("localisation")),
                         title=f"MAGDDPG from scratch, {ROBOTS} robots, kilobot world (mean ± 2 std over seeds)")
    print(f"wrote {out}")


def main() -> None:
    p = argparse.ArgumentParser(prog="python -m experiments.marl_scale", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("--variant", choices=sorted(VARIANTS), required=True)
    t.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    t.add_argument("--minutes", type=float, default=50.0)
    t.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("evaluate")
    e.add_argument("runs", type=Path, nargs="+")
    e.add_argument("--out", type=Path, required=True)
    pl = sub.add_parser("plot")
    pl.add_argument("runs", nargs="+")
    pl.add_argument("--out", required=True)
    a = p.parse_args()
    if a.command == "train":
        train(a.variant, a.seeds, a.minutes, a.out)
    elif a.command == "evaluate":
        evaluate(a.runs, a.out)
    else:
        plot(a.runs, a.out)


if __name__ == "__main__":
    main()
