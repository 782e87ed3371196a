"""Closed loop: float actor vs int8 firmware emulator in the simulator, and its speed (prints tables).

    python -m tests.bench.bench_closed_loop [--policy P] [--robots 4 16 32] [--episodes 200]
                                            [--steps N] [--scaling]

Not a test: numbers depend on the machine and on the policy. Default policy: the shipped
``export/data/default_policy.npz``. Quantised as ``python -m export`` does by default (calibration
on 4 and 16 robots, one episode each, seed 0). Table 1: per robot count, float vs int8 mean final
coverage, return and time to find with 95 % CIs, the paired difference of final coverage, the ratio
int8/float (paired-bootstrap CI), PASS/FAIL against 97 %, and episodes/s of each side.
``--scaling``: table 2, int8 throughput as the batch grows (B envs x M robots in one emulator),
showing how the per-period Python overhead is amortised.
"""
from __future__ import annotations

import argparse
import time
from importlib import resources
from pathlib import Path

from export.quantize import calibrate, error_report, quantize_policy
from export.verify.closed_loop import compare, run_firmware
from kiloforge.policies import load_policy


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", type=Path, default=None)
    ap.add_argument("--robots", type=int, nargs="+", default=[4, 16, 32])
    ap.add_argument("--episodes", type=int, default=200)
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scaling", action="store_true", help="also print the throughput-vs-batch table")
    args = ap.parse_args()

    if args.policy is None:
        with resources.as_file(resources.files("export").joinpath("data", "default_policy.npz")) as f:
            policy = load_policy(f)
        source = "export/data/default_policy.npz"
    else:
        policy, source = load_policy(args.policy), str(args.policy)
    calib = calibrate(policy, episodes=1, n_robots=(4, 16), seed=0)
    qp = quantize_policy(policy, calib)
    rep = error_report(policy, qp, calib)
    T = args.steps or policy.world.episode_steps
    print(f"policy {source} ({policy.hash[:12]}, world '{policy.world.name}', {policy.describe()}); "
          f"{policy.provenance.get('notes', '')}")
    print(f"quantised: e_in {qp.e_in}, mean |du| {rep.du_mean:.4f}, same uint8 command {100 * rep.same_command:.1f}%; "
          f"{args.episodes} episodes x {T} steps per robot count, seed {args.seed}")
    head = (f"{'robots':>6} {'final cov float':>16} {'final cov int8':>16} {'int8-float':>15} {'ratio [95% CI]':>22} "
            f"{'goal':>4} {'return float':>16} {'return int8':>16} {'t-find float':>14} {'t-find int8':>14} "
            f"{'float ep/s':>10} {'int8 ep/s':>9} {'B':>4}")
    print(head)
    print("-" * len(head))
    for M in args.robots:
        c = compare(policy, qp, M, args.episodes, args.seed, steps=args.steps)
        s = c.stats
        lo, hi = c.ratio_ci
        ratio = f"{c.ratio:.3f} [{lo:.3f},{hi:.3f}]" if c.ratio == c.ratio else "n/a"
        pm = lambda x: f"{x.mean:.3f}±{x.ci95:.3f}"  # noqa: E731
        pm1 = lambda x: f"{x.mean:.1f}±{x.ci95:.1f}"  # noqa: E731
        print(f"{M:>6} {pm(s['final_coverage']['float']):>16} {pm(s['final_coverage']['int8']):>16} "
              f"{s['final_coverage']['diff'].mean:>+8.3f}±{s['final_coverage']['diff'].ci95:.3f} {ratio:>22} "
              f"{'PASS' if c.passed else 'FAIL':>4} {pm1(s['return']['float']):>16} {pm1(s['return']['int8']):>16} "
              f"{pm1(s['time_to_find']['float']):>14} {pm1(s['time_to_find']['int8']):>14} "
              f"{c.float_run.episodes_per_s:>10.1f} {c.int8_run.episodes_per_s:>9.1f} {c.float_run.n_envs:>4}",
              flush=True)

    if args.scaling:
        steps = min(T, 50)
        print(f"\nint8 firmware in the loop, throughput vs batch ({steps} steps per episode)")
        print(f"{'robots':>6} {'envs B':>6} {'B*M':>6} {'episodes':>8} {'s':>7} {'episodes/s':>10} {'robot-steps/s':>13}")
        for M, B in [(16, 1), (16, 16), (16, 64), (16, 128), (16, 256), (64, 1), (64, 16), (64, 32), (64, 64)]:
            E = max(B, 4 if B == 1 else B)
            t0 = time.perf_counter()
            run_firmware(qp, M, E, args.seed, steps=steps, n_envs=B)
            dt = time.perf_counter() - t0
            print(f"{M:>6} {B:>6} {B * M:>6} {E:>8} {dt:>7.2f} {E / dt:>10.1f} {E * steps * M / dt:>13,.0f}",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
