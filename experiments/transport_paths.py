"""Where does the object go? Its paths under the learned transport policy and the hand-written shadow pusher.

    python -m experiments.transport_paths --policy default shadow_pusher --robots 16 --episodes 20 \
        --out docs/img/transport_paths.png

Plays each policy (a shipped transport policy's name or a policy file) on the same held-out episodes
(``sim.config.HELD_OUT_SEED``, 500 steps) and draws, one panel per policy, every episode's object path from its start
(dot) to its end (cross) in the arena, with the goal zone shaded; the panel's title has the mean final displacement
and the share of episodes that end in the goal zone. Written up in docs/results/transport.md.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from kiloforge.plotting import figure, save_png
from kiloforge.policies import swarm_policy
from kiloforge.shipped import load_task_policy
from sim.config import BENCHMARK_STEPS, HELD_OUT_SEED
from sim.env import SwarmEnv
from sim.rollout import rollout
from sim.tasks import get_task

TASK = get_task("transport")


def paths(spec: str, robots: int, episodes: int, seed: int):
    """(object tracks (E, T+1, 2), final displacement (E,), in goal (E,), world) of ``spec`` on the episodes."""
    art = load_task_policy(spec, TASK)
    world = dataclasses.replace(art.world, episode_steps=BENCHMARK_STEPS)
    env = SwarmEnv(world, min(episodes, 50), robots, seed=0, task=TASK)
    res = rollout(env, swarm_policy(art, world), episodes, seed=seed, record=episodes)
    per = res.metrics()
    return (res.trajectories.target, per.per_episode(TASK.primary_metric), per.per_episode("success_rate"), world)


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m experiments.transport_paths", description=__doc__.split("\n")[0])
    ap.add_argument("--policy", nargs="+", default=["default", "shadow_pusher"])
    ap.add_argument("--robots", type=int, default=16)
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    ap.add_argument("--out", type=Path, default=Path("transport_paths.png"))
    a = ap.parse_args()
    fig = figure(4.2 * len(a.policy), 4.4)
    for i, spec in enumerate(a.policy):
        track, disp, goal, world = paths(spec, a.robots, a.episodes, a.seed)
        h = world.arena_half_mm
        ax = fig.add_subplot(1, len(a.policy), i + 1)
        g = TASK.goal_along(world)
        ax.axvspan(g, h, color="gold", alpha=0.3, lw=0, label="goal zone (lamp at the right wall)")
        for e in range(track.shape[0]):
            ax.plot(track[e, :, 0], track[e, :, 1], lw=1.0, alpha=0.8)
            ax.plot(*track[e, 0], "k.", ms=4)
            ax.plot(*track[e, -1], "kx", ms=5)
        ax.set_xlim(-h, h)
        ax.set_ylim(-h, h)
        ax.set_aspect("equal")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_title(f"{Path(spec).stem}: displacement {np.mean(disp):.2f}, in goal {np.mean(goal):.0%}", fontsize=9)
        if i == 0:
            ax.legend(loc="lower left", fontsize=7)
    fig.suptitle(f"object paths, {a.robots} robots, {a.episodes} held-out episodes x {BENCHMARK_STEPS} steps",
                 fontsize=10)
    fig.tight_layout()
    print(f"wrote {save_png(fig, a.out)}")


if __name__ == "__main__":
    main()
