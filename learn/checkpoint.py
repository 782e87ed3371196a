"""Checkpoints: everything needed to resume a run exactly, written atomically and incrementally.

A run directory's checkpoint is ``checkpoint.pt`` plus the replay memory in blocks under
``replay/`` (``g{group}_b{block}_{generation}.pt``). Every file is *self-verifying*: an 8-byte magic,
the payload's length and SHA-256, then the payload (``torch.save`` of a nested dict of tensors and
plain values; NumPy arrays are stored as tensors and come back as arrays). It is read with
``torch.load(weights_only=True)``, which refuses anything but tensors and plain data: a checkpoint
never runs code when it is loaded. A truncated or altered file is refused with one line.

Incremental: a block is written again only when an episode slot in it changed since the last
checkpoint; each write gets a new generation number, and ``checkpoint.pt`` (written last, atomically)
names the exact block files (and their hashes) it belongs with. Killing the process at any moment
therefore leaves the previous checkpoint and its blocks intact: resuming continues exactly from it.
Block files no checkpoint names (and orphan temporary files) are removed when a run starts.
"""
from __future__ import annotations

import hashlib
import os
import re
import struct
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch

from kiloforge.io import atomic_path

from .config import ConfigError

_NP_TAG = "__ndarray__"
MAGIC = b"KFCKPT01"
_HEADER = struct.Struct("<8sQ32s")  # magic, payload length, sha256
REPLAY_DIR = "replay"
_BLOCK_RE = re.compile(r"g(\d+)_b(\d+)_(\d+)\.pt$")


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


def save_file(state: Any, path: str | os.PathLike) -> str:
    """Write ``state`` to ``path`` atomically as a self-verifying file; returns the payload's SHA-256."""
    import io

    buf = io.BytesIO()
    torch.save(_to_torch(state), buf)
    payload = buf.getbuffer()
    digest = hashlib.sha256(payload).digest()

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(_HEADER.pack(MAGIC, len(payload), digest))
        f.write(payload)
    return digest.hex()


def load_file(path: str | os.PathLike, sha256: str | None = None) -> Any:
    """Read a file written by :func:`save_file`; a missing, truncated, altered or foreign file is a
    one-line :class:`ConfigError` (``sha256``: the digest it must have)."""
    import io

    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"checkpoint file '{path}' is missing; the run cannot be resumed exactly") from None
    except OSError as e:
        raise ConfigError(f"cannot read checkpoint file '{path}': {e.strerror or e}") from None
    if len(data) < _HEADER.size or data[:8] != MAGIC:
        hint = " (written by an older kiloforge: resume it with that version)" if data[:2] == b"PK" else ""
        raise ConfigError(f"'{path}' is not a kiloforge checkpoint file{hint}")
    _, length, digest = _HEADER.unpack_from(data)
    payload = memoryview(data)[_HEADER.size:]
    if len(payload) != length:
        raise ConfigError(f"checkpoint file '{path}' is truncated ({len(payload)} of {length} payload bytes); "
                          "delete it to restart the run, or restore a complete copy")
    if hashlib.sha256(payload).digest() != digest or (sha256 is not None and digest.hex() != sha256):
        raise ConfigError(f"checkpoint file '{path}' does not match its hash (corrupt or from another checkpoint)")
    return _from_torch(torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True))


class Checkpointer:
    """Writes and reads a run directory's checkpoint with its replay blocks (see the module doc)."""

    def __init__(self, run_dir: str | os.PathLike) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / "checkpoint.pt"
        self.refs: dict[tuple[int, int], dict] = {}  # (group, block) -> {"file", "sha256"} of the last checkpoint
        self.generation = 0

    def exists(self) -> bool:
        return self.path.is_file()

    def save(self, state: dict, replays: Iterable) -> None:
        """``state`` and the replay memories' blocks written since the last save, then checkpoint.pt."""
        replays = list(replays)
        blocks_dir = self.run_dir / REPLAY_DIR
        blocks_dir.mkdir(exist_ok=True)
        self.generation += 1
        refs = dict(self.refs)
        for g, rep in enumerate(replays):
            for b in rep.used_blocks():
                if (g, b) in refs and not rep.dirty[b]:
                    continue
                name = f"g{g}_b{b}_{self.generation}.pt"
                refs[(g, b)] = {"file": name, "sha256": save_file(rep.block(b), blocks_dir / name)}
            rep.dirty[:] = False
        state = {**state, "replay": [rep.meta() for rep in replays], "generation": self.generation,
                 "blocks": [[g, b, r["file"], r["sha256"]] for (g, b), r in sorted(refs.items())]}
        save_file(state, self.path)
        self.refs = refs
        self.clean()

    def load(self, replays: Iterable | None = None) -> dict:
        """checkpoint.pt, with every replay block verified and loaded into ``replays`` (when given)."""
        state = load_file(self.path)
        if not isinstance(state, dict) or "blocks" not in state:
            raise ConfigError(f"'{self.path}' is not a training checkpoint")
        self.generation = int(state["generation"])
        self.refs = {(int(g), int(b)): {"file": f, "sha256": h} for g, b, f, h in state["blocks"]}
        if replays is not None:
            replays = list(replays)
            if len(replays) != len(state["replay"]):
                raise ConfigError(f"'{self.path}' holds {len(state['replay'])} replay memories, this run has {len(replays)}")
            for rep, meta in zip(replays, state["replay"]):
                try:
                    rep.load_meta(meta)
                except ValueError as e:
                    raise ConfigError(f"cannot resume from '{self.path}': {e}") from None
            for (g, b), ref in self.refs.items():
                arrays = load_file(self.run_dir / REPLAY_DIR / ref["file"], ref["sha256"])
                try:
                    replays[g].load_block(b, arrays)
                except ValueError as e:
                    raise ConfigError(f"cannot resume from '{self.path}': {e}") from None
                replays[g].dirty[b] = False
        return state

    def clean(self) -> None:
        """Remove orphan temporary files and replay blocks the current checkpoint does not name."""
        keep = {r["file"] for r in self.refs.values()}
        for d in (self.run_dir, self.run_dir / REPLAY_DIR):
            if not d.is_dir():
                continue
            for p in d.iterdir():
                orphan_tmp = p.name.startswith(".") and (".tmp" in p.name or p.name.endswith(".bak"))
                stale_block = d.name == REPLAY_DIR and _BLOCK_RE.match(p.name) and p.name not in keep
                if (orphan_tmp or stale_block) and p.is_file():
                    p.unlink(missing_ok=True)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """A run directory's checkpoint (the directory or its checkpoint.pt) as one dict; ``["replay"][g]``
    also holds replay g's used slots (``tuples``, ``states``, ``rewards`` as NumPy arrays) from its blocks."""
    path = Path(path)
    ck = Checkpointer(path.parent if path.name == "checkpoint.pt" else path)
    state = ck.load(None)
    for g, meta in enumerate(state["replay"]):
        blocks = sorted((b, ref) for (gg, b), ref in ck.refs.items() if gg == g)
        parts = [load_file(ck.run_dir / REPLAY_DIR / ref["file"], ref["sha256"]) for _, ref in blocks]
        for name in ("tuples", "states", "rewards"):
            meta[name] = np.concatenate([np.asarray(p[name]) for p in parts]) if parts else np.zeros(0)
    return state
