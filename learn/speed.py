"""Where and how fast the trainer computes: the device and the number of torch threads.

* ``--device auto`` is CUDA when torch sees a GPU, else the CPU; networks and replay tensors live
  there, the simulator stays NumPy (transfers go through reused pinned buffers, :mod:`learn.replay`).
* :func:`tune_allocator` keeps glibc's malloc from returning freed memory to the kernel and from
  mapping every large tensor afresh: an update allocates and frees the same sizes thousands of times,
  and the default thresholds turned that into page faults (issue 14: ≈5 M page faults per 100 s,
  10 % of CPU time in the kernel; raising the thresholds gave ×1.2 updates/s).
* ``--threads 0`` (auto) is one torch thread per process: the networks are small, and on a shared
  CPU more threads oversubscribe the cores (measured: 2 threads made updates 10-20x slower on a busy
  2-core machine). Run several trainings (seeds, a sweep) to use more cores.
"""
from __future__ import annotations

import ctypes
import ctypes.util

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
    """Set torch's intra-op threads (0 = auto: 1); returns the number set."""
    n = threads or 1
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    return n


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
