"""Tune the hand-written phototaxis baselines (sim.tasks.phototaxis: StopInLight, RunAndTumble) on validation episodes.

A grid over each rule's constants at 16 robots in the phototaxis world (the kilobot preset with the task's
spot lamp), 500-step episodes (the evaluation benchmark's), validation seed 777 (used by no evaluation):
prints each point's final fraction in the spot and each rule's best, whose values are the rule's
defaults (StopInLightParams, RunAndTumbleParams).

    python -m tools.tune_phototaxis [--robots 16] [--episodes 20]
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools

from sim.config import BENCHMARK_STEPS, VALIDATION_SEED, preset
from sim.env import SwarmEnv
from sim.rollout import rollout
from sim.tasks.phototaxis import Phototaxis, RunAndTumble, RunAndTumbleParams, StopInLight, StopInLightParams

#: (rule, its parameters, the grid): the second grids, around the first's best; their best are the rules' defaults
#: (StopInLight threshold 550, run 5, turn 2: 0.920; RunAndTumble fall 12, run 40, turn 6: 0.515). First grids:
#: StopInLight threshold 400 / 500 / 600, run 5..40, turn 2 / 4: best 600, run 5, turn 2, 0.914;
#: RunAndTumble fall 2..16, run 10..80, turn 2 / 4: best fall 8, run 40, turn 4, 0.404 (turn 4 beat 2 everywhere)
GRIDS = (
    (StopInLight, StopInLightParams, {"threshold": (550, 600, 650, 700), "run_steps": (3, 5, 8),
                                      "turn_max_steps": (1, 2, 3)}),
    (RunAndTumble, RunAndTumbleParams, {"fall": (4, 8, 12), "run_steps": (20, 40),
                                        "turn_max_steps": (4, 6, 8, 12)}),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--episodes", type=int, default=20)
    a = ap.parse_args()
    task = Phototaxis()
    world = task.world(dataclasses.replace(preset("kilobot"), episode_steps=BENCHMARK_STEPS))
    env = SwarmEnv(world, min(a.episodes, 20), a.robots, seed=0, task=task)
    for rule, params, grid in GRIDS:
        rows = []
        for values in itertools.product(*grid.values()):
            p = dataclasses.replace(params(), **dict(zip(grid, values)))
            m = rollout(env, rule(world, p), a.episodes, seed=VALIDATION_SEED).metrics()
            s = m.summary()[task.primary_metric]
            rows.append((s.mean, values))
            print(f"{rule.__name__} {dict(zip(grid, values))}  final in spot {s}", flush=True)
        best = max(rows)
        print(f"best {rule.__name__}: {dict(zip(grid, best[1]))}  final in spot {best[0]:.3f}", flush=True)


if __name__ == "__main__":
    main()
