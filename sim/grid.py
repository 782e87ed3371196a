"""Neighbour search: every pair of points closer than a radius, vectorised over (B envs, N points).

Two methods give identical results (same pairs, same order, same float distances):

``dense``
    All pairs by broadcasting, a (B, N, N) distance matrix. Fastest for small N.
``grid``
    A uniform grid of square cells at least ``radius`` wide over ``[-extent, extent]²``; points are
    sorted by cell, and each point is compared only with the points of its own cell and of four of
    its eight neighbour cells (a half stencil, so each unordered pair is visited once). Envs are
    processed in chunks so the candidate arrays stay within a memory bound.

``method="auto"`` picks dense for small N (and for grids too coarse to prune anything), else grid.
No Python loop runs over points; the grid method loops only over env chunks.

Squared distances are always ``dx * dx + dy * dy`` with ``dx = x[i] - x[j]`` (float64, or float32 on
request); a pair is in range when ``d2 <= radius * radius`` and its distance is ``sqrt(d2)`` (taken
in float64), so neither the pair set nor a distance depends on the method or the direction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: dense all-pairs up to this many points per env (tuned with tests/bench/bench_sim.py)
DENSE_MAX_N = 64
#: max unordered pairs of a dense chunk of envs
DENSE_CHUNK_PAIRS = 1 << 20
#: max candidate pairs of a grid chunk
CHUNK_ENTRIES = 1 << 22
#: the grid method processes envs in chunks of about this many points (cache-sized work arrays)
GRID_CHUNK_POINTS = 8192

# half stencil: (0, 0) is handled separately (only later points of the same cell)
_HALF_STENCIL = ((1, 0), (-1, 1), (0, 1), (1, 1))


@dataclass
class Pairs:
    """Pairs of points within the radius, sorted by (env, i, j). All arrays have shape (K,).

    For unordered pairs ``i < j``; for ordered pairs ``i`` is the receiver and ``j`` the sender and
    both directions are present.
    """

    env: np.ndarray  # (K,) int64
    i: np.ndarray  # (K,) int64
    j: np.ndarray  # (K,) int64
    dist: np.ndarray  # (K,) float64
    #: ordered pairs only: the unordered pairs' distances (U,) and each ordered pair's slot in them,
    #: so ``dist == udist[uidx]`` (lets callers evaluate symmetric functions once per pair)
    udist: np.ndarray | None = None
    uidx: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.env.shape[0])


def _empty(ordered: bool = False) -> Pairs:
    z = np.zeros(0, np.int64)
    if ordered:
        return Pairs(z, z.copy(), z.copy(), np.zeros(0), np.zeros(0), z.copy())
    return Pairs(z, z.copy(), z.copy(), np.zeros(0))


def distance2(x: np.ndarray, y: np.ndarray, env: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Squared distance between points i and j of env, the one formula every method uses. x, y: (B, N).

    A pair is within ``radius`` when ``d2 <= radius * radius``; its distance is ``sqrt(d2)``.
    """
    dx = x[env, i] - x[env, j]
    dy = y[env, i] - y[env, j]
    return dx * dx + dy * dy


def distance(x: np.ndarray, y: np.ndarray, env: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Distance between points i and j of env: ``sqrt(distance2(...))``."""
    return np.sqrt(distance2(x, y, env, i, j))


def choose_method(n_envs: int, n_points: int, radius: float, extent: float) -> str:
    """'dense' for small N or a grid too coarse to prune (<= 3 cells a side), else 'grid'."""
    cells = max(1, int(2.0 * extent // radius))
    if n_points <= DENSE_MAX_N or cells <= 3:
        return "dense"
    return "grid"


def pairs_within(pos: np.ndarray, radius: float, extent: float, method: str = "auto",
                 ordered: bool = False, dtype: type = np.float64) -> Pairs:
    """All pairs of points of the same env with distance <= ``radius``.

    ``pos`` (B, N, 2): points, expected within ``[-extent, extent]²`` (points outside are put in the
    border cells, still correct). ``ordered=False``: unordered pairs i < j sorted by (env, i, j);
    ``ordered=True``: both directions, sorted by (env, i, j) (i = receiver, j = sender).
    ``dtype``: precision of the coordinate differences and squared distances (float32 is about twice
    as fast; its distances are within ~1e-7 relative of the float64 ones). Distances are returned
    as float64 either way.
    """
    pos = np.asarray(pos, np.float64)
    assert pos.ndim == 3 and pos.shape[2] == 2, f"pos must be (B, N, 2), got {pos.shape}"
    assert radius > 0 and extent > 0, f"radius and extent must be > 0, got {radius}, {extent}"
    B, N, _ = pos.shape
    if B == 0 or N < 2:
        return _empty(ordered)
    if method == "auto":
        method = choose_method(B, N, radius, extent)
    x = np.ascontiguousarray(pos[..., 0], dtype=dtype)  # (B, N)
    y = np.ascontiguousarray(pos[..., 1], dtype=dtype)
    if method == "dense":
        return _dense(x, y, radius, ordered)
    if method == "grid":
        step = max(1, GRID_CHUNK_POINTS // N)  # envs per chunk: keeps the work arrays cache-sized
        if step >= B:
            return _grid(x, y, radius, extent, ordered)
        parts = []
        for b0 in range(0, B, step):  # loop over env chunks, not points
            p = _grid(x[b0:b0 + step], y[b0:b0 + step], radius, extent, ordered)
            p.env += b0
            parts.append(p)
        return _concat(parts)
    raise ValueError(f"unknown neighbour-search method '{method}'; use auto, dense or grid")


_FLAT_INDEX: dict[tuple[int, int], tuple[np.ndarray, ...]] = {}


def _flat_index(nb: int, n: int) -> tuple[np.ndarray, ...]:
    """Flat ids (nb * n_u,) of the first and second point of every unordered pair i < j, and (I, J)."""
    key = (nb, n)
    if key not in _FLAT_INDEX:
        if len(_FLAT_INDEX) >= 4:
            _FLAT_INDEX.clear()
        I, J = np.triu_indices(n, 1)  # (n_u,) sorted by (i, j)
        off = (np.arange(nb, dtype=np.int64) * n)[:, None]
        _FLAT_INDEX[key] = ((off + I).ravel(), (off + J).ravel(), I.astype(np.int64), J.astype(np.int64))
    return _FLAT_INDEX[key]


def _dense(x: np.ndarray, y: np.ndarray, radius: float, ordered: bool) -> Pairs:
    """All unordered pairs i < j per env (gathered with precomputed flat ids), in chunks of envs."""
    B, N = x.shape
    step = max(1, DENSE_CHUNK_PAIRS // (N * (N - 1) // 2))  # bounds memory and the cached index size
    parts = []
    for b0 in range(0, B, step):
        p = _dense_chunk(x[b0:b0 + step], y[b0:b0 + step], radius, ordered)
        p.env += b0
        parts.append(p)
    return parts[0] if len(parts) == 1 else _concat(parts)


def _dense_chunk(x: np.ndarray, y: np.ndarray, radius: float, ordered: bool) -> Pairs:
    nb, N = x.shape
    IF, JF, I, J = _flat_index(nb, N)
    n_u = I.size
    xf, yf = x.ravel(), y.ravel()
    d2 = xf.take(IF)  # (nb * n_u,): x[i] - x[j], then squared distance, in place
    d2 -= xf.take(JF)
    dy = yf.take(IF)
    dy -= yf.take(JF)
    np.multiply(d2, d2, out=d2)
    np.multiply(dy, dy, out=dy)
    d2 += dy
    fu = np.flatnonzero(d2 <= radius * radius)  # sorted by (env, i, j)
    udist = np.sqrt(d2.take(fu).astype(np.float64))
    e = fu // n_u
    k = fu - e * n_u
    i, j = I.take(k), J.take(k)
    if not ordered:
        return Pairs(e, i, j, udist)
    return _both_directions(e, i, j, udist, nb, N)


def _sort_packed(key: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """(sorted key, permutation) for unique non-negative keys < limit, by sorting ``key << sh | index``
    (a plain SIMD sort of int64 is several times faster than argsort here)."""
    n = key.size
    sh = max(1, int(n).bit_length())
    if int(limit).bit_length() + sh > 62:  # would overflow int64: plain argsort
        perm = np.argsort(key)
        return key[perm], perm
    packed = (key << sh) | np.arange(n, dtype=np.int64)
    packed.sort()
    return packed >> sh, packed & ((1 << sh) - 1)


def _both_directions(e: np.ndarray, i: np.ndarray, j: np.ndarray, udist: np.ndarray, nb: int, N: int) -> Pairs:
    """Ordered pairs (both directions) of unordered ones, sorted by (env, rx, snd), with uidx."""
    nu = e.size
    base = e * N
    key = np.concatenate([(base + i) * N + j, (base + j) * N + i])  # (2 nu,) unique
    flat, perm = _sort_packed(key, nb * N * N)
    uidx = np.where(perm < nu, perm, perm - nu)
    eo = flat // (N * N)
    rem = flat - eo * (N * N)
    rx = rem // N
    return Pairs(eo, rx, rem - rx * N, udist.take(uidx), udist, uidx)


def _concat(parts: list[Pairs]) -> Pairs:
    cat = [np.concatenate([getattr(p, f) for p in parts]) for f in ("env", "i", "j", "dist")]
    if parts[0].uidx is None:
        return Pairs(*cat)
    offs = np.cumsum([0] + [p.udist.size for p in parts[:-1]])
    return Pairs(*cat, np.concatenate([p.udist for p in parts]),
                 np.concatenate([p.uidx + o for p, o in zip(parts, offs)]))


def _grid(x: np.ndarray, y: np.ndarray, radius: float, extent: float, ordered: bool) -> Pairs:
    B, N = x.shape
    # cells per side; cell width 2*extent/nc >= radius. At most ~4N cells per env: wider cells find the same
    # pairs, and an arena millions of radii wide (a valid, if odd, world) would otherwise allocate that many
    nc = max(1, min(int(2.0 * extent // radius), 2 * math.isqrt(N) + 2))
    cw = 2.0 * extent / nc
    xf, yf = x.ravel(), y.ravel()  # (B*N,) flat id = env * N + index
    cx = np.clip(((xf + extent) / cw).astype(np.int64), 0, nc - 1)
    cy = np.clip(((yf + extent) / cw).astype(np.int64), 0, nc - 1)
    env_of = np.repeat(np.arange(B, dtype=np.int64), N)  # (B*N,)
    cell = (env_of * nc + cy) * nc + cx  # (B*N,) global cell id, env-major
    order = np.argsort(cell)  # sorted slot -> flat id; the order within a cell is irrelevant
    counts = np.bincount(cell, minlength=B * nc * nc)
    start = np.cumsum(counts) - counts  # first sorted slot of each cell
    s_cell, s_cx, s_cy, s_env = cell[order], cx[order], cy[order], env_of[order]
    xs, ys = xf[order], yf[order]  # coordinates in sorted order (locality)
    slot = np.arange(B * N, dtype=np.int64)

    # candidate ranges (lo, n) per sorted point and stencil entry: (5, B*N)
    lo = np.empty((5, B * N), np.int64)
    n = np.empty((5, B * N), np.int64)
    lo[0] = slot + 1  # same cell: only later points
    n[0] = start[s_cell] + counts[s_cell] - lo[0]
    for k, (ox, oy) in enumerate(_HALF_STENCIL, 1):
        nx, ny = s_cx + ox, s_cy + oy
        ok = (nx >= 0) & (nx < nc) & (ny >= 0) & (ny < nc)
        ncell = np.where(ok, (s_env * nc + ny) * nc + nx, 0)
        lo[k] = start[ncell]
        n[k] = np.where(ok, counts[ncell], 0)
    # chunks of envs with a bounded number of candidates (sorted slots are env-major)
    per_env = np.bincount(s_env, weights=n.sum(0), minlength=B)  # (B,)
    cum = np.cumsum(per_env)
    cuts = np.searchsorted(cum, np.arange(1, int(cum[-1] // CHUNK_ENTRIES) + 1) * CHUNK_ENTRIES)
    bounds = np.unique(np.concatenate([[0], cuts, [B]]))
    r2 = radius * radius
    parts = []
    for b0, b1 in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
        sel = slice(b0 * N, b1 * N)
        lo_c, n_c = lo[:, sel].ravel(), n[:, sel].ravel()
        tot = int(n_c.sum())
        if tot == 0:
            continue
        first = np.cumsum(n_c) - n_c
        src = np.repeat(np.broadcast_to(slot[sel], (5, (b1 - b0) * N)).ravel(), n_c)  # (tot,) sorted slots
        dst = np.repeat(lo_c - first, n_c) + np.arange(tot, dtype=np.int64)
        dx = xs[src] - xs[dst]  # (x[a] - x[b])^2 == (x[b] - x[a])^2 exactly: direction is irrelevant
        dy = ys[src] - ys[dst]
        d2 = dx * dx + dy * dy
        m = d2 <= r2
        a, b = order[src[m]], order[dst[m]]  # flat ids
        parts.append((np.minimum(a, b), np.maximum(a, b), d2[m]))
    if not parts:
        return _empty(ordered)
    lo_id, hi_id, d2 = (np.concatenate(v) if len(parts) > 1 else v[0] for v in zip(*parts))
    key, perm = _sort_packed(lo_id * N + (hi_id - (lo_id // N) * N), B * N * N)  # (e*N + i)*N + j
    e = key // (N * N)
    rem = key - e * (N * N)
    i = rem // N
    j = rem - i * N
    d = np.sqrt(d2.take(perm).astype(np.float64))
    if not ordered:
        return Pairs(e, i, j, d)
    return _both_directions(e, i, j, d, B, N)
