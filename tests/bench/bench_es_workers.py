"""ES generations per second on 1 and on N Ray workers: paired, alternating runs of one config, the ratio.

    python -m tests.bench.bench_es_workers                      # issue 45: 32 robots, 8 pairs, 4 generations, 1 vs 2
    python -m tests.bench.bench_es_workers --workers 1 2 4 --rounds 3 --robots 16 32

Each round runs ``python -m learn train-es --robots M --demo-policy none --generations G --pairs P --seed S
--workers N`` once per worker count, the order rotating from round to round (so a change of load hits
every count alike). Each run's summary.json gives ``generations`` and ``generation_s``, the wall seconds
spent in generations (Ray's start-up, the evaluations and the checkpoints excluded); generations/s is
their quotient. The table shows per worker count the median generations/s, member-episodes/s, and the
median and range of the per-round ratios to one worker. Every run must end with the same weights as
the one-worker run of its round (the script checks the policy arrays and says so). Print ``uptime``
with the table: on a shared machine the ratios, not the rates, are what two runs can be compared by,
and only a run on an idle machine measures the scaling itself.

A second table (``--cpu-generations``, 0 = none) reads what load hides: the same population evaluated in
this process through :mod:`learn.es_pool` for each worker count, with the CPU seconds each process (this
one, or each Ray worker) spent per generation. The busiest process's CPU seconds bound a generation's
wall time on idle cores; their ratio to one worker's is the ratio an idle machine would show at most
(Ray's own processes and the dispatch not counted), and the total shows what splitting the batch costs.

A third table (``--rollout-repeats``, 0 = none) splits a block's cost: the CPU seconds of this process evaluating
a block of 1, pairs and 2·pairs members (one rollout batch each), the least of several rounds; their differences
give the cost per member and the fixed cost per block (per step of the episode, whatever the batch size), and
2·pairs over pairs members is what two workers can gain at most, before Ray's own costs.

A fourth (``--side-by-side``, 0 = none) reads what the machine itself gives: the wall seconds of a block of pairs
members in one process alone, and in each of two processes running at once (no Ray). On a machine whose two cores
slow each other (shared caches, a virtual machine's host), the second number is the larger, and two workers' ratio
is at most the third table's ratio (2·pairs over pairs members) times their quotient.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]


def run(args: argparse.Namespace, workers: int, out: Path) -> dict:
    """One train-es run; its summary.json."""
    cmd = [sys.executable, "-m", "learn", "train-es", "--robots", *map(str, args.robots), "--demo-policy", "none",
           "--generations", str(args.generations), "--pairs", str(args.pairs), "--seed", str(args.seed),
           "--eval-every", str(args.generations), "--eval-episodes", "1", "--eval-steps", "50",
           "--workers", str(workers), "--quiet", "--out", str(out)]
    res = subprocess.run(cmd, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stderr[-2000:]}")
    return json.loads((out / "summary.json").read_text())


def weights(run_dir: Path) -> list[np.ndarray]:
    from kiloforge.policies import load_policy

    p = load_policy(run_dir / "policy_last.npz")
    return [np.asarray(a) for a in (*p.weights, *p.biases)]


def _uptime() -> str:
    """The machine's load, as ``uptime`` prints it."""
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _population(args: argparse.Namespace):
    """(config, fitness, weights) of the benchmark's train-es config, evaluated in this process on one thread."""
    from learn.config import ESConfig
    from learn.es import PopulationMLP
    from learn.es_train import actor_algo, get_theta, task_fitness
    from learn.speed import set_threads

    set_threads(1)
    cfg = ESConfig(n_robots=tuple(args.robots), demo_policy="none", pairs=args.pairs, seed=args.seed)
    world = cfg.world_config()
    algo = actor_algo(cfg, world)
    return cfg, task_fitness(cfg, world, PopulationMLP.of(algo.actor.net), [None] * len(args.robots)), get_theta(algo)


def cpu_table(args: argparse.Namespace) -> dict[int, tuple[float, float, float]]:
    """Per worker count: (median wall s, median busiest-process CPU s, median total CPU s) per generation."""
    from learn.es_pool import worker_pool

    class NoStop:
        def check(self) -> None:
            pass

    cfg, fitness, theta = _population(args)
    out = {}
    for w in args.workers:
        with worker_pool(w, log=lambda _m: None) as pool:
            pool.warm(fitness, theta)
            pids = list(getattr(pool, "pids", [os.getpid()]))
            walls, busiest, total = [], [], []
            for g in range(args.cpu_generations):
                c0 = [_cpu_s(p) for p in pids]
                t0 = time.perf_counter()
                pool.evaluate(fitness, theta, cfg.sigma, cfg.pairs, np.random.SeedSequence([args.seed, g]), NoStop())
                walls.append(time.perf_counter() - t0)
                spent = [_cpu_s(p) - c for p, c in zip(pids, c0)]
                busiest.append(max(spent))
                total.append(sum(spent))
        out[w] = (statistics.median(walls), statistics.median(busiest), statistics.median(total))
    return out


def _block(args: argparse.Namespace, cfg, theta, r: int, k: int):
    """(members 0..k of generation ``r``'s population, the generation's seed)."""
    from learn.es_pool import members, noise

    seed = np.random.SeedSequence([args.seed, r])
    return members(theta, cfg.sigma, noise(seed, args.pairs, theta.numel()), 0, k), seed


def rollout_table(args: argparse.Namespace) -> dict[int, float]:
    """Per block size k (1, pairs, 2·pairs members): the least CPU seconds, over ``--rollout-repeats`` alternating
    rounds, of this process evaluating members 0..k of a generation on the first swarm size (what a worker does
    with a block of k members)."""
    cfg, fitness, theta = _population(args)
    sizes = (1, args.pairs, 2 * args.pairs)
    best = {k: float("inf") for k in sizes}
    for r in range(args.rollout_repeats + 1):  # round 0 warms up (compiles, allocates)
        for k in sizes:
            block, seed = _block(args, cfg, theta, r, k)
            c0 = time.process_time()
            fitness(block, 0, seed)
            if r:
                best[k] = min(best[k], time.process_time() - c0)
    return best


_WARM_BLOCK = None  # (fitness, block, seed) of a process of the side-by-side table, built and evaluated once


def _time_blocks(args: argparse.Namespace, n: int) -> list[float]:
    """Wall seconds of each of ``n`` evaluations of a block of ``pairs`` members (one worker's share at 2 workers)
    in this process, after one unmeasured evaluation on the process's first call (a process of the side-by-side
    table)."""
    global _WARM_BLOCK
    if _WARM_BLOCK is None:
        cfg, fitness, theta = _population(args)
        block, seed = _block(args, cfg, theta, 0, args.pairs)
        fitness(block, 0, seed)
        _WARM_BLOCK = fitness, block, seed
    fitness, block, seed = _WARM_BLOCK
    walls = []
    for _ in range(n):
        t0 = time.perf_counter()
        fitness(block, 0, seed)
        walls.append(time.perf_counter() - t0)
    return walls


def side_by_side_table(args: argparse.Namespace) -> tuple[float, float]:
    """Median wall seconds of a block of ``pairs`` members in one process alone, and in each of two processes running
    at once (no Ray), over ``--side-by-side`` rounds of 3 blocks, alone and together alternating: what two cores of
    this machine give for this work by themselves."""
    import concurrent.futures
    import multiprocessing

    alone, together = [], []
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(2, mp_context=ctx) as ex:
        list(ex.map(_time_blocks, [args, args], [0, 0]))  # both processes started, imported and warmed
        for _ in range(args.side_by_side):
            alone += ex.submit(_time_blocks, args, 3).result()
            for f in [ex.submit(_time_blocks, args, 3) for _ in range(2)]:
                together += f.result()
    return statistics.median(alone), statistics.median(together)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", nargs="+", type=int, default=[1, 2], help="worker counts; the first is the baseline")
    p.add_argument("--robots", nargs="+", type=int, default=[32])
    p.add_argument("--generations", type=int, default=4)
    p.add_argument("--pairs", type=int, default=8)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--rounds", type=int, default=2, help="paired train-es rounds (0: only the CPU table)")
    p.add_argument("--cpu-generations", type=int, default=6, help="generations of the CPU-seconds table (0: none)")
    p.add_argument("--rollout-repeats", type=int, default=0,
                   help="rounds of the rollout table: one block of 1, pairs and 2·pairs members in this process (0: none)")
    p.add_argument("--side-by-side", type=int, default=0,
                   help="rounds of the side-by-side table: a block of pairs members in one process alone, then in two "
                        "processes at once, no Ray (0: none)")
    args = p.parse_args(argv)
    base = args.workers[0]
    rates: dict[int, list[float]] = {w: [] for w in args.workers}
    episodes: dict[int, list[float]] = {w: [] for w in args.workers}
    ratios: dict[int, list[float]] = {w: [] for w in args.workers}
    same = True
    with tempfile.TemporaryDirectory(prefix="bench_es_workers.") as tmp:
        for r in range(args.rounds):
            k = r % len(args.workers)
            order = args.workers[k:] + args.workers[:k]
            got = {}
            for w in order:
                out = Path(tmp) / f"r{r}_w{w}"
                s = run(args, w, out)
                got[w] = s["generations"] / s["generation_s"]
                rates[w].append(got[w])
                episodes[w].append(s["episodes"] / s["generation_s"])
                print(f"round {r}, {w} worker(s): {s['generations']} generations in {s['generation_s']:.2f} s "
                      f"= {got[w]:.3f} generations/s", flush=True)
            ref = weights(Path(tmp) / f"r{r}_w{base}")
            for w in args.workers:
                ratios[w].append(got[w] / got[base])
                same &= all(np.array_equal(a, b) for a, b in zip(ref, weights(Path(tmp) / f"r{r}_w{w}"), strict=True))
    if args.rounds:
        load = _uptime()
        print(f"\ntrain-es --robots {' '.join(map(str, args.robots))} --demo-policy none --generations {args.generations} "
              f"--pairs {args.pairs} --seed {args.seed}; {args.rounds} rounds; {os.cpu_count()} CPUs; {load}")
        print(f"{'workers':>7} | {'generations/s':>13} | {'member-episodes/s':>17} | {'ratio (median)':>14} | ratio range")
        print("-" * 7 + "-+-" + "-" * 13 + "-+-" + "-" * 17 + "-+-" + "-" * 14 + "-+-" + "-" * 12)
        for w in args.workers:
            rr = ratios[w]
            print(f"{w:>7} | {statistics.median(rates[w]):>13.3f} | {statistics.median(episodes[w]):>17.1f} | "
                  f"{statistics.median(rr):>14.2f} | {min(rr):.2f}-{max(rr):.2f}")
        print(f"policy_last.npz weights equal across worker counts in every round: {'yes' if same else 'NO'}")
    if args.cpu_generations:
        cpu = cpu_table(args)
        b = cpu[base][1]
        print(f"\nCPU seconds per generation (median of {args.cpu_generations}; "
              f"{_uptime()})")
        print(f"{'workers':>7} | {'wall s':>7} | {'busiest process CPU s':>21} | {'all workers CPU s':>17} | "
              "idle-core bound on the ratio")
        print("-" * 7 + "-+-" + "-" * 7 + "-+-" + "-" * 21 + "-+-" + "-" * 17 + "-+-" + "-" * 28)
        for w in args.workers:
            wall, busy, tot = cpu[w]
            print(f"{w:>7} | {wall:>7.3f} | {busy:>21.3f} | {tot:>17.3f} | {b / busy:.2f}")
    if args.rollout_repeats:
        t = rollout_table(args)
        P = args.pairs
        v = (t[2 * P] - t[P]) / P
        print(f"\nOne block's CPU seconds in this process (least of {args.rollout_repeats} rounds; "
              f"{_uptime()})")
        print(f"{'members':>7} | {'CPU s':>6}")
        print("-" * 7 + "-+-" + "-" * 6)
        for k, c in t.items():
            print(f"{k:>7} | {c:>6.3f}")
        print(f"per member {v:.4f} s, fixed per block {t[P] - P * v:.3f} s; "
              f"{2 * P} members / {P} members = {t[2 * P] / t[P]:.2f} (2 workers' bound before Ray's own costs)")
    if args.side_by_side:
        alone, together = side_by_side_table(args)
        print(f"\nA block of {args.pairs} members, wall s (median of {3 * args.side_by_side} per column; no Ray; "
              f"{_uptime()})")
        print(f"one process alone {alone:.3f}, each of two processes at once {together:.3f}: two cores run this work "
              f"at {alone / together:.2f} of one core's speed each (two workers' ratio is at most the time of "
              f"{2 * args.pairs} members over {args.pairs} × this, before Ray's own costs)")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
