"""Host build == emulator for a trained policy (any actor kind) over > 100,000 searcher control steps.

    python -m tests.soak.host_bit_exact runs/NAME/policy_best.npz

Quantises the policy as ``python -m export`` does (calibration on 4 and 16 robots, one episode, seed
0), builds the rendered C with the host compiler and replays two random event streams (256 robots,
dense and sparse radio, state filled with 0x5A before setup()) through it and the emulator; exits
non-zero on the first integer that differs. The CI tests do the same with synthetic policies.
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from export.codegen.render import POLICY_FILE, render_firmware
from export.quantize import calibrate, quantize_policy
from export.verify.emulator import FirmwareEmulator
from export.verify.hostbuild import StreamSpec, build_host, compare, random_inputs, run_host
from kiloforge.policies import load_policy


def main(policy: str) -> None:
    p = load_policy(policy)
    world = p.world
    q = quantize_policy(p, calibrate(p, episodes=1, n_robots=(4, 16), seed=0))
    total = 0
    with tempfile.TemporaryDirectory() as d:
        exe = build_host(render_firmware(q)[POLICY_FILE], Path(d), name="trained")
        specs = [StreamSpec(n_robots=256, n_steps=260, rate=0.9),
                 StreamSpec(n_robots=256, n_steps=200, rate=0.6, n_senders=8)]
        for i, spec in enumerate(specs):
            rng = np.random.default_rng(np.random.SeedSequence(40 + i))
            inputs = random_inputs(rng, world.period_ticks, (world.emitter_uid,), spec,
                                   comm_radius_mm=world.comm_radius_mm, light_threshold=world.light_threshold)
            emu = FirmwareEmulator(q, inputs.uids, inputs.calib)
            want = emu.run(inputs)
            got = run_host(exe, inputs, world.period_ticks, world.obs_dim, fill="0x5A")
            np.testing.assert_array_equal(got.ticks, want.ticks, err_msg=compare(want, got))
            np.testing.assert_array_equal(got.steps, want.steps, err_msg=compare(want, got))
            total += int((~emu.is_emitter).sum()) * want.steps.shape[1]
    print(f"host build == emulator (assert_array_equal on integers) over {total} searcher control steps")


if __name__ == "__main__":
    main(sys.argv[1])
