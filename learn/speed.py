"""Where and how fast the trainer computes: the device and the number of torch threads.

* ``--device auto`` is CUDA when torch sees a GPU, else the CPU; networks and replay tensors live
  there, the simulator stays NumPy (transfers go through reused pinned buffers, :mod:`learn.replay`).
* :func:`tune_allocator` keeps glibc's malloc from returning freed memory to the kernel and from
  mapping every large tensor afresh: an update allocates and frees the same sizes thousands of times,
  and the default thresholds turned that into page faults (issue 14: ≈5 M page faults per 100 s,
  10 % of CPU time in the kernel; raising the thresholds gave ×1.2 updates/s).
* ``--threads 0`` (auto): acting, evaluation and everything but the update blocks run on one torch thread;
  the update blocks of MAGDDPG/MAGRDPG (:class:`UpdateThreads`) run on one thread or on every usable core
  (at most :data:`AUTO_MAX_THREADS`), whichever the run measures faster, probing the other now and then.
  On a quiet 2-core machine two threads win (1.2x updates/s at 4 robots, 1.5x at 32 on issue 14's command);
  beside other work they are several times slower (oversubscribed cores: 3.4x on a fixed minibatch with the
  other core busy), which the probes notice. Auto never changes results: it uses more than one thread only
  after one update on both counts gave the same bits (:func:`threads_differ`; torch's float32 kernels
  here split rows, not sums), and never with bfloat16. ``--threads N`` fixes N threads for everything. Several
  trainings at once (seeds, a sweep) use the cores better still.
"""
from __future__ import annotations

import contextlib
import copy
import ctypes
import ctypes.util
import os
import statistics
import time
from collections import deque
from typing import Callable, Iterator

import torch

from .config import ConfigError


def resolve_device(name: str) -> torch.device:
    """``auto``, ``cpu`` or ``cuda`` as a torch device; one-line ConfigError when CUDA is asked for but absent."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device cuda: torch sees no CUDA GPU here; use --device cpu (or auto)")
    return torch.device(name)


def set_threads(threads: int) -> int:
    """Set torch's intra-op threads (0 = auto: 1 outside the update blocks); returns the number set."""
    n = threads or 1
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


AUTO_MAX_THREADS = 4  #: auto never tries more update threads than this (the networks are small)


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class UpdateThreads:
    """Torch threads for the update blocks: fixed (``--threads N``), or with ``--threads 0`` the faster of one
    thread and every usable core (at most :data:`AUTO_MAX_THREADS`), measured in seconds per update.

    Each candidate first runs ``window`` blocks (alternating); then the one with the lower median of its last
    ``window`` blocks runs, and every ``probe_every`` blocks the other runs one block. A probe that loses doubles
    the interval to the next (up to ``max_probe_every``), so a steadily busy or quiet machine pays little for
    probing; a switch resets it. Outside the blocks torch keeps one thread.

    Before the first auto block, ``differs(n)`` says why an update on ``n`` threads would not give exactly what
    it gives on one (None: it gives the same bits for the run's own shapes); if it says anything, every block
    runs on one thread and :attr:`why_one` says why.
    """

    def __init__(self, threads: int, device: torch.device | str = "cpu", cores: int | None = None,
                 differs: Callable[[int], str | None] | None = None, window: int = 3, probe_every: int = 16,
                 max_probe_every: int = 512, clock: Callable[[], float] = time.perf_counter) -> None:
        n = min(usable_cores() if cores is None else cores, AUTO_MAX_THREADS)
        auto = threads == 0 and torch.device(device).type == "cpu" and n > 1
        self.choices = (1, n) if auto else (threads or 1,)
        self.differs = differs
        self.why_one: str | None = None  #: why auto stays on one thread (None: it does not, or it was not asked)
        self.outside = threads or 1  #: threads outside the blocks
        self.window, self.base_probe, self.max_probe = window, probe_every, max_probe_every
        self.probe_every = probe_every
        self.clock = clock
        self.times = {c: deque(maxlen=window) for c in self.choices}  # seconds per update, recent blocks
        self.best = self.choices[0]
        self.since_probe = 0

    def next_choice(self) -> int:
        """The thread count of the next block."""
        if len(self.choices) > 1 and self.differs is not None:
            check, self.differs = self.differs, None
            why = check(self.choices[1])
            if why:
                self.why_one = f"{why}: auto keeps one thread so the run is reproducible (--threads N to choose)"
                self.choices = (1,)
        if len(self.choices) == 1:
            return self.choices[0]
        short = [c for c in self.choices if len(self.times[c]) < self.window]
        if short:
            return min(short, key=lambda c: len(self.times[c]))
        if self.since_probe >= self.probe_every:
            return next(c for c in self.choices if c != self.best)
        return self.best

    @contextlib.contextmanager
    def block(self, n_updates: int) -> Iterator[int]:
        """Run ``n_updates`` updates inside: on the chosen threads, timed (yields the thread count)."""
        n = self.next_choice()
        set_threads(n)
        t0 = self.clock()
        try:
            yield n
        finally:
            dt = self.clock() - t0
            set_threads(self.outside)
        if n_updates > 0:
            self.record(n, dt / n_updates)

    def record(self, n: int, per_update: float) -> None:
        """One block's seconds per update on ``n`` threads."""
        if len(self.choices) == 1:
            return
        measured = all(len(q) >= self.window for q in self.times.values())
        probing = measured and n != self.best
        if probing:
            # a probe that beats the best's median is checked again at once; one that loses waits longer
            faster = per_update < statistics.median(self.times[self.best])
            self.probe_every = 1 if faster else min(2 * self.probe_every, self.max_probe)
        self.times[n].append(per_update)
        self.since_probe = 0 if probing or not measured else self.since_probe + 1
        if any(len(q) < self.window for q in self.times.values()):
            return
        best = min(self.choices, key=lambda c: statistics.median(self.times[c]))
        if best != self.best:
            self.best, self.probe_every, self.since_probe = best, self.base_probe, 0


def threads_differ(algo, parts: list, bc_weight: float, n: int) -> str | None:
    """Why updates on ``n`` torch threads would not be bit for bit those on one, or None: one update on ``parts``
    is run both ways from the same state and compared (networks and optimiser state); the agent and torch's RNG
    are left as they were. Float32 kernels that split a sum across threads change almost every output, so one
    update shows it; bfloat16 ones round most such changes away and differ only now and then, so they are
    not tried."""
    if algo.precision != "fp32":
        return f"{algo.precision} products over long sums round differently on {n} threads now and then"
    start, rng = copy.deepcopy(algo.state_dict()), torch.get_rng_state()
    after = []
    for k in (1, n):
        set_threads(k)
        algo.update_parts(parts, bc_weight, train_actor=True)
        after.append(copy.deepcopy(algo.state_dict()))
        algo.load_state_dict(copy.deepcopy(start))
        torch.set_rng_state(rng)
    set_threads(1)
    return None if same_tensors(after[0], after[1]) else f"an update on {n} threads does not give the bits it gives on one"


def same_tensors(a, b) -> bool:
    """Two nested state dicts hold equal tensors (bit for bit) and equal other values."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_tensors(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_tensors(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    return a == b


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  #: glibc mallopt parameters (malloc.h)
TRIM_THRESHOLD = 1 << 30  #: keep up to 1 GiB of freed heap instead of returning it to the kernel
MMAP_THRESHOLD = 32 << 20  #: allocations below 32 MiB (glibc's maximum) come from the heap, not fresh mappings


def tune_allocator() -> bool:
    """Raise glibc's trim and mmap thresholds for this process (no-op elsewhere); returns whether it did."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)) and bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD))
