"""The per-robot random stream the firmware owns: Marsaglia's xorshift32 (13, 17, 5), one word per robot
seeded in ``setup()`` from ``kilo_uid`` (and, for the ``random`` observation feature, one ``rand_hard()`` byte).

The rule kinds (:mod:`kiloforge.actors.rules`) and the ``random`` feature (:mod:`sim.features`) draw from it;
its C twin is ``firmware_templates/_xorshift.c.j2``. NumPy only: the simulator imports it.
"""
from __future__ import annotations

import numpy as np

SEED_MUL = 0x9E3779B1  #: kilo_uid -> xorshift32 seed: uid * SEED_MUL + SEED_ADD (mod 2**32)
SEED_ADD = 0x7F4A7C15


def rng_seed(uids: np.ndarray, hard: np.ndarray | None = None) -> np.ndarray:
    """(R,) uint32 xorshift32 state setup() leaves for these kilo_uids (never 0); ``hard`` (R,) the byte
    rand_hard() returned in setup(), xored into the low byte (the ``random`` observation feature).

    >>> rng_seed(np.array([0, 1])).tolist()
    [2135587861, 495056326]
    """
    x = (np.asarray(uids, np.uint64) * SEED_MUL + SEED_ADD) & 0xFFFFFFFF
    if hard is not None:
        x = x ^ np.asarray(hard, np.uint64)
    return np.where(x == 0, 1, x).astype(np.uint32)


def xorshift32(x: np.ndarray) -> np.ndarray:
    """One step of Marsaglia's xorshift32 (13, 17, 5) on uint32 words.

    >>> xorshift32(np.array([1], np.uint32)).tolist()
    [270369]
    """
    x = np.asarray(x, np.uint32)
    x = x ^ (x << np.uint32(13))
    x = x ^ (x >> np.uint32(17))
    return x ^ (x << np.uint32(5))


def top_byte(word: np.ndarray) -> np.ndarray:
    """int64 signed top byte of xorshift32 words, in [-128, 127] (the ``random`` feature's draw)."""
    b = np.asarray(word, np.uint32).astype(np.int64) >> 24
    return np.where(b >= 128, b - 256, b)
