"""The policies kiloforge ships, per task, and loading a policy by file or shipped name for a task.

``--policy NAME`` (in ``python -m export``, ``export verify``, ``learn evaluate`` and ``python -m sim``) names a
shipped policy of the ``--task`` when no file of that name exists; ``default`` is the task's reference policy.
Every policy loaded here must have been trained for that task (one-line InputError otherwise). The files are
package data of :mod:`export` (``export/data/``, where the exporter's users find them); this registry sits in the
foundation so that the simulator's command line reads them too.
"""
from __future__ import annotations

import os
from contextlib import ExitStack
from importlib import resources
from pathlib import Path

from kiloforge.actors.base import FloatPolicy
from kiloforge.errors import InputError, printable
from kiloforge.policies import load_policy
from sim.tasks import Task, check_policy_task, get_task

#: task -> shipped name -> file in this package's data/
SHIPPED_POLICIES: dict[str, dict[str, str]] = {"localisation": {
    "default": "default_policy.npz",  #: learned by evolution strategies (README, docs/results/localisation.md)
    "searcher": "searcher_policy.npz",  #: sim.baselines' hand-written searcher, TUNED["kilobot"]
    "pusher": "pusher_policy.npz",  #: the same with sim.baselines.PUSHER
}, "aggregation": {
    #: learned from random weights by evolution strategies (docs/results/aggregation.md: the default recipe, seed 2)
    "default": "aggregation_policy.npz",
    "aggregator": "aggregator_policy.npz",  #: sim.tasks.aggregation's hand-written rule, tuned AggregatorParams
}, "phototaxis": {
    #: learned from random weights by evolution strategies (docs/results/phototaxis.md: the sizes recipe, seed 2)
    "default": "phototaxis_policy.npz",
    "stop_in_light": "stop_in_light_policy.npz",  #: sim.tasks.phototaxis' StopInLight, tuned StopInLightParams
    "run_and_tumble": "run_and_tumble_policy.npz",  #: sim.tasks.phototaxis' RunAndTumble, tuned RunAndTumbleParams
}, "transport": {
    #: learned from random weights by evolution strategies (docs/results/transport.md: the bias recipe, seed 2)
    "default": "transport_policy.npz",
    "shadow_pusher": "shadow_pusher_policy.npz",  #: sim.tasks.transport's ShadowPusher, tuned ShadowPusherParams
}}


def shipped_names(task: "Task | str | None" = None) -> list[str]:
    """The shipped policy names of ``task`` (default localisation)."""
    return sorted(SHIPPED_POLICIES.get(get_task(task).name, {}))


def load_task_policy(spec: "str | os.PathLike | None", task: "Task | str | None" = None) -> FloatPolicy:
    """A policy file, or a shipped policy's name (None: ``default``), checked to be a policy of ``task``."""
    task = get_task(task)
    shipped = SHIPPED_POLICIES.get(task.name, {})
    if spec is not None and (os.path.lexists(spec) or str(spec) not in shipped):
        policy = load_policy(Path(spec))
        check_policy_task(policy.task_ref, task, f"policy file {printable(spec)}")
        return policy
    name = str(spec or "default")
    if name not in shipped:
        raise InputError(f"task '{task.name}' ships no policy '{name}'; give a policy file (.npz)"
                         + (f" or one of: {', '.join(sorted(shipped))}" if shipped else ""))
    with ExitStack() as stack:
        policy = load_policy(stack.enter_context(resources.as_file(resources.files("export") / "data" / shipped[name])))
    check_policy_task(policy.task_ref, task, f"shipped policy '{name}'")
    return policy
