"""A user's task (a ``file.py:Class`` or an installed plug-in) behind one boundary: what its code raises or
returns wrongly is one line (:class:`~kiloforge.errors.InputError`) naming the task and the method, never a
traceback from deep inside the simulator.

A user's task is their own code and runs with their rights (docs/hardening.md, threat model); the guard does not
sandbox it, it only keeps the command's contract: one line, exit status 2, nothing half-written.
"""
from __future__ import annotations

import sys
from collections.abc import Mapping
from typing import Any, Callable

import numpy as np

from kiloforge.errors import InputError

from ..config import WorldConfig
from .base import TASK_NAME, Metric, Task

#: the class attributes the tools read, and the type each must have
_ATTRS: dict[str, tuple[type, ...]] = {"description": (str,), "success_label": (str,), "robot_label": (str,),
                                       "success_plot": (str,), "primary_metric": (str,), "mean_metric": (str,), "beacon": (bool,), "beacon_role": (str,),
                                       "firmware": (str,), "emitter_program": (str,),
                                       "metrics": (tuple, list), "features": (tuple, list), "own_features": (tuple, list),
                                       "baselines": (dict,)}


def check_attributes(task: Task, where: str) -> None:
    """Every attribute the tools read, of its type (``metrics`` Metric items, ``features`` and ``baselines`` text)."""
    try:
        values = {n: getattr(task, n) for n in _ATTRS}
    except Exception as e:
        raise InputError(f"{where}: reading its attributes raised {type(e).__name__}: {e}") from None
    for n, types in _ATTRS.items():
        if not isinstance(values[n], types):
            raise InputError(f"{where}: '{n}' must be {' or '.join(t.__name__ for t in types)}, "
                             f"got {type(values[n]).__name__}")
    if not values["metrics"] or not all(isinstance(m, Metric) for m in values["metrics"]):
        raise InputError(f"{where}: 'metrics' must hold sim.tasks.Metric items, at least one")
    if not all(isinstance(f, str) for f in values["features"]):
        raise InputError(f"{where}: 'features' must be feature names (text)")
    if not all(isinstance(k, str) and isinstance(v, str) for k, v in values["baselines"].items()):
        raise InputError(f"{where}: 'baselines' must map labels (text) to names (text)")
    if not TASK_NAME.fullmatch(values["success_plot"]):
        raise InputError(f"{where}: 'success_plot' names files: it must match {TASK_NAME.pattern}, "
                         f"got {values['success_plot']!r}")


def _array(value: Any, shape: tuple[int, ...], what: str) -> None:
    a = np.asarray(value) if isinstance(value, (np.ndarray, list, tuple, float, int)) else None
    if a is None or a.shape != shape or not np.issubdtype(a.dtype, np.number) or not np.all(np.isfinite(a)):
        got = f"{a.dtype} {a.shape}" if a is not None else type(value).__name__
        raise InputError(f"{what} must be {shape} finite numbers, got {got}")


def _spawn(task: Task, env: Any, out: Any) -> None:
    B, M = env.n_envs, env.n_robots
    if not (isinstance(out, tuple) and len(out) == 3):
        raise InputError("spawn() must return (beacon, robots, headings)")
    beacon, pos, heading = out
    if task.beacon:
        _array(beacon, (B, 2), "the beacon")
    elif beacon is not None:
        raise InputError("the beacon must be None: the task has no beacon")
    _array(pos, (B, M, 2), "the robots")
    _array(heading, (B, M), "the headings")
    a = env.cfg.arena_half_mm
    if np.any(np.abs(pos) > a) or (beacon is not None and np.any(np.abs(beacon) > a)):
        raise InputError(f"placed a body outside the arena (|x|, |y| <= {a:g} mm)")


def _world(task: Task, *args: Any) -> None:
    out = args[-1]  # world(cfg) and world_for(cfg, n_robots) alike
    if not isinstance(out, WorldConfig):
        raise InputError(f"must return a WorldConfig, got {type(out).__name__}")


#: the methods through which the tools call a task, and a check of what each returns (None: any value)
_HOOKS: dict[str, Callable[..., None] | None] = {
    "world": _world,
    "world_for": _world,
    "check_world": None,
    "spawn": _spawn,
    "step_info": lambda task, env, out: None if isinstance(out, Mapping) and all(isinstance(k, str) for k in out)
    else _fail("must return a dict with text keys"),
    "reward": lambda task, env, u, info, out: _array(out, (env.n_envs,), "the reward"),
    "state_dim": lambda task, cfg, n, out: None if isinstance(out, (int, np.integer)) and not isinstance(out, bool)
    and 0 <= out <= 1 << 20 else _fail(f"must return an integer in 0..{1 << 20}"),
    "state": lambda task, env, out: _array(out, (env.n_envs, task.state_dim(env.cfg, env.n_robots)), "the state"),
    "make_baseline": None,
    "episode_metrics": lambda task, *a: None if all(hasattr(a[-1], n) for n in ("summary", "to_dict"))
    else _fail("must return metrics with summary() and to_dict() (sim.metrics.success_metrics)"),
    "has_ceiling": lambda task, cfg, out: None if isinstance(out, (bool, np.bool_)) else _fail("must return a bool"),
    "bound_report": lambda task, cfg, out: None if isinstance(out, Mapping) and all(isinstance(k, str) for k in out)
    else _fail("must return a dict with text keys"),
    "no_ceiling_note": lambda task, cfg, out: None if isinstance(out, str) and "\n" not in out
    else _fail("must return one line of text"),
}


def _fail(message: str) -> None:
    raise InputError(message)


def guarded(cls: type[Task], where: str) -> type[Task]:
    """A subclass of the user's ``cls`` whose hooks turn an exception, or a value of the wrong kind, into one line."""

    who = where if where.startswith("task") else f"task {where}"

    def hook(name: str, check: Callable[..., None] | None) -> Callable[..., Any]:
        def call(self: Task, *args: Any, **kwargs: Any) -> Any:
            try:
                out = getattr(cls, name)(self, *args, **kwargs)
                if check is not None:
                    check(self, *args, out)
                return out
            except InputError as e:
                raise InputError(f"{who}: {name}(): {e}") from None
            except Exception as e:
                raise InputError(f"{who}: {name}() raised {type(e).__name__}: {e}") from None

        call.__name__ = call.__qualname__ = name
        return call

    body: dict[str, Any] = {n: hook(n, c) for n, c in _HOOKS.items()}
    name = f"_kiloforge_guarded_{cls.__name__}"
    body.update(__module__=cls.__module__, __qualname__=name, __doc__=cls.__doc__)
    guarded_cls = type(name, (cls,), body)
    module = sys.modules.get(cls.__module__)
    if module is not None:  # found by name, as pickle finds a class
        setattr(module, name, guarded_cls)
    return guarded_cls
