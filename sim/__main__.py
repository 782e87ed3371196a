"""``python -m sim``: run a policy in the simulator, print task metrics, write plots and a GIF.

    python -m sim --preset thesis --robots 4 --seed 0 --policy baseline --out runs/demo
    python -m sim --policy runs/train/policy.npz --robots 16 --episodes 50 --out runs/eval16

``--policy`` is ``random``, ``baseline`` (the hand-written searcher) or the path of a policy
artifact (``.npz`` from ``python -m learn``); an artifact runs in the world it was trained in.
Writes into ``--out``: ``trajectories.png`` and ``episode.gif`` (the first episode),
``coverage.png`` (all episodes) and ``metrics.json``. User errors print one line and exit with 2.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

from kiloforge import io
from kiloforge.errors import KiloforgeError, PolicyError, printable
from kiloforge.interrupts import exit_status, terminate_raises
from kiloforge.io import staged_files
from kiloforge.policies import load_policy, swarm_policy
from kiloforge.validate import int_arg, seed_arg

from .config import MAX_EPISODE_STEPS, PRESETS, preset

EXIT_USAGE = 2
MAX_ROBOTS = 1024
MAX_EPISODES = 100_000
OUTPUT_FILES = ("trajectories.png", "episode.gif", "coverage.png", "metrics.json")


class UserError(Exception):
    """A mistake in the command line or its inputs: reported in one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, no usage dump
        raise UserError(message)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m sim", description="Run a swarm policy in the kiloforge simulator: metrics, "
                "trajectory plot, coverage plot and an animated GIF.")
    p.add_argument("--preset", default=None, help=f"world preset: {', '.join(sorted(PRESETS))} (default: thesis, "
                   "or the artifact's world)")
    p.add_argument("--robots", type=int_arg(1, MAX_ROBOTS), default=4, help="searching robots per env (default 4)")
    p.add_argument("--seed", type=seed_arg, default=0, help="root seed; same seed, same result (default 0)")
    p.add_argument("--policy", default="baseline",
                   help="'random', 'baseline' (hand-written searcher) or a policy artifact file (.npz)")
    p.add_argument("--out", required=True, help="output folder (created if needed)")
    p.add_argument("--episodes", type=int_arg(1, MAX_EPISODES), default=20, help="episodes to run (default 20)")
    p.add_argument("--steps", type=int_arg(1, MAX_EPISODE_STEPS), default=None,
                   help="steps per episode (default: the world's)")
    p.add_argument("--envs", type=int_arg(1, MAX_EPISODES), default=None,
                   help="envs simulated at once (default: min(episodes, 32))")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _check_args(a: argparse.Namespace) -> None:
    if a.preset is not None and a.preset not in PRESETS:
        raise UserError(f"unknown preset '{a.preset}'; choose one of: {', '.join(sorted(PRESETS))}")


def _load_policy(a: argparse.Namespace):
    """(world, policy, description dict, note or None) for the --policy argument."""
    world = preset(a.preset or "thesis")
    if a.steps is not None:
        world = dataclasses.replace(world, episode_steps=a.steps)
    if a.policy in ("random", "baseline"):
        from .baselines import make_policy

        pol = make_policy(a.policy, world)
        desc: dict = {"kind": a.policy}
        if a.policy == "baseline":
            desc["params"] = dataclasses.asdict(pol.p)
        return world, pol, desc, None
    path = Path(a.policy)
    if not os.path.lexists(path):
        raise UserError(f"--policy must be 'random', 'baseline' or a policy file; '{a.policy}' is neither")
    try:
        art = load_policy(path)
    except PolicyError as e:
        raise UserError(str(e)) from None
    art_world = art.world
    if a.steps is not None:
        art_world = dataclasses.replace(art_world, episode_steps=a.steps)
    note = None
    if a.preset is not None and art_world != world:
        note = (f"note: {printable(path.name)} was trained in world '{art.world.name}', which differs from preset "
                f"'{a.preset}'; using the policy's world")
    desc = {"kind": "artifact", "path": str(path), "actor": art.kind, "architecture": art.describe(),
            "hash": art.hash, "layer_sizes": art.layer_sizes}
    return art_world, swarm_policy(art, art_world), desc, note


def run(a: argparse.Namespace) -> dict:
    """Run the command; returns the metrics.json content. Raises :class:`UserError` for user mistakes."""
    _check_args(a)
    world, policy, desc, note = _load_policy(a)
    if note:
        print(note, file=sys.stderr)
    from . import render
    from .env import SwarmEnv
    from .metrics import compare
    from .rollout import rollout

    n_envs = a.envs or min(a.episodes, 32)
    try:
        env = SwarmEnv(world, n_envs, a.robots, seed=a.seed)
    except ValueError as e:  # e.g. too many discs for the arena
        raise UserError(str(e)) from None
    out = Path(a.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out must be a folder; '{out}' is a file")
    # all files appear together or not at all; metrics.json, last, is the set's record
    with staged_files(out, OUTPUT_FILES, create=True) as staging:
        res = rollout(env, policy, a.episodes, seed=a.seed, record=1, progress=a.episodes > 1 and not a.quiet)
        m = res.metrics()
        name = desc["kind"] if desc["kind"] != "artifact" else Path(a.policy).name
        report = {
            "tool": "kiloforge sim",
            "argv": list(a.argv),
            "policy": desc,
            "world": world.to_dict(),
            "robots": a.robots,
            "seed": a.seed,
            "envs": n_envs,
            "rendered_episode": 0,
            "metrics": m.to_dict(),
        }
        tr = res.trajectories
        title = f"{world.name}: {a.robots} robots, {name}, seed {a.seed}, episode 0"
        render.plot_trajectories(tr.positions[0], tr.target[0], world, staging / "trajectories.png", title=title)
        render.animate_episode(tr.positions[0], tr.headings[0], tr.target[0], tr.in_range[0], world,
                               staging / "episode.gif", title=title)
        render.plot_coverage({name: res.coverage}, staging / "coverage.png",
                             title=f"{world.name}: {a.robots} robots, {a.episodes} episodes")
        (staging / "metrics.json").write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    print(compare({name: m}))
    print(f"wrote {out}/: {' '.join(OUTPUT_FILES)}")
    return report


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m sim`` / ``kiloforge-sim``; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    mark = io.published_count()
    try:
        with terminate_raises():
            a = build_parser().parse_args(argv)
            a.argv = argv
            run(a)
    except (UserError, KiloforgeError) as e:
        print(f"python -m sim: error: {printable(e)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as e:
        written = io.published_since(mark)
        what = f"after writing {', '.join(map(str, written))} (complete)" if written else \
            "; nothing written (files from an earlier run are unchanged)"
        print(f"python -m sim: interrupted {what}".replace(" ;", ";"), file=sys.stderr)
        return exit_status(e)
    except SystemExit as e:  # --help
        return int(e.code or 0) if not isinstance(e.code, str) else EXIT_USAGE
    return 0


if __name__ == "__main__":
    sys.exit(main())
