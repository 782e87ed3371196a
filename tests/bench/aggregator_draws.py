"""The aggregator's firmware vs its float rule with the same random streams, and the neighbour count each sees (prints tables).

    python -m tests.bench.aggregator_draws [--robots 16 32] [--episodes 100] [--steps 500] [--seed 20261202]

Not a test. Table 1, per robot count, same episodes (as ``python -m export verify`` pairs them): final
largest-cluster fraction of the float rule with NumPy draws (``export verify``'s float side), of the float rule
drawing from the firmware's xorshift32 streams (:class:`kiloforge.actors.aggregator.FirmwareDrawAggregator`, uid
i + 1 for robot i as in the closed loop) and of the int8 firmware (emulator); the paired difference firmware -
float-with-firmware-draws isolates what the int8 observation changes. Table 2: one firmware-driven run
(8 envs), per robot-period: how often the neighbour count n of the int8 observation equals the float rule's n on
the simulator's float observation of the same period, and the mean difference of their RBF sums (int8 units).
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from kiloforge.shipped import load_task_policy
from export.verify.closed_loop import default_n_envs, run_firmware, run_float
from export.verify.emulator import FirmwareEmulator, events_from_sim
from kiloforge.actors.aggregator import FirmwareDrawAggregator, quantize_aggregator
from sim.config import BENCHMARK_STEPS, HELD_OUT_SEED
from sim.env import SwarmEnv
from sim.metrics import summarise
from sim.rollout import rollout
from sim.tasks import get_task
from sim.tasks.aggregation import ProbabilisticAggregator


def same_draws(policy, cfg, task, M: int, episodes: int, seed: int, B: int) -> np.ndarray:
    """Final cluster per episode of the float rule drawing from the firmware's streams (episodes as run_firmware's)."""
    env = SwarmEnv(cfg, B, M, seed=seed, task=task)
    ref = FirmwareDrawAggregator(cfg, policy.params, np.tile(np.arange(1, M + 1), B))
    return rollout(env, ref, episodes, seed=seed).metrics().per_episode("final_cluster")


def neighbour_agreement(qp, cfg, task, M: int, steps: int, seed: int, B: int = 8) -> tuple[float, float, float]:
    """(n equal, n int8 lower, mean int8 - float RBF sum) over a firmware-driven run."""
    env = SwarmEnv(cfg, B, M, seed=seed, task=task)
    obs, info = env.reset(seed=seed)
    emu = FirmwareEmulator(qp, np.tile(np.arange(1, M + 1), B))
    emu.reset()
    emu.deliver(events_from_sim(info["events"], 0, cfg, M))
    rbf, scale = cfg.obs_slice("rbf"), 1 << qp.e_in
    float_rule = ProbabilisticAggregator(cfg, qp.params)
    eq = low = n = 0
    dsum = 0.0
    for t in range(steps):
        q, o8 = emu.control_step(np.asarray(info["light"]).reshape(B * M))
        if t > 0:  # the int8 observation of period t and the simulator's float one of the same period (step t - 1's)
            s_float = obs[..., rbf].sum(-1).reshape(-1).astype(np.float64)
            n_float, n_int = float_rule.neighbours(obs).reshape(-1), qp.neighbours(o8)
            eq += int((n_int == n_float).sum())
            low += int((n_int < n_float).sum())
            dsum += float((o8[:, rbf].sum(-1) - s_float * scale).sum())
            n += n_int.size
        obs, _, _, _, info = env.step_u8(q.reshape(B, M, 2))
        emu.deliver(events_from_sim(info["events"], t + 1, cfg, M))
    return eq / n, low / n, dsum / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--steps", type=int, default=BENCHMARK_STEPS)
    ap.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    a = ap.parse_args()
    task = get_task("aggregation")
    policy = load_task_policy("aggregator", task)
    qp = quantize_aggregator(policy)
    cfg = dataclasses.replace(policy.world, episode_steps=a.steps)
    print(f"final largest-cluster fraction, {a.episodes} episodes x {a.steps} steps, seed {a.seed} (mean ± 95 % CI)")
    print(f"{'robots':>6} {'float (NumPy draws)':>20} {'float (fw draws)':>17} {'int8 firmware':>14} "
          f"{'int8 - float (fw draws)':>24}")
    for M in a.robots:
        B = default_n_envs(a.episodes, M)
        f = run_float(policy, M, a.episodes, a.seed, steps=a.steps, n_envs=B, task=task)
        q = run_firmware(qp, M, a.episodes, a.seed, steps=a.steps, n_envs=B, task=task)
        fd = same_draws(policy, cfg, task, M, a.episodes, a.seed, B)
        vf, vq = (r.metrics().per_episode("final_cluster") for r in (f, q))
        cells = [summarise(v) for v in (vf, fd, vq, vq - fd)]
        print(f"{M:>6} " + " ".join(f"{s.mean:+.3f} ± {s.ci95:.3f}".lstrip("+").rjust(w)
                                    for s, w in zip(cells, (20, 17, 14, 24))))
    print("\nneighbour count of the int8 observation vs the float one, same periods (8 envs, firmware-driven)")
    print(f"{'robots':>6} {'n equal':>8} {'n int8 lower':>13} {'RBF sum int8 - float (units)':>29}")
    for M in a.robots:
        eq, low, d = neighbour_agreement(qp, cfg, task, M, a.steps, a.seed)
        print(f"{M:>6} {eq:>8.4f} {low:>13.4f} {d:>+29.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
