"""The policy artifact's file format: named float32 arrays plus JSON metadata, plain data, no pickle.

The contract between ``learn`` (which writes policies) and ``sim`` / ``export`` (which read them).
One ``.npz`` in :func:`numpy.savez`'s layout, byte-for-byte reproducible (:func:`npz_bytes`)::

    <array>, ...   float32 arrays, named and shaped by the actor kind (kiloforge.actors)
    meta           uint8 array holding UTF-8 JSON:
        format "kiloforge-policy", format_version 1, kind (a registered actor kind),
        action_mapping "clip01", world (WorldConfig.to_dict()), provenance {...},
        the kind's own fields (layer sizes, hidden size, gate order, ...),
        policy_hash (sha256 of :func:`canonical_bytes`: the arrays and meta without this field)

This module knows no actor kind: :func:`read_artifact` checks what every file has (a zip of
``.npy`` members read with ``allow_pickle=False``, the meta, format, version, action mapping and
world) and :mod:`kiloforge.policies` looks the kind up and lets it validate its arrays. Every
problem raises :class:`~kiloforge.errors.PolicyError` with one line naming the file.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from sim.config import WorldConfig

from .errors import PolicyError

FORMAT = "kiloforge-policy"
FORMAT_VERSION = 1
ACTION_MAPPING = "clip01"  #: actions are the output layer's values clipped to [0, 1]
META = "meta"  #: the member holding the JSON metadata


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


def base_meta(kind: str, world: WorldConfig, provenance: Mapping[str, Any]) -> dict[str, Any]:
    """The meta fields every artifact has (the kind adds its own)."""
    return {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "action_mapping": ACTION_MAPPING,
            "world": world.to_dict(), "provenance": dict(provenance)}


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


def read_artifact(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays, meta) of a policy file after the checks every kind shares; raises PolicyError."""
    path = Path(path)
    bad = file_error(path)
    if not path.exists():
        raise bad("does not exist")
    if path.is_dir():
        raise bad("is a directory, not a .npz file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise bad(f"cannot be read ({e.strerror or e})") from None
    if not raw:
        raise bad("is empty")
    if not zipfile.is_zipfile(io.BytesIO(raw)):
        raise bad("is not a .npz (zip) archive; truncated or not a policy")
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            names = set(z.files)
            if META not in names:
                raise bad("has no 'meta' entry; not a kiloforge policy")
            arrays = {n: z[n] for n in names}
    except PolicyError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, KeyError) as e:
        raise bad(f"is corrupt or truncated ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    except Exception as e:  # zlib.error and friends from a damaged member
        raise bad(f"is corrupt or truncated ({type(e).__name__})") from None

    meta_arr = arrays.pop(META)
    if meta_arr.dtype != np.uint8 or meta_arr.ndim != 1:
        raise bad(f"'meta' must be a 1-D uint8 array of UTF-8 JSON, got {meta_arr.dtype} {meta_arr.shape}")
    try:
        meta = json.loads(meta_arr.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise bad(f"'meta' is not valid UTF-8 JSON ({e})") from None
    if not isinstance(meta, dict):
        raise bad("'meta' must be a JSON object")
    if meta.get("format") != FORMAT:
        raise bad(f"format is {meta.get('format')!r}, expected '{FORMAT}'")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise bad(f"format version {version!r} is not supported (this kiloforge reads version {FORMAT_VERSION})")
    if meta.get("action_mapping", ACTION_MAPPING) != ACTION_MAPPING:
        raise bad(f"action mapping {meta.get('action_mapping')!r} is not supported (only '{ACTION_MAPPING}')")
    return arrays, meta


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
        return PolicyError(f"policy file '{path}': {msg}")
    return bad
