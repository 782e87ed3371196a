"""Checkpoints: everything needed to resume a run exactly, in one file written atomically.

A checkpoint is a nested dict of tensors and plain Python values (str, int, float, bool, list,
dict, None). NumPy arrays are stored as tensors and come back as arrays. It is written with
``torch.save`` to a temp file in the same directory, fsynced, then renamed over the old one, and
read with ``torch.load(weights_only=True)``, which refuses anything but tensors and plain data:
a checkpoint never runs code when it is loaded.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kiloforge.io import atomic_path

_NP_TAG = "__ndarray__"


def _to_torch(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return {_NP_TAG: torch.from_numpy(np.ascontiguousarray(obj))}
    if isinstance(obj, dict):
        return {k: _to_torch(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_torch(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _from_torch(obj: Any) -> Any:
    if isinstance(obj, dict):
        if set(obj) == {_NP_TAG}:
            return obj[_NP_TAG].numpy()
        return {k: _from_torch(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_from_torch(v) for v in obj]
    return obj


def save_checkpoint(state: dict, path: str | os.PathLike) -> Path:
    """Write ``state`` to ``path`` atomically (:func:`kiloforge.io.atomic_path`)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        torch.save(_to_torch(state), tmp)
    return path


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: no code runs)."""
    return _from_torch(torch.load(Path(path), map_location="cpu", weights_only=True))
