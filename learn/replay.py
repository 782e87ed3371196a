"""Replay memory of MAGDDPG transitions (s, h, a, r, s', h') stored as episodes (Algorithm 4).

Storing the joint histories h and h' of every transition would cost 2 · M · t_prev · tuple_dim
floats per transition (5 GB for the thesis's 500 000 transitions of 4 robots). Consecutive
histories share all but one tuple, so the memory keeps each episode's tuples once and rebuilds the
histories when it samples:

* ``tuples[e, k]`` (M, tuple_dim): the tuple ``(a_{k-1}, o_k)`` that the robots pushed at step k of
  episode slot e (k = 0 is ``(0, o_0)``, Algorithm 4's initial tuple);
* ``states[e, k]``: the critic state s_k; ``rewards[e, k]``: r_k for the move from k to k+1.

Transition (e, t) is ``s = states[e, t]``, ``a = tuples[e, t+1][:, :2]``, ``r = rewards[e, t]``,
``s' = states[e, t+1]``, and ``h`` / ``h'`` are the t_prev tuples ending at k = t / t + 1, with
indices before the episode start clamped to 0 — exactly Algorithm 4's "first tuple repeated"
initialisation, and what :class:`sim.history.History` holds at that step.

Slots form a ring: a new episode overwrites the oldest. Sampling is uniform over every stored
transition, including those of the episodes being collected.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.config import ACTION_DIM


@dataclass
class Batch:
    """A minibatch of N transitions (NumPy float32)."""

    s: np.ndarray  # (N, S)
    h: np.ndarray  # (N, M, t_prev * tuple_dim)
    a: np.ndarray  # (N, M, 2)
    r: np.ndarray  # (N,)
    s2: np.ndarray  # (N, S)
    h2: np.ndarray  # (N, M, t_prev * tuple_dim)


class EpisodeReplay:
    """Ring of ``capacity // episode_steps`` episode slots of fixed length ``episode_steps``."""

    def __init__(self, capacity: int, episode_steps: int, n_robots: int, tuple_dim: int,
                 state_dim: int, t_prev: int) -> None:
        assert episode_steps >= 1, f"episode_steps must be >= 1, got {episode_steps}"
        assert capacity >= episode_steps, f"capacity {capacity} < one episode ({episode_steps})"
        assert t_prev >= 1, f"t_prev must be >= 1, got {t_prev}"
        self.T = episode_steps
        self.t_prev = t_prev
        self.n_slots = capacity // episode_steps
        C, T, M = self.n_slots, episode_steps, n_robots
        self.tuples = np.zeros((C, T + 1, M, tuple_dim), np.float32)
        self.states = np.zeros((C, T + 1, state_dim), np.float32)
        self.rewards = np.zeros((C, T), np.float32)
        self.filled = np.zeros(C, np.int64)  # transitions stored per slot, 0..T
        self.next_slot = 0  # ring position of the next episode to begin
        self.wrapped = False  # every slot has been used at least once
        self.active = np.zeros(0, np.int64)  # slots of the episodes being collected
        self.step = 0  # transitions stored so far in each active slot

    def __len__(self) -> int:
        return int(self.filled.sum())

    @property
    def capacity(self) -> int:
        return self.n_slots * self.T

    def begin(self, first_tuples: np.ndarray, states: np.ndarray) -> None:
        """Start B episodes: ``first_tuples`` (B, M, tuple_dim) = (0, o_0), ``states`` (B, S) = s_0."""
        B = first_tuples.shape[0]
        assert B <= self.n_slots, f"{B} parallel episodes do not fit {self.n_slots} slots"
        self.active = (self.next_slot + np.arange(B)) % self.n_slots
        self.wrapped |= self.next_slot + B >= self.n_slots
        self.next_slot = int((self.next_slot + B) % self.n_slots)
        self.filled[self.active] = 0  # overwrite the oldest episodes
        self.tuples[self.active, 0] = first_tuples
        self.states[self.active, 0] = states
        self.step = 0

    def add(self, tuples: np.ndarray, states: np.ndarray, rewards: np.ndarray) -> None:
        """One step of the B active episodes: tuples (a_t, o_{t+1}), s_{t+1}, r_t."""
        assert self.step < self.T, f"episode longer than episode_steps={self.T}"
        k = self.step + 1
        self.tuples[self.active, k] = tuples
        self.states[self.active, k] = states
        self.rewards[self.active, self.step] = rewards
        self.step = k
        self.filled[self.active] = k

    def sample(self, n: int, rng: np.random.Generator) -> Batch:
        """N transitions drawn uniformly (with replacement) from everything stored."""
        cum = np.cumsum(self.filled)  # (C,)
        total = int(cum[-1])
        assert total > 0, "sampling from an empty replay memory"
        k = rng.integers(0, total, n)  # (N,) flat transition index
        e = np.searchsorted(cum, k, side="right")  # (N,) slot holding it
        t = k - (cum[e] - self.filled[e])  # (N,) step within the slot
        return self.gather(e, t)

    def gather(self, e: np.ndarray, t: np.ndarray) -> Batch:
        """The transitions (e, t) (arrays of equal shape (N,))."""
        h = self.history(e, t)
        h2 = self.history(e, t + 1)
        return Batch(s=self.states[e, t], h=h, a=self.tuples[e, t + 1, :, :ACTION_DIM],
                     r=self.rewards[e, t], s2=self.states[e, t + 1], h2=h2)

    def history(self, e: np.ndarray, k: np.ndarray) -> np.ndarray:
        """Flat histories (N, M, t_prev * tuple_dim) ending at tuple k, oldest first, clamped at 0."""
        idx = np.maximum(k[:, None] + np.arange(1 - self.t_prev, 1), 0)  # (N, t_prev)
        h = self.tuples[e[:, None], idx]  # (N, t_prev, M, D)
        N, T, M, D = h.shape
        return np.ascontiguousarray(h.transpose(0, 2, 1, 3)).reshape(N, M, T * D)

    # --- checkpointing -----------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray | int]:
        """Arrays trimmed to the slots ever used, plus the ring position."""
        used = self.n_slots if self.wrapped else self.next_slot
        return {"tuples": self.tuples[:used], "states": self.states[:used],
                "rewards": self.rewards[:used], "filled": self.filled[:used],
                "next_slot": self.next_slot, "wrapped": self.wrapped, "active": self.active, "step": self.step}

    def load_state_dict(self, d: dict) -> None:
        used = d["filled"].shape[0]
        assert used <= self.n_slots and d["tuples"].shape[1:] == self.tuples.shape[1:], \
            "replay checkpoint does not match this configuration"
        self.tuples[:used] = d["tuples"]
        self.states[:used] = d["states"]
        self.rewards[:used] = d["rewards"]
        self.filled[:] = 0
        self.filled[:used] = d["filled"]
        self.next_slot = int(d["next_slot"])
        self.wrapped = bool(d["wrapped"])
        self.active = np.asarray(d["active"], np.int64)
        self.step = int(d["step"])
