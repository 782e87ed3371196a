"""The radio stage: who hears whom during one control period, at what measured distance.

Two message models, chosen by ``cfg.msg_period_ticks``:

Thesis mode (``msg_period_ticks == 0``, :func:`thesis_radio`)
    Every searcher within the communication radius (true distance, after the move) is heard by
    every other searcher exactly once per period, at tick 0; the emitter likewise. Events are
    in arrival order: per receiver the target first, then senders by ascending index.

Tick-level mode (``msg_period_ticks >= 1``, :func:`tick_radio`)
    Every transmitter (the M searchers and the target) has a phase in ``[0, msg_period_ticks)``,
    drawn at reset; it sends at the global ticks ``g`` with ``(g - phase) % msg_period_ticks == 0``.
    Each robot within the communication radius at that tick (true distance, positions of robots
    and emitter after that tick's move) hears it. Events carry the tick within the period (0 .. P-1);
    :meth:`RadioPeriod.events` lists them in arrival order: by tick, then sender index with the
    target first.

In both modes, when configured: each message is lost independently at each receiver with
probability ``msg_loss``; the measured distance is ``clip(round_half_up(true + N(0, σ)), dist_min,
dist_max)`` (rounding only with ``dist_integer``; noise only with ``dist_noise_mm > 0``). A message
carries its sender's ``sensing`` flag as of the sender's last control step; the target's flag is 0.

Random numbers come from one ``numpy.random.Generator`` per env (the env's radio stream), drawn per
env in a fixed order, so an env of a batch sees exactly what it would see alone. Per env and
period: thesis mode draws loss uniforms then noise normals over [searcher messages, target
messages]; tick-level mode draws them over the period's in-range messages in (receiver, sender,
tick) order, the target counting as sender M.

Light (:func:`light_readings`): ``light_wall`` when the robot centre is at most ``wall_sense_mm``
from the nearest wall (or per-wall zones: uneven light), else ``light_floor``; in worlds with lamps or
a sensor model (:mod:`sim.light`) plus the lamps, times a per-robot gain, plus an offset and noise,
rounded and clipped to 0..1023; with probability ``light_dropout`` the reading is -1.

Per-env and per-transmitter variations (:mod:`sim.variants`: message period, loss, noise) are
optional arguments of :func:`tick_radio`; without them everything comes from ``cfg``.

Observations: :func:`observe_period` uses :func:`sim.events.observe` on the period's events, or
:func:`observe_fast`, which computes the same numbers straight from the message arrays, without
building the sorted event list (tested equal bit for bit).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from . import compiled, grid
from .config import ROLE_SEARCHER, ROLE_TARGET, WorldConfig
from .events import HeardEvents, observe
from .features import feature, held_object_light, light_feature, object_light_feature, random_feature
from .light import SensorDraw, sensor_readings
from .table_features import NeighbourTable
from .variants import WorldDraw

_NO_DRAW = WorldDraw()


@dataclass
class RadioPeriod:
    """Messages received in one control period, as searcher and target message arrays.

    Searcher messages (``s_*``, shape (Ns,)) are in pair order (env, receiver, sender, tick), target
    messages (``t_*``, shape (Nt,)) in (env, receiver, tick) order. ``single`` is True when every
    (receiver, sender) pair occurs at most once.
    """

    n_envs: int
    n_robots: int
    period_ticks: int
    s_env: np.ndarray  # (Ns,) int64
    s_rx: np.ndarray  # (Ns,) int64
    s_snd: np.ndarray  # (Ns,) int64, 0..M-1
    s_tick: np.ndarray  # (Ns,) int64
    s_dist: np.ndarray  # (Ns,) float64, measured
    s_flag: np.ndarray  # (Ns,) uint8
    t_env: np.ndarray  # (Nt,) int64
    t_rx: np.ndarray  # (Nt,) int64
    t_tick: np.ndarray  # (Nt,) int64
    t_dist: np.ndarray  # (Nt,) float64, measured
    single: bool
    #: optional: measured distances of unordered pairs (U,) and each searcher message's slot in it
    #: (``s_dist == s_udist[s_uidx]``), set when distances are symmetric (no noise)
    s_udist: np.ndarray | None = None
    s_uidx: np.ndarray | None = None
    #: optional: (Nt,) int the emitter's light reading each target message carries (-1: none yet), set by the env
    #: in worlds whose observation reads it (``object_light``)
    t_light: np.ndarray | None = None
    _events: HeardEvents | None = field(default=None, repr=False)

    def events(self) -> HeardEvents:
        """The period's :class:`HeardEvents` in arrival order (built once, on first call)."""
        if self._events is None:
            M, P = self.n_robots, self.period_ticks
            env = np.concatenate([self.t_env, self.s_env])
            rx = np.concatenate([self.t_rx, self.s_rx])
            snd = np.concatenate([np.full(self.t_env.shape, -1, np.int64), self.s_snd])
            tick = np.concatenate([self.t_tick, self.s_tick])
            key = ((env * M + rx) * P + tick) * (M + 1) + (snd + 1)  # target (-1) first at a tick
            o = np.argsort(key)  # keys are unique (one message per sender and tick)
            role = np.concatenate([np.full(self.t_env.shape, ROLE_TARGET, np.uint8),
                                   np.full(self.s_env.shape, ROLE_SEARCHER, np.uint8)])
            flag = np.concatenate([np.zeros(self.t_env.shape, np.uint8), self.s_flag])
            dist = np.concatenate([self.t_dist, self.s_dist])
            light = None if self.t_light is None else np.concatenate(
                [self.t_light, np.full(self.s_env.shape, -1, np.int64)])[o]
            self._events = HeardEvents(env[o].astype(np.int32), rx[o].astype(np.int32),
                                       snd[o].astype(np.int32), tick[o].astype(np.int16),
                                       dist[o].astype(np.float64), role[o], flag[o], light)
        return self._events


def measure(true_mm: np.ndarray, z: np.ndarray | None, cfg: WorldConfig,
            sigma: np.ndarray | None = None) -> np.ndarray:
    """Measured distance: true + σ·z, rounded half up with ``dist_integer``, clipped to the range.

    σ is ``cfg.dist_noise_mm``, or per message ``sigma`` when given. ``true_mm`` are distances of
    heard messages, so within [0, comm radius]: without noise or rounding, a range that holds
    [0, comm radius] cannot clip anything and ``true_mm`` is returned as is.
    """
    if z is None and not cfg.dist_integer and cfg.dist_min_mm <= 0.0 and cfg.dist_max_mm > 1.001 * cfg.comm_radius_mm:
        return true_mm
    d = true_mm if z is None else true_mm + (cfg.dist_noise_mm if sigma is None else sigma) * z
    if cfg.dist_integer:
        d = np.floor(d + 0.5)
    return np.clip(d, cfg.dist_min_mm, cfg.dist_max_mm)


def _per_env_draws(rngs: Sequence[np.random.Generator], counts: np.ndarray, loss: bool, noise: bool
                   ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Per env e: ``counts[e]`` loss uniforms, then ``counts[e]`` standard normals, concatenated.

    A loop over envs (each env owns its generator), never over robots.
    """
    u = z = None
    if loss or noise:
        total = int(counts.sum())
        u = np.empty(total) if loss else None
        z = np.empty(total) if noise else None
        i = 0
        for rng, n in zip(rngs, counts.tolist()):  # each env's draws straight into its slice (the same values)
            if loss:
                rng.random(out=u[i:i + n])
            if noise:
                rng.standard_normal(out=z[i:i + n])
            i += n
    return u, z


def target_distance(pos: np.ndarray, target: np.ndarray) -> np.ndarray:
    """True robot–target distances (B, M), same formula as :func:`sim.grid.distance`."""
    if compiled.available():  # the same operations, compiled
        return compiled.target_distance(pos, target)
    dx = pos[..., 0] - target[:, None, 0]
    dy = pos[..., 1] - target[:, None, 1]
    return np.sqrt(dx * dx + dy * dy)


#: precision of the pair search. float32 halves the search's arithmetic but costs as much in
#: conversions at these sizes (measured: no gain per step), so distances stay exact float64.
PAIR_DTYPE = np.float64


def thesis_radio(pos: np.ndarray, target: np.ndarray | None, flags: np.ndarray, cfg: WorldConfig,
                 rngs: Sequence[np.random.Generator], target_dist: np.ndarray | None = None,
                 method: str = "auto") -> RadioPeriod:
    """Thesis-mode messages for one period. pos (B, M, 2), target (B, 2) or None (no emitter), flags (B, M) uint8."""
    B, M, _ = pos.shape
    R = cfg.comm_radius_mm
    pr = grid.pairs_within(pos, R, cfg.arena_half_mm, method, ordered=True, dtype=PAIR_DTYPE)  # (env, rx, snd)
    s_env, s_rx, s_snd, s_true, s_uidx = pr.env, pr.i, pr.j, pr.dist, pr.uidx
    if target is None:
        t_env = t_rx = np.zeros(0, np.int64)
        t_true = np.zeros(0)
    else:
        dt = target_distance(pos, target) if target_dist is None else target_dist  # (B, M)
        t_env, t_rx = np.nonzero(dt <= R)  # sorted (env, rx)
        t_true = dt[t_env, t_rx]
    loss, noise = cfg.msg_loss > 0, cfg.dist_noise_mm > 0
    zs = zt = None
    if loss or noise:
        cs = np.bincount(s_env, minlength=B)  # (B,) searcher messages per env
        ct = np.bincount(t_env, minlength=B)
        u, z = _per_env_draws(rngs, cs + ct, loss, noise)
        off = np.cumsum(cs + ct) - (cs + ct)  # first draw of each env
        si = off[s_env] + np.arange(s_env.size) - (np.cumsum(cs) - cs)[s_env]  # draw index per message
        ti = off[t_env] + cs[t_env] + np.arange(t_env.size) - (np.cumsum(ct) - ct)[t_env]
        if noise:
            zs, zt = z[si], z[ti]
        if loss:
            ks, kt = u[si] >= cfg.msg_loss, u[ti] >= cfg.msg_loss  # received
            s_env, s_rx, s_snd, s_true, s_uidx = s_env[ks], s_rx[ks], s_snd[ks], s_true[ks], s_uidx[ks]
            t_env, t_rx, t_true = t_env[kt], t_rx[kt], t_true[kt]
            if noise:
                zs, zt = zs[ks], zt[kt]
    if noise:
        s_dist, s_udist, s_uidx = measure(s_true, zs, cfg), None, None
    else:  # symmetric: measure each unordered pair once
        s_udist = measure(pr.udist, None, cfg)
        s_dist = s_udist[s_uidx]
    return RadioPeriod(
        B, M, cfg.period_ticks,
        s_env, s_rx, s_snd, np.zeros(s_env.shape, np.int64), s_dist,
        flags.reshape(-1).take(s_env * M + s_snd).astype(np.uint8, copy=False),
        t_env, t_rx, np.zeros(t_env.shape, np.int64), measure(t_true, zt, cfg), single=True,
        s_udist=s_udist, s_uidx=s_uidx)


def draw_phases(rngs: Sequence[np.random.Generator], n_robots: int, cfg: WorldConfig,
                periods: np.ndarray | None = None) -> np.ndarray:
    """Transmit phases (B, M + 1) in [0, period); column M is the target. ``periods`` (B, M + 1):
    each transmitter's own ticks between sends (default ``cfg.msg_period_ticks``)."""
    if periods is None:
        return np.stack([rng.integers(0, cfg.msg_period_ticks, n_robots + 1) for rng in rngs]).astype(np.int64)
    return np.stack([rng.integers(0, T) for rng, T in zip(rngs, periods)]).astype(np.int64)


def tick_radio(pos_ticks: np.ndarray, target: np.ndarray | None, phases: np.ndarray, tick0: int,
               flags: np.ndarray, cfg: WorldConfig, rngs: Sequence[np.random.Generator],
               method: str = "auto", *, target_ticks: np.ndarray | None = None,
               msg_period: np.ndarray | None = None, msg_loss: np.ndarray | None = None,
               dist_noise_mm: np.ndarray | None = None) -> RadioPeriod:
    """Tick-level messages of the period covering global ticks ``tick0 .. tick0 + P - 1``.

    pos_ticks (P, B, M, 2): robot positions after each tick's move; target (B, 2) the emitter (None: no
    emitter), or its positions after each tick ``target_ticks`` (P, B, 2) when it moves; phases (B, M + 1)
    (column M, the emitter's, is drawn without an emitter too, so the streams do not depend on the task);
    flags (B, M) uint8 senders' flags. Per-env or per-transmitter variations (None = ``cfg``'s):
    ``msg_period`` (B, M + 1) ticks between sends, ``msg_loss`` (B,), ``dist_noise_mm`` (B,).
    """
    P, B, M, _ = pos_ticks.shape
    R = cfg.comm_radius_mm
    periods = np.full((B, M + 1), cfg.msg_period_ticks, np.int64) if msg_period is None else msg_period
    jit = compiled.available()
    if target is not None and jit and M + 1 <= compiled.RADIO_MAX_N:  # the same, compiled (bit-identical)
        e, rx, snd, k, d, single = compiled.radio_messages(pos_ticks, target, target_ticks, phases, tick0, periods, R)
    else:
        e, rx, snd, k, d, single = _messages(pos_ticks, target, target_ticks, phases, tick0, periods, R, cfg, method)
    loss = cfg.msg_loss > 0 if msg_loss is None else bool(np.any(msg_loss > 0))
    noise = cfg.dist_noise_mm > 0 if dist_noise_mm is None else bool(np.any(dist_noise_mm > 0))
    u, z = _per_env_draws(rngs, np.bincount(e, minlength=B), loss, noise)
    if jit:  # the rest, compiled (the same comparisons and float operations)
        received = compiled.radio_receive(
            e, rx, snd, k, d, u, z,  # None where not drawn
            np.full(B, cfg.msg_loss) if msg_loss is None else msg_loss,
            np.full(B, cfg.dist_noise_mm) if dist_noise_mm is None else dist_noise_mm,
            cfg.dist_integer, cfg.dist_min_mm, cfg.dist_max_mm, flags, M)
        return RadioPeriod(B, M, P, *received, single=single)
    if loss:
        ok = np.flatnonzero(u >= (cfg.msg_loss if msg_loss is None else msg_loss.take(e)))
        e, rx, snd, k, d = e.take(ok), rx.take(ok), snd.take(ok), k.take(ok), d.take(ok)
        z = z.take(ok) if noise else None
    dm = measure(d, z, cfg, None if dist_noise_mm is None or not noise else dist_noise_mm.take(e))
    is_t = snd == M
    t, sr = np.flatnonzero(is_t), np.flatnonzero(~is_t)
    s_env, s_snd = e.take(sr), snd.take(sr)
    return RadioPeriod(B, M, P, s_env, rx.take(sr), s_snd, k.take(sr), dm.take(sr),
                       flags.reshape(-1).take(s_env * M + s_snd).astype(np.uint8, copy=False),
                       e.take(t), rx.take(t), k.take(t), dm.take(t), single=single)


def _messages(pos_ticks: np.ndarray, target: np.ndarray | None, target_ticks: np.ndarray | None, phases: np.ndarray,
              tick0: int, periods: np.ndarray, R: float, cfg: WorldConfig, method: str
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """The period's messages in range, before loss and noise: (env, rx, snd, tick, true distance) in
    (env, receiver, sender, tick) order, and whether no candidate sender sends more than once."""
    P, B, M, _ = pos_ticks.shape
    N = M + (target is not None)
    Z = np.empty((P, B, N), np.complex128)  # robots and (column M) the emitter, if any, after each tick
    Z.real[..., :M], Z.imag[..., :M] = pos_ticks[..., 0], pos_ticks[..., 1]
    if target is not None:
        tt = np.broadcast_to(target, (P, B, 2)) if target_ticks is None else target_ticks
        Z.real[..., M], Z.imag[..., M] = tt[..., 0], tt[..., 1]
    final = Z[-1]
    reach = np.abs(Z - final).max(axis=0)  # (B, N) farthest each transmitter was from its end
    # a pair within R at some tick is within R + reach_i + reach_j at the end
    cand = grid.pairs_within(final.view(np.float64).reshape(B, N, 2), R + 2.0 * float(reach.max()) + 1e-3,
                             cfg.arena_half_mm, method, ordered=True, dtype=PAIR_DTYPE)
    ri, rj = reach[cand.env, cand.i], reach[cand.env, cand.j]
    m = np.flatnonzero((cand.i < M) & (cand.dist <= R + ri + rj + 1e-3))  # the target only sends
    e, rx, snd = cand.env.take(m), cand.i.take(m), cand.j.take(m)  # (K,) sorted by (env, rx, snd)
    moved = (ri.take(m) > 0) | (rj.take(m) > 0)  # (K,) else the distance is the same at every tick
    T = periods[e, snd]
    k0 = (phases[e, snd] - tick0) % T  # (K,) first send tick of the sender in this period
    nsend = np.where(k0 < P, (P - 1 - k0) // T + 1, 0)
    tot = int(nsend.sum())
    first = np.cumsum(nsend) - nsend
    d = np.repeat(cand.dist.take(m), nsend)
    moved = np.repeat(moved, nsend)
    e, rx, snd, k0 = (np.repeat(v, nsend) for v in (e, rx, snd, k0))
    rounds = np.arange(tot, dtype=np.int64) - np.repeat(first, nsend)
    k = k0 + periods[e, snd] * rounds  # (tot,) send tick
    mv = moved.nonzero()[0]  # messages between transmitters that moved: distance at the send tick
    base = (k.take(mv) * B + e.take(mv)) * N
    d[mv] = np.abs(Z.reshape(-1).take(base + rx.take(mv)) - Z.reshape(-1).take(base + snd.take(mv)))
    h = np.flatnonzero(d <= R)  # in range at the send tick; (receiver, sender, tick) order
    return e.take(h), rx.take(h), snd.take(h), k.take(h), d.take(h), bool(nsend.max(initial=0) <= 1)


def light_readings(pos: np.ndarray, cfg: WorldConfig, rngs: Sequence[np.random.Generator],
                   wall_zone_mm: np.ndarray | None = None, sensors: "SensorDraw | None" = None,
                   draw: "WorldDraw | None" = None, body: np.ndarray | None = None) -> np.ndarray:
    """Ambient-light readings (B, M) int16 at the control tick (-1 = dropout).

    ``wall_zone_mm`` (B, 4): per env, how far from the +x, +y, -x, -y walls the reading is high
    (uneven light); default ``cfg.wall_sense_mm`` for every wall. Worlds with graded light
    (``cfg.graded_light``: lamps, noise, per-robot ``sensors``; :mod:`sim.light`) add the lamps and the
    sensor model, with ``draw``'s per-env lamp brightness, shift and noise when randomised; ``body`` (B, 2):
    the heavy body's centre, which shades the side lamps (:func:`sim.light.lamp_field`).
    """
    a = cfg.arena_half_mm
    if wall_zone_mm is None and not cfg.graded_light and compiled.available():  # the same, compiled
        u = _dropout_draws(rngs, pos.shape[1]) if cfg.light_dropout > 0 else None
        return compiled.wall_light(pos, a, cfg.wall_sense_mm, cfg.light_floor, cfg.light_wall, u, cfg.light_dropout)
    if wall_zone_mm is None:
        wall_d = a - np.maximum(np.abs(pos[..., 0]), np.abs(pos[..., 1]))  # (B, M)
        lit = wall_d <= cfg.wall_sense_mm
    else:
        x, y, z = pos[..., 0], pos[..., 1], wall_zone_mm[:, None, :]
        lit = (a - x <= z[..., 0]) | (a - y <= z[..., 1]) | (a + x <= z[..., 2]) | (a + y <= z[..., 3])
    light = np.full(lit.shape, cfg.light_floor, np.int16)
    light[lit] = cfg.light_wall
    if cfg.graded_light:
        d = draw if draw is not None else _NO_DRAW
        light = sensor_readings(light.astype(np.float64), pos, cfg, cfg.lamp_list, rngs, sensors,
                                d.lamp_brightness, d.lamp_shift_mm, d.light_noise, body)
    if cfg.light_dropout > 0:
        light[_dropout_draws(rngs, pos.shape[1]) < cfg.light_dropout] = -1
    return light


def _dropout_draws(rngs: Sequence[np.random.Generator], M: int) -> np.ndarray:
    """(B, M) uniforms, one per robot from its env's light stream: below ``light_dropout``, a reading drops out."""
    u = np.empty((len(rngs), M))
    for row, rng in zip(u, rngs):
        rng.random(out=row)
    return u


@functools.lru_cache(maxsize=16)
def _centres(cfg: WorldConfig) -> np.ndarray:
    """cfg.rbf_centres_mm, computed once per config (it is a linspace on every access)."""
    c = cfg.rbf_centres_mm
    c.setflags(write=False)
    return c


def rbf_fast(cfg: WorldConfig, d_mm: np.ndarray) -> np.ndarray:
    """:func:`sim.events.rbf` for 1-D distances, bit-identical, with fewer passes and temporaries.

    ``-(t) / c == t / -c`` exactly in IEEE arithmetic, so the negation folds into the division.
    """
    t = d_mm[:, None] - _centres(cfg)  # (N, n_rbf)
    np.square(t, out=t)
    np.divide(t, -(2.0 * cfg.rbf_sigma_mm ** 2), out=t)
    np.exp(t, out=t)
    np.divide(t, cfg.rbf_norm, out=t)
    far = d_mm > cfg.comm_radius_mm
    if far.any():
        t[far] = 0.0
    return t


def _segment_sums(rows: np.ndarray, starts: np.ndarray, counts: np.ndarray, index: np.ndarray | None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per segment, the sum of its rows added one after another (0 + r0 + r1 + ...), like np.add.at.

    ``rows`` (N, K); segment s covers positions ``starts[s] .. starts[s] + counts[s] - 1`` (counts
    >= 1), each position p standing for ``rows[index[p]]`` (or ``rows[p]``). Loops over the rank
    within the segment (at most the neighbour-table size), vectorised over segments.
    Returns ``(sums, order)``: ``sums[k]`` is the sum of segment ``order[k]`` (longest segments
    first; the caller scatters once instead of un-permuting here).
    """
    o = np.argsort((-counts).astype(np.int16), kind="stable")  # longest first (radix sort on int16)
    st, cn = starts.take(o), counts.take(o)
    out = np.zeros((st.size, rows.shape[1]))
    n_active = np.searchsorted(-cn, -np.arange(1, cn[0] + 1), side="right")  # segments with > k rows
    for k, na in enumerate(n_active.tolist()):
        pos = st[:na] + k
        out[:na] += rows.take(pos if index is None else index.take(pos), axis=0)  # take: faster than []
    return out, o


@functools.lru_cache(maxsize=16)
def _rbf_table(cfg: WorldConfig) -> np.ndarray:
    """rbf_fast of the integer distances 0..255 (rows), for worlds whose distances are integer mm."""
    t = rbf_fast(cfg, np.arange(256, dtype=np.float64))
    t.setflags(write=False)
    return t


_NO_RBF = np.zeros((1, 0))  #: the RBF table of a world without the rbf feature (no columns)


def _integer_mm(cfg: WorldConfig) -> bool:
    """Whether measured distances are integers in 0..255 mm (ψ by table lookup)."""
    return cfg.dist_integer and cfg.dist_min_mm >= 0 and cfg.dist_max_mm <= 255


def rbf_rows(cfg: WorldConfig, d_mm: np.ndarray) -> np.ndarray:
    """rbf_fast(cfg, d_mm), by table lookup when distances are integer mm (the same values)."""
    if _integer_mm(cfg):
        return _rbf_table(cfg).take(d_mm.astype(np.intp), axis=0)
    return rbf_fast(cfg, d_mm)


def _run_ends(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, last) index of each run of equal values in a non-decreasing ``key``."""
    brk = np.flatnonzero(key[1:] != key[:-1]) + 1
    return np.concatenate(([0], brk)), np.concatenate((brk - 1, [key.size - 1]))


def _table_entries(g: np.ndarray, d: np.ndarray, f: np.ndarray, ui: np.ndarray | None, snd: np.ndarray,
                   tick: np.ndarray, single: bool, B: int, M: int, P: int, table_size: int):
    """The neighbour tables' entries of the messages to receivers ``g``: (g, d, f, ui, counts per receiver).

    One entry per (receiver, sender): its first tick ranks the sender, its last distance is kept; a receiver
    with more than ``table_size`` senders keeps the first by (first tick, sender)."""
    if not single and g.size:  # one entry per (receiver, sender): first tick, latest distance
        first, last = _run_ends(g * M + snd)
        g, snd, tick, f, d, ui = g.take(first), snd.take(first), tick.take(first), f.take(first), d.take(last), None
    counts = np.bincount(g, minlength=B * M)  # (B*M,) table entries per receiver
    if g.size and counts.max() > table_size:  # table full: later senders are dropped
        over = np.flatnonzero(counts.take(g) > table_size)
        o = over.take(np.argsort((g.take(over) * P + tick.take(over)) * M + snd.take(over), kind="stable"))
        go = g.take(o)  # overflowing receivers' entries by (receiver, first tick, sender)
        rank = np.arange(o.size) - np.searchsorted(go, go)
        keep = np.ones(g.size, bool)
        keep[o[rank >= table_size]] = False
        g, d, f = g[keep], d[keep], f[keep]
        ui = ui[keep] if ui is not None else None
        counts = np.minimum(counts, table_size)
    return g, d, f, ui, counts


def _column(cfg: WorldConfig, name: str) -> int:
    """The first observation column of feature ``name``; -1 when the world does not observe it."""
    return cfg.obs_index(name) if cfg.has_feature(name) else -1


def observe_fast(period: RadioPeriod, light: np.ndarray, prev_wall: np.ndarray, cfg: WorldConfig,
                 prev_light: np.ndarray | None = None, rand_word: np.ndarray | None = None,
                 prev_object_light: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sim.events.observe` straight from the period's message arrays (no sorted event list).

    Per (receiver, sender) run of messages: the first tick ranks the sender for the neighbour table,
    the last message's distance is the one kept; the RBF sums go over table entries in sender order
    with the same float64 operations as :func:`sim.events.observe`, so the result is bit-identical.
    """
    B, M = light.shape
    P = period.period_ticks
    g = period.s_env * M + period.s_rx  # (Ns,) receiver id, non-decreasing
    d, f, ui, snd, tick = period.s_dist, period.s_flag, period.s_uidx, period.s_snd, period.s_tick
    # the messages compiled (sim.compiled.observe_messages) where distances are integer mm and asymmetric
    own = cfg.table_features  # a task's own features need the entries themselves
    tables = ui is None and _integer_mm(cfg) and compiled.available() and not own
    if not tables:
        g, d, f, ui, counts = _table_entries(g, d, f, ui, snd, tick, period.single, B, M, P, cfg.neighbour_table_size)
    obs = np.zeros((B, M, cfg.obs_dim), np.float32)
    if own:  # one table (sorted once) for all of them
        table, flat = NeighbourTable.of(g, d, B * M), obs.reshape(B * M, cfg.obs_dim)
        for name in own:
            flat[:, cfg.obs_slice(name)] = feature(name).table.float_values(table, cfg)
    if cfg.has_feature("wall") and not tables:
        wall = (light >= cfg.light_threshold).astype(np.float64)
        obs[..., cfg.obs_index("wall")] = np.where(light < 0, prev_wall, wall) if cfg.light_dropout > 0 else wall
    if cfg.has_feature("light"):
        obs[..., cfg.obs_slice("light")] = light_feature(light, np.full((B, M), -1) if prev_light is None else prev_light)
    if cfg.has_feature("random"):
        assert rand_word is not None, "the random feature needs the robots' xorshift32 words"
        obs[..., cfg.obs_slice("random")] = random_feature(rand_word)
    tg = period.t_env * M + period.t_rx  # non-decreasing; the latest target message wins
    heard = np.zeros(B * M, np.uint8)  # who heard the emitter this period: the robots' new sensing flags
    if not tables:
        tdist = np.zeros(B * M)
        if tg.size:
            _, t_last = _run_ends(tg) if not period.single else (None, np.arange(tg.size))
            heard[tg] = 1
            tdist[tg.take(t_last)] = period.t_dist.take(t_last)
        if cfg.has_feature("target"):
            obs[..., cfg.obs_index("target")] = np.where(heard, np.minimum(tdist / cfg.comm_radius_mm, 1.0),
                                                         -1.0).reshape(B, M)
    if cfg.has_feature("object_light"):
        t_light = np.full(B * M, -1, np.int64)  # the latest target message's reading that carries one
        if tg.size and period.t_light is not None:
            lit = np.flatnonzero(period.t_light >= 0)  # one reading per env and period: the emitter reads at control ticks
            t_light[tg.take(lit)] = period.t_light.take(lit)
        prev = np.full((B, M), -1) if prev_object_light is None else prev_object_light
        obs[..., cfg.obs_slice("object_light")] = object_light_feature(held_object_light(t_light.reshape(B, M), prev))
    if tables:
        compiled.observe_messages(g, snd, tick, f, d, period.single, M, cfg.neighbour_table_size,
                                  _rbf_table(cfg) if cfg.has_feature("rbf") else _NO_RBF, tg, period.t_dist,
                                  cfg.comm_radius_mm, light, prev_wall, cfg.light_threshold, cfg.light_dropout > 0,
                                  obs.reshape(B * M, -1), heard, _column(cfg, "wall"), _column(cfg, "target"),
                                  _column(cfg, "nbr_sensing"), _column(cfg, "rbf"))
        return obs, heard.reshape(B, M)
    if d.size:
        rcv = np.flatnonzero(counts)  # receivers with table entries
        cnt = counts[rcv]
        starts = np.cumsum(cnt) - cnt  # their first entry (entries are grouped by receiver)
        flat = obs.reshape(B * M, cfg.obs_dim)
        if cfg.has_feature("nbr_sensing"):
            # max of the table's 0/1 flags = (their count > 0); one bincount instead of reduceat + scatter
            n_flags = np.bincount(g, weights=f, minlength=B * M)
            flat[:, cfg.obs_index("nbr_sensing")] = n_flags > 0
        if cfg.has_feature("rbf"):
            if ui is None:
                hist, o = _segment_sums(rbf_rows(cfg, d), starts, cnt, None)
            else:  # symmetric distances: ψ once per unordered pair
                hist, o = _segment_sums(rbf_rows(cfg, period.s_udist), starts, cnt, ui)
            flat[rcv.take(o), cfg.obs_slice("rbf")] = hist
    return obs, heard.reshape(B, M)


def observe_period(period: RadioPeriod, light: np.ndarray, prev_wall: np.ndarray, cfg: WorldConfig,
                   fast: bool = True, prev_light: np.ndarray | None = None,
                   rand_word: np.ndarray | None = None,
                   prev_object_light: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Observations (B, M, obs_dim) float32 and new sensing flags (B, M) uint8 for a period."""
    if fast:
        return observe_fast(period, light, prev_wall, cfg, prev_light, rand_word, prev_object_light)
    return observe(period.events(), light, prev_wall, cfg, prev_light, rand_word, prev_object_light)
