"""Does a coin let a learned policy copy the pusher? A scratch world with a random bit in every observation.

    python -m experiments.coin_experiment train-es --seed 1 --randomise table --demo-policy pusher --out runs/coin_s1
    python -m experiments.coin_experiment train-es --init-policy runs/coin_s1/policy_best.npz \\
        --size-randomise table table table-free-beacon --size-weights 2 1 3 --size-episodes 4 1 2 --lr 0.005 \\
        --generations 20 --seed 51 --out runs/coin_ft_s1
    python -m experiments.coin_experiment evaluate runs/coin_ft_s1/policy_last.npz … [--episodes 100 --seed 20261202]

Not a product feature: this script patches the simulator in its own process. Every observation's last entry (the
last RBF bin of the kilobot world) is replaced by a fair random bit per robot and period, and ``--demo-policy pusher``
becomes the pusher taking each turn's direction from that bit (:class:`CoinPusher`), so that a behaviour clone sees
the coin its demonstrator turned by. ``train-es`` is ``python -m learn train-es`` in that world; ``evaluate`` plays
the given policies, the pusher and the pusher on the coin on the same held-out episodes at 4, 16 and 32 robots. The
coin's stream (``--coin-seed``) is not tied to the episode seeds, so reruns move the results slightly.
Results: docs/results/localisation.md ("a coin does not move them").
"""
from __future__ import annotations

import argparse
import dataclasses
import sys

import numpy as np

import learn.demos as demos
import learn.es_train as es_train
import sim.env
from sim.baselines import PUSHER, TUNED, HandWrittenSearcher, make_policy
from sim.config import HELD_OUT_SEED


class CoinPusher(HandWrittenSearcher):
    """The pusher, its turn directions from the coin (the observation's last entry) instead of its own generator."""

    def __init__(self, cfg) -> None:
        super().__init__(cfg, dataclasses.replace(TUNED[cfg.name], **PUSHER))
        self.prox_w = self.prox_w.copy()
        self.prox_w[-1] = 0.0  # the last bin is the coin, not a neighbour distance
        self._coin = None

    def act(self, obs: np.ndarray) -> np.ndarray:
        self._coin = obs[..., -1] > 0.5
        return super().act(obs)

    def draws(self, shape):
        _, tumble, wall_turn, runs = super().draws(shape)
        return np.where(self._coin, 1, -1).astype(np.int8), tumble, wall_turn, runs


def install_coin(seed: int) -> None:
    """Patch this process: the coin in every observation, and the pusher demonstrator on it."""
    rng = np.random.default_rng(seed)
    observe = sim.env.observe_period

    def observe_with_coin(period, light, prev_wall, cfg, fast):
        obs, flags = observe(period, light, prev_wall, cfg, fast)
        obs[..., -1] = (rng.random(obs.shape[:-1]) < 0.5).astype(obs.dtype)
        return obs, flags

    sim.env.observe_period = observe_with_coin
    demonstrator = demos.demonstrator

    def coin_demonstrator(world, stop_dist=0.0, kind="searcher"):
        return CoinPusher(world) if kind == "pusher" else demonstrator(world, stop_dist, kind)

    demos.demonstrator = es_train.demonstrator = coin_demonstrator


def evaluate(paths: list[str], episodes: int, seed: int) -> None:
    from kiloforge.policies import load_policy, swarm_policy
    from sim.config import WorldConfig
    from sim.env import SwarmEnv
    from sim.metrics import compare
    from sim.tasks import get_task
    from sim.rollout import rollout

    world = WorldConfig.from_dict({**load_policy(paths[0]).world.to_dict(), "episode_steps": 500})
    for M in (4, 16, 32):
        env = SwarmEnv(world, n_envs=min(50, episodes), n_robots=M, seed=seed)
        contenders = {"pusher": make_policy("pusher", world), "pusher on the coin": CoinPusher(world)}
        contenders.update({p: swarm_policy(load_policy(p), world) for p in paths})
        table = {k: rollout(env, c, episodes, seed=seed).metrics(ceiling=True) for k, c in contenders.items()}
        print(f"\n{M} robots, 500 steps, {episodes} episodes from seed {seed}, with the coin (mean ± 95 % CI)")
        print(compare(table, get_task("localisation").columns), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--coin-seed", type=int, default=12345, help="seed of the coin's stream")
    ap.add_argument("command", choices=("train-es", "evaluate"))
    args, rest = ap.parse_known_args()
    install_coin(args.coin_seed)
    if args.command == "train-es":
        from learn.__main__ import main as learn_main
        return learn_main(["train-es", *rest])
    ev = argparse.ArgumentParser(prog="coin_experiment.py evaluate")
    ev.add_argument("policies", nargs="+")
    ev.add_argument("--episodes", type=int, default=100)
    ev.add_argument("--seed", type=int, default=HELD_OUT_SEED, help="episode seed no training used")
    e = ev.parse_args(rest)
    evaluate(e.policies, e.episodes, e.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
