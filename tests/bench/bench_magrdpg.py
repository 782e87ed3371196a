"""MAGRDPG (GRU actor) vs MAGDDPG (MLP actor), and the recurrent firmware. Prints tables; asserts nothing.

    python -m tests.bench.bench_magrdpg --train [--minutes 15] [--seed 1]      # both runs at once, then report
    python -m tests.bench.bench_magrdpg --gru RUN --mlp RUN [--episodes 100]   # report on existing runs
    python -m tests.bench.bench_magrdpg --gru RUN --mlp RUN --guided RUN       # ... plus a guided MAGRDPG run
    python -m tests.bench.bench_magrdpg --train-guided [--minutes 15] [--seed 1]   # train one guided run first

The comparison is at a matched parameter count and the same wall-clock budget: a GRU of 32 units
(4,866 parameters) against MAGDDPG's MLP with T_prev 10 and hidden (26, 26) (4,942 parameters),
the ``fast`` hyper-parameters for both, both trained at the same time on the same machine with one
torch thread each, on the thesis task with 2 robots. The report gives

1. the learning curves (evaluation return and final coverage over transitions and over wall clock;
   the trainers' periodic evaluations use the same fixed episodes for equal seeds);
2. the best policies of both runs, the hand-written baseline and random commands on *fresh*
   episodes (another seed), mean ± 95 % CI;
3. the recurrent export: quantisation error, budget (analytic and avr-gcc), host and simavr
   bit-exactness with cycles per control step;
4. the closed loop: the float GRU vs its int8 firmware (emulator) on the same episodes
   (:mod:`export.closed_loop`), and the same for the MLP for reference.

With ``--guided RUN`` (a ``--preset guided`` MAGRDPG run: behaviour cloning of the left-turning
searcher, then MAGRDPG with Q-filtered demonstrations) the fresh-episode table also holds that run's
best policy, its actor right after behaviour cloning (``policy_bc.npz``: what reinforcement learning
started from) and the demonstrator itself, and sections 3 and 4 export and close the loop on the
guided policy.
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

FRESH_SEED = 12345  #: evaluation episodes the trainers never saw


def read_rows(run: Path) -> list[dict]:
    with open(run / "metrics.csv", newline="") as f:
        return [{k: float(v) if v not in ("", None) else float("nan") for k, v in r.items()} for r in csv.DictReader(f)]


def train_both(minutes: float, seed: int, out: Path) -> tuple[Path, Path]:
    """Start the GRU and the matched MLP run together (one thread each); wait for both."""
    gru, mlp = out / f"gru32_2r_s{seed}", out / f"mlp26_2r_s{seed}"
    cmds = [[sys.executable, "-m", "learn", "train-recurrent", "--world", "thesis", "--robots", "2", "--hidden", "32",
             "--seed", str(seed), "--max-minutes", str(minutes), "--threads", "1", "--out", str(gru), "--quiet"],
            [sys.executable, "-m", "learn", "train", "--world", "thesis", "--robots", "2", "--preset", "fast", "--history", "10",
             "--actor-hidden", "26", "26", "--eval-episodes", "20", "--threads", "1", "--seed", str(seed),
             "--max-minutes", str(minutes), "--exp-name", "mlp-matched", "--out", str(mlp), "--quiet"]]
    procs = [subprocess.Popen(c, cwd=ROOT) for c in cmds]
    for p in procs:
        p.wait()
    return gru, mlp


def train_guided(minutes: float, seed: int, out: Path) -> Path:
    """One guided MAGRDPG run (``--preset guided``, GRU 32, 2 robots), one torch thread."""
    run = out / f"gru32_guided_2r_s{seed}"
    subprocess.run([sys.executable, "-m", "learn", "train-recurrent", "--world", "thesis", "--preset", "guided", "--robots", "2",
                    "--hidden", "32", "--seed", str(seed), "--max-minutes", str(minutes), "--threads", "1", "--out", str(run),
                    "--quiet"], cwd=ROOT, check=True)
    return run


def plot_curves(runs: dict[str, list[dict]], path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 3.4))
    FigureCanvasAgg(fig)
    panels = [("env_steps", "eval_return", "transitions", "evaluation return"),
              ("wall_s", "eval_return", "wall clock (s)", "evaluation return"),
              ("env_steps", "eval_final_coverage", "transitions", "final coverage")]
    for i, (x, y, xl, yl) in enumerate(panels):
        ax = fig.add_subplot(1, 3, i + 1)
        for k, (label, rows) in enumerate(runs.items()):
            ax.plot([r[x] for r in rows], [r[y] for r in rows], color=f"C{k}", lw=1.4, marker="o", ms=3, label=label)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.grid(alpha=0.3)
    fig.axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle("2 robots, thesis world: MAGRDPG (GRU 32) vs MAGDDPG (MLP 26x26, T_prev 10), matched parameters",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def report(gru_run: Path, mlp_run: Path, episodes: int, out: Path, robots_loop: list[int],
           guided_run: Path | None = None) -> dict:
    from export.codegen import budget as bud
    from export.codegen.render import render_firmware
    from export.quantize import calibrate, error_report, quantize_policy
    from export.verify import avr, closed_loop
    from export.verify.hostbuild import StreamSpec, verify_host
    from kiloforge.policies import load_policy, swarm_policy
    from sim.baselines import make_policy
    from sim.env import SwarmEnv
    from sim.metrics import compare
    from sim.tasks import get_task
    from sim.rollout import rollout

    out.mkdir(parents=True, exist_ok=True)
    res: dict = {}
    rows = {"MAGRDPG GRU-32": read_rows(gru_run), "MAGDDPG MLP 26x26": read_rows(mlp_run)}
    if guided_run is not None:
        rows["MAGRDPG GRU-32 guided"] = read_rows(guided_run)
    plot_curves(rows, out / "magrdpg_vs_magddpg.png")
    print(f"== 1. learning curves -> {out / 'magrdpg_vs_magddpg.png'}")
    print(f"{'run':<20} {'params':>7} {'evals':>5} {'transitions':>11} {'wall s':>7} {'updates':>8} "
          f"{'best return':>11} {'at step':>8} {'at s':>6} {'best cov':>8} {'first cov>=0.8 (step, s)':>25}")
    pols = {"MAGRDPG GRU-32": load_policy(gru_run / "policy_best.npz"),
            "MAGDDPG MLP 26x26": load_policy(mlp_run / "policy_best.npz")}
    if guided_run is not None:
        pols["MAGRDPG GRU-32 guided"] = load_policy(guided_run / "policy_best.npz")
    res["runs"] = {}
    for name, r in rows.items():
        best = max(r, key=lambda x: x["eval_return"])
        hit = next((x for x in r if x["eval_final_coverage"] >= 0.8), None)
        hit_s = f"{hit['env_steps']:.0f}, {hit['wall_s']:.0f}" if hit else "never"
        print(f"{name:<20} {pols[name].n_params:>7} {len(r):>5} {r[-1]['env_steps']:>11.0f} {r[-1]['wall_s']:>7.0f} "
              f"{r[-1]['updates']:>8.0f} {best['eval_return']:>11.1f} {best['env_steps']:>8.0f} {best['wall_s']:>6.0f} "
              f"{max(x['eval_final_coverage'] for x in r):>8.3f} {hit_s:>25}")
        res["runs"][name] = {"params": pols[name].n_params, "best": best, "last": r[-1],
                             "first_cov_0.8": hit}

    world = pols["MAGRDPG GRU-32"].world
    print(f"\n== 2. best policies on {episodes} fresh episodes (seed {FRESH_SEED}), 2 robots, {world.episode_steps} steps")
    env = SwarmEnv(world, min(episodes, 50), 2, seed=FRESH_SEED)
    contenders = {**{k: swarm_policy(p) for k, p in pols.items()},
                  "hand-written": make_policy("baseline", world), "random": make_policy("random", world)}
    if guided_run is not None:
        from learn.demos import demonstrator
        contenders["GRU-32 after behaviour cloning"] = swarm_policy(load_policy(guided_run / "policy_bc.npz"))
        contenders["demonstrator (searcher, left turns)"] = demonstrator(world)
    metrics = {k: rollout(env, pol, episodes, seed=FRESH_SEED).metrics() for k, pol in contenders.items()}
    print(compare(metrics, get_task("localisation").columns))
    res["fresh"] = {k: m.to_dict(per_episode=False) for k, m in metrics.items()}

    print("\n== 3. recurrent export")
    gp = pols["MAGRDPG GRU-32 guided" if guided_run is not None else "MAGRDPG GRU-32"]
    print("policy:", "guided run" if guided_run is not None else "MAGRDPG run", "(best)")
    t0 = time.perf_counter()
    cal = calibrate(gp, episodes=2, n_robots=(2, 4, 16), seed=0)
    qp = quantize_policy(gp, cal)
    rep = error_report(gp, qp, cal)
    print(f"calibration + quantisation {time.perf_counter() - t0:.1f} s")
    print(rep.table())
    files = render_firmware(qp)
    b = bud.for_quantized(qp)
    hc = verify_host(qp, files, spec=StreamSpec(n_robots=128, n_steps=200))
    print(hc)
    res["export"] = {"error": rep.to_dict(), "host": str(hc), "summary": qp.summary()}
    if avr.missing_tools(simulate=True) is None:
        sc = avr.verify_simavr(qp, files, n_robots=16, n_steps=40, seed=1)
        print(sc)
        exact = avr.exact_budget(files, qp)
        b = b.with_exact(exact)
        res["export"].update(simavr=str(sc), cycles_step_median=int(np.median(sc.cycles_step)),
                             cycles_step_max=sc.cycles_step_max, cycles_per_mac=sc.cycles_per_mac, exact=exact)
    print(b.table())
    res["export"]["budget"] = b.to_dict()

    print(f"\n== 4. closed loop, float vs int8 firmware, {episodes} episodes (seed {FRESH_SEED})")
    res["closed_loop"] = {}
    mp = pols["MAGDDPG MLP 26x26"]
    mqp = quantize_policy(mp, calibrate(mp, episodes=2, n_robots=(2, 4, 16), seed=0))
    for name, (fp, q) in {"GRU-32": (gp, qp), "MLP 26x26": (mp, mqp)}.items():
        for m in robots_loop:
            c = closed_loop.compare(fp, q, m, episodes, seed=FRESH_SEED)
            print(f"-- {name}\n{c.table()}")
            res["closed_loop"][f"{name} {m}"] = {k: v for k, v in c.to_dict().items()
                                                  if k not in ("per_episode", "success_curve")}
    (out / "bench_magrdpg.json").write_text(json.dumps(res, indent=1, default=float))
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", action="store_true", help="train both runs (one thread each, concurrently) first")
    ap.add_argument("--minutes", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--gru", type=Path, help="a MAGRDPG run directory")
    ap.add_argument("--mlp", type=Path, help="a MAGDDPG run directory")
    ap.add_argument("--guided", type=Path, help="a guided MAGRDPG run directory (--preset guided)")
    ap.add_argument("--train-guided", action="store_true", help="train a guided MAGRDPG run first")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--robots-loop", type=int, nargs="+", default=[2])
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "bench_magrdpg")
    a = ap.parse_args()
    if a.train:
        a.gru, a.mlp = train_both(a.minutes, a.seed, a.out)
    if a.train_guided:
        a.guided = train_guided(a.minutes, a.seed, a.out)
    if not (a.gru and a.mlp):
        ap.error("give --train, or --gru RUN and --mlp RUN")
    report(a.gru, a.mlp, a.episodes, a.out, a.robots_loop, a.guided)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
