"""Where and how fast the trainer computes: the device and the number of torch threads.

* ``--device auto`` is CUDA when torch sees a GPU, else the CPU; networks and replay tensors live
  there, the simulator stays NumPy (transfers go through reused pinned buffers, :mod:`learn.replay`).
* ``--threads 0`` (auto) is one torch thread per process: the networks are small, and on a shared
  CPU more threads oversubscribe the cores (measured: 2 threads made updates 10-20x slower on a busy
  2-core machine). Run several trainings (seeds, a sweep) to use more cores.
"""
from __future__ import annotations

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
