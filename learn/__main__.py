"""``python -m learn``: train MAGDDPG, evaluate policies, plot learning curves.

    python -m learn train --robots 4 --history 10 --out runs/NAME [--preset fast] [--world thesis]
                          [--seed S] [--config file.json] [--resume] [--<any TrainConfig field> VALUE]
    python -m learn evaluate --policy P [P ...] --robots 16 32 --episodes 500 --steps 500 --out DIR
    python -m learn plot RUN_DIR [RUN_DIR ...] [--out curve.png]
    python -m learn export-onnx --policy P.npz --out actor.onnx
    python -m learn sweep --seeds 1 2 3 --robots 1 2 4 --preset quick --out DIR   (Ray Tune; docs/sweeps.md)

Every ``TrainConfig`` field is an option (``--lr-actor 3e-4``, ``--actor-hidden 32 32``).
Precedence: defaults < ``--preset`` < ``--config`` file < options on the command line.
User errors print one line and exit with status 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import re
import sys
import typing
from pathlib import Path

from sim.config import PRESETS as WORLD_PRESETS

from .config import FIELD_TYPES, TRAIN_PRESETS, ConfigError, TrainConfig, coerce

ALIASES = {"n_robots": ["--robots"], "t_prev": ["--history"]}


class ArgumentParser(argparse.ArgumentParser):
    """argparse with one-line errors (exit status 2)."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def field_docs() -> dict[str, str]:
    """The ``#:`` comment of every TrainConfig field (used as --help text)."""
    docs = {}
    for line in inspect.getsource(TrainConfig).splitlines():
        m = re.match(r"\s+(\w+): .*?#: (.*)$", line)
        if m:
            docs[m.group(1)] = m.group(2).strip()
    return docs


def add_config_options(p: argparse.ArgumentParser) -> None:
    """One option per TrainConfig field, default SUPPRESS so only given options override."""
    docs = field_docs()
    hints = typing.get_type_hints(TrainConfig)
    g = p.add_argument_group("training configuration (TrainConfig fields)")
    for f in dataclasses.fields(TrainConfig):
        flags = ALIASES.get(f.name, []) + [f"--{f.name.replace('_', '-')}"]
        default = f.default
        kw: dict = {"dest": f.name, "default": argparse.SUPPRESS, "help": f"{docs.get(f.name, '')} (default {default})"}
        if typing.get_origin(hints[f.name]) is tuple:
            kw.update(nargs="+", metavar="N", type=str, help=f"{docs.get(f.name, '')} (default {' '.join(map(str, default))})")
        else:
            kw.update(type=str, metavar=hints[f.name].__name__.upper())
        g.add_argument(*flags, **kw)


def train_preset(name: str) -> str:
    """argparse type of --preset, with a hint when a world preset is given instead."""
    if name in TRAIN_PRESETS:
        return name
    hint = f"'{name}' is a world: use --world {name}; " if name in WORLD_PRESETS else ""
    raise argparse.ArgumentTypeError(f"{hint}training presets are {', '.join(TRAIN_PRESETS)}")


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog="python -m learn", description="MAGDDPG trainer for Kilobot swarm policies.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)

    t = sub.add_parser("train", help="train a policy (MAGDDPG)", description="Train a swarm policy with MAGDDPG.")
    t.add_argument("--preset", default=None, type=train_preset, metavar="{" + ",".join(TRAIN_PRESETS) + "}",
                   help="training preset (default: 'default', the thesis hyper-parameters); "
                        "the world is chosen with --world")
    t.add_argument("--config", default=None, help="JSON file of TrainConfig fields")
    t.add_argument("--out", default=None, help="run directory (default runs/<task>__<exp>__<seed>__<time>)")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    t.add_argument("--quiet", action="store_true", help="no progress bar; one line per evaluation")
    add_config_options(t)

    e = sub.add_parser("evaluate", help="evaluate policies against the baselines",
                       description="Evaluate policy artifacts and the random / hand-written baselines.")
    e.add_argument("--policy", nargs="+", required=True, help="policy artifact(s) (.npz)")
    e.add_argument("--robots", nargs="+", type=int, default=[16, 32], help="swarm sizes (default 16 32)")
    e.add_argument("--episodes", type=int, default=500, help="episodes per policy and size (default 500)")
    e.add_argument("--steps", type=int, default=500, help="steps per episode (default 500)")
    e.add_argument("--out", required=True, help="output directory")
    e.add_argument("--seed", type=int, default=0, help="episode seed (same for every policy)")
    e.add_argument("--n-envs", type=int, default=50, help="episodes simulated together (default 50)")
    e.add_argument("--no-baselines", action="store_true", help="skip the random and hand-written baselines")
    e.add_argument("--no-gif", action="store_true", help="skip the episode GIF")
    e.add_argument("--quiet", action="store_true", help="no progress bars")

    sub.add_parser("train-recurrent", add_help=False,
                   help="train a recurrent (GRU) policy with MAGRDPG (python -m learn train-recurrent --help)")
    sub.add_parser("export-onnx", add_help=False,
                   help="write a policy artifact's float actor as ONNX (python -m learn export-onnx --help)")

    sub.add_parser("sweep", add_help=False,
                   help="a grid of trainings x seeds on Ray Tune, aggregated (python -m learn sweep --help)")

    pl = sub.add_parser("plot", help="learning curves of runs (mean ± 2 std over seeds)",
                        description="Plot learning curves; runs that differ only in seed are averaged.")
    pl.add_argument("runs", nargs="+", help="run directories")
    pl.add_argument("--out", default=None, help="PNG path (default learning_curves.png here)")
    pl.add_argument("--title", default=None)
    return p


def resolve_train_config(args: argparse.Namespace) -> tuple[TrainConfig, Path]:
    given = {f: getattr(args, f) for f in FIELD_TYPES if hasattr(args, f)}
    given = {k: coerce(k, v) for k, v in given.items()}
    if args.resume:
        if not args.out:
            raise ConfigError("--resume needs --out RUN_DIR")
        path = Path(args.out) / "config.json"
        if not path.is_file():
            raise ConfigError(f"cannot resume: '{path}' does not exist")
        cfg = TrainConfig.from_dict(read_json(path), base=TrainConfig())
        cfg = dataclasses.replace(cfg, **given)
        return cfg.validate(), Path(args.out)
    cfg = TrainConfig.from_dict(TRAIN_PRESETS[args.preset or "default"])
    if args.config:
        cfg = TrainConfig.from_dict(read_json(Path(args.config)), base=cfg)
    cfg = dataclasses.replace(cfg, **given).validate()
    if args.out:
        out = Path(args.out)
    else:
        from .train import run_name

        out = Path("runs") / run_name(cfg)
    return cfg, out


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"'{path}' does not exist") from None
    except (OSError, json.JSONDecodeError) as e:
        raise ConfigError(f"cannot read '{path}': {e}") from None


def cmd_train(args: argparse.Namespace) -> int:
    cfg, out = resolve_train_config(args)
    from export.codegen.budget import estimate
    from kiloforge.actors.mlp import MLP, MLPArch

    from .train import train

    budget = estimate(MLP, cfg.world_config(), MLPArch(cfg.t_prev, tuple(cfg.actor_hidden)))
    if not budget.ok:
        print(f"note: this actor (t_prev {cfg.t_prev}, hidden {list(cfg.actor_hidden)}) does not fit the Kilobot "
              f"budget ({budget.summary()}); it trains, but the exporter will refuse it", file=sys.stderr)
    res = train(cfg, out, resume=args.resume, progress=not args.quiet)
    c = res.counters
    best = max(c.rows, key=lambda r: r["eval_return"]) if c.rows else None
    print(f"run: {res.run_dir}  ({res.stopped})")
    print(f"  {c.env_steps} transitions, {c.updates} updates in {c.wall_s:.0f} s: "
          f"{c.env_steps / c.env_s if c.env_s else float('nan'):.0f} env steps/s while collecting, "
          f"{c.updates / c.update_s if c.update_s else float('nan'):.0f} updates/s while updating")
    if best:
        print(f"  best evaluation at {best['env_steps']:.0f} transitions: return {best['eval_return']:.1f}, "
              f"final coverage {best['eval_final_coverage']:.3f}, time to find {best['eval_time_to_find']:.1f}")
    print(f"  policies: {res.run_dir / 'policy_best.npz'}, {res.run_dir / 'policy_last.npz'}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    from kiloforge.policies import load_policy

    from .evaluate import evaluate_policies

    for name, v, lo in (("--episodes", args.episodes, 1), ("--steps", args.steps, 1), ("--n-envs", args.n_envs, 1)):
        if v < lo:
            raise ConfigError(f"{name} must be >= {lo}, got {v}")
    if any(m < 1 or m > 1024 for m in args.robots):
        raise ConfigError(f"--robots must be in 1..1024, got {args.robots}")
    policies = {}
    for path in args.policy:
        p = load_policy(path)
        name = Path(path).stem if Path(path).parent.name in ("", ".") else f"{Path(path).parent.name}/{Path(path).stem}"
        policies[name] = p
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ConfigError(f"cannot create '{out}': {e.strerror or e}") from None
    evaluate_policies(policies, args.robots, args.episodes, args.steps, out, seed=args.seed,
                      n_envs=args.n_envs, baselines=not args.no_baselines, gif=not args.no_gif,
                      progress=not args.quiet)
    print(f"wrote {out}/evaluation.json and plots")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from .plots import plot_learning_curves
    from .train import read_metrics

    groups: dict[str, list] = {}
    for run in args.runs:
        cfg = read_json(Path(run) / "config.json")
        rows = read_metrics(run)
        label = f"{cfg.get('exp_name', '?')}: {cfg.get('n_robots', '?')} robots, T_prev {cfg.get('t_prev', '?')}"
        groups.setdefault(label, []).append(rows)
    out = Path(args.out or "learning_curves.png")
    plot_learning_curves(groups, out, title=args.title or "MAGDDPG learning curves (mean ± 2 std over seeds)")
    print(f"wrote {out}")
    return 0


def main(argv: list[str] | None = None) -> int:
    from kiloforge.errors import KiloforgeError

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] == "train-recurrent":  # MAGRDPG (learn/magrdpg.py) has its own parser
        from .magrdpg import main_train_recurrent

        return main_train_recurrent(argv[1:])
    if argv and argv[0] == "export-onnx":  # its own parser lives with the exporter (learn/onnx_export.py)
        from .onnx_export import main_export_onnx

        return main_export_onnx(argv[1:])
    if argv and argv[0] == "sweep":  # its own parser lives with the sweep (learn/sweep/cli.py)
        from .sweep import main_sweep

        return main_sweep(argv[1:])
    args = build_parser().parse_args(argv)
    try:
        return {"train": cmd_train, "evaluate": cmd_evaluate, "plot": cmd_plot}[args.command](args)
    except (ConfigError, KiloforgeError, ValueError) as e:
        print(f"python -m learn {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
