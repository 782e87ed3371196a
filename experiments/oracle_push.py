"""How much of the packing ceiling can driving at the beacon reach? An omniscient controller as a bound.

    python -m experiments.oracle_push --robots 32 --episodes 100 --steps 500 --seed 20261202

The *oracle* knows every robot's true position, heading and the beacon's (no Kilobot does): a robot out
of range pivots towards the beacon until it faces it within ``--aim-deg``, then drives straight at it.
Inside the range it stops (``--inside stop``) or keeps pushing at the beacon too (``--inside push``),
``--agitate p`` replaces a fraction p of all commands by random ones (shaking a jam loose), and ``--slide n``
makes a robot out of range that touches a body in front of it (within 60°) drive along the cluster instead, at
90° to the beacon's bearing on a side drawn per blocking, for n periods before it aims again; ``--swirl w`` makes
every robot aim w degrees to the left of the beacon (all the same way, a vortex about it). ``--ring H,S``
keeps a hole and a band: a robot closer than H mm to the beacon turns away from it and drives out, and with
``--inside stop`` a robot in range stops only within S mm (between S and the range it keeps driving in);
``--bearing-error N,F`` aims with an error on the bearing: a fresh normal error of standard deviation N degrees every
step plus a fixed one (standard deviation F degrees) per robot and episode. On the
same episodes as the shipped default and the hand-written searcher it prints final coverage and its
fraction of each episode's packing ceiling: where the oracle jams, the contact model (frictionless
discs pushed apart, a taped-down beacon) jams, and no policy that only gets there by pushing does better.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

from kiloforge.policies import load_policy, swarm_policy
from sim.baselines import make_policy
from sim.config import HELD_OUT_SEED, WorldConfig
from sim.env import SwarmEnv
from sim.kinematics import wrap_angle
from sim.metrics import compare
from sim.tasks import get_task
from sim.rollout import rollout

#: the kilobot world's pivot commands: (1, 0) turns counter-clockwise (heading grows), (0, 1) clockwise
TURN_CCW, TURN_CW = (1.0, 0.0), (0.0, 1.0)


def touching_ahead(env: SwarmEnv, gap_mm: float) -> np.ndarray:
    """(B, i, j): robot j's body is within ``gap_mm`` of robot i's, in front of i (within 60°), from the true state."""
    rel = env.pos[:, None, :, :] - env.pos[:, :, None, :]  # (B, i, j, 2) from robot i to robot j
    dist = np.linalg.norm(rel, axis=-1)
    ahead = np.abs(wrap_angle(np.arctan2(rel[..., 1], rel[..., 0]) - env.heading[:, :, None])) < np.pi / 3
    return (dist < 2 * env.cfg.robot_radius_mm + gap_mm) & ahead & (dist > 0)


def episode_args(ap: argparse.ArgumentParser) -> None:
    """The flags every oracle script shares: the policy to compare with, swarm sizes and the held-out episodes."""
    ap.add_argument("--policy", default=str(ROOT / "export" / "data" / "default_policy.npz"))
    ap.add_argument("--robots", nargs="+", type=int, default=[32])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="episode seed no training used")


class OraclePush:
    """Drive every robot at the beacon from the env's true state (a bound, not a Kilobot policy)."""

    def __init__(self, env: SwarmEnv, aim_deg: float, inside: str, agitate: float, queue: bool = False,
                 slide: int = 0, swirl_deg: float = 0.0, ring: tuple[float, float] | None = None,
                 bearing_error: tuple[float, float] = (0.0, 0.0)) -> None:
        self.env, self.aim, self.inside, self.agitate = env, np.deg2rad(aim_deg), inside, agitate
        self.queue, self.slide, self.swirl = queue, slide, np.deg2rad(swirl_deg)
        self.hole_mm, self.stop_mm = ring if ring is not None else (0.0, env.cfg.comm_radius_mm)
        self.noise, self.bias_sd = np.deg2rad(bearing_error[0]), np.deg2rad(bearing_error[1])
        self.rng = np.random.default_rng(0)

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.rng = rng
        self.sliding = np.zeros((n_envs, n_robots), np.int64)  # periods of sliding left
        self.side = np.ones((n_envs, n_robots))  # +1: slide counter-clockwise about the beacon, -1 clockwise
        self.bias = rng.normal(0.0, self.bias_sd, (n_envs, n_robots)) if self.bias_sd else 0.0

    def act(self, obs: np.ndarray) -> np.ndarray:
        env = self.env
        d = env.target[:, None, :] - env.pos
        r = np.linalg.norm(d, axis=-1)
        inside = r <= env.cfg.comm_radius_mm  # (B, M)
        goal = np.arctan2(d[..., 1], d[..., 0]) + self.swirl + self.bias
        if self.noise:
            goal = goal + self.rng.normal(0.0, self.noise, goal.shape)
        hole = r < self.hole_mm
        goal = np.where(hole, goal + np.pi, goal)  # in the hole: drive out
        if self.slide:  # blocked out of range: drive along the cluster, tangent to the beacon's bearing
            start = touching_ahead(env, 2.0).any(axis=2) & ~inside & (self.sliding <= 0)
            self.side = np.where(start, np.where(self.rng.random(start.shape) < 0.5, 1.0, -1.0), self.side)
            self.sliding = np.where(start, self.slide, self.sliding - 1)
            goal = np.where(self.sliding > 0, goal + self.side * (np.pi / 2), goal)
        off = wrap_angle(goal - env.heading)
        a = np.ones(obs.shape[:2] + (2,))
        a[(off > self.aim)] = TURN_CCW
        a[(off < -self.aim)] = TURN_CW
        if self.inside == "stop":
            a[inside & ~hole & (r <= self.stop_mm)] = 0.0
        if self.queue:  # out of range, touching a robot in range in front (within 60°): wait, don't push the cluster
            touching = touching_ahead(env, 3.0) & inside[:, None, :]
            a[touching.any(axis=2) & ~inside] = 0.0
        if self.agitate > 0:
            shake = self.rng.random(obs.shape[:2]) < self.agitate
            a[shake] = self.rng.integers(0, 2, (int(shake.sum()), 2))
        return a


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    episode_args(ap)
    ap.add_argument("--aim-deg", type=float, default=23.0, help="drive straight once facing the beacon within this")
    ap.add_argument("--inside", nargs="+", choices=("stop", "push"), default=["stop", "push"])
    ap.add_argument("--agitate", nargs="+", type=float, default=[0.0, 0.3])
    ap.add_argument("--slide", nargs="+", type=int, default=[0],
                    help="periods a blocked robot out of range drives along the cluster (0: it pushes on); "
                         "each value adds a row per --inside and --agitate")
    ap.add_argument("--swirl", nargs="+", type=float, default=[0.0],
                    help="degrees every robot aims to the left of the beacon (all the same way: a vortex); "
                         "each value adds a row")
    ap.add_argument("--ring", nargs="+", default=[None], type=lambda s: tuple(float(v) for v in s.split(",")),
                    help="H,S: robots nearer than H mm drive out, robots in range stop only within S mm; "
                         "each value adds a row")
    ap.add_argument("--bearing-error", nargs="+", default=[(0.0, 0.0)],
                    type=lambda s: tuple(float(v) for v in s.split(",")),
                    help="N,F: aim with a fresh N-degree (sd) error every step and a fixed F-degree (sd) one per robot; "
                         "each value adds a row")
    args = ap.parse_args()
    pol = load_policy(args.policy)
    world = WorldConfig.from_dict({**pol.world.to_dict(), "episode_steps": args.steps})
    for M in args.robots:
        env = SwarmEnv(world, n_envs=min(50, args.episodes), n_robots=M, seed=args.seed)
        contenders = {"shipped default": swarm_policy(pol, world), "hand-written": make_policy("baseline", world)}
        for inside in args.inside:
            for p in args.agitate:
                for n in args.slide:
                    for w in args.swirl:
                        for ring in args.ring:
                            for err in args.bearing_error:
                                name = (f"oracle, inside {inside}, agitate {p:g}" + (f", slide {n}" if n else "")
                                        + (f", swirl {w:g}" if w else "")
                                        + (f", hole {ring[0]:g} mm, stop within {ring[1]:g} mm" if ring else "")
                                        + (f", bearing error {err[0]:g} deg/step + {err[1]:g} deg/robot" if any(err)
                                           else ""))
                                contenders[name] = OraclePush(env, args.aim_deg, inside, p, slide=n, swirl_deg=w,
                                                              ring=ring, bearing_error=err)
        table = {name: rollout(env, c, args.episodes, seed=args.seed).metrics(ceiling=True)
                 for name, c in contenders.items()}
        print(f"\n{M} robots, {args.steps} steps, {args.episodes} episodes from seed {args.seed} (mean ± 95 % CI)")
        print(compare(table, get_task("localisation").columns), flush=True)


if __name__ == "__main__":
    main()
