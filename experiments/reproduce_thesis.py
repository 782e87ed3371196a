"""Re-run the thesis experiments (§5) at this machine's scale; write docs/report plots and tables.

    python -m experiments.reproduce_thesis [STAGE ...] [--minutes-scale F] [--episodes N]
                                           [--verify-episodes N] [--jobs 2] [--dry-run] [--force]

Stages (default: all, in this order):

``kilobot``   train the reference policy on the ``kilobot`` world (4 robots, T_prev 20, 32-32 ELU;
              seed 1 plain, seed 2 with 16 phantom neighbours), 14 min each.
``ship``      evaluate the kilobot candidates (best and last checkpoint of each run) on 16 robots,
              episode seed 1 (not the report's seed 0), and save the best as
              ``runs/reference/default_policy.npz`` with its provenance (the report's reference
              policy; it was the shipped default once, and the script leaves today's alone).
``robots``    thesis Experiment 1 (thesis world): learning with 1, 2, 4, 8 robots.
``history``   thesis Experiment 2: T_prev in {1, 2, 5, 10} with 2 robots, 4 minutes each.
``seeds``     Experiments 1 and 2 again as 3-seed sweeps (``python -m learn sweep``), budgeted in
              episodes (10⁵ environment steps per trial), not minutes; their aggregates (tables,
              learning curves as mean ± 2 std over seeds) are copied into docs/report.
``eval``      thesis §5.1.2: the Experiment 1 policies on 16 and 32 robots (500 steps) with the
              random and hand-written baselines; the shipped policy on 4, 16, 32 robots (kilobot).
``closed``    float actor vs int8 firmware emulator in the closed loop (``python -m export verify``),
              for the shipped kilobot policy and the 4-robot thesis policy.
``plots``     learning curves per robot count, history study, and ``docs/report/tables.md``.

Every stage shells out to the project's own CLIs (``python -m learn ...``, ``python -m export ...``)
and prints each command before running it, so the log is the list of commands. A training whose run
directory already holds ``metrics.csv`` is skipped (``--force`` retrains); runs are time-capped with
``--max-minutes`` (scaled by ``--minutes-scale``), so results depend on the CPU: the report's numbers
come from a shared 2-core CPU without GPU. At most ``--jobs`` trainings run at once.

Not a test (nothing asserted): a benchmark script that writes what ``docs/report.md`` shows.
"""
from __future__ import annotations

import argparse
import csv
import json
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RUNS = ROOT / "runs"
OUT = ROOT / "docs" / "report"
PY = sys.executable
FAST = ["--preset", "fast", "--quiet"]

#: (run name, robots, t_prev, minutes, extra args) of each experiment. The names of runs made before
#: this script existed (goal2_s1, goal4_s1) are kept so the report's numbers stay traceable.
KILOBOT_RUNS = [
    ("kb4_s1", 4, 20, 14, ["--world", "kilobot", "--seed", "1", "--phantom-neighbours", "0",  # `fast` has 16 now
                           "--eval-episodes", "20", "--exp-name", "kb4"]),
    ("kb4_s2", 4, 20, 14, ["--world", "kilobot", "--seed", "2", "--phantom-neighbours", "16",
                           "--eval-episodes", "20", "--exp-name", "kb4"]),
]
ROBOT_RUNS = [
    ("th_r1_s1", 1, 10, 8, ["--world", "thesis", "--seed", "1", "--eval-episodes", "20", "--exp-name", "th_r1"]),
    ("goal2_s1", 2, 10, 15, ["--world", "thesis", "--seed", "1", "--eval-episodes", "20"]),
    ("goal4_s1", 4, 10, 45, ["--world", "thesis", "--seed", "1", "--eval-episodes", "20"]),
    ("th_r8_s1", 8, 10, 8, ["--world", "thesis", "--seed", "1", "--eval-episodes", "20", "--exp-name", "th_r8"]),
]
HISTORY_RUNS = [(f"th_h{t}_s1", 2, t, 4, ["--world", "thesis", "--seed", "1", "--eval-episodes", "20",
                                         "--exp-name", f"th_h{t}"])
                for t in (1, 2, 5, 10)]
#: kilobot runs continued with ``--resume`` for this many more minutes (seed 2 had collapsed: not resumed)
KILOBOT_RESUME = {"kb4_s1": 14}
#: the report's reference policy (``ship`` writes it, ``eval`` and ``closed`` read it); not export/data's default
REFERENCE = RUNS / "reference" / "default_policy.npz"
#: Experiments 1 and 2 as sweeps: 3 seeds, 32 warm-up + 468 learning episodes = 10⁵ environment steps per
#: trial; two sweeps side by side with one CPU each, trials at the command's niceness (RAY_worker_niceness)
SWEEP = ["--preset", "fast", "--world", "thesis", "--seeds", "1", "2", "3", "--grid", "episodes=468",
         "eval_every=12800", "eval_episodes=20", "tensorboard=true", "--cpus-per-trial", "1", "--num-cpus", "1", "--quiet"]
#: (sweep directory, figure in docs/report, grid). Experiment 2's T_prev 10 is Experiment 1's 2-robot
#: configuration: its trials are linked into the Experiment 2 sweep, not trained twice
SWEEPS = (("thesis_exp1", "learning_curves_robots_seeds.png", ["--robots", "1", "2", "4", "--history", "10"]),
          ("thesis_exp2", "learning_curves_history_seeds.png", ["--robots", "2", "--history", "1", "2", "5"]))
STAGES = ("kilobot", "ship", "robots", "history", "seeds", "eval", "closed", "plots")


def sh(cmd: list[str], dry: bool, log: Path | None = None, background: bool = False):
    """Print and run one command (optionally into a log file, optionally without waiting)."""
    print("$ " + " ".join(shlex.quote(c) for c in cmd), flush=True)
    if dry:
        return None
    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)  # runs/ does not exist in a fresh clone
    out = open(log, "w") if log is not None else None
    p = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT if out else None)
    return p if background else p.wait()


def train(runs: list[tuple], args, resume: dict[str, float] | None = None) -> None:
    """Train each run not already present, at most ``args.jobs`` at once; then resume those in ``resume``."""
    todo = []
    for name, robots, t_prev, minutes, extra in runs:
        out = RUNS / name
        if (out / "metrics.csv").exists() and not args.force:
            print(f"# {name}: already trained ({out / 'metrics.csv'}), skipped")
            continue
        cmd = [PY, "-m", "learn", "train", *FAST, "--robots", str(robots), "--history", str(t_prev),
               "--actor-hidden", "32", "32", "--max-minutes", f"{minutes * args.minutes_scale:g}",
               *extra, "--out", str(out)]
        todo.append((cmd, RUNS / f"{name}.log"))
        if name in (resume or {}):
            todo.append(([PY, "-m", "learn", "train", "--out", str(out), "--resume", "--quiet", "--max-minutes",
                          f"{resume[name] * args.minutes_scale:g}"], RUNS / f"{name}.resume.log"))
    running: list[subprocess.Popen] = []
    for cmd, log in todo:
        if "--resume" in cmd:  # continue a run: wait until its first session has ended
            for p in running:
                if str(p.args[p.args.index("--out") + 1]) == cmd[cmd.index("--out") + 1]:
                    p.wait()
        while len([p for p in running if p.poll() is None]) >= args.jobs:
            time.sleep(5)
        p = sh(cmd, args.dry_run, log, background=True)
        if p is not None:
            running.append(p)
    for p in running:
        p.wait()


def seed_sweeps(args) -> None:
    """Both sweeps at once; then Experiment 2 aggregated over T_prev 1, 2, 5, 10 and the aggregates copied."""
    import os
    import shutil

    os.environ.setdefault("RAY_worker_niceness", "0")
    print(f"# RAY_worker_niceness={os.environ['RAY_worker_niceness']}")
    sweep = lambda name, grid: [PY, "-m", "learn", "sweep", *SWEEP, *grid, "--out", str(RUNS / name)]  # noqa: E731
    procs = [sh(sweep(name, grid), args.dry_run, RUNS / f"{name}.log", background=True) for name, _, grid in SWEEPS]
    if any(p is not None and p.wait() != 0 for p in procs):
        sys.exit("a sweep did not finish (see its log in runs/); rerun this stage to resume it")
    exp1, exp2 = RUNS / SWEEPS[0][0], RUNS / SWEEPS[1][0]
    for run in ([] if args.dry_run else sorted(exp1.glob("thesis-m2-t10_s*"))):
        link = exp2 / run.name
        if not link.exists():
            link.symlink_to(Path("..") / exp1.name / run.name)
    print(f"# ln -s ../{exp1.name}/thesis-m2-t10_s* {exp2.relative_to(ROOT)}/")
    sh(sweep(exp2.name, [*SWEEPS[1][2], "10"]), args.dry_run)  # every trial finished: only aggregates
    for name, png, _ in ([] if args.dry_run else SWEEPS):
        shutil.copyfile(RUNS / name / "learning_curves.png", OUT / png)
        shutil.copyfile(RUNS / name / "table.txt", OUT / f"{name}_table.txt")
        print(f"wrote {OUT / png}, {OUT / f'{name}_table.txt'}")


def ship(args) -> None:
    """Pick the kilobot candidate with the best 16-robot final coverage and save it as the default policy."""
    import datetime

    from kiloforge.policies import load_policy, save_policy

    cands = [RUNS / name / f for name, *_ in KILOBOT_RUNS for f in ("policy_best.npz", "policy_last.npz")
             if (RUNS / name / f).exists() or args.dry_run]
    sel = RUNS / "kb_select"
    sh([PY, "-m", "learn", "evaluate", "--policy", *map(str, cands), "--robots", "16", "--episodes",
        str(args.select_episodes), "--seed", "1", "--no-baselines", "--no-gif", "--quiet", "--out", str(sel)], args.dry_run)
    if args.dry_run:
        return
    res = json.loads((sel / "evaluation.json").read_text())["robots"]["16"]["metrics"]
    score = {k: (v["summary"]["final_coverage"]["mean"], v["summary"]["return"]["mean"]) for k, v in res.items()}
    best_key = max(score, key=score.get)
    path = next(c for c in cands if best_key.endswith(f"{c.parent.name}/{c.stem}"))
    p = load_policy(path)
    prov = dict(p.provenance)
    prov.update({
        "notes": "trained reference policy (MAGDDPG, kilobot world); see docs/report.md",
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "source_run": f"runs/{path.parent.name}/{path.name}",
        "sessions": (f"{1 + (path.parent.name in KILOBOT_RESUME)} training session(s): --max-minutes per session, "
                     "continued with --resume; wall_s is the total"),
        "selection": {"robots": 16, "episodes": args.select_episodes, "episode_seed": 1,
                      "criterion": "highest mean final coverage, then return",
                      "candidates": {k: {"final_coverage": v[0], "return": v[1]} for k, v in score.items()}},
        "eval_16_robots": res[best_key]["summary"],
    })
    shipped = type(p)(weights=list(p.weights), biases=list(p.biases), activations=list(p.activations),
                      t_prev=p.t_prev, world=p.world, provenance=prov)
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    save_policy(shipped, REFERENCE)
    print(f"shipped {path} -> {REFERENCE} ({REFERENCE.stat().st_size} B), hash {shipped.hash[:16]}")


def evaluate(args) -> None:
    """Thesis §5.1.2 on the thesis world; the shipped policy vs the baselines on the kilobot world."""
    pols = [str(RUNS / name / "policy_best.npz") for name, *_ in ROBOT_RUNS
            if (RUNS / name / "policy_best.npz").exists() or args.dry_run]
    sh([PY, "-m", "learn", "evaluate", "--policy", *pols, "--robots", "16", "32", "--episodes",
        str(args.episodes), "--seed", "0", "--out", str(OUT / "eval_thesis"), "--no-gif", "--quiet"], args.dry_run)
    # the baselines and the shipped policy in two commands (so the baselines could run while the reference
    # policy was still training); the same episode seed gives the same episodes, merged in plot_eval
    sh([PY, "-m", "learn", "evaluate", "--policy", str(RUNS / "kb4_s2" / "policy_best.npz"), "--robots", "4", "16", "32",
        "--episodes", str(args.episodes), "--seed", "0", "--out", str(OUT / "eval_kilobot_baselines"), "--no-gif",
        "--quiet"], args.dry_run)
    sh([PY, "-m", "learn", "evaluate", "--policy", str(REFERENCE), "--robots", "4", "16", "32", "--episodes",
        str(args.episodes), "--seed", "0", "--out", str(OUT / "eval_kilobot"), "--no-gif", "--quiet", "--no-baselines"],
       args.dry_run)
    if not args.dry_run:  # keep only evaluation.json: the report's figures are drawn from it by ``plots``
        for d in ("eval_thesis", "eval_kilobot_baselines", "eval_kilobot"):
            for png in (OUT / d).glob("*.png"):
                png.unlink()


def closed_loop(args) -> None:
    """Float vs int8 in the closed loop: shipped kilobot policy and the 4-robot thesis policy."""
    for policy, name in ((REFERENCE, "closed_loop_kilobot"), (RUNS / "goal4_s1" / "policy_best.npz", "closed_loop_thesis")):
        sh([PY, "-m", "export", "verify", "--policy", str(policy), "--robots", "16", "32",
            "--episodes", str(args.verify_episodes), "--out", str(OUT / name), "--quiet"], args.dry_run)


def read_curve(run: Path) -> dict[str, list[float]]:
    """The metrics CSV of a run as columns of floats."""
    with open(run / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    return {k: [float(r[k]) if r[k] not in ("", "nan") else float("nan") for r in rows] for k in rows[0]}


def plot_curves(runs: list[tuple], label_key: str, title: str, path: Path) -> list[dict]:
    """Evaluation return and final coverage vs environment steps, one line per run; returns a summary."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    summary = []
    for name, robots, t_prev, minutes, _ in runs:
        run = RUNS / name
        if not (run / "metrics.csv").exists():
            continue
        c = read_curve(run)
        label = {"robots": f"{robots} robots ({name})", "t_prev": f"T_prev={t_prev} ({name})"}[label_key]
        axes[0].plot(c["env_steps"], c["eval_return"], label=label)
        axes[1].plot(c["env_steps"], c["eval_final_coverage"], label=label)
        best = max(range(len(c["eval_return"])), key=lambda i: c["eval_return"][i])
        summary.append({"run": name, "robots": robots, "t_prev": t_prev, "env_steps": int(c["env_steps"][-1]),
                        "updates": int(c["updates"][-1]), "wall_min": c["wall_s"][-1] / 60,
                        "best_return": c["eval_return"][best], "best_cov": c["eval_final_coverage"][best],
                        "last_return": c["eval_return"][-1], "last_cov": c["eval_final_coverage"][-1]})
    axes[0].set(xlabel="environment steps (transitions)", ylabel="evaluation return (20 episodes)", title=title)
    axes[1].set(xlabel="environment steps (transitions)", ylabel="final coverage", ylim=(0, 1.02))
    for a in axes:
        a.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")
    return summary


def merged_eval(paths: list[Path]) -> dict | None:
    """Several evaluation.json files of the same episodes (same world, seed, steps) as one."""
    docs = [json.loads(p.read_text()) for p in paths if p.exists()]
    if not docs:
        return None
    base = docs[0]
    for d in docs[1:]:
        assert (d["seed"], d["steps"], d["episodes"], d["world"]) == (base["seed"], base["steps"], base["episodes"],
                                                                     base["world"]), "evaluations of other episodes"
        for m, r in d["robots"].items():
            for key in ("mean_reward_over_time", "metrics", "returns"):
                base["robots"].setdefault(m, {}).setdefault(key, {}).update(r[key])
    return base


def plot_eval(d: dict, keep: list[str], prefix: Path) -> None:
    """Thesis figures 5.11-5.14: mean reward over time and return box plots, one pair per swarm size."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    for m, r in d["robots"].items():
        names = [k for k in keep if k in r["returns"]] or list(r["returns"])
        fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
        for k in names:
            a.plot(np.arange(1, len(r["mean_reward_over_time"][k]) + 1), r["mean_reward_over_time"][k], label=k)
        a.set(xlabel="time step", ylabel=f"mean reward ({d['episodes']} episodes)", title=f"{m} robots")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
        b.boxplot([r["returns"][k] for k in names], tick_labels=names)
        b.set(ylabel="undiscounted return", title=f"{m} robots, {d['steps']} steps")
        b.tick_params(axis="x", labelrotation=15, labelsize=8)
        fig.tight_layout()
        fig.savefig(f"{prefix}_{m}.png", dpi=110)
        plt.close(fig)
        print(f"wrote {prefix}_{m}.png")


def eval_table(path: Path | dict) -> list[str]:
    """Markdown rows of an evaluation.json: robots, policy, return, final coverage, time to find."""
    if isinstance(path, dict):
        d = path
    elif not path.exists():
        return [f"(missing: {path.relative_to(ROOT)})"]
    else:
        d = json.loads(path.read_text())
    rows = ["| robots | policy | return | final coverage | mean coverage | steps to find |",
            "|---:|---|---:|---:|---:|---:|"]
    for m, r in sorted(d["robots"].items(), key=lambda kv: int(kv[0])):
        for pol, met in sorted(r["metrics"].items()):
            s = met["summary"]
            rows.append(f"| {m} | {pol} | {s['return']['mean']:.1f} ± {s['return']['ci95']:.1f} | "
                        f"{s['final_coverage']['mean']:.3f} ± {s['final_coverage']['ci95']:.3f} | "
                        f"{s['mean_coverage']['mean']:.3f} | {s['time_to_find']['mean']:.1f} |")
    rows.append(f"\n{d['episodes']} episodes of {d['steps']} steps per policy and size, episode seed {d['seed']} "
                f"(same episodes for every policy); ± is the 95 % CI of the mean.")
    return rows


def sweep_table(path: Path) -> list[str]:
    """Markdown rows of a sweep's summary.json: per configuration, each seed's value and mean ± std over seeds."""
    if not path.exists():
        return [f"(missing: {path.relative_to(ROOT)})"]
    d = json.loads(path.read_text())

    def cells(m: dict, digits: int) -> list[str]:
        seeds = " / ".join(f"{v:.{digits}f}" for _, v in sorted(m["per_seed"].items(), key=lambda kv: int(kv[0])))
        if m["mean"] is None:
            return [seeds or "-", "-"]
        if m["std"] is None:
            return [seeds, f"{m['mean']:.{digits}f}"]
        lo, hi = m["ci95"]
        return [seeds, f"{m['mean']:.{digits}f} ± {m['std']:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"]

    rows = ["| robots | T_prev | seeds | best eval return, per seed | mean ± std [95 % CI] | its final cov, per seed | "
            "mean ± std [95 % CI] | last final cov, per seed | mean ± std [95 % CI] |",
            "|---:|---:|---|---|---|---|---|---|---|"]
    for c in sorted(d["configurations"], key=lambda c: (c["fields"]["n_robots"], c["fields"]["t_prev"])):
        m = c["metrics"]
        rows.append(f"| {c['fields']['n_robots']} | {c['fields']['t_prev']} | {', '.join(map(str, c['seeds'])) or '-'} | "
                    + " | ".join([*cells(m["best_return"], 1), *cells(m["best_final_coverage"], 3),
                                  *cells(m["last_final_coverage"], 3)]) + " |")
    left = [t for t in d["trials"] if t["status"] != "finished"]
    rows.append("\nBest = the evaluation (20 episodes, 200 steps, training size) with the highest return; its final "
                "coverage beside it; last = the final evaluation. Per-seed values in seed order; ± is the sample "
                "standard deviation over seeds, [ ] the 95 % CI of the mean (Student t)."
                + (" Not finished, not in the statistics: " + ", ".join(
                    f"{t['name']} ({t['status']}, {t['env_steps']:,.0f} env steps)" for t in left) + "." if left else ""))
    return rows


def closed_table(path: Path) -> list[str]:
    """Markdown rows of a closed_loop.json: float vs int8 final coverage and return, ratio, verdict."""
    if not path.exists():
        return [f"(missing: {path.relative_to(ROOT)})"]
    d = json.loads(path.read_text())
    rows = ["| world | robots | episodes | float final cov | int8 final cov | ratio (95 % CI) | float return | int8 return | goal 0.97 |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for c in d["comparisons"]:
        fc, rt = c["metrics"]["final_coverage"], c["metrics"]["return"]
        lo, hi = c["final_coverage_ratio_ci95"]
        ratio = "n/a" if c["final_coverage_ratio"] is None else f"{c['final_coverage_ratio']:.3f} ({lo:.3f}..{hi:.3f})"
        rows.append(f"| {c['world']} | {c['n_robots']} | {c['episodes']} | {fc['float']['mean']:.3f} | "
                    f"{fc['int8']['mean']:.3f} | {ratio} | {rt['float']['mean']:.1f} | {rt['int8']['mean']:.1f} | "
                    f"{'PASS' if c['passed'] else 'FAIL'} |")
    return rows


def plots(args) -> None:
    """Learning-curve figures and docs/report/tables.md from whatever runs and results exist."""
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# Tables (written by experiments/reproduce_thesis.py)", ""]
    for runs, key, title, png in ((ROBOT_RUNS, "robots", "thesis world, Experiment 1", "learning_curves_robots.png"),
                                  (HISTORY_RUNS, "t_prev", "thesis world, 2 robots, Experiment 2", "learning_curves_history.png"),
                                  (KILOBOT_RUNS, "robots", "kilobot world, 4 robots, T_prev 20", "learning_curves_kilobot.png")):
        summary = plot_curves(runs, key, title, OUT / png)
        lines += [f"## Training: {title}", "",
                  "| run | robots | T_prev | env steps | updates | wall (min) | best eval return | its final cov | last eval return | last final cov |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
        lines += [f"| {s['run']} | {s['robots']} | {s['t_prev']} | {s['env_steps']:,} | {s['updates']:,} | {s['wall_min']:.1f} | "
                  f"{s['best_return']:.1f} | {s['best_cov']:.3f} | {s['last_return']:.1f} | {s['last_cov']:.3f} |"
                  for s in summary] or ["(no runs)"]
        lines.append("")
    for name, png, _ in SWEEPS:
        lines += [f"## Training, 3 seeds: {name} ({png})", "", *sweep_table(RUNS / name / "summary.json"), ""]
    thesis = merged_eval([OUT / "eval_thesis" / "evaluation.json"])
    if thesis is not None:
        plot_eval(thesis, [], OUT / "eval_thesis")
    lines += ["## Evaluation, thesis world", "", *eval_table(OUT / "eval_thesis" / "evaluation.json"), ""]
    kb = merged_eval([OUT / "eval_kilobot" / "evaluation.json", OUT / "eval_kilobot_baselines" / "evaluation.json"])
    if kb is not None:
        keep = [k for k in kb["robots"][next(iter(kb["robots"]))]["returns"] if "default_policy" in k]
        keep += ["hand-written", "random"]
        for r in kb["robots"].values():  # only the shipped policy and the baselines
            for key in ("mean_reward_over_time", "metrics", "returns"):
                r[key] = {k: v for k, v in r[key].items() if k in keep}
        plot_eval(kb, keep, OUT / "eval_kilobot")
        lines += ["## Evaluation, kilobot world (shipped policy)", "", *eval_table(kb), ""]
    lines += ["## Float vs int8 in the closed loop", ""]
    for name in ("closed_loop_kilobot", "closed_loop_thesis"):
        lines += closed_table(OUT / name / "closed_loop.json") + [""]
    (OUT / "tables.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {OUT / 'tables.md'}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stages", nargs="*", metavar="STAGE", help=f"stages to run (default all): {', '.join(STAGES)}")
    ap.add_argument("--minutes-scale", type=float, default=1.0, help="multiply every training's wall-clock cap")
    ap.add_argument("--episodes", type=int, default=100, help="evaluation episodes per policy and size (thesis: 500)")
    ap.add_argument("--verify-episodes", type=int, default=200, help="closed-loop episodes per robot count")
    ap.add_argument("--jobs", type=int, default=2, help="trainings run at once")
    ap.add_argument("--force", action="store_true", help="retrain runs that already exist")
    ap.add_argument("--dry-run", action="store_true", help="print the commands only")
    ap.add_argument("--select-episodes", type=int, default=30, help="episodes per candidate when choosing the shipped policy")
    args = ap.parse_args(argv)
    stages = args.stages or list(STAGES)
    bad = sorted(set(stages) - set(STAGES))
    if bad:
        ap.error(f"unknown stage(s) {', '.join(bad)}; choose from {', '.join(STAGES)}")
    if "kilobot" in stages:
        train(KILOBOT_RUNS, args, KILOBOT_RESUME)
    if "ship" in stages:
        ship(args)
    if "robots" in stages:
        train(ROBOT_RUNS, args)
    if "history" in stages:
        train(HISTORY_RUNS, args)
    if "seeds" in stages:
        seed_sweeps(args)
    if "eval" in stages:
        evaluate(args)
    if "closed" in stages:
        closed_loop(args)
    if "plots" in stages and not args.dry_run:
        plots(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
