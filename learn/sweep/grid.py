"""Sweep grids: parsing (command line and JSON / TOML files), validation, trials and their names.

A grid is a trainer, one or more presets, axes of config fields (a list of values each) and seeds.
Its trials are the Cartesian product of presets × axes (a *configuration*) × seeds, seed-major (the
first seed of every configuration, then the second, ...), so an interrupted sweep has covered every
configuration as evenly as it could. Every trial's config is resolved and validated before anything
runs, so a bad key or value is one line, exit 2, with nothing started.

A trial's directory name is ``{world}-m{robots}-t{history}_s{seed}_{hash}`` where the hash covers the
trainer, preset and the fields the grid sets (seed included): the same command finds the same
directories, and a field added to the trainer later (with its default) does not rename them.
Budgets (``--max-minutes``, CPUs per trial) are not part of a trial's identity: a rerun may change them.

File format (JSON, or TOML with Python >= 3.11)::

    trainer = "magddpg"          # optional; magddpg, magrdpg or es
    preset = "quick"             # or a list of presets (an axis)
    seeds = [1, 2, 3]
    max_minutes = 30             # per trial, over all its sessions
    cpus_per_trial = 1
    eval_robots = [16, 32]       # optional final evaluation against the baselines
    eval_episodes = 500
    eval_steps = 500

    [grid]                       # config fields: a list is an axis, a scalar a fixed value
    n_robots = [1, 2, 4, 8]
    t_prev = 10
    actor_hidden = [[32, 32], [64, 32]]   # tuple fields: a list of lists is an axis

Options on the command line replace the file's.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sim.config import BENCHMARK_EPISODES, BENCHMARK_STEPS, MAX_ROBOTS

from ..config import ConfigError
from . import trial as tr

#: file keys besides [grid]
FILE_KEYS = ("trainer", "preset", "seeds", "max_minutes", "cpus_per_trial", "eval_robots", "eval_episodes",
             "eval_steps")
#: fields that a grid may not set: they have their own options
RESERVED = {"seed": "--seeds", "max_minutes": "--max-minutes", "threads": "--cpus-per-trial"}


@dataclass
class Grid:
    """What a sweep runs, before expansion into trials."""

    trainer: str = "magddpg"
    presets: list[str] = field(default_factory=list)  # empty: the trainer's default preset
    axes: dict[str, list] = field(default_factory=dict)  # field → canonical values
    seeds: list[int] = field(default_factory=lambda: [1])
    max_minutes: float | None = None  # None: the preset's max_minutes
    cpus_per_trial: float = 1.0
    evaluation: tr.EvalSpec | None = None

    def to_dict(self) -> dict:
        return {"trainer": self.trainer, "presets": self.presets, "axes": self.axes, "seeds": self.seeds,
                "max_minutes": self.max_minutes, "cpus_per_trial": self.cpus_per_trial,
                "evaluation": None if self.evaluation is None else {
                    "robots": list(self.evaluation.robots), "episodes": self.evaluation.episodes,
                    "steps": self.evaluation.steps, "seed": self.evaluation.seed}}


@dataclass(frozen=True)
class Trial:
    """One run of a sweep: its identity (trainer, preset, overrides with the seed) and its names."""

    name: str  # run directory name inside the sweep directory
    config_id: str  # the same for all seeds of one configuration
    trainer: str
    preset: str
    overrides: dict  # field → canonical JSON value, seed included
    config: dict  # the resolved config (without the sweep's budget)

    @property
    def seed(self) -> int:
        return int(self.config["seed"])

    def to_dict(self) -> dict:
        return {"name": self.name, "config_id": self.config_id, "trainer": self.trainer, "preset": self.preset,
                "overrides": self.overrides, "config": self.config}

    @classmethod
    def from_dict(cls, d: dict) -> "Trial":
        return cls(d["name"], d["config_id"], d["trainer"], d["preset"], d["overrides"], d["config"])


def digest(obj: Any, n: int = 8) -> str:
    """Short stable hash of a JSON-able object."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:n]


def split_values(text: str) -> list:
    """``"1e-4,3e-4"`` → ``["1e-4", "3e-4"]``; a JSON array (``[[32,32],[64,32]]``) is read as JSON."""
    text = text.strip()
    if text.startswith("["):
        try:
            values = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"cannot read {text!r} as a JSON list: {e.msg}") from None
        if not isinstance(values, list):
            raise ConfigError(f"{text!r} is not a list")
        return values
    values = [v.strip() for v in text.split(",")]
    if not all(values):
        raise ConfigError(f"empty value in {text!r}")
    return values


def parse_grid_option(text: str) -> tuple[str, list]:
    """``--grid KEY=V1,V2`` → (KEY, [V1, V2]) with the values still raw."""
    key, sep, values = text.partition("=")
    key = key.strip().replace("-", "_")
    if not sep or not key or not values.strip():
        raise ConfigError(f"--grid expects KEY=VALUE[,VALUE...], got {text!r}")
    try:
        return key, split_values(values)
    except ConfigError as e:
        raise ConfigError(f"--grid {key}: {e}") from None


def read_grid_file(path: str | Path) -> dict:
    """A grid file (``.json`` or ``.toml``) as a dict, unknown top-level keys refused."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"cannot read grid file '{path}': {e.strerror or e}") from None
    if path.suffix.lower() == ".toml":
        try:
            import tomllib
        except ImportError:  # Python 3.10
            raise ConfigError("TOML grid files need Python >= 3.11; write the grid as JSON") from None
        try:
            d = tomllib.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, tomllib.TOMLDecodeError) as e:
            raise ConfigError(f"cannot read grid file '{path}': {e}") from None
    else:
        try:
            d = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise ConfigError(f"cannot read grid file '{path}': {e}") from None
    if not isinstance(d, dict):
        raise ConfigError(f"grid file '{path}' must hold an object (a table), got {type(d).__name__}")
    unknown = sorted(set(d) - set(FILE_KEYS) - {"grid"})
    if unknown:
        raise ConfigError(f"grid file '{path}': unknown key(s) {', '.join(unknown)} "
                          f"(known: {', '.join(FILE_KEYS)}, grid)")
    if not isinstance(d.get("grid", {}), dict):
        raise ConfigError(f"grid file '{path}': 'grid' must be a table of config fields")
    return d


def _as_list(v: Any) -> list:
    return v if isinstance(v, list) else [v]


def _axis_values(trainer: str, key: str, value: Any, where: str) -> list:
    """A grid entry as a list of canonical values.

    Tuple fields: a flat list of ints is one value, a list of lists an axis; on the command line
    ``32x32,64x32`` is the axis of (32, 32) and (64, 32).
    """
    tr.check_field(trainer, key, where)
    if key in RESERVED:
        raise ConfigError(f"{where}: '{key}' has its own option: use {RESERVED[key]}")
    if typing.get_origin(tr.field_types(trainer)[key]) is tuple and isinstance(value, list):
        if value and all(isinstance(v, str) for v in value):  # command line: 32x32,64x32
            value = [v if key == "n_robots" and "x" not in v else v.split("x") for v in value]
        elif key != "n_robots" and not any(isinstance(v, list) for v in value):  # a flat list of widths is one value
            value = [value]  # (n_robots: a flat list is an axis of swarm sizes; [4, 16] inside it trains both)
    values = _as_list(value)
    if not values:
        raise ConfigError(f"{where}: '{key}' has no values")
    out = []
    for v in values:
        try:
            c = tr.coerce_value(trainer, key, v)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None
        if c in out:
            raise ConfigError(f"{where}: '{key}' lists {v!r} twice")
        out.append(c)
    return out


def build_grid(file: dict | None = None, *, trainer: str | None = None, presets: list[str] | None = None,
               seeds: list[int] | None = None, robots: list[int] | None = None, world: list[str] | None = None,
               task: list[str] | None = None,
               history: list[int] | None = None, grid: list[str] | None = None, max_minutes: float | None = None,
               cpus_per_trial: float | None = None, eval_robots: list[int] | None = None,
               eval_episodes: int | None = None, eval_steps: int | None = None) -> Grid:
    """A validated grid from a grid file's dict and command-line options (which take precedence)."""
    file = file or {}
    g = Grid()
    g.trainer = trainer or file.get("trainer", "magddpg")
    if g.trainer not in tr.TRAINERS:
        raise ConfigError(f"unknown trainer '{g.trainer}'; choose one of {', '.join(tr.TRAINERS)}")
    table = tr.presets(g.trainer)
    g.presets = list(presets or _as_list(file.get("preset", [next(iter(table))])))
    for p in g.presets:
        if p not in table:
            raise ConfigError(f"unknown {g.trainer} preset '{p}'; choose one of {', '.join(table)}")
    if len(set(g.presets)) != len(g.presets):
        raise ConfigError("a preset is listed twice")

    axes: dict[str, list] = {k: _axis_values(g.trainer, k, v, "grid file") for k, v in file.get("grid", {}).items()}
    cli: dict[str, tuple[list, str]] = {}
    for key, values in (parse_grid_option(s) for s in grid or []):
        if key in cli:
            raise ConfigError(f"--grid {key} is given twice")
        cli[key] = (values, f"--grid {key}")
    for opt, key, values in (("--robots", "n_robots", robots), ("--world", "world", world), ("--task", "task", task),
                             ("--history", "t_prev", history)):
        if values is None:
            continue
        if key not in tr.field_types(g.trainer):
            raise ConfigError(f"{opt}: the {g.trainer} trainer has no field {key}")
        if key in cli:
            raise ConfigError(f"{opt} and --grid {key} set the same field; give one")
        cli[key] = (list(values), opt)
    for key, (values, where) in cli.items():
        axes[key] = _axis_values(g.trainer, key, values, where)
    g.axes = axes

    g.seeds = [int(s) for s in (seeds if seeds is not None else _as_list(file.get("seeds", [1])))]
    for s in g.seeds:
        try:
            tr.coerce_value(g.trainer, "seed", s)
        except ConfigError as e:
            raise ConfigError(f"--seeds: {e}") from None
        if s < 0:
            raise ConfigError(f"--seeds: seeds must be >= 0, got {s}")
    if len(set(g.seeds)) != len(g.seeds):
        raise ConfigError("--seeds: a seed is listed twice")

    mm = max_minutes if max_minutes is not None else file.get("max_minutes")
    if mm is not None and (not isinstance(mm, (int, float)) or isinstance(mm, bool) or not mm >= 0):
        raise ConfigError(f"--max-minutes must be >= 0 (0 = no limit), got {mm!r}")
    g.max_minutes = None if mm is None else float(mm)
    cpt = cpus_per_trial if cpus_per_trial is not None else file.get("cpus_per_trial", 1)
    if not isinstance(cpt, (int, float)) or isinstance(cpt, bool) or not cpt > 0:
        raise ConfigError(f"--cpus-per-trial must be > 0, got {cpt!r}")
    g.cpus_per_trial = float(cpt)

    er = eval_robots if eval_robots is not None else file.get("eval_robots")
    if er:
        ep = eval_episodes if eval_episodes is not None else file.get("eval_episodes", BENCHMARK_EPISODES)
        st = eval_steps if eval_steps is not None else file.get("eval_steps", BENCHMARK_STEPS)
        er = _as_list(er)
        if not all(isinstance(m, int) and not isinstance(m, bool) and 1 <= m <= MAX_ROBOTS for m in er):
            raise ConfigError(f"--eval-robots must be robot counts in 1..{MAX_ROBOTS}, got {er}")
        for name, v in (("--eval-episodes", ep), ("--eval-steps", st)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ConfigError(f"{name} must be an integer >= 1, got {v!r}")
        g.evaluation = tr.EvalSpec(tuple(er), ep, st)
    return g


def expand(g: Grid) -> list[Trial]:
    """The grid's trials, seed-major; every config resolved and validated (one-line error naming the trial)."""
    keys = list(g.axes)
    combos = [(p, dict(zip(keys, values))) for p in g.presets
              for values in itertools.product(*(g.axes[k] for k in keys))]
    trials = []
    for seed in g.seeds:
        for preset, fields in combos:
            overrides = {**fields, "seed": seed}
            where = ", ".join([f"preset {preset}"] + [f"{k}={v}" for k, v in overrides.items()])
            try:
                cfg = tr.resolve_config(g.trainer, preset, overrides)
            except ConfigError as e:
                raise ConfigError(f"trial ({where}): {e}") from None
            ident = {"trainer": g.trainer, "preset": preset, "overrides": overrides}
            config_id = digest({**ident, "overrides": fields})
            name = f"{tr.short_name(g.trainer, cfg)}_s{seed}_{digest(ident)}"
            trials.append(Trial(name, config_id, g.trainer, preset, overrides, cfg.to_dict()))
    tr.task_spec(t.config for t in trials)  # one task: the aggregate's columns are its metrics
    return trials


def labels(trials: list[Trial]) -> dict[str, str]:
    """config_id → a label naming what differs between the configurations (preset and grid fields)."""
    by_id = {t.config_id: t for t in trials}
    specs = {cid: {"preset": t.preset, **{k: v for k, v in t.overrides.items() if k != "seed"}}
             for cid, t in by_id.items()}
    keys = list(dict.fromkeys(k for s in specs.values() for k in s))
    varying = [k for k in keys if len({json.dumps(s.get(k)) for s in specs.values()}) > 1]
    out = {}
    for cid, s in specs.items():
        parts = [f"{k}={_fmt(s.get(k))}" for k in varying]
        out[cid] = ", ".join(parts) if parts else f"{by_id[cid].trainer} {by_id[cid].preset}"
    return out


def _fmt(v: Any) -> str:
    if isinstance(v, list):
        return "x".join(map(str, v))
    return str(v)
