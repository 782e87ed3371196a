"""Column labels of the policies a benchmark compares: one per entry, never two alike."""
from __future__ import annotations

from pathlib import Path


def policy_paths(entries: list[str]) -> dict[str, Path]:
    """label → artifact for run directories (their ``policy_best.npz``) and ``.npz`` files.

    A run directory is labelled by its name, a file by its stem; when two labels would collide (three
    runs' ``policy_best.npz``), files are labelled ``run/stem`` instead. Same file twice: SystemExit.
    """
    paths = [Path(e) if Path(e).suffix == ".npz" else Path(e) / "policy_best.npz" for e in entries]
    short = [Path(e).stem if Path(e).suffix == ".npz" else Path(e).name for e in entries]
    if len(set(short)) < len(short):
        short = [f"{p.parent.name}/{p.stem}" if Path(e).suffix == ".npz" else s
                 for e, p, s in zip(entries, paths, short)]
    if len(set(short)) < len(short):
        dup = next(s for s in short if short.count(s) > 1)
        raise SystemExit(f"error: two entries are both '{dup}'; give each policy once")
    return dict(zip(short, paths))
