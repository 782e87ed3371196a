"""Reading a run directory's files with the core dependencies only (no torch, no tyro): ``learn plot``
runs where the learn extra is not installed.

A run directory is input like any other file (it may come from someone else, or be damaged): every
file is read through :mod:`kiloforge.validate` (a regular file, at most a size cap, never a FIFO or a
device; strict JSON), ``config.json`` must be an object whose fields ``learn plot`` uses have their
types, and ``metrics.csv`` must have a header with the columns plotted, rows as wide as the header
and numbers of at most :data:`MAX_CSV_FIELD` characters. Every refusal is one line naming the file.
"""
from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import Any

from kiloforge.errors import InputError
from kiloforge.validate import MIB, check_int, check_str, quote, read_json_file, read_regular_file, show

#: how ``learn plot`` names each trainer's runs (the ``algorithm`` key of config.json)
ALGORITHM_NAMES = {"magddpg": "MAGDDPG", "magrdpg": "MAGRDPG", "es": "ES"}
MAX_METRICS_BYTES = 64 * MIB  #: metrics.csv (a row is about 200 bytes; a long run has thousands)
MAX_CSV_FIELD = 64  #: characters of one metrics.csv field (the trainer writes numbers as %.6g)
MAX_CSV_LINE = 64 * 1024  #: characters of one metrics.csv line (checked before the csv module parses it)
PLOTTED_COLUMNS = ("env_steps", "eval_return")  #: what every trainer writes, whatever its task


#: fields that may differ between a checkpoint and a resumed run (budgets, speed and logging knobs)
RESUME_MAY_CHANGE = ("episodes", "generations", "max_minutes", "threads", "checkpoint_every", "device", "tensorboard",
                     "keep_evaluated", "workers", "ray_address")
#: config fields that do not make two runs different experiments: the seed, and what a resume may change
NOT_THE_EXPERIMENT = ("seed", *RESUME_MAY_CHANGE)


def experiment_groups(configs: list[dict[str, Any]], base: list[str]) -> list[str]:
    """A label per run for ``learn plot``: ``base[i]`` (what the runs show), followed by the config fields in which
    the runs sharing that base label differ (``reward=local, critic=robot``), so that only runs differing in
    :data:`NOT_THE_EXPERIMENT` share a label and are averaged."""
    labels = []
    for i, cfg in enumerate(configs):
        peers = [c for c, b in zip(configs, base) if b == base[i]]
        keys = sorted({k for c in peers for k in c} - set(NOT_THE_EXPERIMENT))
        differ = [k for k in keys if any(c.get(k) != cfg.get(k) for c in peers)]
        extra = ", ".join(f"{k}={_short(cfg.get(k))}" for k in differ)
        labels.append(f"{base[i]}, {extra}" if extra else base[i])
    return labels


def _short(value: Any) -> str:
    """A config value as a legend shows it: text as is, lists joined by '-', at most 40 characters."""
    text = "-".join(map(str, value)) if isinstance(value, list) else str(value)
    return text if len(text) <= 40 else text[:39] + "…"


def read_json(path: str | os.PathLike, what: str = "run file") -> dict:
    """A JSON object from a file (:func:`kiloforge.validate.read_json_file`); one-line InputError otherwise."""
    doc = read_json_file(path, what)
    if not isinstance(doc, dict):
        raise InputError(f"{what} {quote(path)} must be a JSON object, got {show(doc)}")
    return doc


def read_config(run_dir: str | os.PathLike) -> dict[str, Any]:
    """A run's config.json, with the fields ``learn plot`` shows checked: ``exp_name``, ``algorithm`` and ``task``
    strings, ``t_prev`` an integer, ``n_robots`` an integer or a list of them (each may be absent)."""
    path = Path(run_dir) / "config.json"
    cfg = read_json(path, "run config")
    where = f"run config {quote(path)}"
    for key in ("exp_name", "algorithm", "task"):
        if key in cfg:
            check_str(cfg[key], f"{where}: {key}", printable_only=False)
    if "t_prev" in cfg:
        check_int(cfg["t_prev"], f"{where}: t_prev", 0)
    sizes = cfg.get("n_robots", 1)
    for i, m in enumerate(sizes if isinstance(sizes, list) else [sizes]):
        check_int(m, f"{where}: n_robots" + (f"[{i}]" if isinstance(sizes, list) else ""), 1)
    return cfg


def read_metrics(run_dir: str | os.PathLike, columns: tuple[str, ...] = PLOTTED_COLUMNS) -> list[dict]:
    """metrics.csv of a run directory as a list of float dicts (empty fields are NaN); ``columns`` must be there."""
    path = Path(run_dir) / "metrics.csv"
    if not os.path.lexists(path):
        raise InputError(f"{quote(run_dir)} has no metrics.csv; is it a training run directory?")
    name = f"metrics file {quote(path)}"
    try:
        text = read_regular_file(path, "metrics file", MAX_METRICS_BYTES).decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{name} is not UTF-8 text (invalid byte at offset {e.start})") from None
    lines = text.splitlines()
    long = next((i for i, line in enumerate(lines) if len(line) > MAX_CSV_LINE), None)
    if long is not None:
        raise InputError(f"{name}: line {long + 1} has {len(lines[long]):,} characters, more than the "
                         f"{MAX_CSV_LINE:,} allowed")
    try:
        table = list(csv.reader(io.StringIO(text)))
    except csv.Error as e:
        raise InputError(f"{name}: not valid CSV ({e})") from None
    if not table:
        raise InputError(f"{name} is empty; expected a header with {', '.join(columns)}")
    header = table[0]
    missing = [c for c in columns if c not in header]
    if missing or len(set(header)) != len(header):
        why = f"no column {', '.join(missing)}" if missing else "a column name appears twice"
        raise InputError(f"{name}: its header has {why}")
    rows = []
    for n, row in enumerate(table[1:], start=2):
        if len(row) != len(header):
            raise InputError(f"{name}: line {n} has {len(row)} fields, the header {len(header)}")
        rows.append({k: _number(v, name, n, k) for k, v in zip(header, row)})
    return rows


def _number(text: str, name: str, line: int, column: str) -> float:
    if text == "":
        return float("nan")
    if len(text) > MAX_CSV_FIELD:
        raise InputError(f"{name}: line {line} column {quote(column)} has {len(text):,} characters, more than "
                         f"the {MAX_CSV_FIELD} of a number")
    try:
        return float(text)
    except ValueError:
        raise InputError(f"{name}: line {line} column {quote(column)} is {quote(text)}, not a number") from None
