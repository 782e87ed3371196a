"""Reading a run directory's files with the core dependencies only (no torch, no tyro): ``learn plot``
runs where the learn extra is not installed."""
from __future__ import annotations

import csv
import json
import os
from pathlib import Path

from kiloforge.errors import InputError

#: how ``learn plot`` names each trainer's runs (the ``algorithm`` key of config.json)
ALGORITHM_NAMES = {"magddpg": "MAGDDPG", "magrdpg": "MAGRDPG", "es": "ES"}


def read_json(path: Path) -> dict:
    """A JSON file as a dict; one-line InputError when it is missing or unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(f"'{path}' does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"cannot read '{path}': {e}") from None


def read_metrics(run_dir: str | os.PathLike) -> list[dict]:
    """metrics.csv of a run directory as a list of float dicts."""
    path = Path(run_dir) / "metrics.csv"
    if not path.is_file():
        raise InputError(f"'{run_dir}' has no metrics.csv; is it a training run directory?")
    with open(path, newline="") as f:
        return [{k: float(v) if v not in ("", None) else float("nan") for k, v in r.items()}
                for r in csv.DictReader(f)]
