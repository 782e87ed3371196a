"""Load and save policy artifacts of every actor kind (:mod:`kiloforge.artifact` is the file format).

``load_policy`` reads a file with the checks every artifact shares, looks its kind up in the
registry and lets the kind validate its arrays (shapes against the world's tuple width, finite
values, ...), then checks the stored hash; every problem is a one-line
:class:`~kiloforge.errors.PolicyError` naming the file.
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


def load_policy(path: str | os.PathLike) -> FloatPolicy:
    """Read and validate a policy artifact of any registered kind; raises :class:`PolicyError`."""
    path = Path(path)
    bad = file_error(path)
    arrays, meta = read_artifact(path)
    try:
        kind = kind_named(meta.get("kind"))
        policy = kind.from_arrays(arrays, meta, world_of(meta), meta.get("provenance", {}))
    except PolicyError as e:
        raise bad(str(e).removeprefix("policy: ")) from None
    stored = meta.get("policy_hash")
    if stored is not None and stored != policy.hash:
        raise bad(f"policy_hash {str(stored)[:12]}... does not match the contents ({policy.hash[:12]}...); "
                  "the file was modified")
    return policy


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
