"""Load and save policy artifacts of every actor kind (:mod:`kiloforge.artifact` is the file format).

``load_policy`` reads a file with the checks every artifact shares, looks its kind up in the
registry and lets the kind validate its arrays (shapes against the world's tuple width, finite
values, ...), refuses meta that differs from what the kind writes (a field added, left out or
written differently), then checks the stored hash, which is
mandatory; every problem is a one-line :class:`~kiloforge.errors.PolicyError` naming the file.
``rehash_policy`` re-writes a file one trusts with the hash of its contents
(``python -m export rehash FILE``).
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

from sim.config import WorldConfig

from .actors.base import FloatPolicy
from .actors.registry import kind_named, kind_of
from .artifact import canonical_json, file_error, read_artifact, task_of, world_of
from .errors import OutputError, PolicyError
from .io import write_atomic
from .validate import quote, show


def _policy_of(path: Path, arrays: dict, meta: dict) -> FloatPolicy:
    bad = file_error(path)
    try:
        kind = kind_named(meta.get("kind"))
        policy = kind.from_arrays(arrays, meta, world_of(meta), meta.get("provenance", {}))
        task = task_of(meta)
        if task is not None:
            policy = dataclasses.replace(policy, task=task)
    except PolicyError as e:
        raise bad(str(e).removeprefix("policy: ")) from None
    _same_meta(bad, {k: v for k, v in meta.items() if k != "policy_hash"}, policy.meta(), policy.kind)
    return policy


def _same_meta(bad, given: dict, derived: dict, kind: str, where: str = "meta") -> None:
    """The file's meta must be exactly what its policy writes: no field missing, added or written differently
    (a field left out would otherwise silently take a default)."""
    if canonical_json(given) == canonical_json(derived):
        return
    unknown = sorted(set(given) - set(derived))
    if unknown:
        raise bad(f"{where} has field(s) a '{kind}' policy does not have: {', '.join(map(quote, unknown[:8]))}")
    missing = sorted(set(derived) - set(given))
    if missing:
        raise bad(f"{where} lacks {', '.join(map(quote, missing[:8]))}")
    for k in sorted(given):
        if isinstance(given[k], dict) and isinstance(derived[k], dict):
            _same_meta(bad, given[k], derived[k], kind, f"{where} {k}")
        elif canonical_json(given[k]) != canonical_json(derived[k]):
            raise bad(f"{where} field {quote(k)} is {show(given[k])}, which reads back as {show(derived[k])}")


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


def policy_labels(entries: list[str], short: bool = False) -> list[str]:
    """A label per policy file (its name without ``.npz``) or run directory (its name), never two alike.

    A file not in the current directory starts as ``parent/stem`` (``short``: as ``stem``); labels that
    collide grow by one leading path component at a time until they differ. The same entry twice:
    ValueError.

    >>> policy_labels(["runs/a/policy_best.npz", "runs/b/policy_best.npz", "p.npz"])
    ['a/policy_best', 'b/policy_best', 'p']
    >>> policy_labels(["r1/generations/gen_020.npz", "r2/generations/gen_020.npz"])
    ['r1/generations/gen_020', 'r2/generations/gen_020']
    >>> policy_labels(["runs/s1", "x/default_policy.npz", "y/default_policy.npz"], short=True)
    ['s1', 'x/default_policy', 'y/default_policy']
    """
    paths = [Path(e) for e in entries]
    parts = [(p.with_suffix("") if p.suffix == ".npz" else p).parts for p in paths]
    depth = [1 if short or len(q) < 2 or p.suffix != ".npz" else 2 for p, q in zip(paths, parts)]
    while True:
        labels = ["/".join(q[-d:]) for q, d in zip(parts, depth)]
        dup = {lab for lab in labels if labels.count(lab) > 1}
        if not dup:
            return labels
        grow = [i for i, lab in enumerate(labels) if lab in dup and depth[i] < len(parts[i])]
        if not grow:
            raise ValueError(f"'{sorted(dup)[0]}' is given twice; give each policy once")
        for i in grow:
            depth[i] += 1


def policy_paths(entries: list[str]) -> dict[str, Path]:
    """label → artifact for run directories (their ``policy_best.npz``) and ``.npz`` files, the policies a
    benchmark or an experiment compares: labels are :func:`policy_labels` ``short`` (a run directory's name, a
    file's stem, longer only where two would collide). The same entry twice: ValueError.

    >>> policy_paths(["runs/s1", "x/default_policy.npz"])
    {'s1': PosixPath('runs/s1/policy_best.npz'), 'default_policy': PosixPath('x/default_policy.npz')}
    """
    labels = policy_labels(entries, short=True)
    return {lab: Path(e) if Path(e).suffix == ".npz" else Path(e) / "policy_best.npz" for lab, e in zip(labels, entries)}
