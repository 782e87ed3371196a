"""``python -m sim`` / ``kiloforge sim``: run a policy in the simulator, print task metrics, write plots and a GIF.

    python -m sim --robots 4 --seed 0 --policy baseline --out runs/demo            (the kilobot world)
    python -m sim --world thesis --robots 4 --seed 0 --policy baseline --out runs/thesis
    python -m sim --policy runs/train/policy.npz --robots 16 --episodes 50 --out runs/eval16
    python -m sim --suite robustness --policy baseline --robots 4 16 --episodes 50 --steps 500 --out runs/rob

``--policy`` is one of the task's baselines (localisation: ``random``, ``baseline``, the hand-written searcher,
``pusher``, its crowd variant), a shipped policy of the task (``default``: its reference policy,
:mod:`kiloforge.shipped`) or the path of a policy artifact (``.npz`` from ``python -m learn``); an artifact runs in
the world it was trained in.
Writes into ``--out``: ``trajectories.png`` and ``episode.gif`` (the first episode),
the task's success over time (``<success_plot>.png``, :attr:`sim.tasks.Task.success_plot`; all episodes) and
``metrics.json``. ``--suite robustness`` instead runs the policy
in every world variant of :func:`sim.variants.robustness_suite` (of the kilobot world, or the
artifact's) at each ``--robots`` count and writes ``robustness.json`` and
``robustness.md`` (the task's primary metric per variant, and as a fraction of nominal). User errors print
one line and exit with 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

from kiloforge import io
from kiloforge.cliparse import ArgumentParser, deprecated_alias, error_line, program
from kiloforge.errors import InputError, KiloforgeError, printable
from kiloforge.interrupts import exit_status, terminate_raises
from kiloforge.io import staged_files
from kiloforge.policies import load_policy, swarm_policy
from kiloforge.shipped import load_task_policy, shipped_names
from kiloforge.validate import int_arg, seed_arg
from sim.config import DEFAULT_WORLD, MAX_EPISODE_STEPS, MAX_ROBOTS, PRESETS, preset, run_steps
from sim.tasks import TASK_HELP, Task, check_policy_task, get_task

EXIT_USAGE = 2
MAX_EPISODES = 100_000


def output_files(task: type[Task] | Task) -> tuple[str, ...]:
    """What a run of ``task`` writes into ``--out``, the record (metrics.json) last."""
    return ("trajectories.png", "episode.gif", f"{task.success_plot}.png", "metrics.json")


OUTPUT_FILES = output_files(Task)  #: the files of a run of a task that keeps the default plot name
SUITE_FILES = ("robustness.md", "robustness.json")  #: the record (kiloforge.io) last, as in OUTPUT_FILES
SUITES = ("robustness",)


class UserError(Exception):
    """A mistake in the command line or its inputs: reported in one line, exit code 2."""


class _Parser(ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]  # one line, no usage dump
        raise UserError(self.explain(message))


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m sim", description="Run a swarm policy in the kiloforge simulator: metrics, "
                "trajectory plot, success-over-time plot and an animated GIF.")
    world = p.add_argument("--world", default=None, help=f"world preset: {', '.join(sorted(PRESETS))} (default: "
                           f"{DEFAULT_WORLD}, or the artifact's world)")
    deprecated_alias(p, "--preset", world)
    p.add_argument("--robots", type=int_arg(1, MAX_ROBOTS), nargs="+", default=[4],
                   help="searching robots per env (default 4); with --suite, one or more counts")
    p.add_argument("--seed", type=seed_arg, default=0, help="root seed; same seed, same result (default 0)")
    p.add_argument("--policy", default="baseline",
                   help="one of the task's baselines (localisation: 'baseline', the hand-written searcher, its crowd "
                        "variant 'pusher', 'random'), a shipped policy of the task (e.g. 'default'), or a policy "
                        "artifact file (.npz); default 'baseline'")
    p.add_argument("--out", required=True, help="output folder (created if needed)")
    p.add_argument("--episodes", type=int_arg(1, MAX_EPISODES), default=20, help="episodes to run (default 20)")
    p.add_argument("--steps", type=int_arg(1, MAX_EPISODE_STEPS), default=None,
                   help="steps per episode (default: the world's episode, thesis 200, kilobot 300, as trained; "
                        "learn evaluate's 500 is the thesis benchmark's)")
    n_envs = p.add_argument("--n-envs", type=int_arg(1, MAX_EPISODES), default=None,
                            help="envs simulated at once (default: min(episodes, 32))")
    deprecated_alias(p, "--envs", n_envs)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--task", default=None, metavar="TASK", help=TASK_HELP)
    p.add_argument("--suite", choices=SUITES, default=None,
                   help="robustness: the task's primary metric in every world variant (sim.variants) instead of one run")
    return p


def _check_args(a: argparse.Namespace) -> None:
    if a.world is not None and a.world not in PRESETS:
        raise UserError(f"unknown world '{a.world}'; choose one of: {', '.join(sorted(PRESETS))}")
    if a.suite is None and len(a.robots) != 1:
        raise UserError(f"--robots takes one count without --suite, got {len(a.robots)}")


def _load_policy(a: argparse.Namespace, task: Task):
    """(world, policy factory (world -> SwarmPolicy), description dict, note or None) for --policy: one of the
    task's baselines, or a policy file trained for the task."""
    names = list(task.baselines.values())

    world = task.world(preset(a.world or DEFAULT_WORLD))  # the task's bodies and observation layout
    if a.steps is not None:
        world = dataclasses.replace(world, episode_steps=a.steps)
    if a.policy in names:
        desc: dict = {"kind": a.policy}
        params = getattr(task.make_baseline(a.policy, world), "p", None)
        if dataclasses.is_dataclass(params):
            desc["params"] = dataclasses.asdict(params)
        return world, lambda w: task.make_baseline(a.policy, w), desc, None
    path = Path(a.policy)
    shipped = [n for n in shipped_names(task) if n not in names]  # a shipped rule of a baseline's name is that baseline
    if not os.path.lexists(path) and a.policy not in shipped:
        raise UserError(f"--policy must be one of {', '.join(names + shipped)} or a policy file; "
                        f"'{a.policy}' is neither")
    try:
        if os.path.lexists(path):
            art = load_policy(path)
            check_policy_task(art.task_ref, task, f"policy file {printable(path.name)}")
        else:
            art = load_task_policy(a.policy, task)  # a shipped policy of the task, e.g. default
    except InputError as e:
        raise UserError(str(e)) from None
    try:
        art_world = dataclasses.replace(art.world, episode_steps=run_steps(art.world, a.steps, "--steps"))
    except InputError as e:
        raise UserError(str(e)) from None
    note = None
    if a.world is not None and art_world != world:
        note = (f"note: {printable(path.name)} was trained in world '{art.world.name}', which differs from --world "
                f"'{a.world}'; using the policy's world")
    desc = {"kind": "artifact", "path": str(path), "actor": art.kind, "architecture": art.describe(),
            "hash": art.hash, "layer_sizes": art.layer_sizes}
    return art_world, lambda w: swarm_policy(art, w), desc, note


def _staged_output(out: Path, files: tuple[str, ...]):
    """The ``files`` written into the yielded staging folder appear in ``out`` together, or (on any error)
    nothing does and a folder this run created is removed (:func:`kiloforge.io.staged_files`; the last
    file, the set's record, is published last)."""
    if out.exists() and not out.is_dir():
        raise UserError(f"--out must be a folder; '{out}' is a file")
    return staged_files(out, files, create=True)


def run(a: argparse.Namespace) -> dict:
    """Run the command; returns the metrics.json content. Raises :class:`UserError` for user mistakes."""
    _check_args(a)
    io.check_name_lengths(a.out, temp=False)  # before any work
    try:
        task = get_task(a.task)
    except InputError as e:
        raise UserError(str(e)) from None
    world, factory, desc, note = _load_policy(a, task)
    if note:
        print(note, file=sys.stderr)
    if a.suite:
        return _run_suite(a, world, factory, desc, task)
    policy = factory(world)
    robots = a.robots[0]
    from sim import render
    from sim.env import SwarmEnv
    from sim.metrics import compare
    from sim.rollout import rollout

    n_envs = a.n_envs or min(a.episodes, 32)
    try:
        env = SwarmEnv(task.world_for(world, robots), n_envs, robots, seed=a.seed, task=task)
    except ValueError as e:  # e.g. too many discs for the arena
        raise UserError(str(e)) from None
    out = Path(a.out)
    files = output_files(task)
    with _staged_output(out, files) as staging:
        res = rollout(env, policy, a.episodes, seed=a.seed, record=1, progress=a.episodes > 1 and not a.quiet)
        m = res.metrics()
        name = desc["kind"] if desc["kind"] != "artifact" else Path(a.policy).name
        report = {
            "tool": "kiloforge sim",
            "argv": list(a.argv),
            "policy": desc,
            "task": task.ref.to_dict(),
            "world": world.to_dict(),
            "robots": robots,
            "seed": a.seed,
            "envs": n_envs,
            "rendered_episode": 0,
            "metrics": m.to_dict(),
        }
        tr = res.trajectories
        title = f"{world.name}: {robots} robots, {name}, seed {a.seed}, episode 0"
        target = None if tr.target is None else tr.target[0]
        render.plot_trajectories(tr.positions[0], target, world, staging / "trajectories.png", title=title)
        render.animate_episode(tr.positions[0], tr.headings[0], target, tr.in_range[0], world,
                               staging / "episode.gif", title=title, label=task.robot_label)
        render.plot_success({name: res.success}, staging / f"{task.success_plot}.png",
                            title=f"{world.name}: {robots} robots, {a.episodes} episodes", ylabel=task.success_label)
        (staging / "metrics.json").write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    print(compare({name: m}, task.columns))
    print(f"wrote {printable(out)}/: {' '.join(files)}")
    return report


def _run_suite(a: argparse.Namespace, world, factory, desc: dict, task: Task) -> dict:
    """``--suite robustness``: every variant at every robot count; robustness.json and .md."""
    from sim.env import SwarmEnv
    from sim.robustness import run_suite
    from sim.variants import robustness_suite

    try:
        suite = robustness_suite(world)
        for M in a.robots:  # every variant has the nominal arena: too many discs fail here, before any output
            SwarmEnv(world, 1, M, seed=0, task=task)
    except ValueError as e:
        raise UserError(str(e)) from None
    out = Path(a.out)
    with _staged_output(out, SUITE_FILES) as staging:
        table = run_suite(factory, world, a.robots, a.episodes, world.episode_steps, a.seed, suite, a.n_envs,
                          progress=not a.quiet, task=task)
        name = desc["kind"] if desc["kind"] != "artifact" else Path(a.policy).name
        report = {"tool": "kiloforge sim", "argv": list(a.argv), "suite": a.suite, "policy": desc,
                  "world": world.to_dict(), "variants": {v: {"world": w.to_dict(), "randomisation":
                                                             None if r is None else dataclasses.asdict(r)}
                                                         for v, (w, r) in suite.items()},
                  **table.to_dict()}
        md = (f"# Robustness of {name} ({world.name} world, {a.episodes} episodes x {world.episode_steps} steps, "
              f"seed {a.seed})\n\n{table.format()}\n")
        (staging / "robustness.json").write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
        (staging / "robustness.md").write_text(md)
    print(table.format())
    print(f"wrote {printable(out)}/: {' '.join(SUITE_FILES)}")
    return report


def main(argv: list[str] | None = None) -> int:
    """The ``python -m sim`` command (:mod:`sim.__main__` runs it; ``argv`` None: ``sys.argv``); returns the exit
    status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    mark = io.published_count()
    try:
        with terminate_raises():
            a = build_parser().parse_args(argv)
            a.argv = argv
            run(a)
    except (UserError, KiloforgeError) as e:
        print(error_line(program('python -m sim'), printable(e)), file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as e:
        written = io.published_since(mark)
        what = (f"after writing {', '.join(map(str, written))} (complete)" if written
                else "; nothing written (files from an earlier run are unchanged)")
        print(f"{program('python -m sim')}: interrupted {what}".replace(" ;", ";"), file=sys.stderr)
        return exit_status(e)
    except SystemExit as e:  # --help
        return int(e.code or 0) if not isinstance(e.code, str) else EXIT_USAGE
    return 0

