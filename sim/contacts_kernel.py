"""Numba kernels of :mod:`sim.contacts_jit` (imported only when the compiled contact loop is used).

Kept apart so that importing the simulator never imports Numba, and at module level so that Numba
caches the compiled code on disk (a first use compiles for a few seconds; later processes load it).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c with one rounding (llvm.fma; Numba's math module has no fma)."""
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        f = builder.module.declare_intrinsic("llvm.fma", [d], ir.FunctionType(d, [d, d, d]))
        return builder.call(f, args)

    return sig, codegen


jit = numba.njit(cache=True)


@jit
def cabs(x, y):
    """|x + iy| as NumPy's SIMD loop computes it: larger · sqrt(fma(r, r, 1)), r = smaller / larger."""
    re, im = abs(x), abs(y)
    hi, lo = max(re, im), min(re, im)
    if hi == 0.0:
        return 0.0
    r = lo / hi
    return math.sqrt(fma(r, r, 1.0)) * hi


@jit
def cabs_many(z, out):
    for k in range(z.size):
        out[k] = cabs(z[k].real, z[k].imag)


@jit
def walls(x, y, N, lim):
    """Clip every disc of the env to [-lim, lim]² (np.minimum, then np.maximum)."""
    for i in range(N):
        x[i] = max(min(x[i], lim), -lim)
        y[i] = max(min(y[i], lim), -lim)


@jit
def shares(fj, n, N, has_beacon, m_env, wi, wj):
    """Push shares of an env's n pairs (relative to an equal share), as _Contacts._shares."""
    for p in range(n):
        m = m_env if (has_beacon and fj[p] == N - 1) else 1.0
        wi[p] = 2.0 / (1.0 + m)
        wj[p] = 2.0 * m / (1.0 + m)


@jit
def rebuild(x, y, N, r2, fi, fj):
    """Pairs i < j with dx * dx + dy * dy <= r2, in (i, j) order (sim.grid's test); returns their number."""
    n = 0
    for i in range(N):
        for j in range(i + 1, N):
            dx = x[i] - x[j]
            dy = y[i] - y[j]
            if dx * dx + dy * dy <= r2:
                fi[n] = i
                fj[n] = j
                n += 1
    return n


@jit
def sweeps(x, y, N, n, fi, fj, wi, wj, has_beacon, limit, capped, cap, target, gain, lim, hit, hx, hy, hd,
           max_iters):
    """sim.kinematics._Contacts._sweeps for one env."""
    for sweep in range(max_iters):
        if sweep == cap and capped:
            return
        nh = 0
        for p in range(n):
            dx = x[fi[p]] - x[fj[p]]
            dy = y[fi[p]] - y[fj[p]]
            d = cabs(dx, dy)
            if d < limit:
                hit[nh] = p
                hx[nh] = dx
                hy[nh] = dy
                hd[nh] = d
                nh += 1
        if nh == 0:
            return
        for h in range(nh):  # each disc's equal share of the push
            f = (target - hd[h]) * gain / max(hd[h], 1e-300)
            hx[h] = (hx[h] + 1e-300) * f
            hy[h] = (hy[h] + 0.0) * f
        for h in range(nh):
            p = hit[h]
            if has_beacon:
                x[fi[p]] += hx[h] * wi[p]
                y[fi[p]] += hy[h] * wi[p]
            else:
                x[fi[p]] += hx[h]
                y[fi[p]] += hy[h]
        for h in range(nh):
            p = hit[h]
            if has_beacon:
                x[fj[p]] -= hx[h] * wj[p]
                y[fj[p]] -= hy[h] * wj[p]
            else:
                x[fj[p]] -= hx[h]
                y[fj[p]] -= hy[h]
        walls(x, y, N, lim)


@jit
def tick_loop(zk, z0, zb, sel, inc, moving, limit, loose, ks, kmin, k_end, ptr, pi, pj, built0, mobility,
              has_beacon, lim, target, gain, skin, r2, cap, max_iters, zs, rec):
    """The tick loop of _per_tick for the envs ``sel``; fills rec (k_end - kmin, Bs, N) and zs (Bs, N)."""
    P, B, M = zk.shape
    N = M + 1 if has_beacon else M
    maxp = max(1, N * (N - 1) // 2)
    fi = np.empty(maxp, np.int64)
    fj = np.empty(maxp, np.int64)
    wi = np.empty(maxp)
    wj = np.empty(maxp)
    hit = np.empty(maxp, np.int64)
    hx = np.empty(maxp)
    hy = np.empty(maxp)
    hd = np.empty(maxp)
    x = np.empty(N)
    y = np.empty(N)
    bx = np.empty(N)
    by = np.empty(N)
    half_skin = 0.5 * skin
    for e in range(sel.size):
        b = sel[e]
        k_s = ks[e]
        for i in range(M):
            z = z0[b, i] if k_s == 0 else zk[k_s - 1, b, i]
            x[i] = z.real
            y[i] = z.imag
        if has_beacon:
            x[M] = zb[b].real
            y[M] = zb[b].imag
        for k in range(kmin, k_s):  # before the env's first contact: its closed form, the beacon at rest
            for i in range(M):
                rec[k - kmin, e, i] = zk[k, b, i]
            if has_beacon:
                rec[k - kmin, e, M] = zb[b]
        n = ptr[e + 1] - ptr[e]
        for p in range(n):
            fi[p] = pi[ptr[e] + p]
            fj[p] = pj[ptr[e] + p]
        m_env = mobility[e] if has_beacon else 1.0
        shares(fj, n, N, has_beacon, m_env, wi, wj)
        for i in range(N):
            bx[i] = built0[e, i].real
            by[i] = built0[e, i].imag
        for k in range(k_s, k_end):
            if moving[k]:
                for i in range(M):
                    x[i] += inc[k, e, i].real
                    y[i] += inc[k, e, i].imag
                walls(x, y, N, lim)
            lm = limit[k, e]
            if lm > 0:  # _Contacts.relax: sweep, then rebuild and sweep again while discs left the skin
                capped = loose[k, e]
                sweeps(x, y, N, n, fi, fj, wi, wj, has_beacon, lm, capped, cap, target, gain, lim, hit, hx, hy, hd,
                       max_iters)
                while True:
                    moved = 0.0
                    for i in range(N):
                        moved = max(moved, cabs(x[i] - bx[i], y[i] - by[i]))
                    if moved <= half_skin:
                        break
                    n = rebuild(x, y, N, r2, fi, fj)
                    shares(fj, n, N, has_beacon, m_env, wi, wj)
                    for i in range(N):
                        bx[i] = x[i]
                        by[i] = y[i]
                    sweeps(x, y, N, n, fi, fj, wi, wj, has_beacon, lm, capped, cap, target, gain, lim, hit, hx, hy,
                           hd, max_iters)
            for i in range(N):
                rec[k - kmin, e, i] = complex(x[i], y[i])
        for i in range(N):
            zs[e, i] = complex(x[i], y[i])
