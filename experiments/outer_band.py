"""Where a bearing pays at 32 robots: the outer band of the range, and what distances alone get there.

    python -m experiments.outer_band --robots 32 --episodes 100 --steps 500 --seed 20261202
    python -m experiments.outer_band --episodes 100 --entry-error 0 20 --reach 100 120 170 250 --held-aim 120,0 250,0

Every contender here is the hand-written searcher (``sim.baselines``, tuned) outside the beacon's range, and
differs only inside it, where a robot stops once it hears the beacon within ``--stop-mm`` (the *band*) and,
beyond that (the *outer band*, up to the 85 mm range):

* ``bearing``: drives at the beacon with its true bearing (pivots until it faces it within 23°), an omniscient
  bound; ``--bearing-error F`` adds a fixed error per robot and episode (normal, F degrees sd);
* ``entry``: aims once, on entering the outer band, at the beacon's true bearing (plus a normal error of
  ``--entry-error`` degrees sd, drawn afresh at every entry), holds that heading in the world (a robot's heading
  changes only by its own pivots) and turns it by one pivot, left or right at random, as ``hysteresis`` does;
* ``hysteresis``: drives straight on and pivots once (left or right at random) only when the heard distance has
  grown by more than ``--margin-mm`` above its least since entering the outer band or since its last pivot
  (distances alone; a missed message keeps the latest distance for up to two periods);
* the pusher (``sim.baselines.PUSHER``, the same idea inside the searcher's own rules, as firmware) and the
  shipped default, for comparison.

Two bounds for what the messages could add (a sender's beacon distance, relayed as a gradient, extends "how far
is the beacon" beyond the range, but a Kilobot's one omnidirectional receiver gives no direction):

* ``--reach R``: ``hysteresis`` with a distance that also reaches ``R`` mm, beyond the range the true distance plus
  the world's distance noise (better than any relayed gradient, which adds the hops' noise and overestimates);
  near a wall the searcher's wall turns take over there;
* ``--held-aim R,E``: ``entry``, but the bearing is taken once where that distance begins (out of range, within
  ``R`` mm, error ``E`` degrees sd), while the robot still moves freely and could dead-reckon one, and held from
  there: the robot aims with it out of range and in the outer band; it is forgotten beyond ``R`` mm.

``--compass`` also reports how well a robot could estimate its bearing from its own last ``T_prev`` = 20
periods (commands dead-reckoned into positions, heard distances, the bearing on a 10° grid that fits them
best), against its true bearing, for dead reckoning from the commands and from the true positions (what
collisions cost).
"""
from __future__ import annotations

import argparse

import numpy as np

from experiments.oracle_push import TURN_CCW, TURN_CW, episode_args
from kiloforge.policies import load_policy, swarm_policy
from sim.baselines import TUNED, HandWrittenSearcher, make_policy
from sim.config import OBS_TARGET, OBS_WALL, WorldConfig
from sim.env import SwarmEnv
from sim.kinematics import wrap_angle
from sim.metrics import compare
from sim.tasks import get_task
from sim.rollout import rollout

MEMORY = 3  #: periods a heard distance stays "the latest" (the current one and two missed)
GRID = np.deg2rad(np.arange(0.0, 360.0, 10.0))


def free_moves(world: WorldConfig) -> np.ndarray:
    """(4, 3) body-frame (dx, dy, dphi) of one period of stop, straight, left pivot, right pivot, from the sim."""
    out = []
    for cmd in ((0.0, 0.0), (1.0, 1.0), TURN_CCW, TURN_CW):
        env = SwarmEnv(world, n_envs=1, n_robots=1, seed=0)
        env.reset(seed=0)
        far = -120.0 * np.sign(env.target[:, None, :] + 1e-9)  # on the far side of the arena's centre
        env.pos[:], env.heading[:] = far, 0.0  # clear of the beacon and of the walls
        p0 = env.pos.copy()
        env.step(np.array([[cmd]]))
        out.append((*(env.pos - p0)[0, 0], float(env.heading[0, 0])))
    moves = np.array(out)
    assert abs(np.hypot(*moves[2, :2]) - np.hypot(*moves[3, :2])) < 1e-9 and moves[0, :2].tolist() == [0.0, 0.0], moves
    return moves


def command_code(a: np.ndarray) -> np.ndarray:
    """0 stop, 1 straight, 2 left pivot, 3 right pivot, from (B, M, 2) commands in {0, 1}."""
    left, right = a[..., 0] > 0.5, a[..., 1] > 0.5
    return np.where(left & right, 1, np.where(left, 2, np.where(right, 3, 0)))


class OuterBand:
    """The searcher outside the band; stop in the band; ``mode`` in the outer band (module doc).

    ``mode`` is 'bearing', 'entry', 'hysteresis' or 'held'; ``reach_mm`` > 0 extends the distance beyond the range.
    """

    def __init__(self, env: SwarmEnv, world: WorldConfig, mode: str, stop_mm: float, margin_mm: float = 3.0,
                 bearing_error_deg: float = 0.0, compass: bool = False, aim_deg: float = 23.0,
                 reach_mm: float = 0.0) -> None:
        assert mode in ("bearing", "entry", "hysteresis", "held"), mode
        assert reach_mm == 0.0 or reach_mm > world.comm_radius_mm, f"reach {reach_mm} mm is within the range"
        self.env, self.world, self.mode, self.stop_mm, self.margin = env, world, mode, stop_mm, margin_mm
        self.reach = reach_mm
        self.error, self.aim, self.compass = np.deg2rad(bearing_error_deg), np.deg2rad(aim_deg), compass
        self.moves = free_moves(world) if compass else None
        self.errors: dict[str, list[np.ndarray]] = {"commands": [], "true positions": []}

    def reset(self, n_envs: int, n_robots: int, rng: np.random.Generator) -> None:
        shape = (n_envs, n_robots)
        self.rng = rng
        self.searcher = HandWrittenSearcher(self.world, TUNED[self.world.name])
        self.searcher.reset(n_envs, n_robots, rng)
        self.bias = rng.normal(0.0, self.error, shape) if self.error and self.mode == "bearing" else np.zeros(shape)
        self.recent = np.full(shape + (MEMORY,), -1.0)  # heard distances (mm) of the last periods, newest first
        self.least = np.full(shape, np.inf)  # hysteresis: least distance since entering / the last pivot
        self.was_outer = np.zeros(shape, bool)
        self.aim_world = np.zeros(shape)  # entry, held: the heading to hold, in the world frame
        self.has_aim = np.zeros(shape, bool)  # entry, held: a bearing was taken and is held
        self.prev = np.zeros(shape, np.int64)
        T = 20
        self.odo = np.zeros(shape + (T, 2))  # compass: past positions in the current body frame (from commands)
        self.true_pos = np.zeros(shape + (T, 2))  # the same from the true positions (world frame)
        self.dist = np.full(shape + (T,), -1.0)

    def true_bearing(self) -> np.ndarray:
        d = self.env.target[:, None, :] - self.env.pos
        return wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - self.env.heading)

    def act(self, obs: np.ndarray) -> np.ndarray:
        R = self.world.comm_radius_mm
        t = obs[..., OBS_TARGET]
        heard = t >= 0
        self.recent = np.concatenate([np.where(heard, t * R, -1.0)[..., None], self.recent[..., :-1]], -1)
        have = (self.recent >= 0).any(-1)
        latest = np.take_along_axis(self.recent, np.argmax(self.recent >= 0, -1)[..., None], -1)[..., 0]
        dist = np.where(have, latest, np.inf)
        a = self.searcher.act(obs)
        band = dist <= self.stop_mm
        beyond = np.zeros(band.shape, bool)  # out of range, within the reach
        if self.reach:
            true = np.linalg.norm(self.env.target[:, None, :] - self.env.pos, axis=-1)
            beyond = ~have & (true > R) & (true <= self.reach)
            noisy = np.round(true + self.world.dist_noise_mm * self.rng.standard_normal(true.shape))
            dist = np.where(beyond, noisy, dist)
        # beyond the range the searcher's wall turns still apply (its wall_cool runs from a wall hit to the turn's end)
        wall_turn = beyond & ((obs[..., OBS_WALL] > 0.5) | (self.searcher.wall_cool > 0))
        outer = have & ~band | beyond & ~wall_turn
        fresh = heard | beyond  # a distance this period
        if self.compass:
            self._compass(np.where(heard, t * R, -1.0), outer)
        steer = np.ones(a.shape)
        if self.mode == "bearing":
            off = wrap_angle(self.true_bearing() + self.bias)
            steer[off > self.aim], steer[off < -self.aim] = TURN_CCW, TURN_CW
        else:
            entering = outer & ~self.was_outer
            self.least = np.where(entering, dist, np.where(fresh, np.minimum(self.least, dist), self.least))
            grew = outer & fresh & (dist > self.least + self.margin)
            left = self.rng.random(grew.shape) < 0.5
            self.least = np.where(grew, np.inf, self.least)  # the next distance after the pivot
            steer[grew & left], steer[grew & ~left] = TURN_CCW, TURN_CW
            if self.mode in ("entry", "held"):
                take = entering if self.mode == "entry" else beyond & ~self.has_aim
                self.has_aim |= take
                if self.reach:  # held: forgotten beyond the reach
                    self.has_aim &= np.linalg.norm(self.env.target[:, None, :] - self.env.pos, axis=-1) <= self.reach
                error = self.rng.normal(0.0, self.error, take.shape) if self.error else 0.0
                self.aim_world = np.where(take, self.true_bearing() + self.env.heading + error, self.aim_world)
                self.aim_world += np.where(grew, np.where(left, 1.0, -1.0) * np.deg2rad(45.7), 0.0)
                off = wrap_angle(self.aim_world - self.env.heading)
                aim = np.where((off > self.aim)[..., None], TURN_CCW,
                               np.where((off < -self.aim)[..., None], TURN_CW, 1.0))
                steer = np.where(self.has_aim[..., None], aim, steer)
        a = np.where(outer[..., None], steer, a)
        a[band] = 0.0
        self.was_outer = outer
        self.prev = command_code(a)
        return a

    def _compass(self, heard_mm: np.ndarray, outer: np.ndarray) -> None:
        """Dead-reckon the last period's command, record this period, and score the grid fit in the outer band."""
        dx, dy, dphi = (self.moves[self.prev, k] for k in range(3))
        q = self.odo - np.stack([dx, dy], -1)[..., None, :]
        c, s = np.cos(-dphi)[..., None], np.sin(-dphi)[..., None]
        self.odo = np.stack([c * q[..., 0] - s * q[..., 1], s * q[..., 0] + c * q[..., 1]], -1)
        self.odo = np.concatenate([np.zeros_like(self.odo[..., :1, :]), self.odo[..., :-1, :]], -2)
        self.true_pos = np.concatenate([self.env.pos[..., None, :], self.true_pos[..., :-1, :]], -2)
        self.dist = np.concatenate([heard_mm[..., None], self.dist[..., :-1]], -1)
        q = self.true_pos - self.env.pos[..., None, :]
        c, s = np.cos(-self.env.heading)[..., None], np.sin(-self.env.heading)[..., None]
        from_true = np.stack([c * q[..., 0] - s * q[..., 1], s * q[..., 0] + c * q[..., 1]], -1)
        use = outer & (heard_mm >= 0) & ((self.dist >= 0).sum(-1) >= 4)
        if not use.any():
            return
        truth = self.true_bearing()[use]
        d_now, ok = heard_mm[use], self.dist[use] >= 0
        for name, pos in (("commands", self.odo[use]), ("true positions", from_true[use])):
            b = d_now[:, None, None] * np.stack([np.cos(GRID), np.sin(GRID)], -1)[None]  # (N, A, 2)
            r = np.linalg.norm(b[:, :, None, :] - pos[:, None, :, :], axis=-1) - self.dist[use][:, None, :]
            cost = np.where(ok[:, None, :], r ** 2, 0.0).sum(-1)
            self.errors[name].append(np.abs(wrap_angle(GRID[cost.argmin(-1)] - truth)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    episode_args(ap)
    ap.add_argument("--stop-mm", type=float, default=80.0, help="stop within this distance (the band)")
    ap.add_argument("--margin-mm", nargs="+", type=float, default=[3.0], help="hysteresis margins, a row each")
    ap.add_argument("--bearing-error", nargs="+", type=float, default=[0.0],
                    help="fixed bearing errors (sd, degrees) per robot for the bearing bound, a row each")
    ap.add_argument("--entry-error", nargs="+", type=float, default=[],
                    help="aim once on entering the outer band, with this error (sd, degrees; fresh per entry), a row each")
    ap.add_argument("--reach", nargs="+", type=float, default=[],
                    help="the hysteresis rule on a distance that reaches this far (mm; beyond the range: the true "
                         "distance + noise, a bound for a gradient relayed in messages), a row each")
    ap.add_argument("--held-aim", nargs="+", default=[], metavar="R,E",
                    help="a bearing taken once out of range within R mm (error E degrees sd) and held, a row each")
    ap.add_argument("--compass", action="store_true", help="also score a 20-period dead-reckoned compass")
    args = ap.parse_args()
    pol = load_policy(args.policy)
    world = WorldConfig.from_dict({**pol.world.to_dict(), "episode_steps": args.steps})
    for M in args.robots:
        env = SwarmEnv(world, n_envs=min(50, args.episodes), n_robots=M, seed=args.seed)
        contenders = {"shipped default": swarm_policy(pol, world), "searcher": make_policy("baseline", world),
                      "pusher": make_policy("pusher", world)}
        for err in args.bearing_error:
            contenders["true bearing in the outer band" + (f", {err:g} deg error" if err else "")] = OuterBand(
                env, world, "bearing", args.stop_mm, bearing_error_deg=err)
        for err in args.entry_error:
            contenders[f"outer band: aim once on entry ({err:g} deg error), then as below"] = OuterBand(
                env, world, "entry", args.stop_mm, bearing_error_deg=err)
        margin = args.margin_mm[0]
        for reach in args.reach:
            contenders[f"outer band and out of range within {reach:g} mm: straight, a pivot once {margin:g} mm "
                       "further"] = OuterBand(env, world, "hysteresis", args.stop_mm, margin_mm=margin, reach_mm=reach)
        for spec in args.held_aim:
            reach, err = (float(v) for v in spec.split(","))
            contenders[f"a bearing taken within {reach:g} mm ({err:g} deg error) and held"] = OuterBand(
                env, world, "held", args.stop_mm, margin_mm=margin, bearing_error_deg=err, reach_mm=reach)
        for m in args.margin_mm:
            contenders[f"outer band: straight, a pivot once {m:g} mm further"] = OuterBand(
                env, world, "hysteresis", args.stop_mm, margin_mm=m, compass=args.compass)
        table = {name: rollout(env, c, args.episodes, seed=args.seed).metrics(ceiling=True)
                 for name, c in contenders.items()}
        print(f"\n{M} robots, {args.steps} steps, {args.episodes} episodes from seed {args.seed}, band within "
              f"{args.stop_mm:g} mm (mean ± 95 % CI)")
        print(compare(table, get_task("localisation").columns), flush=True)
        for c in contenders.values():
            if isinstance(c, OuterBand) and c.compass:
                for name, errs in c.errors.items():
                    e = np.rad2deg(np.concatenate(errs)) if errs else np.zeros(0)
                    if e.size:
                        print(f"compass in the outer band, dead reckoning from {name}: {e.size} fits, median error "
                              f"{np.median(e):.0f} deg, within 45 deg {np.mean(e < 45):.2f}, within 90 deg "
                              f"{np.mean(e < 90):.2f}")


if __name__ == "__main__":
    main()
