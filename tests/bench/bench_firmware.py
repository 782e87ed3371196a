"""Throughput of the firmware emulator and the host build on random event streams (prints a table).

    python -m tests.bench.bench_firmware

Not a test: numbers depend on the machine. Each row replays the same stream through
export.emulator.FirmwareEmulator and the host build of the rendered C, and checks they agree.
"""
from __future__ import annotations

import tempfile
import time

import numpy as np

from export.codegen.render import POLICY_FILE, render_firmware
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, random_inputs, run_host
from tests.fixtures import synthetic_qpolicy
from sim.config import preset

ROWS = [  # (world, t_prev, hidden, activations, robots, control steps)
    (preset("kilobot"), 10, (32, 32), ("elu", "elu"), 256, 200),
    (preset("kilobot"), 20, (32, 32), ("elu", "elu"), 256, 200),
    (preset("thesis", period_ticks=4), 4, (16,), ("relu",), 512, 400),
]


def main() -> int:
    print(f"{'world':>8} {'P':>3} {'t_prev':>6} {'hidden':>9} {'robots':>6} {'steps':>8} {'robot-ticks':>11} "
          f"{'events':>9} {'emulator s':>10} {'host s':>7} {'emu steps/s':>11} {'equal':>5}")
    with tempfile.TemporaryDirectory() as tmp:
        for i, (w, t_prev, hidden, acts, R, S) in enumerate(ROWS):
            qp = synthetic_qpolicy(w, t_prev, hidden, acts, seed=i)
            exe = build_host(render_firmware(qp, generator_version="bench")[POLICY_FILE], tmp, name=f"b{i}")
            rng = np.random.default_rng(np.random.SeedSequence(i))
            inputs = random_inputs(rng, w.period_ticks, (w.emitter_uid,), StreamSpec(n_robots=R, n_steps=S),
                                   comm_radius_mm=w.comm_radius_mm, light_threshold=w.light_threshold)
            emu = FirmwareEmulator(qp, inputs.uids, inputs.calib)
            t0 = time.perf_counter()
            want = emu.run(inputs)
            t1 = time.perf_counter()
            got = run_host(exe, inputs, w.period_ticks, w.obs_dim)
            t2 = time.perf_counter()
            steps = int((~emu.is_beacon).sum()) * want.steps.shape[1]
            print(f"{w.name:>8} {w.period_ticks:>3} {t_prev:>6} {'x'.join(map(str, hidden)):>9} {R:>6} {steps:>8,} "
                  f"{R * inputs.n_ticks:>11,} {inputs.events.size:>9,} {t1 - t0:>10.2f} {t2 - t1:>7.2f} "
                  f"{steps / (t1 - t0):>11,.0f} {'yes' if not compare(want, got) else 'NO':>5}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
