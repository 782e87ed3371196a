"""A task's emitter as the generic layers see it: the robot of the task's that only transmits, with the role bit
(localisation's beacon, transport's object robot), and its firmware.

The task declares it in its own words (``Task.beacon``, ``beacon_role``, ``firmware``, ``emitter_program``);
:func:`task_emitter` is the one place that reads them for the exporter, so export/ names no task's robot.
"""
from __future__ import annotations

from dataclasses import dataclass

from .base import Task


@dataclass(frozen=True)
class Emitter:
    """What the exporter renders for a task's emitter (validated there, where the templates are)."""

    role: str  #: what users call the robot, e.g. "the beacon" (banners, the exporter's next steps)
    firmware: str  #: its partials' folder under firmware_templates/tasks/
    program: str  #: the file its own program is written to, e.g. kilobot_target.c


def task_emitter(task: Task) -> Emitter | None:
    """``task``'s emitter, or None for a task without one."""
    if not task.beacon:
        return None
    return Emitter(role=task.beacon_role, firmware=task.firmware, program=task.emitter_program)
