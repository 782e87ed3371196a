"""Tune the hand-written transport baseline (sim.tasks.transport.ShadowPusher) on validation episodes.

A grid over the rule's constants at 16 robots in the transport world (the kilobot preset with the task's object,
side lamp and episode length), validation seed 777 (used by no evaluation): prints each point's final
displacement and success rate and the best point by their sum (the two metrics a learned policy has to beat), whose
values are the rule's defaults (ShadowPusherParams).

    python -m tools.tune_transport [--robots 16] [--episodes 40]
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools

from sim.config import preset
from sim.env import SwarmEnv
from sim.rollout import rollout
from sim.tasks.transport import ShadowPusher, ShadowPusherParams, Transport

VALIDATION_SEED = 777
#: the fifth grid, for task version 2 (the object 30..80 mm short of a goal zone 200 mm deep), on 40 episodes: best dark
#: 650, touch_mm 79, back_steps 4, run_steps 20 (final displacement 0.633, in goal 0.475), the defaults; the top six
#: re-run on 100 episodes: this one 0.666 ± 0.067 and 0.49 in goal, dark 550 0.700 ± 0.053 but 0.33 in goal.
#: The grids before were for version 1 (the object 175..225 mm short of a zone 100 mm deep), where no setting reached
#: the goal zone in 500 periods: the third (60 mm object) best at touch_mm 79, dark 550, back_steps 3, run_steps 20
#: (0.228); a fourth over fall / rise 5 / 10 / 20 and dark 500 / 550 found nothing clearly better; the first two were
#: for a 50 mm object (best 0.165).
GRID = {"dark": (500, 550, 600, 650), "touch_mm": (79.0, 81.0), "back_steps": (3, 4), "run_steps": (10, 20)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--episodes", type=int, default=40)
    a = ap.parse_args()
    task = Transport()
    world = task.world(preset("kilobot"))
    env = SwarmEnv(world, min(a.episodes, 20), a.robots, seed=0, task=task)
    rows = []
    for values in itertools.product(*GRID.values()):
        p = dataclasses.replace(ShadowPusherParams(), **dict(zip(GRID, values)))
        s = rollout(env, ShadowPusher(world, p), a.episodes, seed=VALIDATION_SEED).metrics().summary()
        rows.append((s[task.primary_metric].mean + s["success_rate"].mean, values))
        print(f"{dict(zip(GRID, values))}  final displacement {s[task.primary_metric]}  in goal {s['success_rate']}",
              flush=True)
    best = max(rows)
    print(f"best: {dict(zip(GRID, best[1]))}  final displacement + in goal {best[0]:.3f}", flush=True)


if __name__ == "__main__":
    main()
