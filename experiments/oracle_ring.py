"""Can packing in rings beat the jam at 32 robots? Omniscient ring-packing controllers as a test.

    python -m experiments.oracle_ring --robots 32 --episodes 100 --steps 500 --seed 20261202

Around a beacon in the open, two rings hold more robots than the disordered cluster that pushing makes
(19-20 in range) or a hexagonal lattice through the beacon's site (18): 9 robots at about 50 mm and 15
at about 82 mm, 24 in range. The *ring oracle* tries to build them from the env's true state (no
Kilobot knows it): a robot out of range drives at the beacon; in range it drives in until it is within
``margin`` of the inner radius, then orbits the beacon counter-clockwise on the nearer ring (heading
the tangent, turned towards the ring by ``gain`` x the radial error / 10 mm, at most 60°). It backs
out when more than 4 mm inside the inner ring, orbits for 5 periods when blocked on its way in, and
waits while a robot touches it from the front (within 60°, ``--touch-gap`` mm), so that each ring
closes up from behind. Turns use the period's pivot ticks for the exact angle (up to 45°, then
straight). With ``wait`` = 1 a robot out of range also waits instead of pushing when it touches one in
front. Each ``--configs`` entry is ``r_in,r_out,gain,wait,margin``.

``--rim`` keeps the shipped default and overrides only the robots in the sparse outer band of its
cluster (in range, farther than ``r_lo``): they orbit on a rim ring of radius ``r_ring`` and wait while
touched from the front (``r_lo,r_ring,gain``). The table prints final coverage and its fraction of
the packing ceiling next to the shipped default on the same episodes; then, per controller, where its robots
sit at the end (by distance from a beacon in the open) and its fraction of the ceiling by where the beacon is
(corner, wall, open).
"""
from __future__ import annotations

import argparse

import numpy as np

from experiments.oracle_push import episode_args, touching_ahead
from kiloforge.policies import load_policy, swarm_policy
from sim.tasks.ceiling import capacity
from sim.config import WorldConfig
from sim.env import SwarmEnv
from sim.kinematics import wrap_angle
from sim.metrics import compare
from sim.tasks import get_task
from sim.tasks.localisation_metrics import final_coverage
from sim.rollout import rollout

FULL_TURN_RAD = np.deg2rad(45.0)  #: a period of full pivoting turns the kilobot world's robot by about this
BLOCKED_ORBIT = 5  #: a robot blocked on its way in orbits this many periods before it tries again


def steer(delta: np.ndarray) -> np.ndarray:
    """Commands (…, 2) that pivot by ``delta`` rad (+ = counter-clockwise, at most 45°), then drive straight."""
    x = np.clip(np.abs(delta) / FULL_TURN_RAD, 0.0, 1.0)
    a = np.ones(delta.shape + (2,))
    a[..., 0] = np.where(delta > 0, 1.0, 1.0 - x)  # u_left > u_right pivots counter-clockwise
    a[..., 1] = np.where(delta > 0, 1.0 - x, 1.0)
    return a


class RingOracle:
    """Orbit the beacon on two rings and close them up from behind (a test of the idea, not a Kilobot policy)."""

    def __init__(self, env: SwarmEnv, r_in: float, r_out: float, gain: float, wait: bool, margin: float,
                 touch_gap: float = 2.0) -> None:
        self.env, self.r_in, self.r_out, self.gain = env, r_in, r_out, gain
        self.wait, self.margin, self.touch_gap = wait, margin, touch_gap

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.blocked = np.zeros((n_envs, n_robots), np.int64)  # periods left orbiting after a blocked run in

    def act(self, obs: np.ndarray) -> np.ndarray:
        env = self.env
        v = env.target[:, None, :] - env.pos
        d = np.linalg.norm(v, axis=-1)
        bearing = np.arctan2(v[..., 1], v[..., 0])
        inside = d <= env.cfg.comm_radius_mm
        touched = touching_ahead(env, self.touch_gap).any(axis=2)  # (B, M)
        ring = np.where(d < (self.r_in + self.r_out) / 2, self.r_in, self.r_out)
        orbit = bearing - np.pi / 2 + np.clip(self.gain * (d - ring) / 10.0, -np.pi / 3, np.pi / 3)
        going_in = inside & (d > self.r_in + self.margin) & (self.blocked == 0)
        self.blocked = np.where(going_in & touched, BLOCKED_ORBIT, np.maximum(self.blocked - 1, 0))
        goal = np.where(~inside | going_in, bearing, orbit)
        goal = np.where(inside & (d < self.r_in - 4.0), bearing + np.pi, goal)
        a = steer(wrap_angle(goal - env.heading))
        a[inside & ~going_in & touched] = 0.0
        if self.wait:
            a[~inside & touched] = 0.0
        return a


class RimOverride:
    """The shipped default everywhere, except that robots in range farther than ``r_lo`` orbit on the rim
    ring (radius ``r_ring``) and wait while touched from the front: only the sparse outer band packs in a ring."""

    def __init__(self, env: SwarmEnv, base, r_lo: float, r_ring: float, gain: float, touch_gap: float = 2.0) -> None:
        self.env, self.base, self.r_lo, self.r_ring, self.gain, self.touch_gap = env, base, r_lo, r_ring, gain, touch_gap

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        self.base.reset(n_envs, n_robots, rng)

    def act(self, obs: np.ndarray) -> np.ndarray:
        a = self.base.act(obs)
        env = self.env
        v = env.target[:, None, :] - env.pos
        d = np.linalg.norm(v, axis=-1)
        rim = (d <= env.cfg.comm_radius_mm) & (d > self.r_lo)
        orbit = np.arctan2(v[..., 1], v[..., 0]) - np.pi / 2 + np.clip(self.gain * (d - self.r_ring) / 10.0,
                                                                        -np.pi / 3, np.pi / 3)
        ao = steer(wrap_angle(orbit - env.heading))
        ao[touching_ahead(env, self.touch_gap).any(axis=2)] = 0.0
        return np.where(rim[..., None], ao, a)


BANDS_MM = (0.0, 40.0, 66.0, 85.0 + 1e-9)  #: first shell, middle, outer band (in range: centre within 85 mm)
OPEN_MM = 85.0


def band_counts(env: SwarmEnv) -> np.ndarray:
    """Mean robots per episode in each band of :data:`BANDS_MM` at the env's current (final) state, over
    the episodes whose beacon is at least :data:`OPEN_MM` from both walls of the centres' box (NaN: none)."""
    d = np.linalg.norm(env.pos - env.target[:, None, :], axis=-1)  # (B, M)
    lim = env.cfg.arena_half_mm - env.cfg.robot_radius_mm  # the walls of the box the centres live in
    open_ = np.all(np.abs(env.target) <= lim - OPEN_MM, axis=1)
    if not open_.any():
        return np.full(len(BANDS_MM) - 1, np.nan)
    return np.stack([np.histogram(row, bins=BANDS_MM)[0] for row in d[open_]]).mean(axis=0)


#: beacon places by the capacity C of its range (sim.tasks.ceiling): (name, lowest C, highest C + 1)
PLACES = {"corner (C < 12)": (0, 12), "wall (12 <= C < 20)": (12, 20), "open (C >= 20)": (20, 10**6)}


def ceiling_by_place(res, world: WorldConfig, n_robots: int) -> list[tuple[float, int]]:
    """(mean fraction of the ceiling, episodes) per place of :data:`PLACES`, at the final beacon positions."""
    cap = capacity(world, res.emitter)
    frac = final_coverage(res.success) * n_robots / np.minimum(cap, n_robots)
    rows = []
    for lo, hi in PLACES.values():
        sel = (cap >= lo) & (cap < hi)
        rows.append((float(frac[sel].mean()) if sel.any() else float("nan"), int(sel.sum())))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    episode_args(ap)
    ap.add_argument("--touch-gap", type=float, default=2.0, help="mm between bodies that counts as touching")
    ap.add_argument("--configs", nargs="*", default=["48,82,1,0,3", "52,84,4,0,3", "52,84,2,1,15"],
                    help="r_in,r_out,gain,wait,margin per ring oracle (mm, -, 0/1, mm)")
    ap.add_argument("--rim", nargs="*", default=["70,80,2", "72,82,4"],
                    help="r_lo,r_ring,gain per rim override of the shipped default (mm, mm, -)")
    args = ap.parse_args()
    pol = load_policy(args.policy)
    world = WorldConfig.from_dict({**pol.world.to_dict(), "episode_steps": args.steps})
    for M in args.robots:
        env = SwarmEnv(world, n_envs=min(50, args.episodes), n_robots=M, seed=args.seed)
        contenders = {"shipped default": swarm_policy(pol, world)}
        for c in args.configs:
            r_in, r_out, gain, wait, margin = (float(x) for x in c.split(","))
            contenders[f"ring oracle {c}"] = RingOracle(env, r_in, r_out, gain, bool(wait), margin, args.touch_gap)
        for c in args.rim:
            r_lo, r_ring, gain = (float(x) for x in c.split(","))
            contenders[f"default + rim ring {c}"] = RimOverride(env, swarm_policy(pol, world), r_lo, r_ring, gain,
                                                                 args.touch_gap)
        table, bands, by_place = {}, {}, {}
        for name, p in contenders.items():
            res = rollout(env, p, args.episodes, seed=args.seed)
            table[name] = res.metrics(ceiling=True)
            bands[name] = band_counts(env)
            by_place[name] = ceiling_by_place(res, world, M)
        print(f"\n{M} robots, {args.steps} steps, {args.episodes} episodes from seed {args.seed} (mean ± 95 % CI)")
        print(compare(table, get_task("localisation").columns), flush=True)
        print(f"\nrobots per episode by distance from the beacon (mm) at the end, beacon in the open "
              f"(>= {OPEN_MM:g} mm from both walls of the centres' box), last batch of episodes: "
              + "  ".join(f"[{lo:g}, {hi:g})" for lo, hi in zip(BANDS_MM[:-1], BANDS_MM[1:])))
        for name, b in bands.items():
            print(f"{name:<32} " + "  ".join(f"{x:9.1f}" for x in b))
        print("\nfinal coverage as a fraction of the packing ceiling, by where the beacon is (capacity C; episodes): "
              + "  ".join(PLACES))
        for name, rows in by_place.items():
            print(f"{name:<32} " + "  ".join(f"{f:.3f} ({n})" if n else "-" for f, n in rows))


if __name__ == "__main__":
    main()
