"""Evolution strategies for the shared actor: search the actor's weights on the task metric itself.

OpenAI-ES (Salimans, Ho, Chen, Sidor & Sutskever 2017, "Evolution strategies as a scalable
alternative to reinforcement learning"): around the current weights θ, draw ``pairs`` Gaussian
directions ε_i, run the actor with θ + σ ε_i and θ − σ ε_i (antithetic pairs) in the simulator,
and move θ along Σ_i (F(θ + σ ε_i) − F(θ − σ ε_i)) ε_i / (2 n σ) with Adam, where F is a fitness
shaped into centred ranks. No critic, no credit assignment: the swarm's own final success at
several swarm sizes is what is ascended, which is what the exported policy is judged on.

* **One batched pass.** Every population member drives its own environments; the members' MLPs run
  as one batched matrix product over (member, robot-steps) (:class:`PopulationMLP`), and all envs
  of one swarm size step together in one :class:`sim.env.SwarmEnv`.
* **Common random numbers.** For each swarm size and episode, every member meets the same episode
  (same spawn, same radio and light streams, same domain-randomisation draw): the pair difference
  then measures the weights, not the luck of the episode.
* **Fitness per size, ranks per size.** Each size's fitness (the members' mean final success over
  that size's episodes) becomes centred ranks in [−0.5, 0.5] (:func:`centred_ranks`); the sizes'
  ranks are averaged with the size weights, so a size whose success varies little still counts.
* Deterministic actor, exactly the exported one: the history of :class:`sim.history.History` and
  actions clipped to [0, 1], as :class:`sim.rollout.HistoryActor` and the firmware do.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
from torch import nn

from sim.config import WorldConfig
from sim.env import SwarmEnv
from sim.history import History
from sim.metrics import final_success
from sim.rollout import EpisodeLoop

ACTIVATIONS = {"elu": torch.nn.functional.elu, "relu": torch.relu, "tanh": torch.tanh,
               "sigmoid": torch.sigmoid, "identity": lambda x: x}


class PopulationMLP:
    """K weight vectors of one MLP architecture, evaluated in one batched pass.

    ``layers``: ``(out, in)`` shape and activation of every linear layer, input first, as the
    actor's ``nn.Sequential`` holds them. A flat parameter vector is the concatenation of each
    layer's weight (row-major, (out, in)) then bias, which is ``nn.utils.parameters_to_vector``'s
    order for that module.
    """

    def __init__(self, layers: Sequence[tuple[tuple[int, int], str]]) -> None:
        assert layers, "an MLP needs at least one layer"
        for (shape, act) in layers:
            assert len(shape) == 2 and act in ACTIVATIONS, f"bad layer {shape} {act}"
        for (a, _), (b, _) in zip(layers[:-1], layers[1:]):
            assert b[1] == a[0], f"layer widths do not chain: {a} then {b}"
        self.layers = [(tuple(int(s) for s in shape), act) for shape, act in layers]
        self.n_params = sum(o * i + o for (o, i), _ in self.layers)

    @classmethod
    def of(cls, net: nn.Sequential) -> "PopulationMLP":
        """The architecture of a Linear/activation ``nn.Sequential`` (the last Linear is linear)."""
        mods = list(net)
        layers = []
        for k, m in enumerate(mods):
            if isinstance(m, nn.Linear):
                nxt = mods[k + 1] if k + 1 < len(mods) else None
                act = {nn.ELU: "elu", nn.ReLU: "relu", nn.Tanh: "tanh", nn.Sigmoid: "sigmoid"}.get(type(nxt), "identity")
                layers.append(((m.out_features, m.in_features), act))
        return cls(layers)

    @property
    def in_dim(self) -> int:
        return self.layers[0][0][1]

    def bind(self, theta: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor, Callable]]:
        """theta (K, P) -> per layer (bias (K, 1, out), weight (K, in, out), activation): views of theta, cut once
        for the many calls of one rollout (:meth:`forward_bound`)."""
        K = theta.shape[0]
        assert theta.shape == (K, self.n_params), f"theta must be (K, {self.n_params}), got {tuple(theta.shape)}"
        i, out = 0, []
        for (o, n), act in self.layers:
            w = theta[:, i:i + o * n].reshape(K, o, n)
            b = theta[:, i + o * n:i + o * n + o]
            i += o * n + o
            out.append((b[:, None, :], w.transpose(1, 2), ACTIVATIONS[act]))
        return out

    @staticmethod
    def forward_bound(bound: list[tuple[torch.Tensor, torch.Tensor, Callable]], x: torch.Tensor) -> torch.Tensor:
        """x (K, N, in) -> raw outputs (K, N, out) through the layers of :meth:`bind`."""
        for b, wt, act in bound:
            x = act(torch.baddbmm(b, x, wt))
        return x

    def forward(self, theta: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """theta (K, P), x (K, N, in) -> raw outputs (K, N, out) of member k on its rows x[k]."""
        return self.forward_bound(self.bind(theta), x)


@dataclass
class PopulationResult:
    """Per member (K,) and episode (E,): the task's final success and return."""

    final_success: np.ndarray  # (K, E)
    returns: np.ndarray  # (K, E)


@torch.inference_mode()
def rollout_population(pop: PopulationMLP, theta: torch.Tensor, world: WorldConfig, n_robots: int,
                       episode_seeds: Sequence[np.random.SeedSequence], t_prev: int,
                       randomise=None, task=None) -> PopulationResult:
    """Every member (rows of ``theta``) plays every episode of ``episode_seeds`` (common random numbers).

    One SwarmEnv of K·E envs: env (k, e) is member k in episode e, seeded with ``episode_seeds[e]``,
    so all members meet exactly the same episodes (env e of a batch equals the single env with that
    seed sequence). Episodes last ``world.episode_steps``; fitness is the final value of the task's success
    (``task``: a :class:`sim.tasks.Task` or name, default localisation).
    """
    K, E, M = theta.shape[0], len(episode_seeds), n_robots
    assert pop.in_dim == world.history_dim(t_prev), \
        f"actor input {pop.in_dim} != history width {world.history_dim(t_prev)} (t_prev {t_prev})"
    seeds = [episode_seeds[e] for _ in range(K) for e in range(E)]  # env index k * E + e
    env = SwarmEnv(world, n_envs=K * E, n_robots=M, seed=seeds, randomise=randomise, task=task)
    history = History(t_prev, world.obs_dim)
    layers = pop.bind(theta.float())
    prev = None  # the members' last actions (float32), as the history holds them

    def act(t: int, obs: np.ndarray, info) -> np.ndarray:
        nonlocal prev
        h = history.reset(obs) if t == 0 else history.push(prev, obs)
        x = torch.from_numpy(h).reshape(K, E * M, -1)
        prev = pop.forward_bound(layers, x).clamp_(0.0, 1.0).reshape(K * E, M, -1).numpy()
        return prev.astype(np.float64)

    loop = EpisodeLoop(env).run(act)
    return PopulationResult(final_success(loop.success).reshape(K, E), loop.returns.reshape(K, E))


def centred_ranks(f: np.ndarray) -> np.ndarray:
    """Fitness values (K,) -> ranks scaled to [−0.5, 0.5]; ties share their mean rank.

    >>> centred_ranks(np.array([0.2, 0.9, 0.5, 0.5])).tolist()
    [-0.5, 0.5, 0.0, 0.0]
    """
    f = np.asarray(f, np.float64)
    K = f.size
    if K < 2:
        return np.zeros(K)
    order = np.argsort(f, kind="stable")
    ranks = np.empty(K)
    ranks[order] = np.arange(K)
    _, inv = np.unique(f, return_inverse=True)  # average the ranks of equal values
    ranks = (np.bincount(inv, ranks) / np.bincount(inv))[inv]
    return ranks / (K - 1) - 0.5


def es_direction(utility: np.ndarray, eps: torch.Tensor, sigma: float) -> torch.Tensor:
    """Ascent direction from antithetic utilities: utility (2n,) = [members θ+σε_i ..., θ−σε_i ...]."""
    n = eps.shape[0]
    assert utility.shape == (2 * n,), f"need 2n = {2 * n} utilities, got {utility.shape}"
    diff = torch.from_numpy(utility[:n] - utility[n:]).to(eps.dtype)
    return diff @ eps / (2 * n * sigma)


class Adam:
    """Adam ascent on a flat parameter vector (Kingma & Ba 2015), with its state for checkpoints."""

    def __init__(self, n: int, lr: float, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8) -> None:
        self.lr, self.beta1, self.beta2, self.eps = float(lr), float(beta1), float(beta2), float(eps)
        self.m = torch.zeros(n, dtype=torch.float64)
        self.v = torch.zeros(n, dtype=torch.float64)
        self.t = 0

    def step(self, theta: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """θ + lr · m̂ / (√v̂ + eps) for ascent direction g."""
        self.t += 1
        self.m.mul_(self.beta1).add_(g, alpha=1 - self.beta1)
        self.v.mul_(self.beta2).addcmul_(g, g, value=1 - self.beta2)
        mh = self.m / (1 - self.beta1 ** self.t)
        vh = self.v / (1 - self.beta2 ** self.t)
        return theta + self.lr * mh / (vh.sqrt() + self.eps)

    def state_dict(self) -> dict:
        return {"m": self.m.clone(), "v": self.v.clone(), "t": self.t}

    def load_state_dict(self, d: dict) -> None:
        self.m.copy_(d["m"])
        self.v.copy_(d["v"])
        self.t = int(d["t"])
