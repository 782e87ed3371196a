"""The packing ceiling: how many robots can physically be within communication range of the beacon.

In a collision world (discs of radius r that cannot overlap) at most ``capacity`` robots fit within
the communication radius R of the target beacon (a disc of the same size), so final coverage is at
most ``min(M, capacity) / M``: the episode's *ceiling*. It depends on the beacon's distances to
the nearest walls, ``dx`` and ``dy``: robot centres stay in ``[-L, L]²`` with L = arena_half - r
(:func:`sim.kinematics.clip_walls`), as does the beacon's, and a robot is in range when its centre
is at most R from the beacon's (:meth:`sim.env.SwarmEnv._sense`).

A packing (beacon frame, beacon at the origin, near walls at x = dx and y = dy, far walls at
-(2L - dx), -(2L - dy)) is valid when every pair of centres is >= 2r apart, every centre is >= 2r
from the origin and <= R from it, and inside the walls. :func:`pack` searches one deterministically
(the best hexagonal lattice over rotations and offsets, then repeated insertion of one more disc
and penalty relaxation from deterministic random starts) and returns the configuration, checked
by :func:`is_valid`. The count is a **lower bound** on the true maximum: the ceiling is the best
packing we found, and a policy's fraction of it can exceed 1 only if its robots pack better.

The shipped table (``sim/data/packing_ceiling.npz``, written by ``tools/packing_table.py``)
holds the search's count and configuration at every (dx, dy) on a 5 mm grid from 0 to
min(R, L) (at dx >= R the wall no longer cuts the range disc), together with the world
parameters it was computed for. The lookup uses the **monotone envelope** of the table, the best
count over all grid points nearer both walls (a configuration valid nearer the walls is valid
farther from them, as long as the far walls stay beyond R, i.e. L >= R), at the grid point just
below (dx, dy): so a looked-up capacity is never more than a packing we found for a region
contained in the episode's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from kiloforge.errors import InputError

from ..config import WorldConfig

TABLE_PATH = Path(__file__).parent.parent / "data" / "packing_ceiling.npz"
GRID_STEP_MM = 5.0  #: spacing of the (dx, dy) grid of the shipped table
LATTICE_EPS_MM = 1e-6  #: lattice spacing 2r + this, so lattice neighbours pass the exact check
RELAX_MARGIN_MM = 0.02  #: the relaxation aims at constraints tightened by this much
RELAX_ITERS = 1500  #: penalty-descent steps per attempt at most
RELAX_CHECK = 50  #: steps between checks of the exact constraints
ATTEMPTS = 24  #: relaxation attempts (run as one batch) per extra disc
LATTICE_ROTATIONS = 30  #: rotations over [0, 60°) tried for the lattice
LATTICE_OFFSETS = 12  #: offsets per lattice axis tried


@dataclass(frozen=True)
class Packing:
    """The packing problem of one world: disc diameter ``d``, comm radius ``R``, centre box half ``L``."""

    d: float
    R: float
    L: float

    @classmethod
    def of(cls, world: WorldConfig) -> "Packing":
        r = world.robot_radius_mm
        return cls(d=2.0 * r, R=world.comm_radius_mm, L=world.arena_half_mm - r)

    @property
    def open_mm(self) -> float:
        """Largest wall distance that matters (and the largest one a beacon can have)."""
        return min(self.R, self.L)

    def grid(self, step: float = GRID_STEP_MM) -> np.ndarray:
        g = np.arange(0.0, self.open_mm + 1e-9, step)
        return g if g[-1] >= self.open_mm - 1e-9 else np.append(g, self.open_mm)


def _walls(prob: Packing, dx: float, dy: float) -> tuple[float, float, float, float]:
    """(x_lo, x_hi, y_lo, y_hi) of the centres, beacon frame."""
    return -(2 * prob.L - dx), dx, -(2 * prob.L - dy), dy


def violation(points: np.ndarray, prob: Packing, dx: float, dy: float) -> float:
    """Largest violation (mm) of any constraint by ``points`` (K, 2); <= 0 means valid."""
    p = np.asarray(points, np.float64)
    return -math.inf if p.shape[0] == 0 else float(_batch_violation(p[None], prob, dx, dy)[0])


def is_valid(points: np.ndarray, prob: Packing, dx: float, dy: float) -> bool:
    """True when ``points`` (K, 2) is a valid packing (exact constraints, no tolerance)."""
    return violation(points, prob, dx, dy) <= 0.0


def _lattice(prob: Packing, dx: float, dy: float) -> np.ndarray:
    """The best hexagonal lattice packing over rotations and offsets (first best in a fixed order)."""
    s = prob.d + LATTICE_EPS_MM
    n = int(math.ceil(prob.R / s)) + 2
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    base = np.stack([s * (i + 0.5 * j), s * (math.sqrt(3) / 2) * j], -1).reshape(-1, 2)  # (P, 2)
    th = np.arange(LATTICE_ROTATIONS) * (math.pi / 3) / LATTICE_ROTATIONS
    u = np.arange(LATTICE_OFFSETS) / LATTICE_OFFSETS
    ou, ov = np.meshgrid(u, u, indexing="ij")
    off = np.stack([s * (ou + 0.5 * ov), s * (math.sqrt(3) / 2) * ov], -1).reshape(-1, 2)  # (O, 2)
    c, sn = np.cos(th), np.sin(th)
    rot = np.stack([np.stack([c, -sn], -1), np.stack([sn, c], -1)], -2)  # (Θ, 2, 2)
    pts = np.einsum("tab,opb->topa", rot, base[None] + off[:, None])  # (Θ, O, P, 2)
    x_lo, x_hi, y_lo, y_hi = _walls(prob, dx, dy)
    rho = np.hypot(pts[..., 0], pts[..., 1])
    ok = ((rho <= prob.R) & (rho >= prob.d) & (pts[..., 0] <= x_hi) & (pts[..., 0] >= x_lo)
          & (pts[..., 1] <= y_hi) & (pts[..., 1] >= y_lo))
    counts = ok.sum(-1)
    t, o = np.unravel_index(int(np.argmax(counts)), counts.shape)
    return pts[t, o][ok[t, o]]


def _batch_violation(x: np.ndarray, prob: Packing, dx: float, dy: float) -> np.ndarray:
    """(A,) largest constraint violation of each configuration of a batch x (A, K, 2)."""
    x_lo, x_hi, y_lo, y_hi = _walls(prob, dx, dy)
    xs, ys = x[..., 0], x[..., 1]
    rho = np.sqrt(xs * xs + ys * ys)
    ddx = xs[:, :, None] - xs[:, None, :]
    ddy = ys[:, :, None] - ys[:, None, :]
    dist = np.sqrt(ddx * ddx + ddy * ddy)
    iu = np.triu_indices(x.shape[1], 1)
    parts = [rho - prob.R, prob.d - rho, xs - x_hi, x_lo - xs, ys - y_hi, y_lo - ys, prob.d - dist[:, iu[0], iu[1]]]
    return np.max(np.concatenate(parts, axis=1), axis=1)


def _relax(x: np.ndarray, prob: Packing, dx: float, dy: float) -> np.ndarray | None:
    """Penalty descent of a batch of configurations x (A, K, 2) towards the tightened constraints;
    the first configuration that meets the exact ones (checked every ``RELAX_CHECK`` steps), or None."""
    m = RELAX_MARGIN_MM
    d, R = prob.d + m, prob.R - m
    x_lo, x_hi, y_lo, y_hi = _walls(prob, dx, dy)
    K = x.shape[1]
    eye = np.eye(K, dtype=bool)
    xs, ys = x[..., 0].copy(), x[..., 1].copy()
    for it in range(1, RELAX_ITERS + 1):
        ddx = xs[:, :, None] - xs[:, None, :]  # (A, K, K)
        ddy = ys[:, :, None] - ys[:, None, :]
        dist = np.sqrt(ddx * ddx + ddy * ddy)
        dist[:, eye] = np.inf
        f = np.maximum(d - dist, 0.0) / np.maximum(dist, 1e-12)  # pairwise overlap / distance
        rho = np.sqrt(xs * xs + ys * ys)
        g = (np.maximum(d - rho, 0.0) - np.maximum(rho - R, 0.0)) / np.maximum(rho, 1e-12)  # into the annulus
        xs = xs + 0.25 * np.einsum("akj,akj->ak", f, ddx) + g * xs
        ys = ys + 0.25 * np.einsum("akj,akj->ak", f, ddy) + g * ys
        np.clip(xs, x_lo + m, x_hi - m, out=xs)
        np.clip(ys, y_lo + m, y_hi - m, out=ys)
        if it % RELAX_CHECK == 0:
            ok = np.flatnonzero(_batch_violation(np.stack([xs, ys], -1), prob, dx, dy) <= 0.0)
            if ok.size:
                return np.stack([xs[ok[0]], ys[ok[0]]], -1)
    return None


def pack(prob: Packing, dx: float, dy: float, seed: int = 0) -> np.ndarray:
    """A valid packing (K, 2) for the beacon at wall distances (dx, dy); deterministic in ``seed``."""
    best = _lattice(prob, dx, dy)
    assert is_valid(best, prob, dx, dy), "lattice packing violates a constraint"
    rng = np.random.default_rng(np.random.SeedSequence([seed, round(dx * 1000), round(dy * 1000)]))
    x_lo, x_hi, y_lo, y_hi = _walls(prob, dx, dy)
    while True:
        K = best.shape[0] + 1
        # half the attempts: the best packing plus one disc at a random place, jittered;
        # the other half: K discs at random places in the range disc (inside the walls)
        n_keep = ATTEMPTS // 2
        starts = np.empty((ATTEMPTS, K, 2))
        starts[:n_keep, :-1] = best + rng.normal(0.0, 0.1 * prob.d, (n_keep, K - 1, 2))
        ang = rng.uniform(0, 2 * math.pi, (ATTEMPTS, K))
        rad = prob.R * np.sqrt(rng.uniform((prob.d / prob.R) ** 2, 1.0, (ATTEMPTS, K)))
        rand = np.stack([rad * np.cos(ang), rad * np.sin(ang)], -1)
        starts[:n_keep, -1] = rand[:n_keep, -1]
        starts[n_keep:] = rand[n_keep:]
        np.clip(starts, [x_lo, y_lo], [x_hi, y_hi], out=starts)
        found = _relax(starts, prob, dx, dy)
        if found is None:
            return best
        assert is_valid(found, prob, dx, dy), "relaxed packing violates a constraint"
        best = found


# --- the shipped table --------------------------------------------------------------------------
def build_table(prob: Packing, step: float = GRID_STEP_MM, seed: int = 0, progress=None) -> dict:
    """Counts and configurations on the (dx, dy) grid (symmetric: computed for dx <= dy, mirrored)."""
    g = prob.grid(step)
    n = g.size
    configs: dict[tuple[int, int], np.ndarray] = {}
    for i in range(n):
        for j in range(i, n):
            configs[i, j] = pack(prob, float(g[i]), float(g[j]), seed)
            if progress is not None:
                progress(i, j, configs[i, j].shape[0])
    kmax = max(c.shape[0] for c in configs.values())
    counts = np.zeros((n, n), np.int64)
    pts = np.full((n, n, kmax, 2), np.nan)
    for (i, j), c in configs.items():
        counts[i, j] = counts[j, i] = c.shape[0]
        pts[j, i, :c.shape[0]] = c[:, ::-1]  # mirror x <-> y (the diagonal keeps the search's own)
        pts[i, j, :c.shape[0]] = c
    return {"grid_mm": g, "counts": counts, "configs": pts, "seed": np.int64(seed),
            "robot_radius_mm": np.float64(prob.d / 2), "comm_radius_mm": np.float64(prob.R),
            "arena_half_mm": np.float64(prob.L + prob.d / 2)}


@dataclass(frozen=True)
class CeilingTable:
    """A loaded packing table and its monotone envelope."""

    prob: Packing
    grid_mm: np.ndarray  # (n,)
    counts: np.ndarray  # (n, n) int: the search's count at each grid point
    configs: np.ndarray  # (n, n, K, 2) float: its configuration, NaN-padded
    seed: int

    @property
    def envelope(self) -> np.ndarray:
        """(n, n) int: the best count over every grid point nearer both walls (monotone)."""
        return np.maximum.accumulate(np.maximum.accumulate(self.counts, axis=0), axis=1)

    def capacity(self, dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
        """Capacity (int) for wall distances dx, dy (mm, any shape): envelope at the grid point below."""
        g = self.grid_mm
        ix = np.clip(np.searchsorted(g, np.asarray(dx, np.float64) + 1e-9, side="right") - 1, 0, g.size - 1)
        iy = np.clip(np.searchsorted(g, np.asarray(dy, np.float64) + 1e-9, side="right") - 1, 0, g.size - 1)
        return self.envelope[ix, iy]


def _world_key(world: WorldConfig) -> tuple[float, float, float]:
    return (world.robot_radius_mm, world.comm_radius_mm, world.arena_half_mm)


@lru_cache(maxsize=4)
def load_table(path: Path = TABLE_PATH) -> CeilingTable:
    """The packing table at ``path`` (default: the shipped one)."""
    with np.load(path, allow_pickle=False) as z:
        prob = Packing(d=2.0 * float(z["robot_radius_mm"]), R=float(z["comm_radius_mm"]),
                       L=float(z["arena_half_mm"]) - float(z["robot_radius_mm"]))
        return CeilingTable(prob, z["grid_mm"], z["counts"], z["configs"], int(z["seed"]))


def has_ceiling(world: WorldConfig) -> bool:
    """True when :func:`episode_ceiling` can answer for ``world``."""
    if not world.collisions or world.robot_radius_mm == 0:
        return True
    t = load_table()
    return (t.prob.d / 2, t.prob.R, t.prob.L + t.prob.d / 2) == _world_key(world)


def _table_for(world: WorldConfig) -> CeilingTable:
    if not has_ceiling(world):
        t = load_table()
        raise InputError(
            f"no packing table for robot_radius_mm {world.robot_radius_mm}, comm_radius_mm "
            f"{world.comm_radius_mm}, arena_half_mm {world.arena_half_mm} (the shipped one is for "
            f"{t.prob.d / 2}, {t.prob.R}, {t.prob.L + t.prob.d / 2}); write one with tools/packing_table.py")
    return load_table()


def capacity(world: WorldConfig, beacon: np.ndarray) -> np.ndarray:
    """(E,) int: robots that fit in range of a beacon at each position (E, 2) mm, in a collision world."""
    t = _table_for(world)
    b = np.abs(np.asarray(beacon, np.float64))
    lim = world.arena_half_mm - world.robot_radius_mm
    return t.capacity(np.maximum(lim - b[..., 0], 0.0), np.maximum(lim - b[..., 1], 0.0))


def episode_ceiling(world: WorldConfig, n_robots: int, beacon: np.ndarray) -> np.ndarray:
    """(E,) the highest final coverage each episode allows: min(M, capacity) / M (1 without collisions)."""
    b = np.asarray(beacon, np.float64)
    if not world.collisions or world.robot_radius_mm == 0:
        return np.ones(b.shape[:-1])
    return np.minimum(n_robots, capacity(world, b)) / n_robots


def open_capacity(world: WorldConfig) -> int:
    """Capacity with the beacon beyond range of every wall."""
    return int(_table_for(world).envelope[-1, -1])


def spawn_weights(world: WorldConfig, grid: np.ndarray) -> np.ndarray:
    """(n,) probability that a beacon spawned uniformly (sim.env) has its x wall distance in each
    grid cell [g_i, g_{i+1}) (the last cell: everything beyond the last grid point)."""
    lim = world.arena_half_mm - world.robot_radius_mm
    h = world.arena_half_mm - max(world.spawn_margin_mm, world.robot_radius_mm)
    lo, hi = lim - h, lim  # wall distance is uniform on [lo, hi]
    edges = np.append(grid, np.inf)
    w = np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0.0, None)
    return w / w.sum()


def mean_capacity(world: WorldConfig, n_robots: int | None = None) -> float:
    """Mean capacity over the env's beacon spawn (each capped at ``n_robots`` when given)."""
    t = _table_for(world)
    w = spawn_weights(world, t.grid_mm)
    cap = t.envelope if n_robots is None else np.minimum(t.envelope, n_robots)
    return float(w @ cap @ w)
