"""What makes evolution strategies learn a new task from random weights (issue 42 item 5, issue 43 item 5)?

    python -m experiments.task_es train --task aggregation --recipe bias --seeds 1 2 3 --out runs/aggexp
    python -m experiments.task_es train --task phototaxis --recipe sizes --seeds 1 2 3 --out runs/photoexp
    python -m experiments.task_es train --task transport --recipe bias --seeds 1 2 3 --out runs/transport
    python -m experiments.task_es evaluate --task phototaxis runs/photoexp/sizes_s1 … [--robots 16 32 64] [--episodes 20]
    python -m experiments.task_es behaviour --task aggregation runs/aggexp/default_s1 …

``train`` runs ``python -m learn train-es --task TASK --demo-policy none`` (random initial weights, no
demonstrations) with one of the task's :data:`RECIPES` for every training seed, into ``OUT/RECIPE_sSEED`` (a recipe of
several stages runs them in ``OUT/RECIPE_sSEED/stageN``, each starting from the previous stage's ``policy_best.npz``).
Every stage runs a fixed number of generations (``generations``; ``max_minutes`` is only a safety stop), so a run is
the same on any machine.
A recipe with ``init_bias`` starts from random weights whose output layer's bias is that value (the actor's outputs
are clipped to [0, 1], so the default initialisation, outputs near 0, starts every robot standing still at the clip):
``train-es --init-bias``. Aggregation's documented ``bias`` runs predate that flag: their ``init_artifact_bias``
draws the random weights from ``torch.manual_seed(seed)``, writes them as a policy artifact ``init.npz`` and passes it
as ``init_policy`` (the same start but other random weights than ``--init-bias``); nothing is learned from a behaviour.

``evaluate`` plays every run's result (the last stage's ``policy_best.npz``, selected on the run's own evaluation
episodes) and the task's hand-written and random baselines on held-out episodes (``sim.config.HELD_OUT_SEED``,
never used for training or selection), 500 steps, and prints the task's primary metric per run and size.
Results: docs/results/aggregation.md, docs/results/phototaxis.md, docs/results/transport.md.
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from kiloforge.policies import load_policy, save_policy
from learn.config import ESConfig
from learn.es_train import actor_algo, set_output_bias, train_es
from learn.evaluate import evaluate_policies
from sim.config import HELD_OUT_SEED, VALIDATION_SEED
from sim.tasks import get_task

COMMON = dict(demo_policy="none", eval_every=5, eval_episodes=8, generations=200, max_minutes=12)

#: task -> recipe name -> stages; a stage is ESConfig overrides plus ``init_artifact_bias`` (first stage only, above)
RECIPES: dict[str, dict[str, list[dict]]] = {
    "aggregation": {
        "default": [dict(n_robots=(16,))],  # train-es's own ES settings: 16 pairs, sigma 0.02, lr 0.01, 300 steps
        "robots8": [dict(n_robots=(8,))],  # the swarm size of the monkeypatched trial that stalled
        "curriculum": [dict(n_robots=(8,), generations=100), dict(n_robots=(16,), generations=100)],
        "pairs8": [dict(n_robots=(16,), pairs=8)],
        "sigma": [dict(n_robots=(16,), sigma=0.1, lr=0.03)],
        "bias": [dict(n_robots=(16,), init_artifact_bias=0.5)],
    },
    "phototaxis": {
        "default": [dict(n_robots=(16,))],
        # random start driving (output bias 0.5), 16 robots until it gathers; then every evaluated size (64 in the
        # anchor's larger arena, Task.world_for) from the first stage's best, with half the population
        "sizes": [dict(n_robots=(16,), init_bias=0.5, max_minutes=30),
                  dict(n_robots=(16, 32, 64), generations=100, pairs=8, max_minutes=50)],
        # ``sizes`` with twice the first stage's population: near its plateau a 16-pair gradient from one episode
        # per generation is mostly noise (sizes_s1's fitness swung +-0.06 while its evaluation stayed at 0.86)
        "pairs32": [dict(n_robots=(16,), init_bias=0.5, pairs=32, max_minutes=60),
                    dict(n_robots=(16, 32, 64), generations=100, pairs=8, max_minutes=50)],
    },
    "transport": {
        # random start driving (output bias 0.5), 16 robots: three are needed to move the object
        "bias": [dict(n_robots=(16,), init_bias=0.5, generations=400, max_minutes=50)],
    },
}


def stage_config(task: str, stage: dict, seed: int, init_policy: str) -> ESConfig:
    fields = {k: v for k, v in stage.items() if k != "init_artifact_bias"}
    return ESConfig(**(COMMON | fields), task=task, seed=seed, init_policy=init_policy)


def write_init(cfg: ESConfig, bias: float, path: Path) -> str:
    """Random initial weights (the actor's own initialisation, seeded by the run's seed) with the output bias
    ``bias``, saved as a policy artifact for ``init_policy``."""
    world = cfg.world_config()
    torch.manual_seed(cfg.seed)
    algo = actor_algo(cfg, world)
    set_output_bias(algo, bias)
    path.parent.mkdir(parents=True, exist_ok=True)
    art = algo.artifact(world, {"trainer": "experiments.task_es random init", "seed": cfg.seed,
                                "output_bias": bias})
    save_policy(dataclasses.replace(art, task=cfg.task_spec().ref), path)
    return str(path)


def train(task: str, recipe: str, seeds: list[int], out: Path) -> None:
    for seed in seeds:
        run = out / f"{recipe}_s{seed}"
        stages = RECIPES[task][recipe]
        init, t0 = "", time.perf_counter()
        for k, stage in enumerate(stages):
            d = run if len(stages) == 1 else run / f"stage{k}"
            if k == 0 and "init_artifact_bias" in stage:
                init = write_init(stage_config(task, stage, seed, ""), stage["init_artifact_bias"], run / "init.npz")
            train_es(stage_config(task, stage, seed, init), d, progress=False)
            init = str(d / "policy_best.npz")
        print(f"{run}: {time.perf_counter() - t0:.0f} s")


def result_of(run: Path) -> Path:
    stages = sorted(run.glob("stage*"))
    return (stages[-1] if stages else run) / "policy_best.npz"


def evaluate(task: str, runs: list[Path], robots: list[int], episodes: int, seed: int) -> None:
    """One table per metric of the task (its primary first): every run and baseline at every size."""
    spec = get_task(task)
    results, names = [], []
    for i, run in enumerate(runs):
        names.append(str(run))
        results.append(evaluate_policies({str(run): load_policy(result_of(run))}, robots, episodes, 500, None,
                                         seed=seed, baselines=i == 0, gif=False, progress=False, log=lambda s: None,
                                         task=task))
    which = "held-out" if seed == HELD_OUT_SEED else "validation" if seed == VALIDATION_SEED else "other"
    for key in spec.eval_keys:
        def cell(res: dict, M: int, name: str) -> tuple[float, float]:
            s = res["robots"][str(M)]["metrics"][name]["summary"][key]
            return s["mean"], s["ci95"]

        rows = {n: {M: cell(r, M, n) for M in robots} for n, r in zip(names, results)}
        rows |= {b: {M: cell(results[0], M, b) for M in robots} for b in spec.baselines}
        print(f"\n{key} on {episodes} {which} episodes (seed {seed}), 500 steps, mean ± 95 % CI over episodes")
        print("| policy | " + " | ".join(f"{M} robots" for M in robots) + " |")
        print("|---|" + "---:|" * len(robots))
        for name, r in rows.items():
            print(f"| {name} | " + " | ".join(f"{r[M][0]:.3f} ± {r[M][1]:.3f}" for M in robots) + " |")
        if len(names) > 1:
            print("| learned: mean ± std over runs | " + " | ".join(
                f"{np.mean([rows[n][M][0] for n in names]):.3f} ± {np.std([rows[n][M][0] for n in names], ddof=1):.3f}"
                for M in robots) + " |")


def behaviour(task: str, runs: list[Path], robots: int, episodes: int, seed: int) -> None:
    """Mean motor commands of each run's result for robots that hear nobody (empty RBF histogram) and the others."""
    from kiloforge.policies import swarm_policy
    from sim.env import SwarmEnv

    for run in runs:
        p = load_policy(result_of(run))
        world = dataclasses.replace(p.world, episode_steps=500)
        env = SwarmEnv(world, episodes, robots, seed=seed, task=task)
        pol = swarm_policy(p, world)
        obs, _ = env.reset()
        pol.reset(episodes, robots, np.random.default_rng(seed))
        rbf = world.obs_slice("rbf")
        alone, cmds = [], []
        for _ in range(world.episode_steps):
            a = pol.act(obs)
            alone.append(obs[..., rbf].sum(-1) == 0)
            cmds.append(a)
            obs, *_ = env.step(a)
        lone, a = np.stack(alone), np.stack(cmds)
        print(f"{run}: hears nobody {lone.mean():.0%} of robot-steps, mean commands {a[lone].mean(0).round(2).tolist()}; "
              f"hears a neighbour: {a[~lone].mean(0).round(2).tolist()}")


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m experiments.task_es", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train-es from random weights with a recipe, one run per seed")
    t.add_argument("--recipe", required=True, help="a recipe of the task: " + "; ".join(
        f"{task}: {', '.join(r)}" for task, r in RECIPES.items()))
    t.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    t.add_argument("--out", type=Path, required=True)
    e = sub.add_parser("evaluate", help="held-out primary metric of runs against the task's baselines")
    e.add_argument("runs", type=Path, nargs="+")
    e.add_argument("--robots", type=int, nargs="+", default=[16, 32])
    e.add_argument("--episodes", type=int, default=20)
    e.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    b = sub.add_parser("behaviour", help="mean motor commands of runs' results, alone and among neighbours")
    b.add_argument("runs", type=Path, nargs="+")
    b.add_argument("--robots", type=int, default=16)
    b.add_argument("--episodes", type=int, default=10)
    b.add_argument("--seed", type=int, default=HELD_OUT_SEED)
    for p in (t, e, b):
        p.add_argument("--task", required=True, choices=sorted(RECIPES))
    a = ap.parse_args()
    if a.cmd == "train" and a.recipe not in RECIPES[a.task]:
        ap.error(f"task {a.task} has no recipe {a.recipe!r}; its recipes: {', '.join(RECIPES[a.task])}")
    if a.cmd == "train":
        train(a.task, a.recipe, a.seeds, a.out)
    elif a.cmd == "behaviour":
        behaviour(a.task, a.runs, a.robots, a.episodes, a.seed)
    else:
        missing = [str(r) for r in a.runs if not result_of(r).exists()]
        if missing:
            ap.error(f"no policy_best.npz in {', '.join(missing)}")
        evaluate(a.task, a.runs, a.robots, a.episodes, a.seed)


if __name__ == "__main__":
    main()
