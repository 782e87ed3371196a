"""What the exporter's sub-commands share: exit codes, the one-line-error parser, argument types
(every number range-checked by :mod:`kiloforge.validate`), policy loading."""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from kiloforge.actors.base import FloatPolicy, QuantizedActor
from kiloforge.cliparse import ArgumentParser, deprecated_alias
from kiloforge.errors import printable
from kiloforge.validate import float_arg, int_arg, seed_arg
from sim.config import MAX_EPISODE_STEPS, MAX_ROBOTS, WorldConfig
from sim.tasks import TASK_HELP, Task, get_task

from ..errors import ExportError
from ..interop.onnx_import import load_onnx_policy
from ..quantize import calibrate, error_report, quantize_policy
from kiloforge.shipped import SHIPPED_POLICIES, load_task_policy

EXIT_OK = 0
EXIT_FAIL = 1  #: does not fit, or a verification failed
EXIT_USER_ERROR = 2


def policy_help() -> str:
    """``--policy``'s help, naming every shipped policy of every task."""
    shipped = "; ".join(f"{', '.join(names)} ({task})" for task, names in SHIPPED_POLICIES.items())
    return (f"policy artifact .npz, or the name of a shipped policy: {shipped} (default: default, the task's reference "
            "policy; for localisation trained by evolution strategies in the kilobot world, and searcher and pusher "
            "are the hand-written rules of sim/baselines.py)")


class Parser(ArgumentParser):
    """argparse (no abbreviations) that raises instead of exiting, so main() keeps the one-line error contract."""

    def error(self, message: str) -> None:  # type: ignore[override]
        explained = self.explain(message)
        raise ExportError(explained if explained != message else f"{message} (see --help)")


MAX_EPISODES = 100_000

positive = int_arg(1, 1 << 20)  #: a size flag (layers, history, hidden units); the budget refuses what does not fit
robots_arg = int_arg(1, MAX_ROBOTS)
episodes_arg = int_arg(1, MAX_EPISODES)
steps_arg = int_arg(1, MAX_EPISODE_STEPS)
percentile_arg = float_arg(0.0, 100.0, lo_open=True)


def add_quiet(ap: argparse.ArgumentParser) -> None:
    """``--quiet`` (no progress bar; one is shown only on a terminal), and its old spelling ``--no-progress``."""
    deprecated_alias(ap, "--no-progress", ap.add_argument("--quiet", action="store_true",
                                                          help="no progress bar (one is shown only on a terminal)"))


def add_calibration(ap: argparse.ArgumentParser, seed_flag: str = "--seed") -> None:
    """The flags of the calibration rollouts and the quantiser, the same in ``export`` and ``export verify``
    (whose ``--seed`` seeds its episodes, so its calibration seed is ``--calib-seed``)."""
    ap.add_argument("--robots-calib", type=robots_arg, nargs="+", default=[4, 16], metavar="N",
                    help="robot counts of the calibration rollouts (default 4 16)")
    ap.add_argument("--calib-episodes", type=episodes_arg, default=1,
                    help="calibration episodes per robot count (default 1)")
    ap.add_argument("--calib-steps", type=steps_arg, default=None,
                    help="control periods per calibration episode (default: the world's episode length)")
    ap.add_argument(seed_flag, type=seed_arg, default=0, help="calibration seed, a non-negative integer (default 0)")
    ap.add_argument("--percentile", type=percentile_arg, default=100.0,
                    help="range percentile for exponent choice, in (0, 100] (default 100: the largest value seen)")


def quantise(policy: FloatPolicy, args: argparse.Namespace, seed: int, steps: int,
             progress: bool) -> tuple[Any, QuantizedActor, Any]:
    """(calibration, int8 actor, float-vs-int8 error report) of ``policy`` as the flags of :func:`add_calibration`
    say, calibrated from ``seed`` on episodes of ``steps`` control periods."""
    calib = calibrate(policy, episodes=args.calib_episodes, n_robots=args.robots_calib, seed=seed, steps=steps,
                      progress=progress, task=args.task)
    qp = quantize_policy(policy, calib, percentile=args.percentile)
    return calib, qp, error_report(policy, qp, calib)


def check_robots(world: WorldConfig, counts: list[int], flag: str, task: "Task | str | None" = None) -> None:
    """The largest robot count fits the world's arena (SwarmEnv refuses too many discs) of ``task`` (default
    localisation)."""
    from sim.env import SwarmEnv

    try:
        SwarmEnv(world, 1, max(counts), seed=0, task=task)
    except ValueError as e:
        raise ExportError(f"{flag} {max(counts)}: {e}") from None


def add_task(ap: argparse.ArgumentParser) -> None:
    """``--task`` (default localisation): the task the policy must have been trained for."""
    ap.add_argument("--task", default=None, metavar="TASK", help=TASK_HELP)


def load(policy: Path | None, onnx: Path | None = None, world_json: Path | None = None,
         task: "Task | str | None" = None) -> FloatPolicy:
    """The policy of ``--policy`` (a file, or the name of one of the task's shipped policies: ``default``,
    ``searcher``, ...), ``--onnx`` (with ``--world-json``; taken as a policy of ``task``), or the task's
    shipped default policy; a policy trained for another task than ``task`` (default localisation) is refused."""
    if onnx is not None:
        return dataclasses.replace(load_onnx_policy(onnx, world_json=world_json), task=get_task(task).ref)
    if world_json is not None:
        raise ExportError("--world-json only goes with --onnx")
    return load_task_policy(policy, task)


def describe(policy: FloatPolicy) -> str:
    """The lines every sub-command prints about the policy it works on."""
    lines = [f"policy {policy.hash[:16]}: world '{printable(policy.world.name)}', {printable(policy.describe())}"]
    notes = policy.provenance.get("notes")
    if notes:
        lines.append(f"  provenance: {printable(notes, 300)}")
    return "\n".join(lines)
