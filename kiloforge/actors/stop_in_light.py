"""Actor kind ``"stop_in_light"``: the hand-written stop-in-the-light rule of :mod:`sim.tasks.phototaxis` as firmware.

The float actor is :class:`sim.tasks.phototaxis.StopInLight` (walk; stand while the held reading is at least
``threshold`` ADC counts); its artifact holds only the :class:`~sim.tasks.phototaxis.StopInLightParams` and
records task phototaxis. The shipped one is ``export/data/stop_in_light_policy.npz`` (the tuned defaults in
phototaxis's kilobot world), written by ``python -m tools.ship_rules``. The integer rule stands where the int8
light level ``lq >= KF_LEVEL_T = ceil(threshold · ONE / 2**10)``, exactly the float ``level >= threshold`` on
``lq / ONE · 2**10`` counts; the walk, its draws and the rest are :mod:`.light_rules`'.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

import numpy as np

from sim.config import WorldConfig
from sim.tasks.phototaxis import StopInLight, StopInLightParams

from .base import CDefine
from .light_rules import (LEVEL_BITS, FirmwareLightDraws, LightRuleKind, LightRulePolicy, QuantizedLightRule,
                          level_threshold, quantize_light_rule, task_policy)
from .rules import OwnSeeds


class SeededStopInLight(OwnSeeds, StopInLight):
    """The float rule; ``reset`` without a generator takes the next child of its own seed sequence."""


class FirmwareDrawStopInLight(FirmwareLightDraws, StopInLight):
    """The float rule drawing from the firmware's xorshift32 streams (one per robot, seeded by uid)."""


@dataclass(frozen=True, eq=False)
class StopInLightPolicy(LightRulePolicy):
    """The stop-in-the-light rule with its parameters in a world; no arrays."""

    kind: ClassVar[str] = "stop_in_light"
    params_cls: ClassVar[type] = StopInLightParams
    seeded_cls: ClassVar[type] = SeededStopInLight
    label: ClassVar[str] = "stop-in-the-light"


def stop_in_light_policy(world: WorldConfig, params: StopInLightParams | None = None,
                         provenance: Mapping[str, Any] | None = None) -> StopInLightPolicy:
    """The stop_in_light artifact of task phototaxis in ``world`` made the task's (default: the tuned parameters)."""
    return task_policy(StopInLightPolicy, world, params, provenance)


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedStopInLight(QuantizedLightRule):
    """The integer rule: stand where the light level >= level_t."""

    kind: ClassVar[str] = "stop_in_light"
    level_t: int  #: stand when the int8 level >= this (threshold at e_in, rounded up)

    def decide(self, level: np.ndarray, change: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return level >= self.level_t, np.zeros(level.shape, bool)

    def thresholds(self) -> dict[str, int]:
        return {"level_t": int(self.level_t)}

    def describe(self) -> str:
        return (f"hand-written stop-in-the-light: stand at light level >= {self.level_t} (of {1 << self.e_in} per "
                f"{1 << LEVEL_BITS} counts), random turns out of 2^16, e_in {self.e_in}")


def quantize_stop_in_light(policy: StopInLightPolicy, e_in: int | None = None) -> QuantizedStopInLight:
    """The integer rule of ``policy``."""
    return quantize_light_rule(QuantizedStopInLight, policy, e_in,
                               level_t=lambda one: level_threshold(policy.params.threshold, one))


class StopInLightKind(LightRuleKind):
    """The stop-in-the-light rule of sim.tasks.phototaxis (a baseline to flash next to a learned policy)."""

    name: ClassVar[str] = "stop_in_light"
    template: ClassVar[str] = "actors/stop_in_light.c.j2"
    policy_cls = StopInLightPolicy
    draw_cls = FirmwareDrawStopInLight

    def quantize_rule(self, policy: StopInLightPolicy, e_in: int | None) -> QuantizedStopInLight:
        return quantize_stop_in_light(policy, e_in)

    def rule_defines(self, qp: QuantizedStopInLight) -> tuple[CDefine, ...]:
        return (CDefine("KF_LEVEL_T", qp.level_t, "int16_t",
                        f"stand while the light level >= this ({qp.params.threshold} counts at e_in, rounded up)"),)


STOP_IN_LIGHT = StopInLightKind()
