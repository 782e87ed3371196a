"""The export manifest: ``<out>.manifest.json`` records how a firmware file was made.

It holds the number format, rounding rule and every exponent, the architecture, the budget
breakdown, the quantisation error, the policy hash and the generator version, and the sha256 of
every file written alongside, so a C file found on a lab machine can be traced back to its policy,
and a reader can check that the files beside a manifest are the set it describes
(:func:`verify_manifest`).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Mapping

from kiloforge import numfmt
from kiloforge.actors.base import FloatPolicy, QuantizedActor
from kiloforge.errors import InputError
from kiloforge.validate import read_json_file

from .budget import Budget

MANIFEST_FORMAT = "kiloforge-export-manifest"
MANIFEST_VERSION = 1


def generator_version() -> str:
    """kiloforge's version (``kiloforge.__version__``, installed or run from a checkout)."""
    from kiloforge import __version__
    return __version__


def _sha256(text: str | bytes) -> str:
    return hashlib.sha256(text.encode("utf-8") if isinstance(text, str) else text).hexdigest()


def build_manifest(policy: FloatPolicy, qp: QuantizedActor, budget: Budget, report: Any,
                   calib: Any, files: Mapping[str, str | bytes],
                   options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The manifest as a JSON-ready dict; ``files`` maps written file names to their contents."""
    return {
        "format": MANIFEST_FORMAT,
        "format_version": MANIFEST_VERSION,
        "generator": "kiloforge export",
        "generator_version": generator_version(),
        "number_format": numfmt.FORMAT_NAME,
        "rounding": numfmt.ROUNDING,
        "accumulator_bits": numfmt.ACC_BITS_REFERENCE,
        "policy_hash": policy.hash,
        "policy_provenance": policy.provenance,
        "world": policy.world.to_dict(),
        "kind": policy.kind,
        "architecture": policy.describe(),
        "layer_sizes": policy.layer_sizes,
        "quantization": qp.summary(),
        "calibration": dict(calib.info, n_samples=calib.n),
        "error": report.to_dict(),
        "budget": budget.to_dict(),
        "options": dict(options or {}),
        "files": {name: {"sha256": _sha256(c), "bytes": len(c.encode("utf-8") if isinstance(c, str) else c)}
                  for name, c in files.items()},
    }


def manifest_json(manifest: Mapping[str, Any]) -> str:
    """Stable, human-readable JSON text (sorted keys, trailing newline)."""
    return json.dumps(manifest, indent=2, sort_keys=True, allow_nan=False) + "\n"


def verify_manifest(path: str | os.PathLike) -> list[str]:
    """What does not match in the set a manifest describes: each file it lists must exist beside it
    with the recorded size and sha256. An empty list: the manifest and its files are one complete set
    (:mod:`kiloforge.io` publishes the manifest last, so a present manifest describes its files)."""
    path = Path(path)
    try:
        doc = read_json_file(path, "manifest")
    except InputError as e:
        return [str(e)]
    if not isinstance(doc, dict) or doc.get("format") != MANIFEST_FORMAT or not isinstance(doc.get("files"), dict):
        return [f"{path}: not a kiloforge export manifest"]
    problems = []
    for name, rec in doc["files"].items():
        f = path.parent / name
        try:
            data = f.read_bytes()
        except OSError as e:
            problems.append(f"{f}: {e.strerror or e}")
            continue
        if not isinstance(rec, dict) or rec.get("bytes") != len(data) or rec.get("sha256") != _sha256(data):
            problems.append(f"{f}: does not match the manifest")
    return problems
