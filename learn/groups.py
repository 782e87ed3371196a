"""One env group per trained swarm size: its environments, replay, exploration noise and reward.

``--robots 4 16 32`` trains one actor and one critic on three groups stepped in lockstep (same episode
length): ``n_envs`` environments of each size, a replay memory per size, and every update draws its
minibatch from all sizes, in the proportion ``size_mix`` says (:func:`size_shares`): ``equal``
(the same number of samples from each size) or ``robots`` (proportional to the robot count, so every
robot-transition weighs the same). Each size is evaluated separately.
"""
from __future__ import annotations


import numpy as np

from sim.config import ACTION_DIM, WorldConfig
from sim.env import SwarmEnv
from sim.rollout import EpisodeLoop
from sim.tasks import Task, get_task

from .augment import PhantomNeighbours
from .config import randomisation
from .noise import OUNoise
from .replay import EpisodeReplay
from .rewards import LearningReward


def make_env(world: WorldConfig, n_envs: int, n_robots: int, seed: int, randomise: str = "none",
             task: "Task | str | None" = None) -> SwarmEnv:
    """A SwarmEnv of ``task`` (default localisation) in the task's world for ``n_robots`` (``Task.world_for``),
    domain-randomised when ``randomise`` names a randomisation."""
    task = get_task(task)
    return SwarmEnv(task.world_for(world, n_robots), n_envs=n_envs, n_robots=n_robots, seed=seed,
                    randomise=randomisation(randomise), task=task)


def size_shares(n: int, robots: tuple[int, ...], mix: str) -> list[int]:
    """Split n samples over the swarm sizes (each at least 1 when n >= len(robots)); largest remainder.

    >>> size_shares(256, (4, 16, 32), "equal"), size_shares(256, (4, 16, 32), "robots")
    ([86, 85, 85], [20, 79, 157])
    """
    if n == 0:
        return [0] * len(robots)
    w = np.ones(len(robots)) if mix == "equal" else np.asarray(robots, np.float64)
    exact = n * w / w.sum()
    out = np.floor(exact).astype(int)
    for k in np.argsort(-(exact - out), kind="stable")[: n - out.sum()]:
        out[k] += 1
    short = np.flatnonzero(out == 0)
    for k in short:  # every size gets a sample, taken from the largest share
        out[np.argmax(out)] -= 1
        out[k] += 1
    return out.tolist()


class EnvGroup:
    """The environments of one swarm size and everything that follows them through an episode."""

    def __init__(self, cfg, world: WorldConfig, n_robots: int, algo, env_rng: np.random.Generator,
                 noise_rng: np.random.Generator, aug_rng: np.random.Generator) -> None:
        B, M, T = cfg.n_envs, n_robots, world.episode_steps
        self.n_envs, self.n_robots, self.world = B, M, world
        self.env = make_env(world, B, M, int(env_rng.integers(2 ** 31)), cfg.randomise, cfg.task_spec())
        self.replay = EpisodeReplay(cfg.replay_size, T, M, world.tuple_dim, world.state_dim(M), algo.replay_t_prev,
                                    algo.device, with_obs=cfg.critic_obs, per_robot_rewards=cfg.reward == "local")
        self.noise = OUNoise((B, M, ACTION_DIM), cfg.noise_theta, cfg.noise_sigma, cfg.noise_mu, noise_rng)
        self.phantoms = PhantomNeighbours(world, cfg.phantom_neighbours, aug_rng)
        self.reward = LearningReward(cfg.reward, world, cfg.gamma, cfg.shaping_weight, cfg.extra_action_penalty)
        self.acting = algo.acting(B, M, world)
        self.demos: EpisodeReplay | None = None
        self.loop = EpisodeLoop(self.env)  # stepped by the trainer, in lockstep with the other groups

    def begin(self, env_rng: np.random.Generator) -> None:
        """Start a batch of B synchronised episodes."""
        obs, _ = self.loop.begin(int(env_rng.integers(2 ** 31)))
        self.noise.reset()
        self.phantoms.reset(self.n_envs)
        first = self.acting.reset(self.phantoms(obs))  # (B, M, tuple_dim): (a_0 = 0, o_0)
        self.replay.begin(first, self.env.state())
        self.reward.reset(self.env)

    def step(self) -> np.ndarray:
        """One control step of every env with exploration noise; returns ``truncated`` (B,)."""
        a = np.clip(self.acting.act() + self.noise.sample(), 0.0, 1.0).astype(np.float32)  # (B, M, 2)
        obs, reward, truncated, info = self.loop.step(a)
        obs = self.phantoms(obs)
        self.acting.push(a, obs)
        r_learn = self.reward(self.env, reward, info, a)
        self.replay.add(np.concatenate([a, obs.astype(np.float32, copy=False)], axis=-1), self.env.state(), r_learn)
        return truncated

    @property
    def ep_return(self) -> np.ndarray:
        """(B,) the returns of the current episodes so far."""
        return self.loop.returns
