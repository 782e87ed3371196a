"""Heard-message events and the observation computed from them (docs/design.md control-step contract).

The radio model (:mod:`sim.radio`) produces, for one control period, a flat list of *events*: one per
message that one robot received. The simulator turns them into observations with
:func:`observe`; the firmware (and its emulator, :mod:`export.verify.emulator`) consumes exactly the same
events tick by tick. This module is the single written-down definition of what a robot does with
what it hears, in float; the firmware does the same in fixed point.

Per receiver and control period (semantics shared with the firmware):

1. Events are taken in arrival order: by ``tick`` (0 .. period_ticks-1), ties in array order.
2. Target messages (``role == ROLE_TARGET``) fill one slot: the latest distance wins; the latest light reading
   a target message carries (``light`` >= 0) is kept too (the ``object_light`` feature holds it across periods).
3. Searcher messages go into a neighbour table of ``cfg.neighbour_table_size`` entries. A sender
   gets an entry at its first message of the period while the table has room; when the table is
   full, messages from senders without an entry are dropped for the rest of the period. Each later
   message of a sender that has an entry overwrites its distance and sensing flag (latest wins), so
   each sender counts once per period.
4. At the end of the period the observation is formed and the table is cleared: the world's features
   (``cfg.obs_features``, chosen by the task) in order, each as :func:`sim.features.reference` defines it
   (localisation: wall flag, target distance, "a neighbour senses the target", the RBF histogram).
5. The robot's own "I sense the target" flag for the next period's messages is
   ``target was heard this period``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import ROLE_TARGET, WorldConfig
from .features import rbf, reference

__all__ = ["HeardEvents", "PeriodSummary", "observe", "rbf", "summarise"]


@dataclass
class HeardEvents:
    """Messages received during one control period, flattened over envs and receivers.

    All arrays have shape (N,). ``sender`` is the robot index 0..M-1 of a searcher, or -1 for the
    task's transmitting robot (role 1, the uid the world names; searcher i has kilo_uid i + 1).
    ``dist_mm`` is the measured distance (float; integer-valued in worlds with ``dist_integer``).
    """

    env: np.ndarray  # (N,) int32, 0..B-1
    rx: np.ndarray  # (N,) int32, receiving robot 0..M-1
    sender: np.ndarray  # (N,) int32, sending robot 0..M-1, or -1 for the target
    tick: np.ndarray  # (N,) int16, tick within the period, 0..period_ticks-1
    dist_mm: np.ndarray  # (N,) float64, measured distance
    role: np.ndarray  # (N,) uint8, ROLE_SEARCHER or ROLE_TARGET
    flag: np.ndarray  # (N,) uint8, sender's "I sense the target" flag carried in the message
    #: (N,) int, the emitter's light reading a target message carries (-1: none); None: no message carries one
    light: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = self.env.shape[0]
        for name in ("rx", "sender", "tick", "dist_mm", "role", "flag") + (("light",) if self.light is not None else ()):
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
    #: (B, M) int, the light reading of the latest target message that carried one this period (-1: none)
    target_light: np.ndarray | None = None


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
    target_light = np.full(B * M, -1, np.int64)
    is_t = role == ROLE_TARGET
    if is_t.any():
        g_t, d_t = group[is_t], dist[is_t]
        # later assignments win in NumPy fancy assignment with repeated indices only by accident;
        # take the last occurrence explicitly
        last = _last_index_per_key(g_t)
        target_heard[g_t[last]] = True
        target_dist[g_t[last]] = d_t[last]
        if events.light is not None:
            lit = is_t & (events.light[order] >= 0)
            g_l = group[lit]
            if g_l.size:
                last = _last_index_per_key(g_l)
                target_light[g_l[last]] = events.light[order][lit][last]

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
                         t_d, t_f, target_light.reshape(B, M))


def observe(events: HeardEvents, light: np.ndarray, prev_wall: np.ndarray, cfg: WorldConfig,
            prev_light: np.ndarray | None = None, rand_word: np.ndarray | None = None,
            prev_object_light: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Observations (B, M, obs_dim) float32 and the robots' new sensing flags (B, M) uint8.

    ``light`` (B, M) int: ambient-light readings at the control tick (-1 = busy, keep last flag).
    ``prev_wall`` (B, M) float: last period's wall flag (0 at reset).
    ``prev_light`` (B, M) int: the held light reading before this period (-1: none; the ``light`` feature).
    ``prev_object_light`` (B, M) int: the emitter reading held before this period (-1: none; ``object_light``).
    """
    B, M = light.shape
    assert prev_wall.shape == (B, M), f"prev_wall shape {prev_wall.shape} != light shape {(B, M)}"
    summ = summarise(events, cfg, B, M)
    obs = np.zeros((B, M, cfg.obs_dim), np.float64)
    for name in cfg.features:
        obs[..., cfg.obs_slice(name)] = reference(name, summ, light, prev_wall, cfg, prev_light, rand_word,
                                                     prev_object_light)
    return obs.astype(np.float32), summ.target_heard.astype(np.uint8)


def _first_index_per_key(keys: np.ndarray) -> np.ndarray:
    """Index of the first occurrence of each distinct key (in order of the distinct keys)."""
    _, idx = np.unique(keys, return_index=True)
    return idx


def _last_index_per_key(keys: np.ndarray) -> np.ndarray:
    """Index of the last occurrence of each distinct key (in order of the distinct keys)."""
    _, idx = np.unique(keys[::-1], return_index=True)
    return keys.size - 1 - idx
