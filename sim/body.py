"""A heavy body that robots push together: quasi-static pushing against static friction.

A world with ``body_radius_mm > 0`` (the transport task's) mounts its emitter on a disc of that
radius, centred on the emitter (``env.target``). Robots move through their period as if the body were
not there (:mod:`sim.kinematics`; the body takes no part in the per-tick contacts); then, once per
control period, :func:`push_body` settles the contacts:

1. **Pushes.** A robot whose disc overlaps the body by at least ``PRESS_FRAC · d_full`` (``d_full = v_max · ΔT``,
   the depth of a whole period driven straight at it) presses on it: one full push along the contact normal
   ``n_i`` (from the robot's centre to the body's). Robots pushing robots that push the body add nothing (only
   contacts with the body count).
2. **Friction.** With ``F = Σ n_i`` over the pressing robots and the static friction ``μ = body_friction``: if
   ``|F| <= μ`` the body stays. Otherwise it moves by ``(1 - μ / |F|)`` times their mean penetration ``mean(d_i n_i)``
   (``d_i`` a robot's overlap): a linear force-speed motor model, so k aligned robots pushing at full speed
   move the body at ``(1 - μ / k)`` of their speed. k - 1 robots (``|F| <= k - 1``) never move a body with
   ``μ >= k - 1``; k robots pushing the same way move it once ``μ < k``. The body's centre stays
   ``body_radius_mm`` inside the walls.
3. **Hold-off.** Every robot overlapping the body is put back on its rim along the normal (the body
   acts as a wall), robot pairs are separated (:meth:`sim.kinematics.Collider.resolve`), and the two
   repeat until nothing overlaps. Where robots end jammed between the body and a wall the body
   returns to where it was this period and the hold-off runs again.

All of it is batched over (B, M), computed only in the envs where a robot touches the body.
"""
from __future__ import annotations

import numpy as np

from .config import WorldConfig
from .kinematics import OVERLAP_TOL_MM, RELAX_MARGIN_MM, Collider

HOLD_ROUNDS = 12  #: rim projection / robot separation rounds per hold-off at most
PRESS_FRAC = 0.1  #: a robot presses on the body (a full push) when it drove this share of a period's travel into it
JAM_TOL_MM = 0.5  #: a robot still this deep in the body after the rounds is jammed: the body's move is undone


def body_depth(pos: np.ndarray, body: np.ndarray, cfg: WorldConfig) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's overlap with the body (B, M) mm (0 where apart) and the unit normals (B, M, 2) from
    the robot's centre towards the body's."""
    d = body[:, None, :] - pos  # (B, M, 2)
    dist = np.hypot(d[..., 0], d[..., 1])
    depth = np.maximum(cfg.body_radius_mm + cfg.robot_radius_mm - dist, 0.0)
    return depth, d / np.maximum(dist, 1e-12)[..., None]


def body_move(depth: np.ndarray, normal: np.ndarray, cfg: WorldConfig) -> np.ndarray:
    """(B, 2) the body's quasi-static move from the robots' overlaps ``depth`` (B, M) and normals (module doc,
    steps 1 and 2)."""
    f = (depth >= PRESS_FRAC * cfg.v_max_mm_s * cfg.control_period_s).astype(np.float64)  # (B, M) pressing robots
    force = np.einsum("bm,bmk->bk", f, normal)
    mag = np.hypot(force[:, 0], force[:, 1])
    mean_push = np.einsum("bm,bmk->bk", f * depth, normal) / np.maximum(f.sum(axis=1), 1e-12)[:, None]
    excess = np.where(mag > cfg.body_friction, 1.0 - cfg.body_friction / np.maximum(mag, 1e-12), 0.0)
    return excess[:, None] * mean_push


def _hold_off(pos: np.ndarray, body: np.ndarray, cfg: WorldConfig, collider: Collider) -> np.ndarray:
    """Put robots overlapping the body on its rim and separate robot pairs, in rounds (module doc, step 3);
    returns each env's deepest remaining overlap (B,)."""
    lim = cfg.arena_half_mm - cfg.robot_radius_mm
    rim = cfg.body_radius_mm + cfg.robot_radius_mm + RELAX_MARGIN_MM
    for _ in range(HOLD_ROUNDS):
        depth, normal = body_depth(pos, body, cfg)
        inside = depth > 0
        pos[...] = np.where(inside[..., None], body[:, None, :] - normal * rim, pos)
        np.clip(pos, -lim, lim, out=pos)
        if collider.resolve(pos, None) == 0:
            break
    return body_depth(pos, body, cfg)[0].max(axis=1, initial=0.0)


def push_body(pos: np.ndarray, body: np.ndarray, cfg: WorldConfig, collider: Collider) -> None:
    """Settle one period's robot-body contacts in place: ``pos`` (B, M, 2) the robots after their moves,
    ``body`` (B, 2) its centre (the emitter's position), moved when the pushes beat the friction."""
    depth, normal = body_depth(pos, body, cfg)
    sel = np.flatnonzero((depth > OVERLAP_TOL_MM).any(axis=1))
    if not sel.size:
        return
    p, b0 = pos[sel], body[sel]
    lim = cfg.arena_half_mm - cfg.body_radius_mm
    b = np.clip(b0 + body_move(depth[sel], normal[sel], cfg), -lim, lim)
    jammed = _hold_off(p, b, cfg, collider) > JAM_TOL_MM
    if jammed.any():  # the body pressed a robot into a wall: it stays where it was
        j = np.flatnonzero(jammed)
        pj = pos[sel[j]]
        _hold_off(pj, b0[j], cfg, collider)
        p[j], b[j] = pj, b0[j]
    pos[sel], body[sel] = p, b
