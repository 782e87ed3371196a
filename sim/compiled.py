"""Two hot loops of the kilobot world compiled with Numba, bit-identical to their NumPy versions.

* :func:`period_contacts`: the collision part of :func:`sim.kinematics.tick_move` after the closed-form
  paths: which pairs can touch, each env's first contact (``_first_contacts``), and the per-tick loop of
  the envs that have one (``_per_tick``: move, walls, over-relaxed Jacobi sweeps of
  :class:`sim.kinematics._Contacts`). In NumPy the loop is a Python loop over ticks and sweeps on arrays
  of a few dozen discs, so interpreter overhead is most of its cost. Here it runs env by env in machine code.
* :func:`radio_messages`: who hears whom at which tick in :func:`sim.radio.tick_radio` (before loss and
  noise, which stay with the envs' NumPy generators), without the ordered pair search and its sort.

Both compute exactly what the NumPy code does, float operation for float operation:

* envs are independent in the NumPy code (every decision is per env, pushes only touch an env's own
  discs), so one env after the other gives the same numbers;
* a sweep measures every pair of the env's list at the sweep's start, then adds all i-pushes in pair
  order, then subtracts all j-pushes (as ``np.add.at`` then ``np.subtract.at`` do), then clips;
* complex products with a real factor are two real products (exact either way); distances between
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


@functools.lru_cache(maxsize=1)
def _checked():
    """The kernels when Numba is there and their |z| is NumPy's here, else None."""
    k = _compiled()
    if k is None:
        return None
    try:
        same = _cabs_matches_numpy(k.cabs_many)
    except Exception as e:  # compilation failed on this machine: the NumPy code runs
        _problem.append(f"numba cannot compile the kernels here ({type(e).__name__}: {e})")
        return None
    if not same:
        _problem.append("NumPy computes |z| differently on this machine, so compiled code would not be bit-identical")
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
    k = _kernels()
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


def period_contacts(zk, z0, zb, travel, leg, disp, inc, e, t, s, mobility, target_record, diam, skin, lim, margin,
                    omega, tol_end, tol_tick, cap, max_iters) -> bool:
    """The collision part of :func:`sim.kinematics.tick_move` after the closed-form paths, compiled: first
    contacts, then the per-tick loop of the envs that have one, written into ``zk`` (P, B, M), ``zb`` (B,)
    and ``target_record`` (P, B, 2) in place. ``inc`` (P, B, M) the per-tick steps of curved runs, else
    ``e`` (B, M) the step of every straight tick. Returns whether any env had a contact (when none,
    ``target_record`` is not written)."""
    kernel = _need().period_contacts
    assert zk.flags.c_contiguous and zk.dtype == np.complex128, "zk must be C-contiguous complex128 (written in place)"
    has_beacon = zb is not None
    want = has_beacon and target_record is not None
    if want:
        assert target_record.flags.c_contiguous and target_record.dtype == np.float64
    c0 = np.zeros(1, np.complex128)
    return bool(kernel(
        zk, np.ascontiguousarray(z0), zb if has_beacon else c0, has_beacon, np.ascontiguousarray(travel, np.float64),
        bool(leg), np.ascontiguousarray(disp), np.ascontiguousarray(inc) if inc is not None else np.zeros((1, 1, 1), np.complex128),
        inc is not None, np.ascontiguousarray(e, np.complex128) if e is not None else np.zeros((1, 1), np.complex128),
        np.ascontiguousarray(t, np.int64), np.ascontiguousarray(s, np.int64),
        np.ascontiguousarray(mobility, np.float64) if has_beacon else np.zeros(1),
        target_record if want else np.zeros((1, 1, 2)), want,
        float(skin), float(diam), float(diam - tol_end), float(diam - tol_tick), float(diam + skin), float(lim),
        float(diam + margin), float(0.5 * omega), float((diam + skin) * (diam + skin)), int(cap), int(max_iters)))
