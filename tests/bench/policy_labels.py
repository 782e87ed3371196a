"""Column labels of the policies a benchmark compares: one per entry, never two alike."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from kiloforge.policies import policy_labels  # noqa: E402


def policy_paths(entries: list[str]) -> dict[str, Path]:
    """label → artifact for run directories (their ``policy_best.npz``) and ``.npz`` files.

    Labels are :func:`kiloforge.policies.policy_labels` (short: a run directory's name, a file's stem,
    longer only where two would collide). The same entry twice: SystemExit with one line.
    """
    try:
        labels = policy_labels(entries, short=True)
    except ValueError as e:
        raise SystemExit(f"error: {e}") from None
    return {lab: Path(e) if Path(e).suffix == ".npz" else Path(e) / "policy_best.npz"
            for lab, e in zip(labels, entries)}
