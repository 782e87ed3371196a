"""The per-tick contact loop of :func:`sim.kinematics.tick_move`, compiled with Numba, bit-identical.

:func:`sim.kinematics._per_tick` re-runs the envs in which discs touch tick by tick: move, walls,
over-relaxed Jacobi sweeps (:class:`sim.kinematics._Contacts`). In NumPy that is a Python loop over
ticks and sweeps on arrays of a few dozen discs, so interpreter overhead is most of its cost (about
half of an env step at 32 robots). :func:`tick_loop` runs the same loop env by env in machine code.

It computes exactly what the NumPy loop does, float operation for float operation:

* envs are independent in the NumPy loop (every decision is per env, pushes only touch an env's own
  discs), so one env after the other gives the same numbers;
* a sweep measures every pair of the env's list at the sweep's start, then adds all i-pushes in pair
  order, then subtracts all j-pushes (as ``np.add.at`` then ``np.subtract.at`` do), then clips;
* complex products with a real factor are two real products (exact either way); distances are
  :func:`cabs`, NumPy's own formula for ``np.abs`` of a complex number on this machine, which is
  checked against ``np.abs`` before the kernel is used (:func:`available`): where NumPy computes it
  differently (another CPU, another NumPy) the kernel is not used and the NumPy loop runs;
* rebuilt pair lists use :mod:`sim.grid`'s test ``dx * dx + dy * dy <= r * r`` and its (i, j) order;
  the first list of a period is the one the NumPy code builds, passed in.

``tests/test_sim_contacts_jit.py`` compares whole episodes of both paths with ``assert_array_equal``.
Numba is optional (``pip install kiloforge[fast]``); without it, or with ``KILOFORGE_JIT=0`` in the
environment, the NumPy loop runs. The first call in a process compiles (cached on disk afterwards).
"""
from __future__ import annotations

import functools
import os

import numpy as np

ENV_SWITCH = "KILOFORGE_JIT"  #: "0" turns the compiled loop off (the NumPy loop runs)


@functools.lru_cache(maxsize=1)
def _compiled():
    """The compiled kernels (:mod:`sim.contacts_kernel`), or None when Numba is missing."""
    try:
        from . import contacts_kernel
    except ImportError:
        return None
    return contacts_kernel


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
    c = _compiled()
    if c is None or not _cabs_matches_numpy(c.cabs_many):
        return None
    return c.tick_loop


def available() -> bool:
    """Whether the compiled loop runs: Numba importable, ``KILOFORGE_JIT`` not 0, and its distance
    formula bit-identical to NumPy's on this machine."""
    return _kernel() is not None


def _kernel():
    if os.environ.get(ENV_SWITCH, "").strip() == "0":
        return None
    return _checked()


def why_not() -> str:
    """One line: why the compiled loop does not run here ('' when it does)."""
    if os.environ.get(ENV_SWITCH, "").strip() == "0":
        return f"{ENV_SWITCH}=0 in the environment"
    if _compiled() is None:
        return "numba is not installed (pip install 'kiloforge[fast]')"
    if _checked() is None:
        return "NumPy computes |z| differently on this machine, so the compiled loop would not be bit-identical"
    return ""


def tick_loop(zk, z0, zb, sel, inc, moving, limit, loose, ks, kmin, k_end, ptr, pi, pj, built0, mobility,
              lim, target, gain, skin, r2, cap, max_iters):
    """Run the compiled loop (arguments as :func:`sim.kinematics._per_tick` computes them; ``gain`` is
    0.5 x RELAX_OMEGA, ``r2`` the squared rebuild radius); returns (rec (k_end - kmin, Bs, N), zs (Bs, N)) complex128."""
    kernel = _kernel()
    assert kernel is not None, why_not()
    Bs = sel.size
    has_beacon = zb is not None
    N = zk.shape[2] + has_beacon
    rec = np.empty((k_end - kmin, Bs, N), np.complex128)
    zs = np.empty((Bs, N), np.complex128)
    zb_arr = zb if has_beacon else np.zeros(1, np.complex128)
    mob = mobility if has_beacon else np.zeros(1)
    kernel(np.ascontiguousarray(zk), np.ascontiguousarray(z0), zb_arr, sel.astype(np.int64), np.ascontiguousarray(inc),
           moving, limit, loose, ks.astype(np.int64), int(kmin), int(k_end), ptr, pi, pj, built0, mob, has_beacon,
           float(lim), float(target), float(gain), float(skin), float(r2), int(cap), int(max_iters), zs, rec)
    return rec, zs
