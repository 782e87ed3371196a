"""Trainer benchmarks: throughput, and the learning goals. Prints tables; asserts nothing about time.

    python -m tests.bench.bench_learn                       # throughput table (about a minute)
    python -m tests.bench.bench_learn --goals               # train the goal runs, then report (~1 h)
    python -m tests.bench.bench_learn --report RUN [RUN ...]  # report on existing runs only

Goals (2-core CPU): the 2-robot thesis task reaches final coverage >= 0.8 within 15 minutes of wall
clock; the 4-robot task within 45 minutes; a policy trained with 4 robots beats the hand-written
baseline on 16 and 32 robots. "Reaches" is read from the run's periodic evaluations (fixed
episodes) and then checked on fresh episodes (other seeds) so that picking the best of many
evaluations does not flatter the number.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

GOAL_COVERAGE = 0.8
GOALS = {2: 15.0, 4: 45.0}  # robots -> wall-clock minutes


def throughput(seconds: float = 4.0) -> None:
    """Env steps/s (acting + stepping, B envs) and updates/s (minibatch N) for a few settings."""
    import torch

    from learn.config import TrainConfig
    from learn.magddpg import MAGDDPG
    from learn.noise import OUNoise
    from learn.replay import EpisodeReplay
    from sim.env import SwarmEnv
    from sim.history import History

    print(f"torch {torch.__version__}, {torch.get_num_threads()} default threads\n")
    print("collection (actor + noise + SwarmEnv.step + history + replay), thesis world, T_prev 10, actor (32, 32)")
    print(f"{'robots':>6} {'n_envs':>6} {'env steps/s':>12}")
    for M in (2, 4):
        for B in (1, 16, 64):
            cfg = TrainConfig(world="thesis", n_robots=M, n_envs=B)
            world = cfg.world_config()
            torch.set_num_threads(1)
            agent = MAGDDPG(world.history_dim(cfg.t_prev), world.state_dim(M), M, cfg.actor_hidden,
                            cfg.critic_hidden, cfg.gamma, cfg.tau, cfg.lr_actor, cfg.lr_critic)
            env = SwarmEnv(world, B, M, seed=0)
            hist = History(cfg.t_prev, world.obs_dim)
            rp = EpisodeReplay(max(B * 200, 20_000), 200, M, world.tuple_dim, world.state_dim(M), cfg.t_prev)
            noise = OUNoise((B, M, 2), 0.15, 0.2, 0.0, np.random.default_rng(0))
            n, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                obs, _ = env.reset(seed=n)
                h = hist.reset(obs)
                rp.begin(hist.buf[:, :, 0], env.state())
                for _ in range(200):
                    a = np.clip(agent.act(h) + noise.sample(), 0, 1).astype(np.float32)
                    obs, r, _, _, _ = env.step(a)
                    h = hist.push(a, obs)
                    rp.add(np.concatenate([a, obs], -1), env.state(), r)
                    n += B
            print(f"{M:>6} {B:>6} {n / (time.perf_counter() - t0):>12.0f}")

    print("\nupdates (sample minibatch + critic step + actor step + soft updates), critic (256, 128, 64)")
    print(f"{'robots':>6} {'batch':>6} {'threads':>7} {'updates/s':>10} {'transitions/s of minibatch':>27}")
    for M in (2, 4):
        for N in (32, 256):
            for threads in (1, 2):
                torch.set_num_threads(threads)
                cfg = TrainConfig(world="thesis", n_robots=M)
                world = cfg.world_config()
                agent = MAGDDPG(world.history_dim(cfg.t_prev), world.state_dim(M), M, cfg.actor_hidden,
                                cfg.critic_hidden, cfg.gamma, cfg.tau, cfg.lr_actor, cfg.lr_critic)
                rp = EpisodeReplay(20_000, 200, M, world.tuple_dim, world.state_dim(M), cfg.t_prev)
                rng = np.random.default_rng(0)
                rp.begin(rng.random((16, M, world.tuple_dim), np.float32), rng.random((16, world.state_dim(M)), np.float32))
                for _ in range(200):
                    rp.add(rng.random((16, M, world.tuple_dim), np.float32),
                           rng.random((16, world.state_dim(M)), np.float32), rng.random(16, np.float32))
                for _ in range(5):
                    agent.update(rp.sample(N, rng))
                n, t0 = 0, time.perf_counter()
                while time.perf_counter() - t0 < seconds / 2:
                    agent.update(rp.sample(N, rng))
                    n += 1
                ups = n / (time.perf_counter() - t0)
                print(f"{M:>6} {N:>6} {threads:>7} {ups:>10.0f} {ups * N:>27.0f}")


def train_goals(seeds: list[int], out: Path) -> list[Path]:
    from learn.config import from_preset
    from learn.train import train

    runs = []
    for M, minutes in GOALS.items():
        for seed in seeds:
            cfg = from_preset("fast", world="thesis", n_robots=M, seed=seed, max_minutes=minutes, threads=1)
            run = out / f"goal{M}__fast__{seed}__{int(time.time())}"
            train(cfg, run, progress=True)
            runs.append(run)
    return runs


def report(runs: list[Path], episodes: int = 200, big_episodes: int = 100) -> None:
    """Per run: when the periodic evaluation first reached the goal; fresh-episode checks of the policies."""
    from kiloforge.policies import load_policy
    from learn.train import read_metrics
    from sim.baselines import make_policy
    from sim.env import SwarmEnv
    from sim.rollout import HistoryActor, rollout

    print(f"\ngoal: final coverage >= {GOAL_COVERAGE} (mean over the last 25 % of each episode)")
    print(f"{'run':<40} {'robots':>6} {'seed':>4} {'first >= goal (eval)':>22} {'max eval':>10} "
          f"{'fresh: best':>11} {'fresh: last':>11} {'hand-written':>12} {'random':>7} {'wall min':>8}")
    for run in runs:
        cfg = json.loads((run / "config.json").read_text())
        rows = read_metrics(run)
        hit = next((r for r in rows if r["eval_final_coverage"] >= GOAL_COVERAGE), None)
        when = f"{hit['wall_s'] / 60:.1f} min, {hit['env_steps'] / 1e3:.0f}k" if hit else "not reached"
        best = max(r["eval_final_coverage"] for r in rows)
        M = cfg["n_robots"]
        env = SwarmEnv(load_policy(run / "policy_best.npz").world, n_envs=50, n_robots=M, seed=0)
        fresh = {}
        for name in ("policy_best", "policy_last"):
            p = load_policy(run / f"{name}.npz")
            fresh[name] = rollout(env, HistoryActor(p.act, p.t_prev, p.world), episodes, seed=12345).metrics()
        for name in ("baseline", "random"):
            fresh[name] = rollout(env, make_policy(name, env.cfg), episodes, seed=12345).metrics()
        fc = {k: m.final_coverage.mean() for k, m in fresh.items()}
        wall = json.loads((run / "summary.json").read_text())["wall_s"] / 60
        print(f"{run.name[:40]:<40} {M:>6} {cfg['seed']:>4} {when:>22} {best:>10.3f} {fc['policy_best']:>11.3f} "
              f"{fc['policy_last']:>11.3f} {fc['baseline']:>12.3f} {fc['random']:>7.3f} {wall:>8.1f}")

    four = [r for r in runs if json.loads((r / "config.json").read_text())["n_robots"] == 4]
    if four:
        print(f"\npolicies trained with 4 robots vs the baselines on big swarms (500 steps, {big_episodes} episodes)")
        print(f"{'policy':<40} {'robots':>6} {'return':>16} {'final cov':>10} {'hand-written':>16} {'hw cov':>7} "
              f"{'random':>8}")
        for run in four:
            p = load_policy(run / "policy_best.npz")
            world = p.world.__class__.from_dict({**p.world.to_dict(), "episode_steps": 500})
            for M in (16, 32):
                env = SwarmEnv(world, n_envs=25, n_robots=M, seed=0)
                m = rollout(env, HistoryActor(p.act, p.t_prev, world), big_episodes, seed=777).metrics()
                b = rollout(env, make_policy("baseline", world), big_episodes, seed=777).metrics()
                r = rollout(env, make_policy("random", world), big_episodes, seed=777).metrics()
                sm, sb = m.summary(), b.summary()
                print(f"{run.name[:40]:<40} {M:>6} {str(sm['return']):>16} {sm['final_coverage'].mean:>10.3f} "
                      f"{str(sb['return']):>16} {sb['final_coverage'].mean:>7.3f} {r.returns.mean():>8.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--goals", action="store_true", help="train the goal runs (about an hour per seed)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--out", default=str(ROOT / "runs"))
    ap.add_argument("--report", nargs="+", default=None, help="report on these run directories")
    ap.add_argument("--seconds", type=float, default=4.0, help="seconds per throughput measurement")
    args = ap.parse_args()
    if args.report:
        report([Path(r) for r in args.report])
    elif args.goals:
        runs = train_goals(args.seeds, Path(args.out))
        report(runs)
    else:
        throughput(args.seconds)


if __name__ == "__main__":
    main()
