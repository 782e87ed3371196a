"""Replay memory of whole episodes, and the two ways of sampling it: transitions (MAGDDPG) and windows (MAGRDPG).

Storing the joint histories h and h' of every transition would cost 2 · M · t_prev · tuple_dim floats
per transition (5 GB for the thesis's 500 000 transitions of 4 robots). Consecutive histories share all
but one tuple, so the memory keeps each episode's tuples once and cuts what it samples out of them:

* ``tuples[e, i, k]`` (tuple_dim,): the tuple ``(a_{k-1}, o_k)`` robot i pushed at step k of episode
  slot e (k = 0 is ``(0, o_0)``, Algorithm 4's initial tuple); stored robot-major behind t_prev − 1
  copies of tuple 0, so every history of a robot is one contiguous run of memory;
* ``states[e, k]``: the critic state s_k; ``rewards[e, k]``: r_k for the move from k to k+1 (the team's
  reward, or with ``per_robot_rewards`` one per robot, (M,): ``--reward local``).

Transition (e, t) is ``s = states[e, t]``, ``a = tuples[e, :, t+1, :2]``, ``r = rewards[e, t]``,
``s' = states[e, t+1]``, and ``h`` / ``h'`` are the t_prev tuples ending at k = t / t + 1, with indices
before the episode start clamped to 0 — exactly Algorithm 4's "first tuple repeated" initialisation,
and what :class:`sim.history.History` holds at that step. :meth:`EpisodeReplay.sample` gathers the
t_prev + 1 tuples ending at t + 1 once per robot (one contiguous run each, thanks to the leading
copies of tuple 0), and h and h' are overlapping views of that one window.

The arrays are torch tensors on the training device; sampled minibatches are views into buffers
the memory allocates once per minibatch size (valid until the next sample of that size). Slots form a
ring: a new episode overwrites the oldest. Sampling is uniform over every stored transition, including
those of the episodes being collected. Slots are grouped in blocks for incremental checkpoints
(:mod:`learn.checkpoint`): only blocks written since the last checkpoint are saved again.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch

from sim.config import ACTION_DIM

BLOCK_BYTES = 8 << 20  #: target size of one checkpoint block of slots


@dataclass
class Batch:
    """A minibatch of N transitions (torch float32 on the replay's device)."""

    s: torch.Tensor  #: (N, S)
    h: torch.Tensor  #: (N, M, t_prev * tuple_dim)
    a: torch.Tensor  #: (N, M, 2)
    r: torch.Tensor  #: (N,), or (N, M) per-robot rewards (the replay's ``reward_shape``)
    s2: torch.Tensor  #: (N, S)
    h2: torch.Tensor  #: (N, M, t_prev * tuple_dim)
    o: torch.Tensor | None = None  #: (N, M, obs_dim) observations o_t (the newest tuple of h)
    o2: torch.Tensor | None = None  #: (N, M, obs_dim) o_{t+1}

    def __len__(self) -> int:
        return int(self.s.shape[0])


@dataclass
class Windows:
    """A minibatch of N windows: L = burn_in + unroll + 1 inputs per robot, unroll transitions.

    A window starts at tuple k_0 = max(0, t_s - burn_in) with a zero hidden state (exact when
    k_0 = 0: the episode's own start), so step t_s is at position ``off = t_s - k_0``; positions
    beyond the episode's stored end repeat its last tuple and are never used.
    """

    x: torch.Tensor  #: (N, M, L, D) actor inputs [a_{k-1}, o_k] for k = k_0 .. k_0 + L - 1
    off: torch.Tensor  #: (N,) position of t_s in the window (burn-in steps actually replayed)
    s: torch.Tensor  #: (N, U, S) s_t for t = t_s .. t_s + U - 1
    a: torch.Tensor  #: (N, U, M, 2) executed actions a_t
    r: torch.Tensor  #: (N, U) rewards r_t, or (N, U, M) per-robot rewards
    s2: torch.Tensor  #: (N, U, S) s_{t+1}
    o: torch.Tensor | None = None  #: (N, U, M, obs_dim) o_t
    o2: torch.Tensor | None = None  #: (N, U, M, obs_dim) o_{t+1}

    def __len__(self) -> int:
        return int(self.s.shape[0])


def concat(a, b):
    """The samples of ``a`` followed by those of ``b`` (two Batch or two Windows of one layout)."""
    return type(a)(**{f.name: None if getattr(a, f.name) is None else torch.cat([getattr(a, f.name), getattr(b, f.name)])
                      for f in fields(a)})


def split(batch, n_tail: int) -> list:
    """``batch`` as [its first len - n_tail samples, its last n_tail] (views; empty parts left out)."""
    n = len(batch)
    cuts = [(0, n - n_tail), (n - n_tail, n)]
    return [type(batch)(**{f.name: None if getattr(batch, f.name) is None else getattr(batch, f.name)[i:j]
                           for f in fields(batch)}) for i, j in cuts if j > i]


class EpisodeReplay:
    """Ring of ``capacity // episode_steps`` episode slots of fixed length ``episode_steps``."""

    def __init__(self, capacity: int, episode_steps: int, n_robots: int, tuple_dim: int,
                 state_dim: int, t_prev: int = 1, device: str | torch.device = "cpu", with_obs: bool = False,
                 per_robot_rewards: bool = False) -> None:
        assert episode_steps >= 1, f"episode_steps must be >= 1, got {episode_steps}"
        assert capacity >= episode_steps, f"capacity {capacity} < one episode ({episode_steps})"
        assert t_prev >= 1, f"t_prev must be >= 1, got {t_prev}"
        self.T, self.t_prev, self.M, self.D, self.S = episode_steps, t_prev, n_robots, tuple_dim, state_dim
        self.device = torch.device(device)
        self.with_obs = with_obs
        self.n_slots = capacity // episode_steps
        C, T, M, D = self.n_slots, episode_steps, n_robots, tuple_dim
        z = dict(dtype=torch.float32, device=self.device)
        self.pad = t_prev - 1  # leading copies of tuple 0: a history never needs clamping
        self._store = torch.zeros((C, M, self.pad + T + 1, D), **z)
        self.tuples = self._store[:, :, self.pad:]  # (C, M, T + 1, D) view
        self.states = torch.zeros((C, T + 1, state_dim), **z)
        self.reward_shape = (M,) if per_robot_rewards else ()  # one transition's reward: the team's, or one per robot
        self.R = math.prod(self.reward_shape)  # rewards per transition
        self.rewards = torch.zeros((C, T) + self.reward_shape, **z)
        self.filled = np.zeros(C, np.int64)  # transitions stored per slot, 0..T
        self.next_slot = 0  # ring position of the next episode to begin
        self.wrapped = False  # every slot has been used at least once
        self.active = np.zeros(0, np.int64)  # slots of the episodes being collected
        self.step = 0  # transitions stored so far in each active slot
        slot_bytes = 4 * (M * (self.pad + T + 1) * D + (T + 1) * state_dim + T * self.R)
        self.block_slots = max(1, BLOCK_BYTES // slot_bytes)
        self.dirty = np.zeros(self.n_blocks, bool)  # blocks written since the last checkpoint
        self._buffers: dict[tuple, torch.Tensor] = {}
        self._active_t: slice | torch.Tensor = slice(0, 0)  # active slots for torch writes
        self._active_np: slice | np.ndarray = slice(0, 0)  # ... and for NumPy writes
        self._views: dict[str, np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self.filled.sum())

    @property
    def capacity(self) -> int:
        return self.n_slots * self.T

    @property
    def n_blocks(self) -> int:
        return -(-self.n_slots // self.block_slots)

    # --- writing -------------------------------------------------------------------------------
    def _to_device(self, x: np.ndarray, dtype=np.float32) -> torch.Tensor:
        """A NumPy array on the device: zero-copy on the CPU, through a reused pinned buffer otherwise."""
        x = np.ascontiguousarray(x, dtype)
        if self.device.type == "cpu":
            return torch.from_numpy(x)
        key = ("pinned", x.dtype.str, x.shape)
        stage = self._buffers.get(key)
        if stage is None:
            stage = self._buffers[key] = torch.empty(x.shape, dtype=torch.from_numpy(x[:0]).dtype).pin_memory()
        stage.numpy()[...] = x
        return stage.to(self.device)  # synchronous: the pinned buffer is reused by the next call

    def begin(self, first_tuples: np.ndarray, states: np.ndarray) -> None:
        """Start B episodes: ``first_tuples`` (B, M, tuple_dim) = (0, o_0), ``states`` (B, S) = s_0."""
        B = first_tuples.shape[0]
        assert B <= self.n_slots, f"{B} parallel episodes do not fit {self.n_slots} slots"
        self.active = (self.next_slot + np.arange(B)) % self.n_slots
        self.wrapped |= self.next_slot + B >= self.n_slots
        self.next_slot = int((self.next_slot + B) % self.n_slots)
        self.filled[self.active] = 0  # overwrite the oldest episodes
        self.dirty[self.active // self.block_slots] = True
        self._set_active(self.active)
        self._write("store", (slice(None), slice(0, self.pad + 1)), first_tuples[:, :, None])
        self._write("states", (0,), states)
        self.step = 0

    def _write(self, name: str, index: tuple, x: np.ndarray) -> None:
        """array[active slots, *index] = x: through NumPy views on the CPU (a few µs), torch otherwise."""
        if self.device.type == "cpu":
            if self._views is None:
                self._views = {n: getattr(self, a).numpy() for n, a in
                               (("store", "_store"), ("tuples", "tuples"), ("states", "states"), ("rewards", "rewards"))}
            self._views[name][(self._active_np,) + index] = x
        else:
            dst = {"store": self._store, "tuples": self.tuples, "states": self.states, "rewards": self.rewards}[name]
            dst[(self._active_t,) + index] = self._to_device(np.asarray(x, np.float32))

    def _set_active(self, active: np.ndarray) -> None:
        """Index of the active slots for writing: a slice when they are consecutive (fast copies)."""
        a = np.asarray(active, np.int64)
        if a.size and np.array_equal(a, np.arange(a[0], a[0] + a.size)):
            self._active_np = self._active_t = slice(int(a[0]), int(a[0]) + a.size)
        else:
            self._active_np, self._active_t = a, self._to_device(a, np.int64).clone()

    def add(self, tuples: np.ndarray, states: np.ndarray, rewards: np.ndarray) -> None:
        """One step of the B active episodes: tuples (a_t, o_{t+1}), s_{t+1}, r_t."""
        assert self.step < self.T, f"episode longer than episode_steps={self.T}"
        k = self.step + 1
        self._write("tuples", (slice(None), k), tuples)
        self._write("states", (k,), states)
        self._write("rewards", (self.step,), rewards)
        self.step = k
        self.filled[self.active] = k

    # --- sampling ------------------------------------------------------------------------------
    def _buffer(self, key: tuple, shape: tuple[int, ...]) -> torch.Tensor:
        buf = self._buffers.get(key)
        if buf is None or tuple(buf.shape) != shape:
            buf = self._buffers[key] = torch.empty(shape, dtype=torch.float32, device=self.device)
        return buf

    def _gather(self, src: torch.Tensor, rows: np.ndarray, key: str) -> torch.Tensor:
        """src rows (flattened leading dims) at ``rows`` (any shape) into a reused buffer of shape rows.shape + (width,)."""
        flat = src.view(-1, src.shape[-1])
        out = self._buffer((key, rows.shape), rows.shape + (flat.shape[1],))
        torch.index_select(flat, 0, self._to_device(rows.ravel(), np.int64), out=out.view(-1, flat.shape[1]))
        return out

    def _tuple_rows(self, e: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """Flat row numbers (N, M, L) of the stored tuples[e, i, idx] for every robot i."""
        M, L1 = self.M, self.pad + self.T + 1
        return ((e[:, None] * M + np.arange(M))[:, :, None] * L1 + self.pad + idx[:, None, :])

    def _locate(self, per_slot: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """N (slot, step) pairs uniform over ``per_slot[e]`` admissible steps of every slot."""
        cum = np.cumsum(per_slot)
        total = int(cum[-1])
        assert total > 0, "sampling from an empty replay memory (or no episode long enough yet)"
        k = rng.integers(0, total, n)
        e = np.searchsorted(cum, k, side="right")
        return e, k - (cum[e] - per_slot[e])

    def sample(self, n: int, rng: np.random.Generator) -> Batch:
        """N transitions drawn uniformly (with replacement) from everything stored."""
        e, t = self._locate(self.filled, n, rng)
        return self.gather(e, t)

    def gather(self, e: np.ndarray, t: np.ndarray) -> Batch:
        """The transitions (e, t) (integer arrays of equal shape (N,)) by one gather of t_prev + 1 tuples."""
        e, t = np.asarray(e, np.int64), np.asarray(t, np.int64)
        N, M, P, D = e.shape[0], self.M, self.t_prev, self.D
        # robot i's tuples t-P+1 .. t+1 (clamped at 0) are the run of P + 1 stored rows starting at padded index t
        starts = ((e[:, None] * M + np.arange(M)) * (self.pad + self.T + 1) + t[:, None])  # (N, M)
        runs = self._store.view(-1).as_strided((self._store.numel() // D - P, (P + 1) * D), (D, 1))
        x = self._gather(runs, starts, "x").view(N, M, P + 1, D)
        srow = e * (self.T + 1) + t
        st = self._gather(self.states, np.stack([srow, srow + 1], 1), "s")  # (N, 2, S)
        r = self._gather(self.rewards.view(-1, self.R), (e * self.T + t)[:, None], "r")  # (N, 1, R)
        obs = (x[:, :, -2, ACTION_DIM:], x[:, :, -1, ACTION_DIM:]) if self.with_obs else (None, None)
        return Batch(s=st[:, 0], h=x[:, :, :-1].reshape(N, M, P * D), a=x[:, :, -1, :ACTION_DIM],
                     r=r.view(N, *self.reward_shape), s2=st[:, 1], h2=x[:, :, 1:].reshape(N, M, P * D), o=obs[0], o2=obs[1])

    def sample_windows(self, n: int, burn_in: int, unroll: int, rng: np.random.Generator) -> Windows:
        """N windows with start t_s uniform over every stored (episode, t_s <= filled - unroll)."""
        starts = np.maximum(self.filled - unroll + 1, 0)  # (C,) admissible t_s per slot
        e, ts = self._locate(starts, n, rng)
        k0 = np.maximum(ts - burn_in, 0)
        L = burn_in + unroll + 1
        idx = np.minimum(k0[:, None] + np.arange(L), self.filled[e][:, None])  # (N, L)
        x = self._gather(self._store, self._tuple_rows(e, idx), "wx")  # (N, M, L, D)
        off = ts - k0
        srow = (e * (self.T + 1) + ts)[:, None] + np.arange(unroll + 1)
        st = self._gather(self.states, srow, "ws")  # (N, U + 1, S)
        r = self._gather(self.rewards.view(-1, self.R), (e * self.T + ts)[:, None] + np.arange(unroll), "wr")
        # a_t (t = t_s + u) is the action of tuple t + 1: window position off + 1 + u
        pos = self._to_device(off[:, None] + 1 + np.arange(unroll), np.int64)  # (N, U)
        rows = torch.arange(n, device=self.device)[:, None]
        xt = x.permute(0, 2, 1, 3)  # (N, L, M, D) view
        nxt = xt[rows, pos]  # (N, U, M, D): tuples t + 1
        obs = (xt[rows, pos - 1][..., ACTION_DIM:], nxt[..., ACTION_DIM:]) if self.with_obs else (None, None)
        return Windows(x=x, off=self._to_device(off, np.int64).clone(), s=st[:, :-1], a=nxt[..., :ACTION_DIM],
                       r=r.view(n, unroll, *self.reward_shape), s2=st[:, 1:], o=obs[0], o2=obs[1])

    # --- checkpointing -------------------------------------------------------------------------
    def meta(self) -> dict:
        """Ring position and fill levels (small; goes into every checkpoint)."""
        return {"filled": self.filled.copy(), "next_slot": self.next_slot, "wrapped": self.wrapped,
                "active": self.active.copy(), "step": self.step, "block_slots": self.block_slots,
                "shape": [self.n_slots, self.M, self.T, self.D, self.S]}

    def used_blocks(self) -> list[int]:
        """Blocks holding slots ever used."""
        used = self.n_slots if self.wrapped else self.next_slot
        return list(range(-(-used // self.block_slots)))

    def block(self, b: int) -> dict[str, torch.Tensor]:
        """The arrays of block b (CPU copies: saving a view would save the whole memory)."""
        sl = slice(b * self.block_slots, min((b + 1) * self.block_slots, self.n_slots))
        return {name: getattr(self, name)[sl].to("cpu", copy=True) for name in ("tuples", "states", "rewards")}

    def load_meta(self, d: dict) -> None:
        if list(d["shape"]) != [self.n_slots, self.M, self.T, self.D, self.S] or d["block_slots"] != self.block_slots:
            raise ValueError("replay checkpoint does not match this configuration")
        self.filled[:] = np.asarray(d["filled"], np.int64)
        self.next_slot = int(d["next_slot"])
        self.wrapped = bool(d["wrapped"])
        self.active = np.asarray(d["active"], np.int64)
        self._set_active(self.active)
        self.step = int(d["step"])
        self.dirty[:] = False

    def load_block(self, b: int, arrays: dict) -> None:
        sl = slice(b * self.block_slots, min((b + 1) * self.block_slots, self.n_slots))
        for name in ("tuples", "states", "rewards"):
            src = torch.as_tensor(arrays[name])
            dst = getattr(self, name)[sl]
            if tuple(src.shape) != tuple(dst.shape):
                raise ValueError(f"replay block {b} has {name} of shape {tuple(src.shape)}, expected {tuple(dst.shape)}")
            dst.copy_(src)
        self._store[sl, :, :self.pad] = self._store[sl, :, self.pad:self.pad + 1]

    def state_dict(self) -> dict:
        """Everything, in one dict (meta and the used slots' arrays)."""
        used = self.n_slots if self.wrapped else self.next_slot
        return {**self.meta(), **{name: getattr(self, name)[:used].to("cpu", copy=True)
                                  for name in ("tuples", "states", "rewards")}}

    def load_state_dict(self, d: dict) -> None:
        self.load_meta(d)
        used = d["tuples"].shape[0]
        for name in ("tuples", "states", "rewards"):
            getattr(self, name)[:used].copy_(torch.as_tensor(d[name]))
        self._store[:used, :, :self.pad] = self._store[:used, :, self.pad:self.pad + 1]
