"""How much of the packing ceiling can driving at the beacon reach? An omniscient controller as a bound.

    python tests/bench/oracle_push.py --robots 32 --episodes 100 --steps 500 --seed 20261202

The *oracle* knows every robot's true position, heading and the beacon's (no Kilobot does): a robot out
of range pivots towards the beacon until it faces it within ``--aim-deg``, then drives straight at it.
Inside the range it stops (``--inside stop``) or keeps pushing at the beacon too (``--inside push``),
and ``--agitate p`` replaces a fraction p of all commands by random ones (shaking a jam loose). On the
same episodes as the shipped default and the hand-written searcher it prints final coverage and its
fraction of each episode's packing ceiling: where the oracle jams, the contact model (frictionless
discs pushed apart, a taped-down beacon) jams, and no policy that only gets there by pushing does better.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from kiloforge.policies import load_policy, swarm_policy  # noqa: E402
from sim.baselines import make_policy  # noqa: E402
from sim.config import WorldConfig  # noqa: E402
from sim.env import SwarmEnv  # noqa: E402
from sim.kinematics import wrap_angle  # noqa: E402
from sim.metrics import compare  # noqa: E402
from sim.rollout import rollout  # noqa: E402

#: the kilobot world's pivot commands: (1, 0) turns counter-clockwise (heading grows), (0, 1) clockwise
TURN_CCW, TURN_CW = (1.0, 0.0), (0.0, 1.0)


class OraclePush:
    """Drive every robot at the beacon from the env's true state (a bound, not a Kilobot policy)."""

    def __init__(self, env: SwarmEnv, aim_deg: float, inside: str, agitate: float, queue: bool = False) -> None:
        self.env, self.aim, self.inside, self.agitate = env, np.deg2rad(aim_deg), inside, agitate
        self.queue = queue
        self.rng = np.random.default_rng(0)

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.rng = rng

    def act(self, obs: np.ndarray) -> np.ndarray:
        env = self.env
        d = env.target[:, None, :] - env.pos
        off = wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - env.heading)
        a = np.ones(obs.shape[:2] + (2,))
        a[(off > self.aim)] = TURN_CCW
        a[(off < -self.aim)] = TURN_CW
        inside = np.linalg.norm(d, axis=-1) <= env.cfg.comm_radius_mm  # (B, M)
        if self.inside == "stop":
            a[inside] = 0.0
        if self.queue:  # out of range, touching a robot in range in front (within 60°): wait, don't push the cluster
            rel = env.pos[:, None, :, :] - env.pos[:, :, None, :]  # (B, i, j, 2) from robot i to robot j
            dist = np.linalg.norm(rel, axis=-1)
            ahead = np.abs(wrap_angle(np.arctan2(rel[..., 1], rel[..., 0]) - env.heading[:, :, None])) < np.pi / 3
            touching = (dist < 2 * env.cfg.robot_radius_mm + 3.0) & ahead & (dist > 0) & inside[:, None, :]
            a[touching.any(axis=2) & ~inside] = 0.0
        if self.agitate > 0:
            shake = self.rng.random(obs.shape[:2]) < self.agitate
            a[shake] = self.rng.integers(0, 2, (int(shake.sum()), 2))
        return a


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", default=str(ROOT / "export" / "data" / "default_policy.npz"))
    ap.add_argument("--robots", nargs="+", type=int, default=[32])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--seed", type=int, default=20261202, help="episode seed no training used")
    ap.add_argument("--aim-deg", type=float, default=23.0, help="drive straight once facing the beacon within this")
    ap.add_argument("--inside", nargs="+", choices=("stop", "push"), default=["stop", "push"])
    ap.add_argument("--agitate", nargs="+", type=float, default=[0.0, 0.3])
    args = ap.parse_args()
    pol = load_policy(args.policy)
    world = WorldConfig.from_dict({**pol.world.to_dict(), "episode_steps": args.steps})
    for M in args.robots:
        env = SwarmEnv(world, n_envs=min(50, args.episodes), n_robots=M, seed=args.seed)
        contenders = {"shipped default": swarm_policy(pol, world), "hand-written": make_policy("baseline", world)}
        for inside in args.inside:
            for p in args.agitate:
                contenders[f"oracle, inside {inside}, agitate {p:g}"] = OraclePush(env, args.aim_deg, inside, p)
        table = {name: rollout(env, c, args.episodes, seed=args.seed).metrics(ceiling=True)
                 for name, c in contenders.items()}
        print(f"\n{M} robots, {args.steps} steps, {args.episodes} episodes from seed {args.seed} (mean ± 95 % CI)")
        print(compare(table), flush=True)


if __name__ == "__main__":
    main()
