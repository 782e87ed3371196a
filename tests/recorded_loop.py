"""Firmware in the loop for the host-build tests: SwarmEnv driven by the emulator, its inputs recorded."""
from __future__ import annotations

from typing import Any

import numpy as np

from export.verify.emulator import FirmwareEmulator, FirmwareInputs, events_from_sim
from kiloforge.actors.base import QuantizedActor
from sim.config import WorldConfig


def record_loop(qp: QuantizedActor, cfg: WorldConfig, n_robots: int, steps: int, seed: int,
                task: Any = None) -> FirmwareInputs:
    """What ``n_robots`` robots (uids 1..M) of one env receive while the emulator drives them ``steps`` control steps
    of ``task`` (a sim.tasks name or Task; default localisation)."""
    from sim.env import SwarmEnv
    from sim.tasks import get_task

    M, P = int(n_robots), cfg.period_ticks
    env = SwarmEnv(cfg, 1, M, seed=seed, task=get_task(task))
    _, info = env.reset()
    emu = FirmwareEmulator(qp, np.arange(1, M + 1))
    events, lights = [], []
    emu.tick_outputs(P)
    ev = events_from_sim(info["events"], 0, cfg, M)
    emu.deliver(ev)
    events.append(ev)
    for k in range(1, steps + 1):
        lights.append(info["light"][0].copy())
        q, _ = emu.control_step(info["light"][0])
        _, _, _, _, info = env.step_u8(q[None])
        emu.tick_outputs(P)
        ev = events_from_sim(info["events"], k, cfg, M)
        emu.deliver(ev)
        events.append(ev)
    return FirmwareInputs(uids=np.arange(1, M + 1), calib=emu.calib, light=np.stack(lights, 1),
                          events=np.concatenate(events), n_ticks=(steps + 1) * P)
