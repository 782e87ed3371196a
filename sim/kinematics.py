"""Robot motion: the thesis kinematics, the Kilobot tick-level motor schedule, walls and collisions.

Thesis (§4.1), once per control period ΔT::

    k_lin = (u_l + u_r) / 2,  k_ang = u_l - u_r
    φ'    = wrap(φ + k_ang · ω_max · ΔT)
    (x, y)' = (x, y) + k_lin · (cos φ', sin φ') · v_max · ΔT

The heading turns first and the robot then moves along the *new* heading, as written in the thesis.

Kilobot (``tick_level`` worlds), once per kilo_tick for ``period_ticks`` ticks: the motor mode of
:func:`sim.motion.mode_at_tick` on the uint8 commands. STRAIGHT moves ``v_max · tick_s`` along the
heading; LEFT / RIGHT turn by ``± ω_max · tick_s``; STOP does nothing. Simplification: a pivot is
modelled as a rotation about the robot's centre (a real Kilobot pivots about one leg, so its centre
also shifts by a few mm per quarter turn).

Headings are wrapped to (-π, π]. Walls: robot centres are clipped to ``[-a + r, a - r]`` (a =
``arena_half_mm``, r = ``robot_radius_mm``). Collisions (``cfg.collisions``): after each move, every
pair of overlapping discs is pushed apart symmetrically along the line between the centres, in
over-relaxed Jacobi sweeps (:data:`RELAX_OMEGA`), until no pair overlaps by more than
:data:`OVERLAP_TOL_MM` at the end of a move (:data:`TICK_OVERLAP_TOL_MM` between the ticks of a
period). The target beacon is a disc of the same size that does not move: a searcher overlapping it
takes the whole push (robots also spawn clear of it).

Trigonometry for the moves is evaluated in float32 (:func:`unit`), ~1e-7 relative, i.e. below
1e-5 mm per thesis step; everything else is float64.
"""
from __future__ import annotations

import math

import numpy as np

from . import grid
from .config import WorldConfig
from .motion import MODE_LEFT, MODE_RIGHT, MODE_STRAIGHT, mode_at_tick, schedule

TWO_PI = 2.0 * math.pi
OVERLAP_TOL_MM = 1e-6  #: discs never end a move overlapping by more than this
TICK_OVERLAP_TOL_MM = 0.01  #: looser tolerance inside a control period (ticks before the last move)
MAX_RELAX_ITERS = 200  #: relaxation sweeps per move at most (dense jams against walls)
#: over-relaxation: a sweep separates an overlapping pair by RELAX_OMEGA x its overlap. Plain Jacobi
#: (1.0) converges slowly in clusters of pushing robots (~0.7x per sweep); 1.5 needs ~4 sweeps and
#: leaves a gap of at most half the resolved overlap (< 0.2 mm per tick at Kilobot speed).
RELAX_OMEGA = 1.5


def wrap_angle(phi: np.ndarray) -> np.ndarray:
    """Wrap angles to (-π, π]; angles already in range are returned bit-exact.

    >>> wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi / 2, 0.0])).round(6).tolist()
    [3.141593, 3.141593, -1.570796, 0.0]
    """
    phi = np.asarray(phi, np.float64)
    w = phi - TWO_PI * np.rint(phi / TWO_PI)  # [-π, π]; in-range angles: rint = 0, w = phi exactly
    return np.where(w <= -math.pi, w + TWO_PI, w)


def unit(heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos φ, sin φ) evaluated in float32 (SIMD; ~1e-7 relative error, 8x faster here), as float64."""
    h32 = heading.astype(np.float32)
    return np.cos(h32).astype(np.float64), np.sin(h32).astype(np.float64)


def clip_walls(pos: np.ndarray, cfg: WorldConfig) -> None:
    """Clip robot centres (..., 2) in place to the square [-a + r, a - r]²."""
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    np.minimum(pos, lim, out=pos)  # ufuncs: np.clip's wrapper costs more than the work here
    np.maximum(pos, -lim, out=pos)


def thesis_move(pos: np.ndarray, heading: np.ndarray, u: np.ndarray, cfg: WorldConfig) -> None:
    """One thesis kinematics step in place. pos (B, M, 2) mm, heading (B, M) rad, u (B, M, 2) in [0, 1]."""
    ul, ur = u[..., 0], u[..., 1]
    k_lin = (ul + ur) / 2.0
    k_ang = ul - ur
    dt = cfg.control_period_s
    heading[...] = wrap_angle(heading + k_ang * (cfg.omega_max_rad_s * dt))
    step = k_lin * (cfg.v_max_mm_s * dt)  # (B, M) mm
    c, s = unit(heading)
    pos[..., 0] += step * c
    pos[..., 1] += step * s
    clip_walls(pos, cfg)


class Collider:
    """Disc-overlap resolution with a Verlet candidate list (pairs within 2r + skin).

    The list is rebuilt whenever some disc has moved more than skin/2 since the last build, so it
    always holds every pair that can overlap. Pairs are kept sorted by (env, i, j), so pushes are
    summed in the same order whatever the batch size (a batch equals its single-env runs).
    """

    def __init__(self, cfg: WorldConfig, skin_mm: float | None = None) -> None:
        assert cfg.robot_radius_mm > 0, "collisions need robot_radius_mm > 0"
        self.cfg = cfg
        self.diam = 2.0 * cfg.robot_radius_mm
        self.skin = skin_mm if skin_mm is not None else 0.5 * self.diam  # rebuild every ~25 ticks
        self.invalidate()

    def invalidate(self) -> None:
        """Forget the candidate list (call after teleporting robots, e.g. at reset)."""
        self._built_at: np.ndarray | None = None

    def _candidates(self, allpos: np.ndarray, has_target: bool) -> None:
        if self._built_at is not None and self._built_at.shape == allpos.shape:
            moved = allpos - self._built_at
            if np.max(moved[..., 0] ** 2 + moved[..., 1] ** 2) <= (0.5 * self.skin) ** 2:
                return
        B, n_all, _ = allpos.shape
        p = grid.pairs_within(allpos, self.diam + self.skin, self.cfg.arena_half_mm)
        self._fi = p.env * n_all + p.i  # (K,) flat ids; i < j, so a fixed target is always j
        self._fj = p.env * n_all + p.j
        fixed = (p.j == n_all - 1) if has_target else np.zeros(len(p), bool)
        self._wi = np.where(fixed, 1.0, 0.5)  # share of the push each disc takes
        self._wj = np.where(fixed, 0.0, 0.5)
        self._built_at = allpos.copy()

    def resolve(self, pos: np.ndarray, target: np.ndarray | None, tol: float = OVERLAP_TOL_MM) -> int:
        """Push overlapping discs apart in place until no pair overlaps by more than ``tol`` mm.

        pos (B, M, 2) robots; target (B, 2) a fixed disc, or None. Returns the number of sweeps.
        Positions are handled as complex numbers x + iy (a view), halving the NumPy calls per sweep.
        """
        B, M, _ = pos.shape
        parts = [pos] if target is None else [pos, target[:, None, :]]
        allpos = np.concatenate(parts, axis=1)  # (B, n_all, 2) contiguous working copy
        n_all = allpos.shape[1]  # M or M + 1; index M is the fixed target
        self._candidates(allpos, target is not None)
        if self._fi.size == 0:
            return 0
        z = allpos.view(np.complex128).reshape(-1)  # (B * n_all,) x + iy, shares memory with allpos
        lim = self.cfg.arena_half_mm - self.cfg.robot_radius_mm
        limit = self.diam - tol  # overlap > tol  <=>  d < 2r - tol
        fi, fj = self._fi, self._fj
        sweeps = 0
        for _ in range(MAX_RELAX_ITERS):
            dz = z.take(fi) - z.take(fj)  # (K,) from j to i
            d = np.abs(dz)
            hit = np.flatnonzero(d < limit)
            if hit.size == 0:
                break
            sweeps += 1
            dh = d.take(hit)
            u = dz.take(hit) / np.maximum(dh, 1e-300)  # unit vector j -> i
            zero = dh == 0.0
            if zero.any():  # coincident centres: separate along x
                u[zero] = 1.0
            push = u * ((self.diam - dh) * RELAX_OMEGA)  # each disc takes its share
            np.add.at(z, fi.take(hit), push * self._wi.take(hit))  # sequential, in pair order
            np.add.at(z, fj.take(hit), push * -self._wj.take(hit))
            for part in (z.real, z.imag):  # walls (the fixed target sits inside them: unaffected)
                np.minimum(part, lim, out=part)
                np.maximum(part, -lim, out=part)
        pos[...] = allpos[:, :M]
        return sweeps


def max_overlap(pos: np.ndarray, target: np.ndarray | None, cfg: WorldConfig) -> float:
    """Largest disc overlap (mm) among robots (and the fixed target), 0 when none. For tests."""
    allpos = pos if target is None else np.concatenate([pos, target[:, None, :]], axis=1)
    p = grid.pairs_within(allpos, 2.0 * cfg.robot_radius_mm, cfg.arena_half_mm)
    return float(np.max(2.0 * cfg.robot_radius_mm - p.dist)) if len(p) else 0.0


def tick_move(pos: np.ndarray, heading: np.ndarray, q: np.ndarray, cfg: WorldConfig,
              collider: Collider | None, target: np.ndarray | None,
              record: np.ndarray | None = None) -> None:
    """One control period of Kilobot motion, tick by tick, in place.

    q (B, M, 2) uint8 motor commands. ``record`` (P, B, M, 2), if given, receives the positions
    after each tick (used by the radio model, which needs who was where when a message flew).
    """
    P = cfg.period_ticks
    turn, tmode, straight = schedule(q[..., 0], q[..., 1], P)  # (B, M) each
    dphi = cfg.omega_max_rad_s * cfg.tick_s
    dl = cfg.v_max_mm_s * cfg.tick_s
    last_turn = int(turn.max()) if turn.size else 0
    last_move = int((turn.astype(np.int32) + straight).max()) if turn.size else 0
    loose = False  # a loose-tolerance resolution happened since the last strict one
    for k in range(P):  # loop over ticks; everything inside is vectorised over (B, M)
        if k < last_move:
            mode = mode_at_tick(turn, tmode, straight, k)  # (B, M)
            if k < last_turn:
                turning = (mode == MODE_LEFT).astype(np.float64) - (mode == MODE_RIGHT)
                heading[...] = wrap_angle(heading + turning * dphi)
            go = (mode == MODE_STRAIGHT) * dl  # (B, M) mm this tick
            moved = bool(go.any())  # pivots about the centre move no centre
            if moved:
                c, s = unit(heading)
                pos[..., 0] += go * c
                pos[..., 1] += go * s
                clip_walls(pos, cfg)
            last = k == last_move - 1
            if collider is not None and (moved or (last and loose)):
                # loose tolerance inside the period, strict at its last moving tick
                collider.resolve(pos, target, OVERLAP_TOL_MM if last else TICK_OVERLAP_TOL_MM)
                loose = not last
        if record is not None:
            record[k] = pos
