"""``python -m export verify``: float actor vs int8 firmware in the simulator, side by side.

    python -m export verify [--policy P] [--robots 16 32] [--episodes 200] [--steps N]
                [--seed S] [--out DIR] [--robots-calib 4 16] [--calib-episodes 1]
                [--calib-steps N] [--calib-seed 0] [--percentile 100] [--goal 0.97]

Quantises the policy exactly as ``python -m export`` does with the same calibration options, then
for each robot count runs the same episodes (same env seeds) twice: with the float actor and with
the firmware emulator in the loop (:mod:`export.verify.closed_loop`). Prints the mean return and the task's
metrics with 95 % confidence intervals, the paired int8 - float difference, the ratio of the int8 to the
float primary metric (with a paired-bootstrap interval) and PASS / FAIL against the goal (ratio >= 0.97 by
default). With ``--out DIR``: the task's success plot (``<success_plot>.png``, :attr:`sim.tasks.Task.success_plot`:
success over time, mean and 95 % band, float vs int8, one panel per robot count), ``returns_box.png`` and
``closed_loop.json`` (every number, per-episode values included), written all-or-nothing.

Exit status: 0 every robot count passes; 1 some robot count fails the goal; 2 bad input.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Sequence

from kiloforge.cliparse import deprecated_noop
from kiloforge.errors import OutputError, printable
from kiloforge.io import check_name_lengths, check_writable, write_files_atomic
from kiloforge.validate import float_arg, seed_arg
from sim.config import run_steps
from sim.tasks import Task, get_task

from ..verify.closed_loop import GOAL_RATIO, compare_many
from .common import (EXIT_FAIL, EXIT_OK, Parser, add_calibration, add_quiet, add_task, check_robots, describe,
                     episodes_arg, load, policy_help, quantise, robots_arg, steps_arg)

RETURNS_PNG = "returns_box.png"
RESULT_JSON = "closed_loop.json"


def verify_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="python -m export verify",
                 description="Closed-loop verification: the simulator driven by the int8 firmware emulator "
                             "vs by the float actor, same episodes. Exit 0 pass, 1 fail, 2 bad input.")
    deprecated_noop(ap, "--closed-loop", "the closed-loop comparison is the only thing verify does")
    ap.add_argument("--policy", type=Path, help=policy_help())
    add_task(ap)
    ap.add_argument("--robots", type=robots_arg, nargs="+", default=[16, 32], metavar="M",
                    help="robot counts to compare at (default 16 32)")
    ap.add_argument("--episodes", type=episodes_arg, default=200, help="episodes per robot count (default 200)")
    ap.add_argument("--steps", type=steps_arg, default=None,
                    help="control periods per episode (default: the world's episode length)")
    ap.add_argument("--seed", type=seed_arg, default=0, help="episode seed, a non-negative integer (default 0)")
    ap.add_argument("--out", type=Path, default=None,
                    help=f"directory for the success plot ({Task.success_plot}.png), returns_box.png and "
                         "closed_loop.json (created if missing)")
    ap.add_argument("--goal", type=float_arg(0.0, 1.5, lo_open=True), default=GOAL_RATIO,
                    help=f"pass when the int8 primary metric >= GOAL x the float one (default {GOAL_RATIO})")
    add_calibration(ap, "--calib-seed")
    add_quiet(ap)
    return ap


def _plots(comps: list, title: str, task: Task) -> tuple[bytes, bytes]:
    """(the success plot, returns_box.png) as bytes."""
    import numpy as np
    from matplotlib.patches import Rectangle

    from kiloforge.plotting import figure, png_bytes

    colours = {"float": "tab:blue", "int8": "tab:orange"}
    n = len(comps)
    fig = figure(5.0 * n, 3.6)
    axes = fig.subplots(1, n, squeeze=False, sharey=True)
    for ax, c in zip(axes[0], comps):
        for label, (mean, half) in c.curves().items():
            t = np.arange(1, mean.size + 1)
            name = "float actor" if label == "float" else "int8 firmware"
            ax.plot(t, mean, color=colours[label], label=name, lw=1.5, ls="-" if label == "float" else "--")
            ax.fill_between(t, np.clip(mean - half, 0, 1), np.clip(mean + half, 0, 1), color=colours[label],
                            alpha=0.25, lw=0)
        ratio = f"{c.ratio:.3f}" if np.isfinite(c.ratio) else "n/a"
        ax.set_title(f"{c.n_robots} robots: int8/float {task.metric(task.primary_metric).label} {ratio} "
                     f"({'PASS' if c.passed else 'FAIL'})", fontsize=9)
        ax.set_xlabel("control step")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(task.success_label)
    axes[0][0].legend(loc="lower right", fontsize=8)
    fig.suptitle(f"{title}: mean and 95% CI over {comps[0].episodes} episodes", fontsize=10)
    cov = png_bytes(fig)

    fig = figure(max(4.0, 2.2 * n), 3.6)
    ax = fig.add_subplot(1, 1, 1)
    data, pos, cols = [], [], []
    for i, c in enumerate(comps):
        for j, run in enumerate((c.float_run, c.int8_run)):
            data.append(run.metrics().returns)
            pos.append(3 * i + j + 1)
            cols.append(colours[run.label])
    bp = ax.boxplot(data, positions=pos, widths=0.8, patch_artist=True, showfliers=True,
                    medianprops={"color": "black"})
    for patch, col in zip(bp["boxes"], cols):
        patch.set_facecolor(col)
        patch.set_alpha(0.6)
    ax.set_xticks([3 * i + 1.5 for i in range(n)], [f"{c.n_robots} robots" for c in comps])
    ax.set_ylabel("episode return")
    handles = [Rectangle((0, 0), 1, 1, color=colours[k], alpha=0.6) for k in ("float", "int8")]
    ax.legend(handles, ["float actor", "int8 firmware"], fontsize=8)
    ax.set_title(f"{title}: returns over {comps[0].episodes} episodes", fontsize=10)
    ax.grid(alpha=0.3, axis="y")
    return cov, png_bytes(fig)


def run_verify(argv: Sequence[str]) -> int:
    """The ``verify`` sub-command; returns the exit status (raises ExportError on bad input)."""
    args = verify_parser().parse_args(list(argv))
    out: Path | None = args.out
    if out is not None:  # fail before the slow part
        check_name_lengths(out, temp=False)
        if out.exists() and not out.is_dir():
            raise OutputError(f"--out must be a directory, '{out}' is a file")
        base = out.resolve()
        while not base.exists():  # the nearest existing ancestor must let us create the rest
            base = base.parent
        if not base.is_dir():
            raise OutputError(f"cannot create '{out}': '{base}' is not a directory")
        check_writable([base / RESULT_JSON])
    policy = load(args.policy, task=args.task)
    print(describe(policy))
    check_robots(policy.world, args.robots, "--robots", args.task)
    check_robots(policy.world, args.robots_calib, "--robots-calib", args.task)
    calib_steps = run_steps(policy.world, args.calib_steps, "--calib-steps")
    steps = run_steps(policy.world, args.steps, "--steps")

    progress = not args.quiet and sys.stderr.isatty()
    calib, qp, report = quantise(policy, args, args.calib_seed, calib_steps, progress)
    print(f"quantised as python -m export would (calibration robots {args.robots_calib}, "
          f"{args.calib_episodes} episode(s), seed {args.calib_seed}, percentile {args.percentile}): "
          f"e_in {qp.e_in}, mean |du| {report.du_mean:.5f}, max |du| {report.du_max:.5f}, "
          f"same uint8 command {100 * report.same_command:.1f}%")

    task = get_task(args.task)
    comps = compare_many(policy, qp, args.robots, args.episodes, args.seed,
                         steps=steps, goal=args.goal,
                         progress=progress, task=task)
    print()
    for c in comps:
        print(c.table())
        print()
    passed = all(c.passed for c in comps)
    verdict = "PASS" if passed else "FAIL"
    print(f"closed loop: {verdict} (goal: int8 {task.metric(task.primary_metric).long} >= {args.goal:.2f} x float at "
          f"{', '.join(str(c.n_robots) for c in comps)} robots)")

    if out is not None:
        doc: dict[str, Any] = {
            "policy_hash": policy.hash, "policy": str(args.policy or "default"), "world": policy.world.name,
            "task": task.ref.to_dict(),
            "quantisation": {"e_in": qp.e_in, "robots_calib": list(args.robots_calib),
                             "calib_episodes": args.calib_episodes, "calib_steps": args.calib_steps,
                             "calib_seed": args.calib_seed,
                             "percentile": args.percentile, "error_report": report.to_dict()},
            "goal_ratio": args.goal, "passed": passed,
            "comparisons": [c.to_dict() for c in comps],
        }
        title = f"policy {policy.hash[:8]} ({policy.world.name})"
        cov, box = _plots(comps, title, task)
        files = {out / f"{task.success_plot}.png": cov, out / RETURNS_PNG: box,
                 out / RESULT_JSON: json.dumps(doc, indent=1, allow_nan=False)}  # the record last
        write_files_atomic(files, create=True)
        print(f"wrote {', '.join(printable(p) for p in files)}")
    return EXIT_OK if passed else EXIT_FAIL
