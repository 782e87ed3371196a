"""The hot loops of the kilobot world compiled with Numba, bit-identical to their NumPy versions.

* :func:`command_bytes`: the env's check of float actions and their uint8 motor commands, in one pass.
* :func:`motor_schedule`: the motor schedule of the uint8 commands and the headings after the pivots, in one pass.
* :func:`closed_form`: the collision-free part of :func:`sim.kinematics.tick_move` for straight runs: every
  tick's displacement (straight ticks and arcs about the pivot legs), the path clipped to the walls, the
  path lengths. The complex exponentials stay NumPy's (they are computed before, once per robot and period).
* :func:`period_contacts`: the collision part of :func:`sim.kinematics.tick_move` after the closed-form
  paths: which pairs can touch, each env's first contact (``_first_contacts``), and the per-tick loop of
  the envs that have one (``_per_tick``: move, walls, over-relaxed Jacobi sweeps of
  :class:`sim.kinematics._Contacts`). In NumPy the loop is a Python loop over ticks and sweeps on arrays
  of a few dozen discs, so interpreter overhead is most of its cost. Here it runs env by env in machine code.
* :func:`straight_period`: :func:`closed_form` then :func:`period_contacts` in one call, writing the period's
  end back into the env's arrays.
* :func:`radio_messages`: who hears whom at which tick in :func:`sim.radio.tick_radio` (before loss and
  noise, which stay with the envs' NumPy generators), without the ordered pair search and its sort.
* :func:`radio_receive`: the received messages of :func:`sim.radio.tick_radio` after the envs' draws, measured and
  split by sender role.
* :func:`target_distance`: the robots' distances to the emitter.
* :func:`wall_light`: the light readings of worlds with plain wall light (who is near a wall, dropouts).
* :func:`observe_messages`: the message part of :func:`sim.radio.observe_fast` (the wall, the emitter's distance, the neighbour
  tables: one entry per sender, the table's overflow, the sensing-neighbour flag and the RBF sums), one receiver
  after the other instead of NumPy passes over all messages; distances in integer mm, so ψ comes from a table
  NumPy computed.

Both compute exactly what the NumPy code does, float operation for float operation:

* envs are independent in the NumPy code (every decision is per env, pushes only touch an env's own
  discs), so one env after the other gives the same numbers;
* a sweep measures every pair of the env's list at the sweep's start, then adds all i-pushes in pair
  order, then subtracts all j-pushes (as ``np.add.at`` then ``np.subtract.at`` do), then clips;
* complex products with a real factor are two real products (exact either way); complex × complex is
  :func:`sim.compiled_kernels.cmul`, NumPy's formula (two fused multiply-adds), checked like ``np.abs``; distances between
  complex positions are :func:`sim.compiled_kernels.cabs`, NumPy's own formula for ``np.abs`` of a
  complex number on this machine, which is checked against ``np.abs`` before anything compiled runs
  (:func:`available`): where NumPy computes it differently (another CPU, another NumPy) the NumPy code
  runs; pair distances are ``sqrt(dx * dx + dy * dy)`` as :mod:`sim.grid` computes them;
* rebuilt pair lists and radio candidates use :mod:`sim.grid`'s test ``dx * dx + dy * dy <= r * r``,
  its (i, j) order and the NumPy path's conservative candidate filters; the first contact list of a
  period is the one the NumPy code builds, passed in.

``tests/test_sim_compiled.py`` compares whole episodes of both paths with ``assert_array_equal``.
Numba is optional (``pip install kiloforge[fast]``); without it, or with ``KILOFORGE_JIT=0`` in the
environment, the NumPy code runs. The first use in a process compiles (cached on disk afterwards).
"""
from __future__ import annotations

import functools
import os

import numpy as np

from .motion import SCHEDULE_SHIFT, schedule_constants

ENV_SWITCH = "KILOFORGE_JIT"  #: "0" turns the compiled code off (the NumPy code runs)


_problem: list[str] = []  #: why the kernels could not be loaded or checked (for why_not)


@functools.lru_cache(maxsize=1)
def _compiled():
    """The kernels (:mod:`sim.compiled_kernels`), or None when Numba is missing or does not load."""
    try:
        from . import compiled_kernels
    except ImportError:
        return None
    except Exception as e:  # a Numba that does not work here: the NumPy code runs
        _problem.append(f"numba does not load here ({type(e).__name__}: {e})")
        return None
    return compiled_kernels


def _cabs_matches_numpy(cabs_many) -> bool:
    """Whether :func:`cabs` gives ``np.abs``'s bits here (random and hard cases, every tail length)."""
    rng = np.random.default_rng(12345)
    n = 1 << 16
    scale = rng.choice([1e-6, 1e-3, 1.0, 33.0, 500.0], (2, n))
    z = rng.standard_normal(n) * scale[0] + 1j * rng.standard_normal(n) * scale[1]
    z[:8] = [0.0, 1j, 3.0, -0.0, 2 + 2j, -3 - 4j, 1e-300 + 5e-301j, 33.0 + 1e-12j]
    for size in list(range(1, 18)) + [n]:
        zz = np.ascontiguousarray(z[:size])
        out = np.empty(size)
        cabs_many(zz, out)
        if not np.array_equal(out, np.abs(zz)):
            return False
    return True


def _cmul_matches_numpy(cmul_many) -> bool:
    """Whether :func:`cmul` gives NumPy's complex products here, contiguous and broadcast as tick_move uses them
    (c (B, M) times rotations (T, B, M), in place)."""
    rng = np.random.default_rng(54321)
    for shape in [(1, 1, 1), (3, 1, 4), (31, 16, 4), (7, 50, 32), (1, 1, 1 << 14)] + [(2, 1, k) for k in range(1, 18)]:
        scale = rng.choice([1e-6, 1e-3, 1.0, 33.0, 500.0], (4,) + shape[1:])
        a = rng.standard_normal(shape[1:]) * scale[0] + 1j * rng.standard_normal(shape[1:]) * scale[1]
        b = rng.standard_normal(shape) * scale[2] + 1j * rng.standard_normal(shape) * scale[3]
        want = b.copy()
        np.multiply(a, want, out=want)
        got = np.empty(shape, np.complex128)
        cmul_many(np.ascontiguousarray(np.broadcast_to(a, shape)).ravel(), b.ravel(), got.ravel())
        if not np.array_equal(got, want):
            return False
    return True


@functools.lru_cache(maxsize=1)
def _checked():
    """The kernels when Numba is there and their |z| and complex products are NumPy's here, else None."""
    k = _compiled()
    if k is None:
        return None
    try:
        same = _cabs_matches_numpy(k.cabs_many), _cmul_matches_numpy(k.cmul_many)
    except Exception as e:  # compilation failed on this machine: the NumPy code runs
        _problem.append(f"numba cannot compile the kernels here ({type(e).__name__}: {e})")
        return None
    for ok, what in zip(same, ("|z|", "complex products")):
        if not ok:
            _problem.append(f"NumPy computes {what} differently on this machine, so compiled code would not be "
                            "bit-identical")
            return None
    return k


def _kernels():
    if os.environ.get(ENV_SWITCH, "").strip() == "0":
        return None
    return _checked()


def available() -> bool:
    """Whether the compiled code runs: Numba importable, ``KILOFORGE_JIT`` not 0, and its distance
    formula bit-identical to NumPy's on this machine."""
    return _kernels() is not None


def why_not() -> str:
    """One line: why the compiled code does not run here ('' when it does)."""
    if os.environ.get(ENV_SWITCH, "").strip() == "0":
        return f"{ENV_SWITCH}=0 in the environment"
    if _checked() is None:
        return _problem[-1] if _problem else "numba is not installed (pip install 'kiloforge[fast]')"
    return ""


def _need():
    """The kernels, for callers that asked :func:`available` (which reads ``KILOFORGE_JIT``) first."""
    k = _checked()
    assert k is not None, why_not()
    return k


#: the compiled radio considers every pair of an env (no grid): used up to this many transmitters
RADIO_MAX_N = 65


def radio_messages(pos_ticks, target, target_ticks, phases, tick0, periods, R):
    """:func:`sim.radio._messages`, compiled: (env, rx, snd, tick, true distance) of the period's
    messages in range in (env, receiver, sender, tick) order, and ``single``."""
    kernel = _need().radio_messages
    moves = target_ticks is not None
    tt = np.ascontiguousarray(target_ticks, np.float64) if moves else np.zeros((1, 1, 2))
    e, rx, snd, k, d, single = kernel(
        np.ascontiguousarray(pos_ticks, np.float64), np.ascontiguousarray(target, np.float64), tt, moves,
        np.ascontiguousarray(phases, np.int64), int(tick0), np.ascontiguousarray(periods, np.int64), float(R))
    return e, rx, snd, k, d, bool(single)


def target_distance(pos, target) -> np.ndarray:
    """:func:`sim.radio.target_distance`, compiled: (B, M) sqrt(dx² + dy²) from the robots (B, M, 2) to ``target``
    (B, 2)."""
    out = np.empty(pos.shape[:2])
    _need().target_distance(np.ascontiguousarray(pos, np.float64), np.ascontiguousarray(target, np.float64), out)
    return out


def wall_light(pos, a, sense_mm, floor, wall, u, dropout) -> np.ndarray:
    """:func:`sim.radio.light_readings` of worlds with even wall light and no sensor model, compiled: (B, M) int16,
    ``wall`` within ``sense_mm`` of a wall of the arena of half side ``a``, else ``floor``; -1 where the uniform ``u``
    (B, M) is below ``dropout`` (``u`` None: no dropout)."""
    pos = np.ascontiguousarray(pos, np.float64)
    out = np.empty(pos.shape[:2], np.int16)
    _need().wall_light(pos, float(a), float(sense_mm), int(floor), int(wall),
                       np.zeros((1, 1)) if u is None else u, u is not None, float(dropout), out)
    return out


def observe_messages(g, snd, tick, f, d, single, M, table_size, table, tg, t_dist, R, light, prev_wall, threshold,
                     held, obs, heard, wall_col, target_col, nbr_col, rbf_col) -> None:
    """The message part of :func:`sim.radio.observe_fast` and its wall feature (integer distances: ``table`` holds ψ of
    0..255), compiled: writes the wall column ``wall_col`` (light (B, M) at or above ``threshold``; where it dropped
    out and ``held``, ``prev_wall``), the emitter's column ``target_col``, the sensing-neighbour column ``nbr_col`` and
    the RBF sums from ``rbf_col`` (-1: not observed) into ``obs`` (B·M, obs_dim) float32, and who heard the emitter
    into ``heard`` (B·M,) uint8, in place."""
    assert obs.flags.c_contiguous and obs.dtype == np.float32, "obs must be C-contiguous float32 (written in place)"
    assert heard.dtype == np.uint8, "heard must be uint8 (written in place)"
    _need().observe_messages(g, snd, tick, f, d, bool(single), int(M), int(table_size), table, tg, t_dist, float(R),
                             np.ravel(light), np.ravel(prev_wall), int(threshold), bool(held), obs, heard,
                             int(wall_col), int(target_col), int(nbr_col), int(rbf_col))


def command_bytes(actions, shape, lo, hi) -> np.ndarray | None:
    """:func:`sim.motion.action_to_u8` of float64 actions of ``shape`` that all lie in [lo, hi] (the env's check, and
    its clip to [0, 1], which changes no command byte), compiled; None when the actions are anything else (NaN, out of
    range, another dtype or shape): the NumPy check then says what is wrong."""
    if not (type(actions) is np.ndarray and actions.dtype == np.float64 and actions.shape == shape
            and actions.flags.c_contiguous):
        return None
    q = np.empty(shape, np.uint8)
    return q if _need().command_bytes(actions, float(lo), float(hi), q) else None


def motor_schedule(q, heading, P, turn_left, turn_right):
    """:func:`sim.motion.schedule` and the pivots of :func:`sim.kinematics.tick_move`, compiled: (t, s, left, θ, φ_s,
    φ_0, any pivots) for uint8 commands ``q`` (B, M, 2); ``heading`` (B, M) C-contiguous float64 becomes
    wrap(φ_s) in place. ``turn_left`` / ``turn_right``: a left / right pivot tick's turn, scalar or (B, M)."""
    k_turn, k_straight = schedule_constants(P)
    shape = heading.shape
    ts, left, angles = np.empty((2,) + shape, np.int64), np.empty(shape, np.bool_), np.empty((3,) + shape)
    turned = _need().motor_schedule(np.ascontiguousarray(q), heading, int(P), k_turn, k_straight, SCHEDULE_SHIFT,
                                    _turn(turn_left), _turn(turn_right), ts[0], ts[1], left, angles[0], angles[1], angles[2])
    return ts[0], ts[1], left, angles[0], angles[1], angles[2], bool(turned)


def _turn(x) -> np.ndarray:
    """A pivot tick's turn, scalar or (B, M), as a C-contiguous float64 array ((1, 1) for a scalar)."""
    return np.full((1, 1), x, np.float64) if np.ndim(x) == 0 else np.ascontiguousarray(x, np.float64)


def radio_receive(e, rx, snd, k, d, u, z, loss_p, sigma, integer, lo, hi, flags, M):
    """What :func:`sim.radio.tick_radio` does after the loss and noise draws (``u``, ``z``: None when not drawn),
    compiled: the received messages, measured and split into the searchers' and the emitter's
    (s_env, s_rx, s_snd, s_tick, s_dist, s_flag, t_env, t_rx, t_tick, t_dist). ``loss_p``, ``sigma`` (B,): each env's
    loss probability and noise σ."""
    none = np.zeros(0)
    return _need().radio_receive(e, rx, snd, k, d, none if u is None else u, none if z is None else z, u is not None,
                                 z is not None, np.ascontiguousarray(loss_p, np.float64),
                                 np.ascontiguousarray(sigma, np.float64), bool(integer), float(lo), float(hi),
                                 np.ascontiguousarray(flags, np.uint8), int(M))


def _per_robot(x, B: int, M: int) -> np.ndarray:
    """A scalar or (B, M) value as a C-contiguous (B, M) float64 array."""
    if np.ndim(x) == 0:
        return np.full((B, M), x, np.float64)
    return np.ascontiguousarray(np.broadcast_to(np.asarray(x, np.float64), (B, M)))


def _closed_form_args(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel) -> tuple:
    B, M = t.shape
    for a in (zk, disp, travel):
        assert a.flags.c_contiguous, "closed_form writes zk, disp and travel in place: they must be C-contiguous"
    return (np.ascontiguousarray(z0), np.ascontiguousarray(t, np.int64), np.ascontiguousarray(s, np.int64),
            np.ascontiguousarray(left, np.bool_), np.ascontiguousarray(e, np.complex128), _per_robot(step, B, M),
            bool(leg), np.ascontiguousarray(c, np.complex128) if leg else np.zeros((1, 1), np.complex128),
            np.ascontiguousarray(table, np.complex128) if table is not None else np.zeros(1, np.complex128),
            np.ascontiguousarray(rot, np.complex128) if rot is not None else np.zeros((1, 1, 1), np.complex128),
            table is not None, _per_robot(R, B, M), np.ascontiguousarray(theta, np.float64), float(lim), zk, disp, travel)


def _contact_args(zb, mobility, target_record, diam, skin, margin, omega, tol_end, tol_tick, cap, max_iters) -> tuple:
    """period_contacts' kernel arguments from ``zb`` on, but ``lim``."""
    has_emitter = zb is not None
    want = has_emitter and target_record is not None
    if want:
        assert target_record.flags.c_contiguous and target_record.dtype == np.float64
    return (zb if has_emitter else np.zeros(1, np.complex128), has_emitter,
            np.ascontiguousarray(mobility, np.float64) if has_emitter else np.zeros(1),
            target_record if want else np.zeros((1, 1, 2)), want,
            float(skin), float(diam), float(diam - tol_end), float(diam - tol_tick), float(diam + skin),
            float(diam + margin), float(0.5 * omega), float((diam + skin) * (diam + skin)), int(cap), int(max_iters))


def closed_form(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel) -> None:
    """The collision-free path of :func:`sim.kinematics.tick_move` (straight runs, no curve), compiled: fills
    ``zk`` (P, B, M) (the clipped positions after each tick), ``disp`` (the unclipped displacements) and
    ``travel`` (B, M). With ``leg``: ``c`` the legs (B, M) and either ``table`` (exp(i j dphi), j = -P..P,
    nominal turn rates) or ``rot`` (T, B, M) their rotations."""
    _need().closed_form(*_closed_form_args(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel))


def period_contacts(zk, z0, zb, travel, leg, disp, inc, e, t, s, mobility, target_record, diam, skin, lim, margin,
                    omega, tol_end, tol_tick, cap, max_iters) -> bool:
    """The collision part of :func:`sim.kinematics.tick_move` after the closed-form paths, compiled: first
    contacts, then the per-tick loop of the envs that have one, written into ``zk`` (P, B, M), ``zb`` (B,)
    and ``target_record`` (P, B, 2) in place. ``inc`` (P, B, M) the per-tick steps of curved runs, else
    ``e`` (B, M) the step of every straight tick. Returns whether any env had a contact (when none,
    ``target_record`` is not written)."""
    assert zk.flags.c_contiguous and zk.dtype == np.complex128, "zk must be C-contiguous complex128 (written in place)"
    (zb, has_emitter, mobility, trec, want, skin, diam, lim_end, lim_tick, diam_skin, target, gain, r2, cap,
     max_iters) = _contact_args(zb, mobility, target_record, diam, skin, margin, omega, tol_end, tol_tick, cap, max_iters)
    return bool(_need().period_contacts(
        zk, np.ascontiguousarray(z0), zb, has_emitter, np.ascontiguousarray(travel, np.float64), bool(leg),
        np.ascontiguousarray(disp), np.ascontiguousarray(inc) if inc is not None else np.zeros((1, 1, 1), np.complex128),
        inc is not None, np.ascontiguousarray(e, np.complex128) if e is not None else np.zeros((1, 1), np.complex128),
        np.ascontiguousarray(t, np.int64), np.ascontiguousarray(s, np.int64), mobility, trec, want, skin, diam,
        lim_end, lim_tick, diam_skin, float(lim), target, gain, r2, cap, max_iters))


def straight_period(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel, zb, mobility,
                    target_record, diam, skin, margin, omega, tol_end, tol_tick, cap, max_iters, pos, emitter) -> None:
    """:func:`closed_form`, then :func:`period_contacts` (straight runs), in one call, and the period's end written
    back: the last positions into ``pos`` (B, M, 2), the emitter's into ``emitter`` (B, 2) (None: no emitter disc),
    both C-contiguous float64; ``target_record`` holds the emitter still where nothing touched it."""
    assert pos.flags.c_contiguous and pos.dtype == np.float64, "pos must be C-contiguous float64 (written in place)"
    if emitter is not None:
        assert emitter.flags.c_contiguous and emitter.dtype == np.float64, "the emitter must be C-contiguous float64"
    _need().straight_period(
        *_closed_form_args(z0, t, s, left, e, step, leg, c, table, rot, R, theta, lim, zk, disp, travel),
        *_contact_args(zb, mobility, target_record, diam, skin, margin, omega, tol_end, tol_tick, cap, max_iters),
        pos, np.zeros((1, 2)) if emitter is None else emitter)
