"""Robot motion: the thesis kinematics, the Kilobot tick-level motor schedule, walls and collisions.

Thesis (§4.1), once per control period ΔT::

    k_lin = (u_l + u_r) / 2,  k_ang = u_l - u_r
    φ'    = wrap(φ + k_ang · ω_max · ΔT)
    (x, y)' = (x, y) + k_lin · (cos φ', sin φ') · v_max · ΔT

The heading turns first and the robot then moves along the *new* heading, as written in the thesis.

Kilobot (``tick_level`` worlds), once per kilo_tick for ``period_ticks`` ticks: the motor mode of
:func:`sim.motion.schedule` on the uint8 commands. STRAIGHT moves ``v_max · tick_s`` along the
heading; LEFT / RIGHT turn by ``± ω_max · tick_s``; STOP does nothing (per-robot factors:
:class:`MotionParams`). A pivot turns the robot about its pivot leg (``cfg.pivot_offset_mm`` R from
the centre, ``cfg.pivot_angle_deg`` α from the heading, on the side of the turn; R = 0: about the
centre). In complex coordinates, with heading φ before the tick, θ = ±ω_max · tick_s and
β = ±α (+ for left pivots)::

    leg  p  = z + R exp(i(φ + β))             (stays put during the tick)
    z'      = p - R exp(i(φ + θ + β)),  φ' = φ + θ

so after m pivot ticks from (z0, φ0) the centre is at ``z0 + R e^{i(φ0+β)} (1 - e^{imθ})``: an arc
of radius R about the leg, each tick a chord of 2R sin(θ/2) in the direction φ + β - sign(θ)·90° + θ/2
(for the Kilobot's α = 125.5°: forwards and towards the turn, heading ± 35.5°).

Headings are wrapped to (-π, π]. Walls: robot centres are clipped to ``[-a + r, a - r]`` after every
tick (a = ``arena_half_mm``, r = ``robot_radius_mm``). Collisions (``cfg.collisions``): after each
tick's move, every pair of overlapping discs is pushed apart along the line between the centres,
in over-relaxed Jacobi sweeps (:data:`RELAX_OMEGA`, aiming at :data:`RELAX_MARGIN_MM` of gap), until
no pair overlaps by more than :data:`TICK_OVERLAP_TOL_MM` or for :data:`TICK_SWEEPS` sweeps, and,
after the period's last moving tick, until no pair overlaps by more than :data:`OVERLAP_TOL_MM`.
Inside a period contacts are thus slightly soft: in a robot pushing into a jam, what the sweeps of
one tick leave is resolved with the next tick's (worst overlap between ticks ≈ 0.6 mm in a
32-robot jam, where sweeping to 0.01 mm every tick took ~20 sweeps per tick); at the end of every
period no discs overlap. Robot pairs share a push equally; the emitter disc takes ``m / (1 + m)`` of a push with its
robot (mobility m: 0 = taped down, the robot takes the whole push; 1 = pushed like a robot).

How a period is computed (same model as stepping every robot tick by tick, without a Python loop
over ticks where nothing touches): a robot's period is ``turn`` pivot ticks, then ``straight``
ticks, then stop, so its collision-free path is closed form, for every tick at once: the arc about
the pivot leg (above; nothing with a centre pivot), then n straight steps along the heading after
the pivots (``curve``: a geometric sum of rotated steps). Walls too: clipping a coordinate tick by
tick equals clipping the unclipped path whenever that coordinate moves in one direction during the
period (always true for a straight run after a centre pivot), and in general, per coordinate,
``x_k = min(x0 + D_k, a - r - (max_{j<=k} D_j - D_k))`` for the unclipped displacement D (a running
maximum; the running minimum for the other wall; :func:`_clip_path`). Only the envs in which two discs on these
paths come closer than 2r at some tick (found from the pairs within ``2r + travel_i + travel_j`` at
the period start, travel = arc + straight path length) are re-run tick by tick from the first such
tick, with the collision resolution; a tick's move there is the closed form's increment, which does
not depend on where pushes put the robot. With Numba installed, the closed form of straight runs and everything from the
contact candidates on run compiled
(:func:`sim.compiled.period_contacts`, the same float operations in the same order; ``KILOFORGE_JIT=0``: this module's code).

Trigonometry: thesis moves use float32 (:func:`unit`, ~1e-7 relative, below 1e-5 mm per step);
Kilobot moves take float64 ``exp(iφ)`` per robot and period (and, for arcs, a table of
``exp(i j ω_max tick_s)``, or one exponential per pivot tick when turn rates vary per robot).
Everything else is float64.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from . import compiled, grid
from .config import WorldConfig
from .motion import MODE_LEFT, schedule

TWO_PI = 2.0 * math.pi
OVERLAP_TOL_MM = 1e-6  #: discs never end a period overlapping by more than this
TICK_OVERLAP_TOL_MM = 0.01  #: between the ticks of a period: sweep until overlaps are below this ...
TICK_SWEEPS = 4  #: ... or for this many sweeps (soft contacts inside a period; see the module doc)
MAX_RELAX_ITERS = 200  #: relaxation sweeps per resolution at most (dense jams against walls)
#: over-relaxation: a sweep separates an overlapping pair by RELAX_OMEGA x its overlap. Plain Jacobi
#: (1.0) converges slowly in clusters of pushing robots (~0.7x per sweep); 1.5 needs ~4 sweeps and
#: leaves a gap of at most half the resolved overlap (< 0.2 mm per tick at Kilobot speed).
RELAX_OMEGA = 1.5
#: pushes aim at a separation of 2r + this: the small gap absorbs what later sweeps push back, so a
#: 32-robot jam reaches OVERLAP_TOL_MM in ~15 sweeps instead of ~120 (measured on captured jams)
RELAX_MARGIN_MM = 0.05
MIN_SKIN_FRAC = 0.25  #: candidate pairs within 2r + skin; the skin is at least this x 2r
#: the skin is this x a period's longest own path: a disc may move skin / 2 (its own path and pushes)
#: before its env's list is rebuilt (at 2.0, with its own path alone, most crowded periods rebuilt)
SKIN_TRAVELS = 2.5


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


@dataclass
class MotionParams:
    """Per-robot motion factors, each (B, M): what a robot's motors really do in each mode.

    ``speed`` scales v_max on straight ticks, ``turn_left`` / ``turn_right`` scale ω_max on left /
    right pivot ticks, ``curve`` is the heading change (rad, + = counter-clockwise) per straight
    tick (a robot whose calibrated "straight" is not quite straight), ``pivot_mm`` the distance of
    each robot's pivot point from its centre. The nominal robot is ``1, 1, 1, 0`` and the world's
    ``pivot_offset_mm``; :mod:`sim.variants` draws these.
    """

    speed: np.ndarray
    turn_left: np.ndarray
    turn_right: np.ndarray
    curve: np.ndarray | None = None  #: None: every straight is straight
    pivot_mm: np.ndarray | None = None  #: None: cfg.pivot_offset_mm for every robot


class _Contacts:
    """Candidate disc pairs of a batch of envs (flat complex positions, ``n_disc`` per env).

    Per env, the pairs within ``2r + skin`` of a build; an env's list is rebuilt (and its relaxation
    repeated) when one of its discs has moved more than skin / 2 since that env's build, so the list
    always holds every pair that can overlap. Pairs are sorted by (env, i, j), pushes are summed in
    that order, and everything is decided per env, so a batch equals its single-env runs.
    """

    def __init__(self, z: np.ndarray, n_env: int, n_disc: int, cfg: WorldConfig, skin: float,
                 mobility: np.ndarray | None, pairs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> None:
        """``z`` (n_env * n_disc,) the positions the list is built at; ``pairs`` (env, i, j), sorted:
        the pairs within 2r + skin there, when the caller has them already."""
        self.n_env, self.n_disc = n_env, n_disc
        self.diam = 2.0 * cfg.robot_radius_mm
        self.lim = cfg.arena_half_mm - cfg.robot_radius_mm
        self.extent = cfg.arena_half_mm
        self.skin = skin
        self.mobility = mobility  # (n_env,) emitter mobility, or None: no emitter disc (last disc is a robot)
        if pairs is None:
            pairs = self._within(z, np.arange(n_env))
        self.pe, self.fi, self.fj, self.wi, self.wj = self._shares(*pairs)
        self.built_at = z.copy()

    def _within(self, z: np.ndarray, envs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(env, i, j) of the pairs of ``envs`` (ascending) within 2r + skin at ``z``, sorted."""
        N = self.n_disc
        zz = z.reshape(self.n_env, N)[envs]
        p = grid.pairs_within(zz.view(np.float64).reshape(envs.size, N, 2), self.diam + self.skin, self.extent)
        return envs.take(p.env), p.i, p.j

    def _shares(self, pe: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple:
        """(env, flat i, flat j, share i, share j) of pairs (env, i, j)."""
        N = self.n_disc
        fi, fj = pe * N + i, pe * N + j  # i < j, so the emitter is always j
        if self.mobility is None:
            return pe, fi, fj, None, None  # every pair shares its push equally
        # robot-emitter pairs: shares by mobility (robot 1, emitter m): 1 / (1 + m) and m / (1 + m)
        m = np.where(j == N - 1, self.mobility.take(pe), 1.0)
        return pe, fi, fj, 2.0 / (1.0 + m), 2.0 * m / (1.0 + m)  # relative to an equal share

    def _rebuild(self, z: np.ndarray, envs: np.ndarray) -> None:
        stale = np.zeros(self.n_env, bool)
        stale[envs] = True
        keep = ~stale.take(self.pe)
        new = self._shares(*self._within(z, envs))
        order = np.argsort(np.concatenate((self.pe[keep], new[0])), kind="stable")
        old = (self.pe, self.fi, self.fj, self.wi, self.wj)
        self.pe, self.fi, self.fj, self.wi, self.wj = (
            None if o is None else np.concatenate((o[keep], n)).take(order) for o, n in zip(old, new))
        zb = self.built_at.reshape(self.n_env, self.n_disc)
        zb[envs] = z.reshape(self.n_env, self.n_disc)[envs]

    def relax(self, z: np.ndarray, limit: np.ndarray, capped: np.ndarray | None = None,
              cap: int = MAX_RELAX_ITERS) -> int:
        """Push overlapping discs of ``z`` (flat complex, in place) apart until, in each env e, no pair
        is closer than ``limit[e]`` (2r - tolerance; a negative limit leaves the env alone), envs with
        ``capped[e]`` stopping after ``cap`` sweeps. Returns the number of sweeps."""
        sweeps = self._sweeps(z, limit, capped, cap)
        while True:
            moved = np.abs(z - self.built_at)
            if moved.max(initial=0.0) <= 0.5 * self.skin:
                return sweeps
            moved = moved.reshape(self.n_env, self.n_disc).max(axis=1) > 0.5 * self.skin  # (n_env,)
            over = (moved & (limit > 0)).nonzero()[0]
            if not over.size:
                return sweeps
            self._rebuild(z, over)  # discs left the skin: pairs may be missing; rebuild, relax again
            sweeps += self._sweeps(z, np.where(moved, limit, -1.0), capped, cap)

    def _sweeps(self, z: np.ndarray, limit_env: np.ndarray, capped: np.ndarray | None, cap: int) -> int:
        lim = self.lim
        target = self.diam + RELAX_MARGIN_MM
        fi, fj, wi, wj, pe = self.fi, self.fj, self.wi, self.wj, self.pe
        limit = limit_env.take(pe)  # (K,) a pair overlaps too much when closer than this
        zf = z.view(np.float64)
        compact_at = 1
        for sweep in range(MAX_RELAX_ITERS):
            if sweep == cap and capped is not None and capped.any():  # capped envs are done
                if capped[limit_env > 0].all():
                    return sweep
                limit = np.where(capped.take(pe), -1.0, limit)
            dz = z.take(fi) - z.take(fj)  # (K,) from j to i
            d = np.abs(dz)
            hit = (d < limit).nonzero()[0]
            if hit.size == 0:
                return sweep
            if sweep == compact_at:  # from now on only the pairs of envs that still have overlaps
                compact_at *= 3
                active = np.zeros(self.n_env, bool)
                active[pe.take(hit)] = True
                keep = active.take(pe).nonzero()[0]
                if keep.size < 0.7 * pe.size:
                    fi, fj, pe, dz, d, limit = (v.take(keep) for v in (fi, fj, pe, dz, d, limit))
                    if wi is not None:
                        wi, wj = wi.take(keep), wj.take(keep)
                    hit = (d < limit).nonzero()[0]
            dh = d.take(hit)
            # each disc's equal share of the push; + 1e-300 separates coincident centres along x
            push = (dz.take(hit) + 1e-300) * ((target - dh) * (0.5 * RELAX_OMEGA) / np.maximum(dh, 1e-300))
            if wi is None:
                np.add.at(z, fi.take(hit), push)  # sequential, in pair order
                np.subtract.at(z, fj.take(hit), push)
            else:
                np.add.at(z, fi.take(hit), push * wi.take(hit))
                np.subtract.at(z, fj.take(hit), push * wj.take(hit))
            np.minimum(zf, lim, out=zf)  # walls (robots and emitter)
            np.maximum(zf, -lim, out=zf)
        return MAX_RELAX_ITERS


class Collider:
    """Disc-overlap resolution for one world: symmetric pushes along the centre line in over-relaxed
    Jacobi sweeps (:data:`RELAX_OMEGA`) until no pair overlaps by more than a tolerance."""

    def __init__(self, cfg: WorldConfig) -> None:
        assert cfg.robot_radius_mm > 0, "collisions need robot_radius_mm > 0"
        self.cfg = cfg
        self.diam = 2.0 * cfg.robot_radius_mm
        #: candidate-pair skin: SKIN_TRAVELS x the longest path of a period at nominal speed (straight run
        #: or arc about the pivot leg), so a list built at a period's start rarely needs a rebuild
        travel = cfg.period_ticks * cfg.tick_s * max(cfg.v_max_mm_s, cfg.pivot_offset_mm * cfg.omega_max_rad_s)
        self.skin = max(SKIN_TRAVELS * travel, MIN_SKIN_FRAC * self.diam)

    def resolve(self, pos: np.ndarray, target: np.ndarray | None, tol: float = OVERLAP_TOL_MM,
                emitter_mobility: float | np.ndarray = 0.0) -> int:
        """Push overlapping discs apart in place until no pair overlaps by more than ``tol`` mm.

        pos (B, M, 2) robots; target (B, 2) the emitter disc (moved in place when its mobility is
        > 0), or None. Returns the number of sweeps.
        """
        B = pos.shape[0]
        allz = _discs(pos, target)
        mob = None if target is None else np.broadcast_to(np.asarray(emitter_mobility, np.float64), (B,))
        flat = allz.reshape(-1)
        sweeps = _Contacts(flat, B, allz.shape[1], self.cfg, self.skin, mob).relax(flat, np.full(B, self.diam - tol))
        _store(allz, pos, target)
        return sweeps


def _discs(pos: np.ndarray, target: np.ndarray | None) -> np.ndarray:
    """(B, N) complex disc centres: the robots, then the emitter (N = M + 1) when given."""
    B, M, _ = pos.shape
    z = np.empty((B, M + (target is not None)), np.complex128)
    z.real[:, :M], z.imag[:, :M] = pos[..., 0], pos[..., 1]
    if target is not None:
        z.real[:, M], z.imag[:, M] = target[:, 0], target[:, 1]
    return z


def _store(z: np.ndarray, pos: np.ndarray, target: np.ndarray | None) -> None:
    M = pos.shape[1]
    pos[..., 0], pos[..., 1] = z.real[:, :M], z.imag[:, :M]
    if target is not None:
        target[:, 0], target[:, 1] = z.real[:, M], z.imag[:, M]


def max_overlap(pos: np.ndarray, target: np.ndarray | None, cfg: WorldConfig) -> float:
    """Largest disc overlap (mm) among robots (and the emitter), 0 when none. For tests."""
    allpos = pos if target is None else np.concatenate([pos, target[:, None, :]], axis=1)
    p = grid.pairs_within(allpos, 2.0 * cfg.robot_radius_mm, cfg.arena_half_mm)
    return float(np.max(2.0 * cfg.robot_radius_mm - p.dist)) if len(p) else 0.0


def tick_move(pos: np.ndarray, heading: np.ndarray, q: np.ndarray, cfg: WorldConfig,
              collider: Collider | None, target: np.ndarray | None, record: np.ndarray | None = None, *,
              target_record: np.ndarray | None = None, motion: MotionParams | None = None,
              emitter_mobility: float | np.ndarray = 0.0) -> None:
    """One control period of Kilobot motion in place (see the module doc for the scheme).

    q (B, M, 2) uint8 motor commands. ``record`` (P, B, M, 2), if given, receives the positions
    after each tick (the radio model needs who was where when a message flew); ``target_record``
    (P, B, 2) the emitter's. ``target`` (B, 2) is the emitter disc (collision worlds), pushed in place
    with ``emitter_mobility`` (0 = taped down, 1 = like a robot; scalar or (B,)). ``motion``: per-robot
    motion factors (None = nominal).
    """
    B, M = heading.shape
    P = cfg.period_ticks
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    dphi, dl = cfg.omega_max_rad_s * cfg.tick_s, cfg.v_max_mm_s * cfg.tick_s
    jit = compiled.available()
    kappa = None
    if motion is None:
        step = dl
    else:
        step = dl * motion.speed
        if motion.curve is not None and np.any(motion.curve != 0):
            kappa = motion.curve
    R = cfg.pivot_offset_mm if motion is None or motion.pivot_mm is None else motion.pivot_mm
    turn_l, turn_r = (dphi, dphi) if motion is None else (dphi * motion.turn_left, dphi * motion.turn_right)
    legs = bool(R > 0) if np.ndim(R) == 0 else bool(np.any(R > 0))  # pivots move the centre (when a robot pivots)
    if jit and kappa is None and _plain(heading):
        # the schedule, the pivots' headings and the wrap in one compiled pass (the same integer and float operations)
        t, s, left, theta, phi_s, phi0, turned = compiled.motor_schedule(q, heading, P, turn_l, turn_r)
        leg = legs and turned
    else:
        turn, tmode, straight = schedule(q[..., 0], q[..., 1], P)
        t, s = turn.astype(np.int64), straight.astype(np.int64)
        left = tmode == MODE_LEFT
        theta = np.where(left, turn_l, -turn_r)
        leg = legs and bool(t.any())
        phi0 = heading.copy() if leg else None
        phi_s = heading + t * theta  # heading when the straight ticks start
        if kappa is None:
            heading[...] = wrap_angle(phi_s)
    u_s = np.exp(1j * phi_s)  # (B, M) unit vector along the straight run
    inc = None  # (P, B, M) each tick's move along the straight run, where it is needed
    z0 = pos[..., 0] + 1j * pos[..., 1]  # (B, M)
    into_record = record is not None and _plain(record)
    has_emitter = collider is not None and target is not None
    zb = target[:, 0] + 1j * target[:, 1] if has_emitter else None
    mobility = _per_env(emitter_mobility, B) if has_emitter else None
    if kappa is None:
        e = step * u_s  # (B, M) displacement of one straight tick
    if kappa is None and jit:  # everything down to the clipped path, compiled (bit-identical)
        zk = record.view(np.complex128).reshape(P, B, M) if into_record else np.empty((P, B, M), np.complex128)
        disp, travel = np.empty((P, B, M), np.complex128), np.empty((B, M))
        c = table = rot = None
        if leg:
            c = _arc_centre(phi0, left, R, cfg)
            if motion is None:
                table = _rotation_table(dphi, P)
            else:
                rot = np.exp(1j * (theta * _pivots_done(t)))
        if collider is not None and _plain(pos) and (target is None or _plain(target)):  # the rest in the same call
            compiled.straight_period(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel, zb,
                                     mobility, target_record,
                                     collider.diam, collider.skin, RELAX_MARGIN_MM, RELAX_OMEGA, OVERLAP_TOL_MM,
                                     TICK_OVERLAP_TOL_MM, TICK_SWEEPS, MAX_RELAX_ITERS, pos, target)
            if record is not None and not into_record:
                record[...] = zk.view(np.float64).reshape(P, B, M, 2)
            return
        compiled.closed_form(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel)
    else:
        k = np.arange(P).reshape(P, 1, 1)
        n = k + 1 - t  # (P, B, M) straight ticks done by the end of tick k
        np.maximum(n, 0, out=n)
        np.minimum(n, s, out=n)
        if kappa is None:
            disp = _scaled(n, e)
        else:  # each straight tick turns by kappa, then moves along the new heading
            inc = ((k >= t) & (k < t + s)) * (step * np.exp(1j * (phi_s + n * kappa)))
            disp = np.cumsum(inc, axis=0)
            heading[...] = wrap_angle(phi_s + s * kappa)
        travel = s * step  # (B, M) path length of the period: a bound on how far a disc gets
        if leg:
            travel = travel + _add_arcs(disp, phi0, theta, t, left, R, cfg, dphi if motion is None else None)
        if into_record:
            zk = record.view(np.complex128).reshape(P, B, M)  # write the ticks straight into the record
            np.add(z0, disp, out=zk)
        else:
            zk = z0 + disp
        zkf = zk.view(np.float64)
        if leg or kappa is not None:  # a coordinate may turn back: the robots that meet a wall
            b, r = (np.abs(zkf) > lim).reshape(P, B, M, 2).any(axis=(0, 3)).nonzero()
            if b.size:
                zk[:, b, r] = _clip_path(z0[b, r], disp.reshape(P, B * M).take(b * M + r, axis=1), lim)
        np.minimum(zkf, lim, out=zkf)  # walls: clipping the path = clipping every tick, for monotone coordinates
        np.maximum(zkf, -lim, out=zkf)
    k0 = np.full(B, P, np.int64)  # per env: the tick from which it runs tick by tick (P: never)
    if collider is not None and jit:  # all of the else branch, compiled (bit-identical)
        if not compiled.period_contacts(zk, z0, zb, travel, leg, disp, inc, None if kappa is not None else e, t, s,
                                        mobility, target_record, collider.diam, collider.skin, lim, RELAX_MARGIN_MM,
                                        RELAX_OMEGA, OVERLAP_TOL_MM, TICK_OVERLAP_TOL_MM, TICK_SWEEPS,
                                        MAX_RELAX_ITERS) and target_record is not None:
            target_record[...] = target  # no contact anywhere: the emitter stays put
    else:
        start = cand = None
        if collider is not None:  # pairs near enough to touch this period (also the per-tick contact lists)
            start = z0 if zb is None else np.concatenate([z0, zb[:, None]], axis=1)  # (B, N) discs at the start
            tr = travel if zb is None else np.concatenate([travel, np.zeros((B, 1))], axis=1)
            reach = max(2.0 * float(tr.max()), collider.skin)
            cand = grid.pairs_within(start.view(np.float64).reshape(B, -1, 2), collider.diam + reach + 1e-9,
                                     cfg.arena_half_mm)
            np.minimum(k0, _first_contacts(cand, zk, zb, tr, collider.diam), out=k0)
        if (k0 < P).any():
            _per_tick(zk, zb, z0, disp, inc if inc is not None else e, t, s, leg, k0, cfg, collider, mobility,
                      target_record, start, cand)
        elif target_record is not None:
            target_record[...] = target  # the emitter stays put
    pos[..., 0], pos[..., 1] = zk[-1].real, zk[-1].imag
    if has_emitter:
        target[:, 0], target[:, 1] = zb.real, zb.imag
    if record is not None and not into_record:
        record[...] = zk.view(np.float64).reshape(P, B, M, 2)


def _plain(a: np.ndarray) -> bool:
    """Whether ``a`` is a C-contiguous float64 array (compiled code writes such arrays in place)."""
    return a.dtype == np.float64 and a.flags.c_contiguous


def _per_env(x: float | np.ndarray, B: int) -> np.ndarray:
    """A scalar or (B,) value as a (B,) float64 array."""
    return np.full(B, x, np.float64) if np.ndim(x) == 0 else np.broadcast_to(np.asarray(x, np.float64), (B,))


def _scaled(n: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``n * e`` for integers n (P, B, M) and complex e (B, M), by two real products (NumPy casts
    integers to complex an order of magnitude slower than it multiplies)."""
    out = np.empty(n.shape, np.complex128)
    f = out.view(np.float64).reshape(n.shape + (2,))
    np.multiply(n, e.real, out=f[..., 0])
    np.multiply(n, e.imag, out=f[..., 1])
    return out


def _clip_path(z0: np.ndarray, disp: np.ndarray, lim: float) -> np.ndarray:
    """Positions (P, K) of paths ``z0 + disp`` (disp (P, K): the unclipped displacement after each
    tick) clipped to [-lim, lim]² after every tick, in closed form.

    Per coordinate, ``x_{k+1} = min(x_k + dx_k, lim)`` gives ``x_k = min(x0 + D_k, lim - (max_{j<=k}
    D_j - D_k))`` (D_0 = 0 included), and likewise for the lower wall with the running minimum. Exact
    for paths that come near one wall per coordinate at most (a period's travel is far below the
    arena width).
    """
    out = []
    for x0, d in ((z0.real, disp.real), (z0.imag, disp.imag)):
        x = x0 + d
        np.minimum(x, lim - (np.maximum(np.maximum.accumulate(d, axis=0), 0.0) - d), out=x)
        np.maximum(x, (d - np.minimum(np.minimum.accumulate(d, axis=0), 0.0)) - lim, out=x)
        out.append(x)
    return out[0] + 1j * out[1]


def _add_arcs(disp: np.ndarray, phi0: np.ndarray, theta: np.ndarray, t: np.ndarray, left: np.ndarray,
              R: float | np.ndarray, cfg: WorldConfig, nominal_dphi: float | None) -> np.ndarray:
    """Add the centre's arcs about the pivot legs to ``disp`` (P, B, M) in place; returns their
    lengths (B, M), a bound on how far they move the centre.

    ``t`` pivot ticks of θ each (per robot) about the leg at ``c = R exp(i(φ0 + β))`` from the centre
    (β = +α for left pivots, -α for right ones; the module doc) put the centre at
    ``z0 + c (1 - exp(i m θ))`` after m of them, and it keeps the whole arc ``c (1 - exp(i t θ))``
    afterwards. ``nominal_dphi``: θ = ±this for every robot (a table of exp(i j θ) instead of one
    exponential per robot and tick), or None.
    """
    P = disp.shape[0]
    c = _arc_centre(phi0, left, R, cfg)
    m = _pivots_done(t)
    T = m.shape[0]
    if nominal_dphi is not None:
        table = _rotation_table(nominal_dphi, P)
        m *= np.where(left, 1, -1)
        m += P
        rot = table.take(m)
    else:
        rot = np.exp(1j * (theta * m))
    arc = np.multiply(c, rot, out=rot)
    np.subtract(c, arc, out=arc)  # (T, B, M) c (1 - exp(i m theta))
    disp[:T] += arc
    disp[T:] += arc[-1]
    return t * (R * np.abs(theta))


def _arc_centre(phi0: np.ndarray, left: np.ndarray, R: float | np.ndarray, cfg: WorldConfig) -> np.ndarray:
    """c = R exp(i(φ0 + β)) (B, M): the pivot leg seen from the centre at the period start (_add_arcs)."""
    a = math.radians(cfg.pivot_angle_deg)
    return R * np.where(left, complex(math.cos(a), math.sin(a)), complex(math.cos(a), -math.sin(a))) * np.exp(1j * phi0)


def _pivots_done(t: np.ndarray) -> np.ndarray:
    """(T, B, M) pivot ticks done by the end of tick k, T = the most pivot ticks of any robot."""
    T = int(t.max())
    return np.minimum(np.arange(1, T + 1).reshape(T, 1, 1), t)


@functools.lru_cache(maxsize=8)
def _rotation_table(dphi: float, P: int) -> np.ndarray:
    """exp(i j dphi) for j = -P..P (2P + 1,), read-only: one per world, not one per period."""
    table = np.exp(1j * dphi * np.arange(-P, P + 1))
    table.flags.writeable = False
    return table


def _first_contacts(cand: grid.Pairs, zk: np.ndarray, zb: np.ndarray | None, tr: np.ndarray,
                    diam: float) -> np.ndarray:
    """(B,) first tick at which two discs on their collision-free paths ``zk`` (P, B, M) come closer
    than 2r - OVERLAP_TOL_MM in each env (P: never). ``cand``: the disc pairs within 2r + the largest
    ``tr[e, i] + tr[e, j]`` at the period start, ``tr`` (B, N) each disc's path length (0: the emitter)."""
    P, B, M = zk.shape
    first = np.full(B, P, np.int64)
    if not len(cand):
        return first
    e, i, j = cand.env, cand.i, cand.j
    reach = tr[e, i] + tr[e, j]
    near = np.flatnonzero(((reach > 0) & (cand.dist < diam + reach)) | (cand.dist < diam - OVERLAP_TOL_MM))
    if not near.size:
        return first
    e, i, j = e.take(near), i.take(near), j.take(near)
    zf = zk.reshape(P, B * M)  # (take keeps the result C-ordered; fancy indexing here would not)
    zi = zf.take(e * M + i, axis=1)  # (P, K)
    if zb is None:
        zj = zf.take(e * M + j, axis=1)
    else:
        emitter = j == M
        zj = zf.take(e * M + np.minimum(j, M - 1), axis=1)
        zj[:, emitter] = zb[e[emitter]]  # the emitter stays put unless pushed
    touch = np.abs(zi - zj) < diam - OVERLAP_TOL_MM  # (P, K)
    hit = touch.any(axis=0).nonzero()[0]
    if hit.size:
        np.minimum.at(first, e.take(hit), touch.take(hit, axis=1).argmax(axis=0))
    return first


def _per_tick(zk: np.ndarray, zb: np.ndarray | None, z0: np.ndarray, disp: np.ndarray, straight: np.ndarray,
              t: np.ndarray, s: np.ndarray, leg: bool, k0: np.ndarray, cfg: WorldConfig, collider: Collider | None,
              mobility: np.ndarray | None, target_record: np.ndarray | None, start: np.ndarray | None,
              cand: grid.Pairs | None) -> None:
    """Re-run the envs with ``k0[e] < P`` tick by tick from their tick k0[e]: move, walls, resolve
    collisions (loose inside the period, strict at the env's last moving tick). Updates zk and zb.
    ``start`` (B, N): the discs at the period start, ``cand`` the pairs within 2r + skin there (or
    farther): the contact lists are built from them.

    A tick's move: ``straight`` (P, B, M) increments, or (B, M) the step of every straight tick,
    when pivots turn about the centre; with ``leg`` pivots, the increments of the unclipped
    closed-form path ``disp`` (P, B, M)."""
    P, B, M = zk.shape
    sel = (k0 < P).nonzero()[0]
    Bs = sel.size
    ks = k0.take(sel)  # (Bs,) tick at which each env leaves its closed form
    kmin = int(ks.min())
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    N = M + (zb is not None)
    zs = np.empty((Bs, N), np.complex128)
    zs[:, :M] = (z0 if kmin == 0 else zk[kmin - 1]).take(sel, axis=0)
    if zb is not None:
        zs[:, M] = zb[sel]
    ticks = np.arange(P)[:, None]
    ts, ss = t[sel], s[sel]
    go = ticks[..., None] < ts + ss  # (P, Bs, M) robots moving at tick k
    if leg:
        d = disp.take(sel, axis=1)
        inc_s = np.empty_like(d)
        inc_s[0] = d[0]
        np.subtract(d[1:], d[:-1], out=inc_s[1:])
    else:
        go &= ticks[..., None] >= ts
        inc_s = straight.take(sel, axis=1) if straight.ndim == 3 else go * straight.take(sel, axis=0)
    moving_env = go.any(axis=2)  # (P, Bs)
    last = np.where(moving_env.any(axis=0), P - np.argmax(moving_env[::-1], axis=0), 0)  # (Bs,) last moving tick + 1
    last = np.maximum(last, ks + 1)  # an env with contacts resolves strictly at least once
    k_end = int(last.max())
    moving = moving_env.any(axis=1).tolist()
    later = (ks > kmin).nonzero()[0]  # envs joining after the first
    starts = {k: later[ks.take(later) == k] for k in set(ks.take(later).tolist())}
    if collider is not None:
        loc = np.full(B, -1)
        loc[sel] = np.arange(Bs)
        le = loc.take(cand.env)
        near = np.flatnonzero((le >= 0) & (cand.dist <= collider.diam + collider.skin))
        contacts = _Contacts(start.take(sel, axis=0).reshape(-1), Bs, N, cfg, collider.skin,
                             None if zb is None else mobility[sel],
                             (le.take(near), cand.i.take(near), cand.j.take(near)))
        diam = collider.diam
        strict = ticks == last - 1
        active = (moving_env | strict) & (ticks >= ks)  # (P, Bs) envs resolving at tick k
        limit = np.where(active, np.where(strict, diam - OVERLAP_TOL_MM, diam - TICK_OVERLAP_TOL_MM), -1.0)
        resolving = active.any(axis=1).tolist()
        loose = ~strict
    flat = zs.reshape(-1)
    zsf = flat.view(np.float64)
    body = zs[:, :M]
    rec = np.empty((k_end - kmin, Bs, N), np.complex128)
    for k in range(kmin, k_end):  # loop over ticks; everything inside is vectorised over (envs, robots)
        if k in starts:  # envs joining now start from their closed-form positions
            j = starts[k]
            body[j] = zk[k - 1, sel.take(j)]
        if moving[k]:
            body += inc_s[k]
            np.minimum(zsf, lim, out=zsf)
            np.maximum(zsf, -lim, out=zsf)
        if collider is not None and resolving[k]:
            contacts.relax(flat, limit[k], loose[k], TICK_SWEEPS)
        rec[k - kmin] = zs
    own = rec[..., :M]  # an env's own ticks; before an env's first tick its closed form stays
    if later.size:
        mine = (np.arange(kmin, k_end)[:, None] >= ks)[..., None]  # (ticks, Bs, 1)
        own = np.where(mine, own, zk[kmin:k_end].take(sel, axis=1))
    if Bs == B:
        zk[kmin:k_end] = own
        zk[k_end:] = body
    else:
        zk[kmin:k_end, sel] = own
        zk[k_end:, sel] = body
    if zb is not None:
        if target_record is not None:  # the emitter rests until the first contact
            bz = np.concatenate([np.broadcast_to(zb[sel], (kmin, Bs)), rec[..., M],
                                 np.broadcast_to(zs[:, M], (P - k_end, Bs))])
            target_record[...] = np.stack([zb.real, zb.imag], -1)[None]
            target_record[:, sel, 0], target_record[:, sel, 1] = bz.real, bz.imag
        zb[sel] = zs[:, M]
