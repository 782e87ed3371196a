"""The policy artifact's file format: named float32 arrays plus JSON metadata, plain data, no pickle.

The contract between ``learn`` (which writes policies) and ``sim`` / ``export`` (which read them).
One ``.npz`` in :func:`numpy.savez`'s layout, byte-for-byte reproducible (:func:`npz_bytes`)::

    <array>, ...   float32 arrays, named and shaped by the actor kind (kiloforge.actors)
    meta           uint8 array holding UTF-8 JSON:
        format "kiloforge-policy", format_version 1, kind (a registered actor kind),
        action_mapping "clip01", world (WorldConfig.to_dict()), provenance {...},
        task {"name", "version"} (the task it was trained for; a file without it was written before
        tasks existed and is a localisation v1 policy: sim.tasks.LEGACY_TASK),
        the kind's own fields (layer sizes, hidden size, gate order, ...),
        policy_hash (sha256 of :func:`canonical_bytes`: the arrays and meta without this field)

This module knows no actor kind: :func:`read_artifact` checks what every file has (a regular file
within the size limit, a zip of plain numeric ``.npy`` members whose sizes are checked before
anything is decompressed, never unpickled; strict JSON meta with format, version, action mapping,
world and a mandatory ``policy_hash``) and :mod:`kiloforge.policies` looks the kind up, lets it
validate its arrays and checks the hash. Every problem raises
:class:`~kiloforge.errors.PolicyError` with one line naming the file.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
import zipfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sim.config import WorldConfig
from sim.tasks.base import LEGACY_TASK, TaskRef

from .errors import InputError, PolicyError
from .validate import MAX_POLICY_BYTES, parse_json, quote, read_npz, read_regular_file, show

FORMAT = "kiloforge-policy"
FORMAT_VERSION = 1
ACTION_MAPPING = "clip01"  #: actions are the output layer's values clipped to [0, 1]
META = "meta"  #: the member holding the JSON metadata
POLICY_HINT = "policy_best.npz"  #: suggested when a directory (a training run) is given as a policy
_HEX64 = re.compile(r"[0-9a-f]{64}")


def canonical_json(obj: Any) -> bytes:
    """Sorted, compact, ASCII JSON (what the hash covers); raises TypeError/ValueError for non-JSON data."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False).encode("ascii")


def plain_provenance(provenance: Any) -> dict[str, Any]:
    """``provenance`` as plain JSON data (a normalised copy); raises PolicyError otherwise."""
    if not isinstance(provenance, dict):
        raise PolicyError(f"policy: provenance must be a dict, got {type(provenance).__name__}")
    try:
        return json.loads(canonical_json(provenance))
    except (TypeError, ValueError) as e:
        raise PolicyError(f"policy: provenance is not plain JSON data ({e})") from None


def base_meta(kind: str, world: WorldConfig, provenance: Mapping[str, Any],
              task: TaskRef | None = None) -> dict[str, Any]:
    """The meta fields every artifact has (the kind adds its own); ``task`` None only for a policy
    read from a file written before tasks existed (so its hash stays what it was)."""
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "action_mapping": ACTION_MAPPING,
            "world": world.to_dict(), "provenance": dict(provenance)}
    if task is not None:
        meta["task"] = task.to_dict()
    return meta


def task_of(meta: Mapping[str, Any]) -> TaskRef | None:
    """The meta's task (None: a file from before tasks, i.e. :data:`~sim.tasks.LEGACY_TASK`); raises PolicyError."""
    if "task" not in meta:
        return None
    t = meta["task"]
    if not (isinstance(t, dict) and set(t) == {"name", "version"}):
        raise PolicyError(f"policy: 'task' must be {{\"name\": ..., \"version\": ...}}, got {show(t)}")
    try:
        return TaskRef(t["name"], t["version"])
    except InputError as e:
        raise PolicyError(f"policy: {e}") from None


def task_or_legacy(task: TaskRef | None) -> TaskRef:
    """The task a policy was trained for: its recorded one, or localisation v1 for files from before tasks."""
    return LEGACY_TASK if task is None else task


def canonical_bytes(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> bytes:
    """What the policy hash covers: every array in order (little-endian float32, with its shape), then the meta."""
    h = io.BytesIO()
    for name, arr in arrays.items():
        h.write(f"{name}:{'x'.join(map(str, arr.shape))}:<f4\n".encode("ascii"))
        h.write(np.ascontiguousarray(arr, "<f4").tobytes())
    h.write(canonical_json(dict(meta)))
    return h.getvalue()


def policy_hash(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> str:
    """sha256 (hex) of :func:`canonical_bytes`: the policy's identity in manifests and C banners."""
    return hashlib.sha256(canonical_bytes(arrays, meta)).hexdigest()


def npz_bytes(arrays: Mapping[str, np.ndarray]) -> bytes:
    """The layout of numpy.savez (one .npy member per array, stored, in the given order), with fixed
    member timestamps so that the same arrays always give the same bytes."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(info, "w") as f:
                np.lib.format.write_array(f, np.ascontiguousarray(arr), allow_pickle=False)
    return buf.getvalue()


def artifact_bytes(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any]) -> bytes:
    """The whole file: the arrays, then ``meta`` with its ``policy_hash``."""
    full = dict(meta, policy_hash=policy_hash(arrays, meta))
    members = dict(arrays)
    members[META] = np.frombuffer(json.dumps(full, sort_keys=True, indent=1).encode("utf-8"), np.uint8)
    return npz_bytes(members)


def read_artifact(path: str | os.PathLike, *, require_hash: bool = True) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays, meta) of a policy file after the checks every kind shares; raises PolicyError.

    The file must be a regular file of at most :data:`~kiloforge.validate.MAX_POLICY_BYTES`; the
    archive's limits are checked before anything is decompressed (:func:`kiloforge.validate.read_npz`),
    the meta is strict JSON (:func:`kiloforge.validate.parse_json`) and must carry a ``policy_hash``
    (``require_hash=False`` only for re-hashing a file one trusts).
    """
    path = Path(path)
    bad = file_error(path)
    try:
        raw = read_regular_file(path, "policy file", MAX_POLICY_BYTES, dir_hint=POLICY_HINT)
    except InputError as e:
        raise PolicyError(str(e)) from None
    if not raw:
        raise bad("is empty")
    arrays = read_npz(raw, bad)
    if META not in arrays:
        raise bad("has no 'meta' entry; not a kiloforge policy")
    meta_arr = arrays.pop(META)
    if meta_arr.dtype != np.uint8 or meta_arr.ndim != 1:
        raise bad(f"'meta' must be a 1-D uint8 array of UTF-8 JSON, got {meta_arr.dtype} {meta_arr.shape}")
    try:
        meta = parse_json(meta_arr.tobytes(), "'meta'")
    except InputError as e:
        raise bad(str(e)) from None
    if not isinstance(meta, dict):
        raise bad(f"'meta' must be a JSON object, got {show(meta)}")
    if meta.get("format") != FORMAT or not isinstance(meta.get("format"), str):
        raise bad(f"format is {show(meta.get('format'))}, expected '{FORMAT}'; not a kiloforge policy")
    version = meta.get("format_version")
    if not (isinstance(version, int) and not isinstance(version, bool) and version == FORMAT_VERSION):
        raise bad(f"format version {show(version)} is not supported (this kiloforge reads version {FORMAT_VERSION})")
    mapping = meta.get("action_mapping", ACTION_MAPPING)
    if not (isinstance(mapping, str) and mapping == ACTION_MAPPING):
        raise bad(f"action mapping {show(mapping)} is not supported (only '{ACTION_MAPPING}')")
    if require_hash or meta.get("policy_hash") is not None:
        check_stored_hash(meta, path)
    return arrays, meta


def check_stored_hash(meta: Mapping[str, Any], path: Path) -> str:
    """The meta's ``policy_hash``: mandatory, 64 lowercase hex digits (the check against the contents
    is :func:`kiloforge.policies.load_policy`'s)."""
    stored = meta.get("policy_hash")
    if stored is None:
        raise file_error(path)("has no policy_hash, so nothing proves its contents are what was trained; if you "
                               f"trust this file, re-hash it: python -m export rehash {quote(path)} (docs/design.md)")
    if not (isinstance(stored, str) and _HEX64.fullmatch(stored)):
        raise file_error(path)(f"policy_hash must be 64 hex digits (sha256), got {show(stored)}")
    return stored


def world_of(meta: Mapping[str, Any]) -> WorldConfig:
    """The WorldConfig of a meta dict; raises PolicyError (``policy: ...``)."""
    if "world" not in meta:
        raise PolicyError("policy: 'meta' lacks 'world'")
    try:
        return WorldConfig.from_dict(meta["world"])
    except (TypeError, ValueError) as e:
        raise PolicyError(f"policy: invalid world config ({e})") from None


def file_error(path: Path):
    """A factory of PolicyErrors that name ``path``: ``bad("is empty")``."""
    def bad(msg: str) -> PolicyError:
        return PolicyError(f"policy file {quote(path)}: {msg}")
    return bad
