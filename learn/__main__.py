"""``python -m learn``: train (MAGDDPG, MAGRDPG), evaluate policies, plot learning curves, export ONNX.

    python -m learn train --robots 4 --history 10 --out runs/NAME [--preset fast] [--world thesis]
                          [--seed S] [--config file.json] [--resume] [--<any TrainConfig field> VALUE]
    python -m learn train-recurrent --robots 2 --out runs/NAME [--preset guided] [--<any RecurrentConfig field>]
    python -m learn train-es --robots 4 16 32 --out runs/NAME [--preset quick] [--<any ESConfig field>]
    python -m learn evaluate --policy P [P ...] --robots 16 32 --episodes 500 --steps 500 --out DIR
    python -m learn plot RUN_DIR [RUN_DIR ...] [--out curve.png]
    python -m learn export-onnx --policy P.npz --out actor.onnx
    python -m learn sweep --seeds 1 2 3 --robots 1 2 4 --preset quick --out DIR   (Ray Tune; docs/sweeps.md)

``train`` and ``train-recurrent`` are :mod:`learn.cli` (every config field is a flag, tyro).
User errors print one line and exit with status 2.
"""

from kiloforge.sighold import hold, release  # first: a Ctrl-C or SIGTERM while the imports below load is held

_held, _previous = hold()
try:
    import argparse
    import sys
    from pathlib import Path

    from kiloforge.cli import run_guarded
    from kiloforge.cliparse import ArgumentParser, error_line, program, version_line
    from kiloforge.interrupts import exit_status, run_entry_point, terminate_raises
    from kiloforge.validate import int_arg, seed_arg
    from sim.config import BENCHMARK_EPISODES, BENCHMARK_STEPS, MAX_EPISODE_STEPS, MAX_ROBOTS
    from sim.tasks import TASK_HELP
finally:
    release(_previous, program=__name__ == "__main__")


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m learn",
                       description="Train (MAGDDPG, MAGRDPG, ES), evaluate and plot Kilobot swarm policies.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)

    sub.add_parser("train", add_help=False,
                   help=f"train an MLP policy with MAGDDPG ({p.prog} train --help)")

    e = sub.add_parser("evaluate", help="evaluate policies against the baselines",
                       description="Evaluate policy artifacts and the random / hand-written baselines.")
    e.add_argument("--policy", nargs="+", required=True,
                   help="policy artifact(s) (.npz), or the name of a shipped policy of the task (e.g. default)")
    e.add_argument("--task", default=None, metavar="TASK", help=TASK_HELP)
    e.add_argument("--robots", nargs="+", type=int_arg(1, MAX_ROBOTS), default=[16, 32],
                   help="swarm sizes (default 16 32)")
    e.add_argument("--episodes", type=int_arg(1, 100_000), default=BENCHMARK_EPISODES,
                   help=f"episodes per policy and size (default {BENCHMARK_EPISODES}, the thesis benchmark's)")
    e.add_argument("--steps", type=int_arg(1, MAX_EPISODE_STEPS), default=BENCHMARK_STEPS,
                   help=f"steps per episode (default {BENCHMARK_STEPS}, the thesis benchmark's, for every world; "
                        "python -m sim runs the world's own episode, thesis 200, kilobot 300)")
    e.add_argument("--out", default=None,
                   help="output directory for evaluation.json, plots and a GIF (default: print the tables only)")
    e.add_argument("--seed", type=seed_arg, default=0, help="episode seed (same for every policy)")
    e.add_argument("--n-envs", type=int_arg(1, 100_000), default=50, help="episodes simulated together (default 50)")
    e.add_argument("--no-baselines", action="store_true", help="skip the random and hand-written baselines")
    e.add_argument("--no-gif", action="store_true", help="skip the episode GIF")
    e.add_argument("--quiet", action="store_true", help="no progress bars")

    sub.add_parser("train-recurrent", add_help=False,
                   help=f"train a recurrent (GRU) policy with MAGRDPG ({p.prog} train-recurrent --help)")
    sub.add_parser("train-es", add_help=False,
                   help="train an MLP policy with evolution strategies from a clone of the searcher "
                        f"({p.prog} train-es --help)")
    sub.add_parser("export-onnx", add_help=False,
                   help=f"write a policy artifact's float actor as ONNX ({p.prog} export-onnx --help)")
    sub.add_parser("sweep", add_help=False,
                   help=f"a grid of trainings x seeds on Ray Tune, aggregated ({p.prog} sweep --help)")

    pl = sub.add_parser("plot", help="learning curves of runs (mean ± 2 std over seeds)",
                        description="Plot learning curves; runs that differ only in seed are averaged.")
    pl.add_argument("runs", nargs="+", help="run directories")
    pl.add_argument("--out", default=None, help="PNG path (default learning_curves.png here)")
    pl.add_argument("--title", default=None)
    pl.add_argument("--task", default=None, metavar="TASK",
                    help="the runs' task, needed when they were trained for a task file (path/to/file.py:ClassName): "
                         "plot never imports code that a run folder names (default: the task their config.json names)")
    return p


def cmd_evaluate(args: argparse.Namespace) -> int:
    from kiloforge.shipped import load_task_policy
    from kiloforge.errors import printable
    from kiloforge.io import check_name_lengths, staged_files
    from kiloforge.policies import policy_labels
    from sim.tasks import get_task

    from .evaluate import evaluate_policies

    if args.out is not None:
        check_name_lengths(args.out, temp=False)  # before any work
    task = get_task(args.task)
    policies = {name: load_task_policy(path, task) for name, path in zip(policy_labels(args.policy), args.policy)}
    run = dict(seed=args.seed, n_envs=args.n_envs, baselines=not args.no_baselines, progress=not args.quiet, task=task)
    if args.out is None:  # the tables on stdout only
        evaluate_policies(policies, args.robots, args.episodes, args.steps, None, gif=False, **run)
        print("nothing written (--out DIR writes evaluation.json, plots and a GIF)")
        return 0
    out = Path(args.out)
    with staged_files(out, record="evaluation.json", create=True) as tmp:  # all files or none
        evaluate_policies(policies, args.robots, args.episodes, args.steps, tmp, gif=not args.no_gif, **run)
    print(f"wrote {printable(out)}/evaluation.json and plots")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from kiloforge.errors import InputError, printable
    from kiloforge.io import check_writable
    from sim.tasks import DEFAULT_TASK, get_task, recorded_task

    from .evaluate import primary_column, success_panel
    from .plots import plot_learning_curves
    from .runfiles import ALGORITHM_NAMES, experiment_groups, read_config, read_metrics

    check_writable([args.out or "learning_curves.png"])  # before reading the runs

    groups: dict[str, list] = {}
    algorithms: list[str] = []
    configs = [(run, read_config(run)) for run in args.runs]
    tasks = {str(cfg.get("task", DEFAULT_TASK)) for _, cfg in configs}
    if len(tasks) > 1:
        raise InputError(f"the runs train different tasks ({', '.join(sorted(tasks))}); plot each task's runs apart")
    # the user's --task, or the one the configs name, by name only: a run folder never makes us import its code
    task = get_task(args.task) if args.task else recorded_task(tasks.pop(), "the runs' config.json", "--task")
    base = []
    for _, cfg in configs:
        sizes = cfg.get("n_robots", "?")
        sizes = "/".join(map(str, sizes)) if isinstance(sizes, list) else sizes
        base.append(f"{cfg.get('exp_name', '?')}: {sizes} robots, T_prev {cfg.get('t_prev', '?')}")
    for (run, cfg), label in zip(configs, experiment_groups([c for _, c in configs], base)):
        rows = read_metrics(run, ("env_steps", "eval_return", primary_column(task)))
        groups.setdefault(label, []).append(rows)
        name = ALGORITHM_NAMES.get(cfg.get("algorithm", "magddpg"), str(cfg.get("algorithm")))
        algorithms += [name] if name not in algorithms else []
    out = Path(args.out or "learning_curves.png")
    title = args.title or f"{' / '.join(algorithms)} learning curves (mean ± 2 std over seeds)"
    plot_learning_curves(groups, out, title=title, success=success_panel(task))
    print(f"wrote {printable(out)}")
    return 0


#: the commands that need the learn extra (torch, tyro); evaluate runs on the core dependencies
TRAIN_COMMANDS = ("train", "train-recurrent", "train-es")


def _load(argv: list[str] | None):
    """The modules the command in ``argv`` needs: the trainer (torch, tyro) for a training command, the
    evaluator (NumPy, the simulator) otherwise; a missing optional dependency raises here."""
    args = sys.argv[1:] if argv is None else argv
    if args and args[0] in TRAIN_COMMANDS:
        from . import cli, train  # noqa: F401
    else:
        from . import evaluate  # noqa: F401
    return _main


def _main(argv: list[str] | None = None) -> int:
    from kiloforge.errors import KiloforgeError

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in ("train", "train-recurrent", "train-es"):  # learn/cli.py: tyro parsers of the configs
        from .cli import main_train, main_train_es, main_train_recurrent

        return {"train": main_train, "train-recurrent": main_train_recurrent,
                "train-es": main_train_es}[argv[0]](argv[1:])
    if argv and argv[0] == "export-onnx":  # its own parser lives with the exporter (learn/onnx_export.py)
        from .onnx_export import main_export_onnx

        return main_export_onnx(argv[1:])
    if argv and argv[0] == "sweep":  # its own parser lives with the sweep (learn/sweep/cli.py)
        from .sweep import main_sweep

        return main_sweep(argv[1:])
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # named by the sub-command, as its own errors are
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        sub.choices[args.command].error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        with terminate_raises():
            return {"evaluate": cmd_evaluate, "plot": cmd_plot}[args.command](args)
    except (KiloforgeError, ValueError) as e:  # learn.config.ConfigError is a ValueError
        print(error_line(program('python -m learn ' + args.command), e), file=sys.stderr)
        return 2
    except KeyboardInterrupt as e:  # evaluate publishes all its files or none; plot writes one file atomically
        print(error_line(program('python -m learn ' + args.command), "interrupted; nothing written"), file=sys.stderr)
        return exit_status(e)


def main(argv: list[str] | None = None) -> int:
    """``python -m learn`` / ``kiloforge-learn``; a Ctrl-C while its modules load ends in one line."""
    if (sys.argv[1:] if argv is None else list(argv)) == ["--version"]:  # without loading torch
        print(version_line())
        return 0
    return run_entry_point(lambda: _load(argv), argv,
                           error_line(program('python -m learn'), "interrupted while starting; nothing written"), _held)


if __name__ == "__main__":
    sys.exit(run_guarded("python -m learn", lambda: main, None))
