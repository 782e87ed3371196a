"""Learned policies of several training seeds against the hand-written searcher, on held-out episodes.

    python -m tests.bench.learning_seeds runs/es_s1 runs/es_s2 runs/es_s3 --robots 4 16 32 \
        --episodes 100 --steps 500 --seed 20261202 --out runs/es_eval

Evaluates each run's ``policy_best.npz`` (or the ``.npz`` given) with ``python -m learn evaluate``'s
machinery: every policy and the baselines play the same episodes, from ``--seed``, which no training
or model selection used (training draws its episodes and evaluation seeds from the run's own
``SeedSequence``). Prints per robot count a table: each seed's final coverage (mean ± 95 % CI over
episodes), the mean and sample standard deviation over seeds, the hand-written searcher, the pusher and
the random walk, and how many seeds beat the searcher and the pusher. Writes ``seeds.json`` and the evaluation folders.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from kiloforge.io import write_atomic
from kiloforge.policies import load_policy, policy_paths
from learn.evaluate import evaluate_policies
from sim.config import HELD_OUT_SEED


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    ap.add_argument("runs", nargs="+", help="run directories (their policy_best.npz) or .npz files")
    ap.add_argument("--robots", nargs="+", type=int, default=[4, 16, 32])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="episode seed no training used")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    try:
        paths = policy_paths(args.runs)
    except ValueError as e:
        ap.error(str(e))
    policies = {name: load_policy(path) for name, path in paths.items()}
    res = evaluate_policies(policies, args.robots, args.episodes, args.steps, out, seed=args.seed, gif=False,
                            progress=False, log=lambda _m: None)
    summary = {"episodes": args.episodes, "steps": args.steps, "seed": args.seed, "robots": {}}
    for M in args.robots:
        m = res["robots"][str(M)]["metrics"]
        fc = {n: m[n]["summary"]["final_coverage"] for n in m}
        learned = [fc[n]["mean"] for n in policies]
        base = fc["hand-written"]["mean"]
        beat = sum(v > base for v in learned)
        print(f"\n{M} robots: final coverage, {args.episodes} episodes x {args.steps} steps, seed {args.seed}")
        for n in policies:
            print(f"  {n:28s} {fc[n]['mean']:.3f} ± {fc[n]['ci95']:.3f}")
        print(f"  {'mean ± std over seeds':28s} {np.mean(learned):.3f} ± {np.std(learned, ddof=1) if len(learned) > 1 else 0:.3f}")
        push = fc["hand-written pusher"]
        beat_push = sum(v > push["mean"] for v in learned)
        print(f"  {'hand-written searcher':28s} {base:.3f} ± {fc['hand-written']['ci95']:.3f}")
        print(f"  {'hand-written pusher':28s} {push['mean']:.3f} ± {push['ci95']:.3f}")
        print(f"  {'random walk':28s} {fc['random']['mean']:.3f} ± {fc['random']['ci95']:.3f}")
        print(f"  seeds beating the searcher: {beat} of {len(learned)}; the pusher: {beat_push} of {len(learned)}")
        summary["robots"][str(M)] = {"per_seed": {n: fc[n] for n in policies}, "searcher": fc["hand-written"],
                                     "pusher": push, "random": fc["random"], "mean": float(np.mean(learned)),
                                     "std": float(np.std(learned, ddof=1)) if len(learned) > 1 else 0.0,
                                     "beat_searcher": beat, "beat_pusher": beat_push}
    write_atomic(out / "seeds.json", json.dumps(summary, indent=1, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
