"""Simulator throughput benchmark: agent-steps per second and peak memory of SwarmEnv.step.

    python -m tests.bench.bench_sim            # full table (a few minutes)
    python -m tests.bench.bench_sim --quick    # small sizes only
    python -m tests.bench.bench_sim --goals    # only the three rows the performance goals name
    python -m tests.bench.bench_sim --goals --repeat 10   # ... timed in 10 rounds: best and median
    python -m tests.bench.bench_sim --kilobot --repeat 3  # kilobot world, 500 mm arena (see below)
    python -m tests.bench.bench_sim --kilobot --against 81d913c --repeat 3   # A/B against a revision
    python -m tests.bench.bench_sim --kilobot --jit-ab --repeat 3   # compiled contact loop on / off

Worlds:
  thesis/fixed     thesis preset, arena ±100 mm whatever M (density grows with M)
  thesis/density   thesis preset, arena scaled to the density of M = 32 in ±100 mm:
                   arena_half_mm = 100 * sqrt(M / 32) (≈ 3.3 neighbours per robot)
  kilobot/density  kilobot preset (tick-level motion, collisions, lossy radio), arena scaled to
                   the density of M = 32 in ±250 mm: arena_half_mm = 250 * sqrt(M / 32)

Kilobot rows (``--kilobot``): the kilobot preset in its own 500 mm arena at M = 4, 16, 32 and
B = 16, 50, driven by random actions and by the hand-written searcher after ``--warm`` steps (then
most robots crowd the beacon: the expensive case). Only ``SwarmEnv.step`` is timed (env time, not
the policy's), in blocks of 5 steps; a run reports its best block. Each row runs in a fresh
subprocess; ``--against REV`` also runs it on the ``sim/``
of git revision REV (``git archive``), alternating the two trees every round, and prints both and
the speed-up (best and median over rounds). ``--old-physics`` runs every tree with a taped-down
beacon and a centre pivot where it has ``emitter_mobility`` (``beacon_mobility`` in older trees) / ``pivot_offset_mm`` (the physics of
81d913c and older trees), so only the code differs. ``--jit-ab`` also runs this tree with
``KILOFORGE_JIT=0`` (the NumPy contact loop instead of :mod:`sim.compiled`'s compiled one).

Timing: random actions, after one warm-up step; each row reports the best of several timed
blocks (wall clock) to reduce the noise of a shared machine, and the process CPU time of the same
blocks. Peak memory: tracemalloc peak (NumPy allocations) during one extra step, measured
separately from the timing. Rows whose estimated memory exceeds --max-gb are skipped.
Not a test: nothing is asserted; print a table to paste into docs.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
import tracemalloc

import numpy as np

from sim.config import preset
from sim.env import SwarmEnv
from sim.grid import choose_method


def world(kind: str, M: int):
    if kind == "thesis/fixed":
        return preset("thesis")
    if kind == "thesis/density":
        return preset("thesis", arena_half_mm=100.0 * math.sqrt(M / 32))
    if kind == "kilobot/density":
        return preset("kilobot", arena_half_mm=250.0 * math.sqrt(M / 32))
    raise ValueError(kind)


def est_bytes(cfg, B: int, M: int) -> float:
    """Rough peak estimate: ~150 bytes per in-range ordered pair plus per-robot state."""
    area = (2 * cfg.arena_half_mm) ** 2
    nbrs = min(M - 1, (M - 1) * math.pi * cfg.comm_radius_mm ** 2 / area)
    ticks = cfg.period_ticks if cfg.tick_level else 1
    return B * M * (nbrs * 150 * (2 if cfg.tick_level else 1) + 64 * ticks + 400)


def bench(cfg, B: int, M: int, min_time: float, max_steps: int) -> dict:
    env = SwarmEnv(cfg, B, M, seed=0)
    env.reset()
    rng = np.random.default_rng(0)
    acts = [rng.random((B, M, 2)) for _ in range(4)]
    env.step(acts[0])  # warm-up
    best_wall = best_cpu = math.inf
    steps_done, t_total = 0, 0.0
    block = 1
    while steps_done < max_steps and (t_total < min_time or steps_done < 3):
        if env.t + block > cfg.episode_steps:
            env.reset()
        w0, c0 = time.perf_counter(), time.process_time()
        for s in range(block):
            *_, info = env.step(acts[s % 4])
        w, c = time.perf_counter() - w0, time.process_time() - c0
        best_wall, best_cpu = min(best_wall, w / block), min(best_cpu, c / block)
        steps_done += block
        t_total += w
        block = max(1, min(8, int(0.2 / max(w / block, 1e-6))))
    nbrs = len(info["events"]) / (B * M)  # messages received per robot in the last period
    if env.t >= cfg.episode_steps:
        env.reset()
    tracemalloc.start()
    env.step(acts[1])
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {"wall": best_wall, "cpu": best_cpu, "peak": peak, "msgs": nbrs, "steps": steps_done}


#: one kilobot row, run in a subprocess whose PYTHONPATH is the tree under test (public APIs only)
_KILOBOT_ROW = r"""
import json, sys, time
import dataclasses
import numpy as np
from sim.config import WorldConfig, preset
from sim.env import SwarmEnv
from sim.baselines import make_policy
M, B, policy, warm, steps = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
fields = {f.name for f in dataclasses.fields(WorldConfig)}
over = {k: 0.0 for k in ("emitter_mobility", "beacon_mobility", "pivot_offset_mm") if k in fields} if sys.argv[6] == "old" else {}
cfg = preset("kilobot", episode_steps=warm + steps + 5, **over)
env = SwarmEnv(cfg, B, M, seed=0)
pol = make_policy(policy, cfg)
obs, _ = env.reset()
pol.reset(B, M, np.random.default_rng(0))
for _ in range(warm):
    obs, *_ = env.step(pol.act(obs))
blocks = []  # (wall, cpu) per block of 5 steps: the best block is the least disturbed by other jobs
for _ in range(max(1, steps // 5)):
    wall = cpu = 0.0
    for _ in range(5):
        a = pol.act(obs)
        w0, c0 = time.perf_counter(), time.process_time()
        obs, *_ = env.step(a)
        wall += time.perf_counter() - w0
        cpu += time.process_time() - c0
    blocks.append((wall / 5, cpu / 5))
import sim
print(json.dumps({"wall": min(b[0] for b in blocks), "cpu": min(b[1] for b in blocks), "sim": sim.__file__}))
"""


def _kilobot_row(tree: str, M: int, B: int, policy: str, warm: int, steps: int, beacon: str,
                 extra_env: dict | None = None) -> dict:
    env = dict(os.environ, PYTHONPATH=tree, **(extra_env or {}))
    out = subprocess.run([sys.executable, "-P", "-c", _KILOBOT_ROW, str(M), str(B), policy, str(warm), str(steps),
                          beacon], env=env, cwd=tree, capture_output=True, text=True, check=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert os.path.realpath(res["sim"]).startswith(os.path.realpath(tree)), f"imported {res['sim']}, not {tree}"
    return res


def _archive(rev: str, dest: str) -> None:
    """Extract sim/ of git revision ``rev`` into ``dest``."""
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
    tar = subprocess.run(["git", "-C", root, "archive", rev, "sim"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", dest], input=tar, check=True)


def kilobot_main(args) -> None:
    here = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
    trees = {"this tree": (here, {})}
    if args.jit_ab:  # the same tree with the compiled contact loop off (sim/compiled.py)
        trees["this tree, NumPy loop"] = (here, {"KILOFORGE_JIT": "0"})
    tmp = None
    if args.against:
        tmp = tempfile.mkdtemp(prefix="kf-bench-")
        _archive(args.against, tmp)
        trees[args.against] = (tmp, {})
    rows = [(M, B, pol) for pol in ("random", "baseline") for M in (4, 16, 32) for B in (16, 50)]
    if args.quick:
        rows = [(M, 16, pol) for pol in ("random", "baseline") for M in (4, 32)]
    print(f"# kilobot world, 500 mm arena, {'taped beacon and centre pivot in every tree' if args.old_physics else 'each tree its own preset'}; "
          f"ms per SwarmEnv.step (wall), best / median of {args.repeat} rounds; searcher rows after {args.warm} warm-up steps")
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, numpy {np.__version__}\n")
    head = "| policy | M | B | " + " | ".join(f"{t} ms/step best (median)" for t in trees)
    print(head + (" | speed-up best (median) |" if len(trees) == 2 else " |"))
    print("|---|---:|---:|" + "---:|" * (len(trees) + (len(trees) == 2)))
    try:
        for M, B, pol in rows:
            res: dict[str, list[dict]] = {t: [] for t in trees}
            for _ in range(args.repeat):  # alternate the trees every round
                for t, (path, extra_env) in trees.items():
                    res[t].append(_kilobot_row(path, M, B, pol, args.warm if pol == "baseline" else 5, args.steps,
                                               "old" if args.old_physics else "preset", extra_env))
            best = {t: min(r["wall"] for r in v) for t, v in res.items()}
            med = {t: float(np.median([r["wall"] for r in v])) for t, v in res.items()}
            cells = " | ".join(f"{best[t] * 1e3:.2f} ({med[t] * 1e3:.2f})" for t in trees)
            line = f"| {'searcher' if pol == 'baseline' else pol} | {M} | {B} | {cells} |"
            if len(trees) == 2:
                a, b = list(trees)
                line += f" {best[b] / best[a]:.2f}× ({med[b] / med[a]:.2f}×) |"
            print(line, flush=True)
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--goals", action="store_true", help="only thesis M=4 B=1024, M=32 B=64, density M=1024 B=64")
    ap.add_argument("--max-gb", type=float, default=4.0, help="skip rows estimated above this")
    ap.add_argument("--min-time", type=float, default=1.0, help="seconds of timed steps per row")
    ap.add_argument("--repeat", type=int, default=1,
                    help="time every row this many times, in rounds over all rows (a noisy host's quiet "
                         "moments show in the best, its typical load in the median)")
    ap.add_argument("--kilobot", action="store_true", help="kilobot-world rows (500 mm arena, random and searcher)")
    ap.add_argument("--against", default=None, help="with --kilobot: also time git revision REV's sim/, alternating")
    ap.add_argument("--jit-ab", action="store_true",
                    help="with --kilobot: also time this tree with KILOFORGE_JIT=0 (the NumPy contact loop), alternating")
    ap.add_argument("--old-physics", action="store_true",
                    help="with --kilobot: taped beacon and centre pivot where the tree has the fields (81d913c's physics)")
    ap.add_argument("--warm", type=int, default=300, help="with --kilobot: searcher warm-up steps (crowding)")
    ap.add_argument("--steps", type=int, default=30, help="with --kilobot: timed steps per row and round")
    args = ap.parse_args()
    if args.kilobot:
        kilobot_main(args)
        return
    Ms = [4, 32, 256] if args.quick else [4, 32, 256, 1024]
    Bs = [1, 64] if args.quick else [1, 64, 1024]
    rows = [("thesis/fixed", M, B) for M in Ms for B in Bs]
    rows += [("thesis/density", M, B) for M in Ms for B in Bs if M != 32]  # M=32 equals fixed
    kb = [(4, 1), (4, 64), (32, 1), (32, 64)] + ([] if args.quick else [(256, 8), (1024, 1)])
    rows += [("kilobot/density", M, B) for M, B in kb]
    if args.goals:
        rows = [("thesis/fixed", 4, 1024), ("thesis/fixed", 32, 64), ("thesis/density", 1024, 64)]
    print(f"# kiloforge simulator benchmark — {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, numpy {np.__version__}, python {platform.python_version()}")
    print("# shared machine: other jobs were running; numbers are best-of-blocks, expect ±30 %\n")
    if args.repeat > 1:
        print(f"# each row timed {args.repeat} times in rounds; agent-steps/s: best and median of the rounds\n")
    print("| world | M | B | search | agent-steps/s (wall) | ms/step | agent-steps/s (cpu) | msgs/robot/period | peak MiB |"
          + (" median agent-steps/s |" if args.repeat > 1 else ""))
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|" + ("---:|" if args.repeat > 1 else ""))
    results: dict[tuple, list[dict]] = {}
    for rnd in range(max(1, args.repeat)):
        for kind, M, B in rows:
            cfg = world(kind, M)
            if est_bytes(cfg, B, M) <= args.max_gb * 2 ** 30:
                results.setdefault((kind, M, B), []).append(bench(cfg, B, M, args.min_time, max_steps=200))
            if rnd == max(1, args.repeat) - 1:
                _print_row(kind, M, B, cfg, results.get((kind, M, B)), args)


def _print_row(kind: str, M: int, B: int, cfg, runs: list[dict] | None, args) -> None:
    method = choose_method(B, M, cfg.comm_radius_mm, cfg.arena_half_mm)
    if not runs:
        print(f"| {kind} | {M} | {B} | {method} | skipped (> {args.max_gb:g} GB est.) | | | | |")
        return
    n = B * M
    r = min(runs, key=lambda x: x["wall"])
    med = f" {n / float(np.median([x['wall'] for x in runs])):,.0f} |" if args.repeat > 1 else ""
    print(f"| {kind} | {M} | {B} | {method} | {n / r['wall']:,.0f} | {r['wall'] * 1e3:.2f} | "
          f"{n / min(x['cpu'] for x in runs):,.0f} | {r['msgs']:.1f} | {max(x['peak'] for x in runs) / 2 ** 20:.1f} |"
          + med, flush=True)


if __name__ == "__main__":
    main()
