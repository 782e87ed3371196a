"""Tune the hand-written aggregation rule (sim.tasks.aggregation.AggregatorParams) on validation episodes.

A grid over its probabilities and run length, at 16 robots in the kilobot world, 500-step episodes
(the evaluation benchmark's), validation seed 777 (used by no evaluation): prints each point's final
cluster fraction and the best one, whose values are AggregatorParams' defaults.

    python -m tools.tune_aggregator [--robots 16] [--episodes 20]
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools

from sim.config import BENCHMARK_STEPS, VALIDATION_SEED, preset
from sim.env import SwarmEnv
from sim.rollout import rollout
from sim.tasks.aggregation import AggregatorParams, Aggregation, ProbabilisticAggregator

#: the fourth and last grid, around the third's best; its best (stop 0.2, leave 0.7, decay 1.0, run 60: 0.923)
#: are AggregatorParams' defaults. First grid (stop 0.05..0.6, leave 0.002..0.03, decay 0.5..8,
#: run 8 / 25): stop 0.05, leave 0.03, decay 0.5, run 25, 0.605. Second (stop 0.01..0.1, leave 0.03..0.1,
#: decay 0.1..1, run 25 / 60): stop 0.1, leave 0.1, decay 0.5, run 60, 0.815. Third (stop 0.1 / 0.2, leave
#: 0.1..0.4, decay 0.25..1, run 60 / 120): stop 0.2, leave 0.4, decay 0.5, run 60, 0.893.
GRID = {"stop_per_nbr": (0.2, 0.4, 0.8), "leave_base": (0.4, 0.7, 1.0),
        "leave_decay": (0.25, 0.5, 1.0), "run_steps": (60,)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--episodes", type=int, default=20)
    a = ap.parse_args()
    world = Aggregation().world(dataclasses.replace(preset("kilobot"), episode_steps=BENCHMARK_STEPS))
    env = SwarmEnv(world, min(a.episodes, 20), a.robots, seed=0, task=Aggregation())
    rows = []
    for values in itertools.product(*GRID.values()):
        p = dataclasses.replace(AggregatorParams(), **dict(zip(GRID, values)))
        m = rollout(env, ProbabilisticAggregator(world, p), a.episodes, seed=VALIDATION_SEED).metrics()
        s = m.summary()["final_cluster"]
        rows.append((s.mean, values))
        print(f"{dict(zip(GRID, values))}  final cluster {s}", flush=True)
    best = max(rows)
    print(f"best: {dict(zip(GRID, best[1]))}  final cluster {best[0]:.3f}")


if __name__ == "__main__":
    main()
