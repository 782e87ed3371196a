"""Column labels of the policies a benchmark compares: one per entry, never two alike."""
from __future__ import annotations

from pathlib import Path


def policy_paths(entries: list[str]) -> dict[str, Path]:
    """label → artifact for run directories (their ``policy_best.npz``) and ``.npz`` files.

    A run directory is labelled by its name, a file by its stem; when two labels would collide (three
    runs' ``policy_best.npz``), files are labelled ``run/stem`` instead. Same file twice: SystemExit.
    """
    files = [Path(e).suffix == ".npz" for e in entries]
    paths = [Path(e) if f else Path(e) / "policy_best.npz" for e, f in zip(entries, files)]
    short = [p.stem if f else p.parent.name for p, f in zip(paths, files)]
    if len(set(short)) < len(short):
        short = [f"{p.parent.name}/{p.stem}" if f else s for p, f, s in zip(paths, files, short)]
    if len(set(short)) < len(short):
        dup = next(s for s in short if short.count(s) > 1)
        raise SystemExit(f"error: two entries are both '{dup}'; give each policy once")
    return dict(zip(short, paths))
