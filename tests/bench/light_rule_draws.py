"""The phototaxis baselines' firmware vs their float rules with the same random streams (prints a table).

    python -m tests.bench.light_rule_draws [--policy stop_in_light run_and_tumble] [--robots 16 32] [--episodes 200]
        [--steps 300] [--seed 0]

Not a test. Per rule and robot count, the episodes of ``python -m export verify`` (same seed, steps and batching):
final fraction in the spot of the float rule with NumPy draws (``export verify``'s float side), of the float rule
drawing from the firmware's xorshift32 streams (the kind's ``draw_reference``, uid i + 1 for robot i as in the
closed loop) and of the int8 firmware (emulator). firmware / float is what ``export verify`` reports; the paired
difference firmware - float-with-firmware-draws isolates what the int8 light feature changes (its 16-count level
steps at e_in 6), float-with-firmware-draws - float what the random streams change.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from kiloforge.shipped import load_task_policy
from export.verify.closed_loop import default_n_envs, run_firmware, run_float
from kiloforge.actors.registry import kind_of
from sim.env import SwarmEnv
from sim.metrics import summarise
from sim.rollout import rollout
from sim.tasks import get_task


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", nargs="+", default=["stop_in_light", "run_and_tumble"])
    ap.add_argument("--robots", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    task = get_task("phototaxis")
    metric = task.primary_metric
    print(f"final fraction in the spot, {a.episodes} episodes x {a.steps} steps, seed {a.seed} (mean ± 95 % CI)")
    cols = ("float (NumPy draws)", "float (fw draws)", "int8 firmware", "fw / float", "fw draws - NumPy",
            "int8 - float (fw draws)")
    print(f"{'policy':>15} {'robots':>6} " + " ".join(f"{c:>24}" for c in cols))
    for name in a.policy:
        policy = load_task_policy(name, task)
        kind = kind_of(policy)
        qp = kind.quantize_rule(policy, None)
        for M in a.robots:
            B = default_n_envs(a.episodes, M)
            cfg = dataclasses.replace(policy.world, episode_steps=a.steps)
            f = run_float(policy, M, a.episodes, a.seed, steps=a.steps, n_envs=B, task=task)
            q = run_firmware(qp, M, a.episodes, a.seed, steps=a.steps, n_envs=B, task=task)
            env = SwarmEnv(cfg, B, M, seed=a.seed, task=task)
            ref = kind.draw_reference(dataclasses.replace(policy, world=cfg), np.tile(np.arange(1, M + 1), B))
            fd = rollout(env, ref, a.episodes, seed=a.seed).metrics().per_episode(metric)
            vf, vq = (r.metrics().per_episode(metric) for r in (f, q))
            cells = [str(summarise(v)) for v in (vf, fd, vq)] + [f"{vq.mean() / vf.mean():.3f}"]
            cells += [str(summarise(d)) for d in (fd - vf, vq - fd)]
            print(f"{name:>15} {M:>6} " + " ".join(f"{c:>24}" for c in cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
