"""Checkpoints: everything needed to resume a run exactly, in one file written atomically.

A checkpoint is a nested dict of tensors and plain Python values (str, int, float, bool, list,
dict, None). NumPy arrays are stored as tensors and come back as arrays. It is written with
``torch.save`` to a temp file in the same directory, fsynced, then renamed over the old one, and
read with ``torch.load(weights_only=True)``, which refuses anything but tensors and plain data:
a checkpoint never runs code when it is loaded.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from export.atomic import new_file_mode, write_bytes_atomic

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
    """Write ``state`` to ``path`` atomically (temp file + fsync + os.replace)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(_to_torch(state), f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (``weights_only=True``: no code runs)."""
    return _from_torch(torch.load(Path(path), map_location="cpu", weights_only=True))


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write a small text file atomically (UTF-8)."""
    return write_bytes_atomic(path, text)
