"""Tasks as plug-ins: the registry, and resolving ``--task`` (a built-in name, an installed package's
entry point in the group ``kiloforge.tasks``, or ``path/to/file.py:ClassName``).

    >>> get_task("localisation").primary_metric
    'final_coverage'
"""
from __future__ import annotations

import importlib.util
import inspect
import sys
from pathlib import Path

from kiloforge.errors import InputError

from ..features import register
from ..table_features import NeighbourTable, TableFeature

from .base import LEGACY_TASK, Metric, Task, TaskRef
from .guard import check_attributes, guarded
from .aggregation import Aggregation
from .localisation import Localisation
from .phototaxis import Phototaxis
from .transport import Transport

__all__ = ["DEFAULT_TASK", "ENTRY_POINT_GROUP", "LEGACY_TASK", "Metric", "NeighbourTable", "TASKS", "TASK_HELP",
           "TableFeature", "Task", "TaskRef",
           "check_policy_task", "get_task", "is_task_file", "recorded_task", "task_names"]

ENTRY_POINT_GROUP = "kiloforge.tasks"
DEFAULT_TASK = "localisation"
#: the built-in tasks, by name
TASKS: dict[str, type[Task]] = {cls.name: cls for cls in (Localisation, Aggregation, Phototaxis, Transport)}

#: the help text of every command's ``--task``
TASK_HELP = (f"the task: {', '.join(sorted(TASKS))}, an installed plug-in (entry point group {ENTRY_POINT_GROUP}) "
             f"or path/to/file.py:ClassName (default {DEFAULT_TASK})")

_REQUIRED = tuple(n for n, v in vars(Task).items() if getattr(v, "__isabstractmethod__", False))


def _entry_points() -> dict[str, object]:
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def task_names() -> list[str]:
    """Every task name ``--task`` takes without a path: built-ins, then installed plug-ins."""
    return sorted(TASKS) + sorted(n for n in _entry_points() if n not in TASKS)


def _checked(cls: object, where: str) -> Task:
    if not (inspect.isclass(cls) and issubclass(cls, Task)):
        raise InputError(f"{where} is not a subclass of sim.tasks.Task")
    missing = [n for n in _REQUIRED if getattr(cls, n, None) is getattr(Task, n)]
    if missing or inspect.isabstract(cls):
        missing = missing or sorted(cls.__abstractmethods__)
        raise InputError(f"{where} does not define {', '.join(missing)} (see docs/tasks.md)")
    if not isinstance(getattr(cls, "name", None), str):
        raise InputError(f"{where} has no 'name' (a class attribute, e.g. name = \"dispersion\")")
    try:
        task = guarded(cls, where)()
        TaskRef(task.name, task.version)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    except Exception as e:  # a user's constructor: report it in one line
        raise InputError(f"{where} could not be created: {type(e).__name__}: {e}") from None
    check_attributes(task, where)
    for f in task.own_features:
        register(f, where)
    keys = [m.key for m in task.metrics]
    if task.primary_metric not in keys:
        raise InputError(f"{where}: primary_metric {task.primary_metric!r} is not among its metrics {keys}")
    return task


def _from_file(spec: str) -> Task:
    path_s, _, cls_name = spec.rpartition(":")
    path = Path(path_s)
    if not cls_name.isidentifier():
        raise InputError(f"--task {spec!r}: expected path/to/file.py:ClassName")
    if path.suffix != ".py" or not path.is_file():
        raise InputError(f"--task {spec!r}: {path_s!r} is not a Python file")
    mod_name = f"kiloforge_user_task_{abs(hash(str(path.resolve())))}"
    try:
        mspec = importlib.util.spec_from_file_location(mod_name, path)
        assert mspec is not None and mspec.loader is not None
        module = importlib.util.module_from_spec(mspec)
        sys.modules[mod_name] = module  # dataclasses and pickling look modules up by name
        mspec.loader.exec_module(module)
    except SyntaxError as e:
        sys.modules.pop(mod_name, None)
        at = f" at line {e.lineno}" if e.lineno else ""
        raise InputError(f"task file {path_s}: syntax error{at}: {e.msg}") from None
    except InputError:
        sys.modules.pop(mod_name, None)
        raise
    except KeyboardInterrupt:  # Ctrl-C or a signal: the command's own handling says what is left
        sys.modules.pop(mod_name, None)
        raise
    except BaseException as e:  # its code, SystemExit included, ends the import, not the command's contract
        sys.modules.pop(mod_name, None)
        raise InputError(f"task file {path_s} failed to import: {type(e).__name__}: {e}") from None
    if not hasattr(module, cls_name):
        raise InputError(f"task file {path_s} defines no {cls_name!r}")
    return _checked(getattr(module, cls_name), f"{path_s}:{cls_name}")


def is_task_file(spec: object) -> bool:
    """True for a ``path/to/file.py:ClassName`` spec (importing it runs that file)."""
    return isinstance(spec, str) and ":" in spec and spec.partition(":")[0].endswith(".py")


def recorded_task(spec: object, where: str, flag: str) -> Task:
    """The task a file records (a run's config.json): a built-in or installed plug-in, by name. A task *file* named
    by a file is never imported (the file may come from someone else): InputError asking for ``flag``."""
    if is_task_file(spec):
        raise InputError(f"{where} names the task file {spec!r}, and code a file names is never imported; if you "
                         f"trust that file, give it yourself: {flag} {spec}")
    return get_task(spec)


def get_task(spec: "str | Task | None" = None) -> Task:
    """The task named by ``spec``: None (the default, localisation), a built-in or plug-in name, a
    ``file.py:Class`` path, or a Task instance (returned as it is). InputError in one line otherwise."""
    if spec is None:
        spec = DEFAULT_TASK
    if isinstance(spec, Task):
        return spec
    if not isinstance(spec, str) or not spec:
        raise InputError(f"task must be a name or path/to/file.py:ClassName, got {spec!r}")
    if spec in TASKS:
        return TASKS[spec]()
    if is_task_file(spec):
        return _from_file(spec)
    eps = _entry_points()
    if spec in eps:
        try:
            cls = eps[spec].load()
        except Exception as e:
            raise InputError(f"task plug-in {spec!r} failed to load: {type(e).__name__}: {e}") from None
        return _checked(cls, f"task plug-in {spec!r}")
    raise InputError(f"unknown task {spec!r}; choose one of: {', '.join(task_names())}, "
                     "or give path/to/file.py:ClassName")


def check_policy_task(policy_task: TaskRef, task: Task, what: str) -> None:
    """Refuse a policy trained for another task (or another version of it) in one line."""
    if policy_task != task.ref:
        raise InputError(f"{what} was trained for task {policy_task}, not {task.ref}; "
                         f"pass --task {policy_task.name} or a policy of task {task.name}")
