"""Numba kernels of :mod:`sim.compiled` (imported only when compiled code is used).

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
def shares(fj, n, N, has_emitter, m_env, wi, wj):
    """Push shares of an env's n pairs (relative to an equal share), as _Contacts._shares."""
    for p in range(n):
        m = m_env if (has_emitter and fj[p] == N - 1) else 1.0
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
def sweeps(x, y, N, n, fi, fj, wi, wj, limit, capped, cap, target, gain, lim, hit, hx, hy, hd, max_iters):
    """sim.kinematics._Contacts._sweeps for one env.

    A pair whose squared distance exceeds ``far2`` = limit² (1 + 1e-12) cannot be closer than ``limit``
    (both |dz| and dx² + dy² are within a few ulps of the exact values), so its exact distance, a
    division and a square root, is only computed for pairs near or below the limit."""
    far2 = limit * limit * (1.0 + 1e-12)
    for sweep in range(max_iters):
        if sweep == cap and capped:
            return
        nh = 0
        for p in range(n):
            dx = x[fi[p]] - x[fj[p]]
            dy = y[fi[p]] - y[fj[p]]
            if dx * dx + dy * dy > far2:  # surely |dz| >= limit: skip the exact distance
                continue
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
        for h in range(nh):  # shares are 1.0 without an emitter (shares()), and a product with 1.0 is exact
            p = hit[h]
            x[fi[p]] += hx[h] * wi[p]
            y[fi[p]] += hy[h] * wi[p]
        for h in range(nh):
            p = hit[h]
            x[fj[p]] -= hx[h] * wj[p]
            y[fj[p]] -= hy[h] * wj[p]
        walls(x, y, N, lim)


@jit
def tick_loop(zk, z0, zb, sel, inc, moving, limit, loose, ks, kmin, k_end, ptr, pi, pj, built0, mobility,
              has_emitter, lim, target, gain, skin, r2, cap, max_iters, zs, rec):
    """The tick loop of sim.kinematics._per_tick for the envs ``sel`` (arguments as _per_tick computes
    them); fills rec (k_end - kmin, Bs, N) and zs (Bs, N)."""
    P, B, M = zk.shape
    N = M + 1 if has_emitter else M
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
        if has_emitter:
            x[M] = zb[b].real
            y[M] = zb[b].imag
        for k in range(kmin, k_s):  # before the env's first contact: its closed form, the emitter at rest
            for i in range(M):
                rec[k - kmin, e, i] = zk[k, b, i]
            if has_emitter:
                rec[k - kmin, e, M] = zb[b]
        n = ptr[e + 1] - ptr[e]
        for p in range(n):
            fi[p] = pi[ptr[e] + p]
            fj[p] = pj[ptr[e] + p]
        m_env = mobility[e] if has_emitter else 1.0
        shares(fj, n, N, has_emitter, m_env, wi, wj)
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
                sweeps(x, y, N, n, fi, fj, wi, wj, lm, capped, cap, target, gain, lim, hit, hx, hy, hd, max_iters)
                while True:
                    moved = 0.0
                    for i in range(N):
                        moved = max(moved, cabs(x[i] - bx[i], y[i] - by[i]))
                    if moved <= half_skin:
                        break
                    n = rebuild(x, y, N, r2, fi, fj)
                    shares(fj, n, N, has_emitter, m_env, wi, wj)
                    for i in range(N):
                        bx[i] = x[i]
                        by[i] = y[i]
                    sweeps(x, y, N, n, fi, fj, wi, wj, lm, capped, cap, target, gain, lim, hit, hx, hy, hd, max_iters)
            for i in range(N):
                rec[k - kmin, e, i] = complex(x[i], y[i])
        for i in range(N):
            zs[e, i] = complex(x[i], y[i])


@jit
def radio_messages(pos, tgt, tgt_ticks, tgt_moves, phases, tick0, periods, R):
    """sim.radio._messages, compiled: the messages in range before loss and noise, in (env, receiver,
    sender, tick) order, as (env, rx, snd, tick, true distance) arrays, and whether no candidate sender
    sends twice (``single``). Candidates and distances use the NumPy path's formulas and filters."""
    P, B, M, _ = pos.shape
    N = M + 1
    reach = np.zeros((B, N))  # farthest each transmitter was from where it ends the period
    top = 0.0
    for b in range(B):
        for i in range(N):
            r = 0.0
            for t in range(P):
                if i < M:
                    dx, dy = pos[t, b, i, 0] - pos[P - 1, b, i, 0], pos[t, b, i, 1] - pos[P - 1, b, i, 1]
                elif tgt_moves:
                    dx, dy = tgt_ticks[t, b, 0] - tgt_ticks[P - 1, b, 0], tgt_ticks[t, b, 1] - tgt_ticks[P - 1, b, 1]
                else:
                    dx, dy = 0.0, 0.0
                r = max(r, cabs(dx, dy))
            reach[b, i] = r
            top = max(top, r)
    far_r = R * R * (1.0 + 1e-12)
    radius = R + 2.0 * top + 1e-3  # sim.grid.pairs_within's radius in the NumPy path
    r2 = radius * radius
    sends = P // max(1, periods.min()) + 1  # at most this many sends of one transmitter in a period
    cap = B * M * N * sends
    e_out, rx_out = np.empty(cap, np.int64), np.empty(cap, np.int64)
    snd_out, k_out = np.empty(cap, np.int64), np.empty(cap, np.int64)
    d_out = np.empty(cap)
    n = 0
    most = 0
    for b in range(B):
        for rx in range(M):
            xr, yr = pos[P - 1, b, rx, 0], pos[P - 1, b, rx, 1]
            for snd in range(N):
                if snd == rx:
                    continue
                if snd < M:
                    xs, ys = pos[P - 1, b, snd, 0], pos[P - 1, b, snd, 1]
                elif tgt_moves:
                    xs, ys = tgt_ticks[P - 1, b, 0], tgt_ticks[P - 1, b, 1]
                else:
                    xs, ys = tgt[b, 0], tgt[b, 1]
                if rx < snd:  # sim.grid measures an unordered pair from its lower index
                    dx, dy = xr - xs, yr - ys
                else:
                    dx, dy = xs - xr, ys - yr
                d2 = dx * dx + dy * dy
                if not d2 <= r2:
                    continue
                dist = math.sqrt(d2)
                ri, rj = reach[b, rx], reach[b, snd]
                if not dist <= R + ri + rj + 1e-3:
                    continue
                moved = ri > 0 or rj > 0
                T = periods[b, snd]
                k0 = (phases[b, snd] - tick0) % T
                nsend = (P - 1 - k0) // T + 1 if k0 < P else 0
                most = max(most, nsend)
                for r in range(nsend):
                    k = k0 + T * r
                    d = dist
                    if moved:
                        if snd < M:
                            xs, ys = pos[k, b, snd, 0], pos[k, b, snd, 1]
                        elif tgt_moves:
                            xs, ys = tgt_ticks[k, b, 0], tgt_ticks[k, b, 1]
                        else:
                            xs, ys = tgt[b, 0], tgt[b, 1]
                        dx, dy = pos[k, b, rx, 0] - xs, pos[k, b, rx, 1] - ys
                        if dx * dx + dy * dy > far_r:  # surely out of range (see sweeps)
                            continue
                        d = cabs(dx, dy)
                    if d <= R:
                        e_out[n] = b
                        rx_out[n] = rx
                        snd_out[n] = snd
                        k_out[n] = k
                        d_out[n] = d
                        n += 1
    return e_out[:n].copy(), rx_out[:n].copy(), snd_out[:n].copy(), k_out[:n].copy(), d_out[:n].copy(), most <= 1


@jit
def moves(k, turn, straight, leg):
    """Whether a robot with ``turn`` pivot ticks, then ``straight`` straight ticks moves its centre at tick k
    (pivots about a leg move it, pivots about the centre do not)."""
    return k < turn + straight and (leg or k >= turn)


@jit
def period_contacts(zk, z0, zb, has_emitter, travel, leg, disp, inc3, use_inc3, e2, t, s, mobility, trec, want_trec,
                    skin, diam, lim_end, lim_tick, diam_skin, lim, target, gain, r2_rebuild, cap, max_iters):
    """The collision part of sim.kinematics.tick_move after the closed-form paths ``zk`` (P, B, M): the pairs
    that can touch (sim.grid's test at the period start), each env's first contact (_first_contacts), and
    for the envs with one the tick loop (_per_tick: its set-up, tick_loop, the write-back into zk, zb and
    ``trec``). Returns whether any env had a contact (else ``trec`` is left to the caller)."""
    P, B, M = zk.shape
    N = M + 1 if has_emitter else M
    trmax = 0.0
    for b in range(B):
        for i in range(M):
            trmax = max(trmax, travel[b, i])
    reach = max(2.0 * trmax, skin)
    radius = diam + reach + 1e-9
    r2 = radius * radius
    far_end = lim_end * lim_end * (1.0 + 1e-12)
    maxp = max(1, N * (N - 1) // 2)
    k0 = np.full(B, P, np.int64)
    cnt = np.zeros(B, np.int64)  # contact-list pairs per env (within 2r + skin at the start)
    pi_all = np.empty((B, maxp), np.int64)
    pj_all = np.empty((B, maxp), np.int64)
    x = np.empty(N)
    y = np.empty(N)
    near_i = np.empty(maxp, np.int64)
    near_j = np.empty(maxp, np.int64)
    for b in range(B):
        n_near = 0
        for i in range(M):
            x[i] = z0[b, i].real
            y[i] = z0[b, i].imag
        if has_emitter:
            x[M] = zb[b].real
            y[M] = zb[b].imag
        for i in range(N):
            for j in range(i + 1, N):
                dx = x[i] - x[j]
                dy = y[i] - y[j]
                d2 = dx * dx + dy * dy
                if not d2 <= r2:
                    continue
                dist = math.sqrt(d2)
                if dist <= diam_skin:
                    pi_all[b, cnt[b]] = i
                    pj_all[b, cnt[b]] = j
                    cnt[b] += 1
                tri = travel[b, i] if i < M else 0.0
                trj = travel[b, j] if j < M else 0.0
                trij = tri + trj
                if (trij > 0 and dist < diam + trij) or dist < lim_end:  # may overlap during the period
                    near_i[n_near] = i
                    near_j[n_near] = j
                    n_near += 1
        for k in range(P):  # the env's first tick at which two paths overlap (tick by tick: zk[k, b] is contiguous)
            for p in range(n_near):
                i, j = near_i[p], near_j[p]
                zi = zk[k, b, i]
                zj = zk[k, b, j] if j < M else zb[b]
                dx, dy = zi.real - zj.real, zi.imag - zj.imag
                if dx * dx + dy * dy > far_end:  # surely apart (see sweeps): no exact distance needed
                    continue
                if cabs(dx, dy) < lim_end:
                    k0[b] = k
                    break
            if k0[b] < P:
                break
    sel = np.nonzero(k0 < P)[0]  # the envs with a contact
    Bs = sel.size
    if Bs == 0:
        return False
    ks = np.empty(Bs, np.int64)
    last = np.empty(Bs, np.int64)
    moving_env = np.zeros((P, Bs), np.bool_)
    for q in range(Bs):
        b = sel[q]
        ks[q] = k0[b]
        lst = 0
        for k in range(P):
            for i in range(M):
                if moves(k, t[b, i], s[b, i], leg):
                    moving_env[k, q] = True
                    lst = k + 1
                    break
        last[q] = max(lst, ks[q] + 1)  # an env with contacts resolves strictly at least once
    kmin = ks.min()
    k_end = last.max()
    moving = np.zeros(P, np.bool_)
    limit = np.empty((P, Bs))
    loose = np.empty((P, Bs), np.bool_)
    for k in range(P):
        for q in range(Bs):
            moving[k] = moving[k] or moving_env[k, q]
            strict = k == last[q] - 1
            active = (moving_env[k, q] or strict) and k >= ks[q]
            limit[k, q] = (lim_end if strict else lim_tick) if active else -1.0
            loose[k, q] = not strict
    inc = np.empty((P, Bs, M), np.complex128)
    for q in range(Bs):
        b = sel[q]
        for k in range(P):
            for i in range(M):
                if leg:
                    inc[k, q, i] = disp[k, b, i] if k == 0 else disp[k, b, i] - disp[k - 1, b, i]
                elif use_inc3:
                    inc[k, q, i] = inc3[k, b, i]
                elif moves(k, t[b, i], s[b, i], False):
                    inc[k, q, i] = e2[b, i]
                else:
                    inc[k, q, i] = 0.0
    ptr = np.zeros(Bs + 1, np.int64)
    for q in range(Bs):
        ptr[q + 1] = ptr[q] + cnt[sel[q]]
    pi = np.empty(ptr[Bs], np.int64)
    pj = np.empty(ptr[Bs], np.int64)
    built0 = np.empty((Bs, N), np.complex128)
    mob = np.empty(Bs)
    for q in range(Bs):
        b = sel[q]
        for p in range(cnt[b]):
            pi[ptr[q] + p] = pi_all[b, p]
            pj[ptr[q] + p] = pj_all[b, p]
        for i in range(M):
            built0[q, i] = z0[b, i]
        if has_emitter:
            built0[q, M] = zb[b]
            mob[q] = mobility[b]
    rec = np.empty((k_end - kmin, Bs, N), np.complex128)
    zs = np.empty((Bs, N), np.complex128)
    tick_loop(zk, z0, zb, sel, inc, moving, limit, loose, ks, kmin, k_end, ptr, pi, pj, built0, mob, has_emitter, lim,
              target, gain, skin, r2_rebuild, cap, max_iters, zs, rec)
    for q in range(Bs):  # _store_ticks
        b = sel[q]
        for k in range(kmin, k_end):
            for i in range(M):
                zk[k, b, i] = rec[k - kmin, q, i]
        for k in range(k_end, P):
            for i in range(M):
                zk[k, b, i] = zs[q, i]
    if has_emitter:
        if want_trec:
            for k in range(P):
                for b in range(B):
                    trec[k, b, 0] = zb[b].real
                    trec[k, b, 1] = zb[b].imag
            for q in range(Bs):
                b = sel[q]
                for k in range(kmin, P):
                    z = rec[k - kmin, q, M] if k < k_end else zs[q, M]
                    trec[k, b, 0] = z.real
                    trec[k, b, 1] = z.imag
        for q in range(Bs):
            zb[sel[q]] = zs[q, M]
    return True


@jit
def cmul(ar, ai, br, bi):
    """(ar + i ai)(br + i bi) as NumPy's SIMD loop computes it: re = fma(ar, br, -(ai bi)), im = fma(ar, bi, ai br)."""
    return fma(ar, br, -(ai * bi)), fma(ar, bi, ai * br)


@jit
def cmul_many(a, b, out):
    for k in range(a.size):
        re, im = cmul(a[k].real, a[k].imag, b[k].real, b[k].imag)
        out[k] = complex(re, im)


@jit
def closed_form(z0, t, s, left, e, step, leg, c, table, rot, use_table, R, theta, lim, zk, disp, travel):
    """The collision-free part of sim.kinematics.tick_move for straight runs (no curve): every tick's
    unclipped displacement ``disp`` (P, B, M) (straight ticks, plus the arcs about the pivot legs when ``leg``),
    the positions ``zk`` = z0 + disp clipped to the walls tick by tick (sim.kinematics._clip_path where a
    coordinate passes a wall, then the clip), and each robot's path length ``travel`` (B, M).
    ``c`` (B, M): c of _add_arcs; its rotations come from ``table`` (exp(i j dphi), j = -P..P) when
    ``use_table``, else from ``rot`` (T, B, M)."""
    P, B, M = zk.shape
    T = 0
    if leg:
        for b in range(B):
            for i in range(M):
                T = max(T, t[b, i])
    for b in range(B):
        for i in range(M):
            tb, sb = t[b, i], s[b, i]
            er, ei = e[b, i].real, e[b, i].imag
            cr, ci = c[b, i].real, c[b, i].imag
            sign = 1 if left[b, i] else -1
            ar = ai = 0.0
            for k in range(P):
                n = min(max(k + 1 - tb, 0), sb)
                dr = n * er
                di = n * ei
                if leg:
                    if k < T:  # the arc after min(k + 1, t) pivot ticks (kept after T: the whole arc)
                        m = min(k + 1, tb)
                        if use_table:
                            q = table[m * sign + P]
                        else:
                            q = rot[k, b, i]
                        rr, ri = cmul(cr, ci, q.real, q.imag)
                        ar, ai = cr - rr, ci - ri
                    dr += ar
                    di += ai
                disp[k, b, i] = complex(dr, di)
            tr = sb * step[b, i]
            if leg:
                tr = tr + tb * (R[b, i] * abs(theta[b, i]))
            travel[b, i] = tr
            x0, y0 = z0[b, i].real, z0[b, i].imag
            out = False
            for k in range(P):
                d = disp[k, b, i]
                if abs(x0 + d.real) > lim or abs(y0 + d.imag) > lim:
                    out = True
                    break
            # _clip_path (pivots may turn a coordinate back), only for robots that pass a wall
            hx = hy = -math.inf
            lx = ly = math.inf
            for k in range(P):
                d = disp[k, b, i]
                x, y = x0 + d.real, y0 + d.imag
                if leg and out:
                    hx, lx = max(hx, d.real), min(lx, d.real)
                    hy, ly = max(hy, d.imag), min(ly, d.imag)
                    x = min(x, lim - (max(hx, 0.0) - d.real))
                    x = max(x, (d.real - min(lx, 0.0)) - lim)
                    y = min(y, lim - (max(hy, 0.0) - d.imag))
                    y = max(y, (d.imag - min(ly, 0.0)) - lim)
                zk[k, b, i] = complex(max(min(x, lim), -lim), max(min(y, lim), -lim))


@jit
def observe_messages(g, snd, tick, f, d, single, M, table_size, table, tg, t_dist, R, light, prev_wall, threshold,
                     held, obs, heard, wall_col, target_col, nbr_col, rbf_col):
    """The message part of sim.radio.observe_fast for integer distances. The emitter: its latest message to each
    receiver of ``tg`` gives ``min(distance / R, 1)`` in column ``target_col`` of ``obs`` (B·M, obs_dim), -1 where none
    came, and ``heard``. The neighbour tables: per receiver ``g`` (non-decreasing, messages in (receiver, sender, tick)
    order) one entry per sender (its first tick and flag, its last distance), the table's first ``table_size``
    entries by (first tick, sender) when it overflows; they give the flag column ``nbr_col`` (any kept sender
    sensing) and the RBF sums from column ``rbf_col``, adding ``table`` rows (ψ of the integer distance) in
    sender order from 0. The wall column ``wall_col``: 1 where the light reading is at least ``threshold``, else 0;
    where the reading dropped out (-1) and ``held``, ``prev_wall``. A column -1 is not written."""
    if wall_col >= 0:
        for r in range(light.size):
            if held and light[r] < 0:
                obs[r, wall_col] = prev_wall[r]
            else:
                obs[r, wall_col] = 1.0 if light[r] >= threshold else 0.0
    tdist = np.zeros(heard.size)
    for j in range(tg.size):
        heard[tg[j]] = 1
        tdist[tg[j]] = t_dist[j]
    if target_col >= 0:
        for r in range(heard.size):
            obs[r, target_col] = min(tdist[r] / R, 1.0) if heard[r] else -1.0
    n = g.size
    nr = table.shape[1]
    eg = np.empty(n, np.int64)
    ek = np.empty(n, np.int64)  # (first tick, sender), the overflow order
    ef = np.empty(n, np.bool_)
    ed = np.empty(n, np.int64)
    m = 0
    i = 0
    while i < n:
        j = i
        if not single:
            while j + 1 < n and g[j + 1] == g[i] and snd[j + 1] == snd[i]:
                j += 1
        eg[m] = g[i]
        ek[m] = tick[i] * M + snd[i]
        ef[m] = f[i] > 0
        ed[m] = int(d[j])
        m += 1
        i = j + 1
    acc = np.empty(nr)
    a = 0
    while a < m:
        r = eg[a]
        b = a
        while b < m and eg[b] == r:
            b += 1
        full = b - a > table_size
        flag = False
        for c in range(nr):
            acc[c] = 0.0
        for x in range(a, b):
            if full:
                rank = 0
                for y in range(a, b):
                    if ek[y] < ek[x]:
                        rank += 1
                if rank >= table_size:
                    continue
            flag = flag or ef[x]
            for c in range(nr):
                acc[c] += table[ed[x], c]
        if nbr_col >= 0:
            obs[r, nbr_col] = 1.0 if flag else 0.0
        if rbf_col >= 0:
            for c in range(nr):
                obs[r, rbf_col + c] = acc[c]
        a = b


@jit
def motor_schedule(q, heading, P, k_turn, k_straight, shift, turn_left, turn_right, t, s, left, theta, phi_s, phi0):
    """sim.motion.schedule of the uint8 commands ``q`` (B, M, 2) (``shift`` fraction bits), then tick_move's pivots, into
    the (B, M) arrays given: per robot the pivot and straight ticks t, s, whether it pivots left, its turn per pivot tick θ
    (``turn_left``, or minus ``turn_right``; (B, M) or (1, 1)), the heading φ + t θ when the straight ticks start,
    and the heading before (``phi0``) and after wrapping to (-π, π] (written into ``heading``). Returns whether any
    robot pivots."""
    B, M = heading.shape
    half = 1 << (shift - 1)
    two_pi = 2.0 * math.pi
    lb, lm, rb, rm = turn_left.shape[0], turn_left.shape[1], turn_right.shape[0], turn_right.shape[1]
    turned = False
    for b in range(B):
        for i in range(M):
            ul, ur = np.int64(q[b, i, 0]), np.int64(q[b, i, 1])
            turn = min((abs(ul - ur) * k_turn + half) >> shift, P)
            straight = min(((ul + ur) * k_straight + half) >> shift, P - turn)
            lft = ul > ur
            th = turn_left[b % lb, i % lm] if lft else -turn_right[b % rb, i % rm]
            phi = heading[b, i]
            ps = phi + turn * th
            w = ps - two_pi * np.rint(ps / two_pi)
            if w <= -math.pi:
                w = w + two_pi
            t[b, i], s[b, i], left[b, i], theta[b, i] = turn, straight, lft, th
            phi_s[b, i], phi0[b, i], heading[b, i] = ps, phi, w
            turned = turned or turn > 0
    return turned


@jit
def radio_receive(e, rx, snd, k, d, u, z, loss, noise, loss_p, sigma, integer, lo, hi, flags, M):
    """The rest of sim.radio.tick_radio after the draws: drop the lost messages (uniform ``u`` below the env's
    ``loss_p``), measure the distance (true + σ z, rounded half up when ``integer``, clipped to [lo, hi]: sim.radio.measure)
    and split the messages into the searchers' (with the sender's flag) and the emitter's (sender M), in order."""
    n = e.size
    ok = np.empty(n, np.bool_)
    ns = nt = 0
    for j in range(n):
        ok[j] = not loss or u[j] >= loss_p[e[j]]
        if ok[j]:
            if snd[j] == M:
                nt += 1
            else:
                ns += 1
    s_env, s_rx, s_snd, s_tick = np.empty(ns, np.int64), np.empty(ns, np.int64), np.empty(ns, np.int64), np.empty(ns, np.int64)
    s_dist, s_flag = np.empty(ns), np.empty(ns, np.uint8)
    t_env, t_rx, t_tick, t_dist = np.empty(nt, np.int64), np.empty(nt, np.int64), np.empty(nt, np.int64), np.empty(nt)
    a = c = 0
    for j in range(n):
        if not ok[j]:
            continue
        dm = d[j]
        if noise:
            dm = dm + sigma[e[j]] * z[j]
        if integer:
            dm = np.floor(dm + 0.5)
        dm = min(max(dm, lo), hi)
        if snd[j] == M:
            t_env[c], t_rx[c], t_tick[c], t_dist[c] = e[j], rx[j], k[j], dm
            c += 1
        else:
            s_env[a], s_rx[a], s_snd[a], s_tick[a], s_dist[a] = e[j], rx[j], snd[j], k[j], dm
            s_flag[a] = flags[e[j], snd[j]]
            a += 1
    return s_env, s_rx, s_snd, s_tick, s_dist, s_flag, t_env, t_rx, t_tick, t_dist


@jit
def wall_light(pos, a, sense_mm, floor, wall, u, drops, dropout, out):
    """sim.radio.light_readings for even wall light without a sensor model: ``wall`` where the distance to the
    nearest wall, a - max(|x|, |y|), is at most ``sense_mm``, else ``floor``; -1 where ``u`` < ``dropout``."""
    B, M = out.shape
    for b in range(B):
        for i in range(M):
            v = wall if a - max(abs(pos[b, i, 0]), abs(pos[b, i, 1])) <= sense_mm else floor
            if drops and u[b, i] < dropout:
                v = -1
            out[b, i] = v


@jit
def straight_period(z0, t, s, left, e, step, leg, c, table, rot, use_table, R, theta, lim, zk, disp, travel, zb,
                    has_emitter, mobility, trec, want_trec, skin, diam, lim_end, lim_tick, diam_skin, target, gain,
                    r2_rebuild, cap, max_iters, pos, emitter):
    """closed_form, then period_contacts (straight runs), then what sim.kinematics.tick_move does with them: the
    emitter's record stays at ``emitter`` (B, 2) where nothing touched it, and the period's last positions go to
    ``pos`` (B, M, 2) and the emitter's to ``emitter``, in place."""
    closed_form(z0, t, s, left, e, step, leg, c, table, rot, use_table, R, theta, lim, zk, disp, travel)
    touched = period_contacts(zk, z0, zb, has_emitter, travel, leg, disp, np.zeros((1, 1, 1), np.complex128), False, e,
                              t, s, mobility, trec, want_trec, skin, diam, lim_end, lim_tick, diam_skin, lim, target,
                              gain, r2_rebuild, cap, max_iters)
    P, B, M = zk.shape
    if want_trec and not touched:
        for k in range(P):
            for b in range(B):
                trec[k, b, 0], trec[k, b, 1] = emitter[b, 0], emitter[b, 1]
    for b in range(B):
        for i in range(M):
            pos[b, i, 0], pos[b, i, 1] = zk[P - 1, b, i].real, zk[P - 1, b, i].imag
    if has_emitter:
        for b in range(B):
            emitter[b, 0], emitter[b, 1] = zb[b].real, zb[b].imag


@jit
def command_bytes(a, lo, hi, q):
    """round-half-up(255 a) clipped to 0..255 into ``q`` (sim.motion.action_to_u8), if every action lies in [lo, hi]
    (NaN does not); returns whether they all do."""
    fa, fq = a.ravel(), q.ravel()
    for j in range(fa.size):
        x = fa[j]
        if not (x >= lo and x <= hi):
            return False
        fq[j] = np.uint8(min(max(np.floor(x * 255.0 + 0.5), 0.0), 255.0))
    return True


@jit
def target_distance(pos, target, out):
    """sim.radio.target_distance: sqrt(dx * dx + dy * dy) per robot (B, M) to its env's ``target``."""
    B, M = out.shape
    for b in range(B):
        for i in range(M):
            dx, dy = pos[b, i, 0] - target[b, 0], pos[b, i, 1] - target[b, 1]
            out[b, i] = math.sqrt(dx * dx + dy * dy)
