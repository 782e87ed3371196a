"""Where does a pushed beacon go? Final coverage, beacon drift and the packing ceiling, taped vs pushed.

    python -m experiments.beacon_drift export/data/default_policy.npz baseline oracle oracle-queue \\
        --robots 32 --episodes 30 --steps 300 --seed 20261202

For each controller, the same episodes with the beacon taped down (mobility 0) and pushed like a robot
(mobility 1): final coverage, the packing ceiling at the beacon's *final* position (sim.tasks.ceiling: fewer
robots fit in range of a beacon at a wall), final coverage as a fraction of it, how far the beacon moved
and the share of episodes whose beacon ends within 5 mm of a wall. Controllers: policy artifacts (.npz),
``baseline`` (the hand-written searcher), ``oracle`` (experiments/oracle_push.py: every robot driven at
the beacon from the true state, stopping in range) and ``oracle-queue`` (the same, but a robot out of
range also waits while a robot in range touches it in front: it queues instead of pushing the cluster).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

from experiments.oracle_push import OraclePush
from kiloforge.policies import load_policy, policy_paths, swarm_policy
from sim.baselines import make_policy
from sim.config import HELD_OUT_SEED, preset
from sim.env import SwarmEnv
from sim.rollout import rollout

SPECIAL = ("baseline", "oracle", "oracle-queue")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("controllers", nargs="+", help=f"policy .npz files or run directories, or one of {', '.join(SPECIAL)}")
    ap.add_argument("--robots", nargs="+", type=int, default=[32])
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="episode seed no training used")
    args = ap.parse_args()
    try:
        files = policy_paths([c for c in args.controllers if c not in SPECIAL])
    except ValueError as e:
        ap.error(str(e))
    policies = {name: load_policy(path) for name, path in files.items()}
    base = next(iter(policies.values())).world if policies else preset("kilobot")
    base = dataclasses.replace(base, episode_steps=args.steps)
    names = [*policies, *(c for c in args.controllers if c in SPECIAL)]
    lim = base.arena_half_mm - base.robot_radius_mm
    print(f"{args.episodes} episodes x {args.steps} steps from seed {args.seed}; ceiling and 'of ceiling' at the "
          "beacon's final position; drift = start to end")
    print("| robots | controller | beacon | final cov | ceiling | of ceiling | drift mm | ends at a wall |")
    print("|---:|---|---|---:|---:|---:|---:|---:|")
    for M in args.robots:
        for name in names:
            for mob in (0.0, 1.0):
                world = dataclasses.replace(base, emitter_mobility=mob)
                env = SwarmEnv(world, min(args.episodes, 50), M, seed=args.seed)
                if name in policies:
                    ctl = swarm_policy(policies[name], world)
                elif name == "baseline":
                    ctl = make_policy("baseline", world)
                else:
                    ctl = OraclePush(env, 23.0, "stop", 0.0, queue=name == "oracle-queue")
                res = rollout(env, ctl, args.episodes, seed=args.seed, record=True)  # record: the start position
                m = res.metrics(ceiling=True)  # ceiling at the final beacon position
                cov, ceil = m.final_coverage, m.ceiling
                wall = (lim - np.abs(res.emitter)).min(axis=1)
                drift = np.linalg.norm(res.emitter - res.trajectories.target[:, 0], axis=1)
                print(f"| {M} | {name} | {'pushed' if mob else 'taped'} | {cov.mean():.3f} | {ceil.mean():.3f} | "
                      f"{np.mean(cov / ceil):.3f} | {drift.mean():.0f} | {np.mean(wall < 5.0):.0%} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
