"""Heard-message events and the observation computed from them (docs/design.md control-step contract).

The radio model (:mod:`sim.radio`) produces, for one control period, a flat list of *events*: one per
message that one robot received. The simulator turns them into observations with
:func:`observe`; the firmware (and its emulator, :mod:`export.verify.emulator`) consumes exactly the same
events tick by tick. This module is the single written-down definition of what a robot does with
what it hears, in float; the firmware does the same in fixed point.

Per receiver and control period (semantics shared with the firmware):

1. Events are taken in arrival order: by ``tick`` (0 .. period_ticks-1), ties in array order.
2. Target messages (``role == ROLE_TARGET``) fill one slot: the latest distance wins.
3. Searcher messages go into a neighbour table of ``cfg.neighbour_table_size`` entries. A sender
   gets an entry at its first message of the period while the table has room; when the table is
   full, messages from senders without an entry are dropped for the rest of the period. Each later
   message of a sender that has an entry overwrites its distance and sensing flag (latest wins), so
   each sender counts once per period.
4. At the end of the period the observation is formed and the table is cleared:
   - wall: ``light >= cfg.light_threshold``; a reading of -1 (busy receiving) keeps the last flag;
   - target: ``min(d / comm_radius, 1)`` when the target was heard this period, else -1;
   - neighbour senses target: 1 when any table entry's latest flag is set;
   - RBF bin k: ``Σ ψ_k(d) / rbf_norm`` over table entries with ``d <= comm_radius``, where
     ``ψ_k(d) = exp(-(d - μ_k)² / (2σ²))`` (summed in sender order; the firmware sums integers).
5. The robot's own "I sense the target" flag for the next period's messages is
   ``target was heard this period``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import OBS_NBR_SENSING, OBS_RBF, OBS_TARGET, OBS_WALL, ROLE_TARGET, WorldConfig


@dataclass
class HeardEvents:
    """Messages received during one control period, flattened over envs and receivers.

    All arrays have shape (N,). ``sender`` is the robot index 0..M-1 of a searcher, or -1 for the
    target beacon (its kilo_uid is ``cfg.target_uid``; searcher i has kilo_uid i + 1).
    ``dist_mm`` is the measured distance (float; integer-valued in worlds with ``dist_integer``).
    """

    env: np.ndarray  # (N,) int32, 0..B-1
    rx: np.ndarray  # (N,) int32, receiving robot 0..M-1
    sender: np.ndarray  # (N,) int32, sending robot 0..M-1, or -1 for the target
    tick: np.ndarray  # (N,) int16, tick within the period, 0..period_ticks-1
    dist_mm: np.ndarray  # (N,) float64, measured distance
    role: np.ndarray  # (N,) uint8, ROLE_SEARCHER or ROLE_TARGET
    flag: np.ndarray  # (N,) uint8, sender's "I sense the target" flag carried in the message

    def __post_init__(self) -> None:
        n = self.env.shape[0]
        for name in ("rx", "sender", "tick", "dist_mm", "role", "flag"):
            arr = getattr(self, name)
            assert arr.shape == (n,), f"HeardEvents.{name} has shape {arr.shape}, expected ({n},)"

    def __len__(self) -> int:
        return int(self.env.shape[0])

    @classmethod
    def empty(cls) -> "HeardEvents":
        z = np.zeros(0, np.int32)
        return cls(z, z.copy(), z.copy(), np.zeros(0, np.int16), np.zeros(0), np.zeros(0, np.uint8),
                   np.zeros(0, np.uint8))

    def arrival_order(self, n_robots: int) -> np.ndarray:
        """Indices that sort events by (env, rx, tick), ties kept in array order."""
        return np.lexsort((self.tick, self.env.astype(np.int64) * n_robots + self.rx))


def rbf(cfg: WorldConfig, d_mm: np.ndarray) -> np.ndarray:
    """ψ_k(d) / rbf_norm for every k, zero beyond the communication radius. Shape d.shape + (n_rbf,)."""
    d = np.asarray(d_mm, dtype=np.float64)[..., None]
    psi = np.exp(-((d - cfg.rbf_centres_mm) ** 2) / (2.0 * cfg.rbf_sigma_mm ** 2)) / cfg.rbf_norm
    return np.where(d <= cfg.comm_radius_mm, psi, 0.0)


@dataclass
class PeriodSummary:
    """What a robot keeps of one period's events (the firmware's end-of-period table)."""

    target_heard: np.ndarray  # (B, M) bool
    target_dist_mm: np.ndarray  # (B, M) float, valid where target_heard
    table_env: np.ndarray  # (K,) int, env of each kept (receiver, sender) entry, in (env, rx, sender) order
    table_rx: np.ndarray  # (K,) int
    table_sender: np.ndarray  # (K,) int
    table_dist_mm: np.ndarray  # (K,) float, latest distance
    table_flag: np.ndarray  # (K,) uint8, latest flag


def summarise(events: HeardEvents, cfg: WorldConfig, n_envs: int, n_robots: int) -> PeriodSummary:
    """Apply the per-period receive rules (steps 1–3 of the module doc), vectorised."""
    B, M = n_envs, n_robots
    order = events.arrival_order(M)
    env, rx, snd = events.env[order], events.rx[order], events.sender[order]
    dist, role, flag = events.dist_mm[order], events.role[order], events.flag[order]
    group = env.astype(np.int64) * M + rx  # (N,) receiver id, non-decreasing

    # target slot: latest target message per receiver
    target_heard = np.zeros(B * M, bool)
    target_dist = np.zeros(B * M)
    is_t = role == ROLE_TARGET
    if is_t.any():
        g_t, d_t = group[is_t], dist[is_t]
        # later assignments win in NumPy fancy assignment with repeated indices only by accident;
        # take the last occurrence explicitly
        last = _last_index_per_key(g_t)
        target_heard[g_t[last]] = True
        target_dist[g_t[last]] = d_t[last]

    # neighbour table: first-arrival rank per receiver, latest values per (receiver, sender)
    s = ~is_t
    g_s, snd_s, d_s, f_s = group[s], snd[s], dist[s], flag[s]
    pair = g_s * (M + 1) + snd_s  # (Ns,) unique per (receiver, sender)
    if pair.size:
        first = _first_index_per_key(pair)  # positions (in arrival order) of each pair's first message
        last = _last_index_per_key(pair)  # both in (receiver, sender) order
        # rank each sender within its receiver by first arrival (arrival order is grouped by receiver)
        by_first = np.argsort(first, kind="stable")
        g_pair = g_s[first[by_first]]
        starts = np.r_[0, np.flatnonzero(np.diff(g_pair)) + 1]
        run_len = np.diff(np.r_[starts, g_pair.size])
        rank = np.arange(g_pair.size) - np.repeat(starts, run_len)
        keep = np.empty(first.size, bool)
        keep[by_first] = rank < cfg.neighbour_table_size  # table entries, back in (receiver, sender) order
        first, last = first[keep], last[keep]
        g_keep = g_s[first]
        t_env, t_rx = g_keep // M, g_keep % M
        t_snd, t_d, t_f = snd_s[first], d_s[last], f_s[last]
    else:
        t_env = t_rx = t_snd = np.zeros(0, np.int64)
        t_d, t_f = np.zeros(0), np.zeros(0, np.uint8)
    return PeriodSummary(target_heard.reshape(B, M), target_dist.reshape(B, M), t_env, t_rx, t_snd,
                         t_d, t_f)


def observe(events: HeardEvents, light: np.ndarray, prev_wall: np.ndarray, cfg: WorldConfig
            ) -> tuple[np.ndarray, np.ndarray]:
    """Observations (B, M, obs_dim) float32 and the robots' new sensing flags (B, M) uint8.

    ``light`` (B, M) int: ambient-light readings at the control tick (-1 = busy, keep last flag).
    ``prev_wall`` (B, M) float: last period's wall flag (0 at reset).
    """
    B, M = light.shape
    assert prev_wall.shape == (B, M), f"prev_wall shape {prev_wall.shape} != light shape {(B, M)}"
    summ = summarise(events, cfg, B, M)
    obs = np.zeros((B, M, cfg.obs_dim), np.float64)
    wall = (light >= cfg.light_threshold).astype(np.float64)
    obs[..., OBS_WALL] = np.where(light < 0, prev_wall, wall)
    obs[..., OBS_TARGET] = np.where(summ.target_heard,
                                    np.minimum(summ.target_dist_mm / cfg.comm_radius_mm, 1.0), -1.0)
    sensing_nbr = np.zeros(B * M)
    np.maximum.at(sensing_nbr, summ.table_env * M + summ.table_rx, summ.table_flag.astype(np.float64))
    obs[..., OBS_NBR_SENSING] = sensing_nbr.reshape(B, M)
    hist = np.zeros((B * M, cfg.n_rbf))
    np.add.at(hist, summ.table_env * M + summ.table_rx, rbf(cfg, summ.table_dist_mm))
    obs[..., OBS_RBF:] = hist.reshape(B, M, cfg.n_rbf)
    return obs.astype(np.float32), summ.target_heard.astype(np.uint8)


def _first_index_per_key(keys: np.ndarray) -> np.ndarray:
    """Index of the first occurrence of each distinct key (in order of the distinct keys)."""
    _, idx = np.unique(keys, return_index=True)
    return idx


def _last_index_per_key(keys: np.ndarray) -> np.ndarray:
    """Index of the last occurrence of each distinct key (in order of the distinct keys)."""
    _, idx = np.unique(keys[::-1], return_index=True)
    return keys.size - 1 - idx
