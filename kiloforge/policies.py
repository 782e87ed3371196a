"""Load and save policy artifacts of every actor kind (:mod:`kiloforge.artifact` is the file format).

``load_policy`` reads a file with the checks every artifact shares, looks its kind up in the
registry and lets the kind validate its arrays (shapes against the world's tuple width, finite
values, ...), refuses meta fields the kind does not write, then checks the stored hash, which is
mandatory; every problem is a one-line :class:`~kiloforge.errors.PolicyError` naming the file.
``rehash_policy`` re-writes a file one trusts with the hash of its contents
(``python -m export rehash FILE``).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from sim.config import WorldConfig

from .actors.base import FloatPolicy
from .actors.registry import kind_named, kind_of
from .artifact import file_error, read_artifact, world_of
from .errors import OutputError, PolicyError
from .io import write_atomic
from .validate import quote


def _policy_of(path: Path, arrays: dict, meta: dict) -> FloatPolicy:
    bad = file_error(path)
    try:
        kind = kind_named(meta.get("kind"))
        policy = kind.from_arrays(arrays, meta, world_of(meta), meta.get("provenance", {}))
    except PolicyError as e:
        raise bad(str(e).removeprefix("policy: ")) from None
    unknown = sorted(set(meta) - set(policy.meta()) - {"policy_hash"})
    if unknown:
        raise bad(f"meta has field(s) a '{policy.kind}' policy does not have: {', '.join(map(quote, unknown[:8]))}")
    return policy


def load_policy(path: str | os.PathLike) -> FloatPolicy:
    """Read and validate a policy artifact of any registered kind; raises :class:`PolicyError`."""
    path = Path(path)
    arrays, meta = read_artifact(path)
    policy = _policy_of(path, arrays, meta)
    stored = meta["policy_hash"]
    if stored != policy.hash:
        raise file_error(path)(f"policy_hash {stored[:12]}... does not match the contents ({policy.hash[:12]}...); "
                               "the file was modified or damaged")
    return policy


def rehash_policy(path: str | os.PathLike, out: str | os.PathLike | None = None) -> tuple[FloatPolicy, str | None]:
    """Re-write a policy file one trusts with the hash of its contents (atomically, to ``out`` or in
    place); returns the policy and the hash the file had (None when it had none). Every other check
    of :func:`load_policy` still applies."""
    path = Path(path)
    arrays, meta = read_artifact(path, require_hash=False)
    policy = _policy_of(path, arrays, meta)
    save_policy(policy, path if out is None else out)
    return policy, meta.get("policy_hash")


def save_policy(policy: FloatPolicy, path: str | os.PathLike) -> Path:
    """Write ``policy`` to one ``.npz`` file atomically (temp file + rename); returns the path."""
    path = Path(path)
    try:
        write_atomic(path, policy.to_npz_bytes())
    except OutputError as e:
        raise PolicyError(str(e)) from None
    return path


def swarm_policy(policy: FloatPolicy, world: WorldConfig | None = None) -> Any:
    """The float actor of any policy as a :class:`sim.rollout.SwarmPolicy` (``world``: an override,
    e.g. another episode length)."""
    return kind_of(policy).swarm_policy(policy, world)
