"""The T_prev history of (previous action, observation) tuples (thesis Algorithm 4).

One definition for the trainer, the simulator wrappers and the exporter. The firmware keeps the
same history in a ring buffer and reads it oldest → newest without copying; :meth:`History.flat`
gives the actor input in exactly that order: ``[a_prev, o]`` of the oldest tuple first, each tuple
``ACTION_DIM + obs_dim`` wide.

Initialisation (Algorithm 4): the first tuple ``(a_0 = 0, o_1)`` repeated ``t_prev`` times.
"""
from __future__ import annotations

import numpy as np

from .config import ACTION_DIM


class History:
    """Ring buffer of shape (B, M, t_prev, ACTION_DIM + obs_dim), vectorised over envs and robots."""

    def __init__(self, t_prev: int, obs_dim: int) -> None:
        assert t_prev >= 1, f"history length t_prev must be >= 1, got {t_prev}"
        assert obs_dim >= 1, f"obs_dim must be >= 1, got {obs_dim}"
        self.t_prev = t_prev
        self.tuple_dim = ACTION_DIM + obs_dim
        self.buf: np.ndarray | None = None  # (B, M, T, tuple_dim)
        self.head = 0  # index of the oldest tuple

    def reset(self, obs: np.ndarray) -> np.ndarray:
        """Fill with (a_0 = 0, o_1) repeated; returns the flat history (B, M, t_prev * tuple_dim)."""
        B, M, D = obs.shape
        assert D + ACTION_DIM == self.tuple_dim, f"obs width {D} != {self.tuple_dim - ACTION_DIM}"
        first = np.concatenate([np.zeros((B, M, ACTION_DIM), np.float32), obs.astype(np.float32)], -1)
        self.buf = np.repeat(first[:, :, None, :], self.t_prev, axis=2)  # (B, M, T, tuple_dim)
        self.head = 0
        return self.flat()

    def push(self, action: np.ndarray, obs: np.ndarray) -> np.ndarray:
        """Drop the oldest tuple, append (action, obs); returns the flat history."""
        assert self.buf is not None, "History.push before reset"
        B, M, T, _ = self.buf.shape
        assert action.shape == (B, M, ACTION_DIM), f"action shape {action.shape} != {(B, M, ACTION_DIM)}"
        assert obs.shape == (B, M, self.tuple_dim - ACTION_DIM), f"obs shape {obs.shape} is wrong"
        self.buf[:, :, self.head, :ACTION_DIM] = action
        self.buf[:, :, self.head, ACTION_DIM:] = obs
        self.head = (self.head + 1) % T  # the slot just written becomes the newest
        return self.flat()

    def reset_where(self, done: np.ndarray, obs: np.ndarray) -> None:
        """Re-initialise the envs where ``done`` (B,) is set from their new first observation."""
        assert self.buf is not None, "History.reset_where before reset"
        if not done.any():
            return
        first = np.concatenate([np.zeros(obs.shape[:2] + (ACTION_DIM,), np.float32),
                                obs.astype(np.float32)], -1)  # (B, M, tuple_dim)
        self.buf[done] = first[done][:, :, None, :]

    def flat(self) -> np.ndarray:
        """Actor input (B, M, t_prev * tuple_dim), oldest tuple first."""
        assert self.buf is not None, "History.flat before reset"
        B, M, T, D = self.buf.shape
        h = self.head  # two slice copies: several times faster than a fancy-index gather on axis 2
        return np.concatenate((self.buf[:, :, h:], self.buf[:, :, :h]), axis=2).reshape(B, M, T * D)
