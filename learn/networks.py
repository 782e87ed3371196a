"""Actor and critic networks (thesis §4.3.1), and a critic invariant to robot order and count.

* :class:`Actor` — the MLP actor over one robot's flat T_prev history;
* :class:`Critic` — the thesis's centralised critic: full state and joint action concatenated;
* :class:`MeanCritic` — a mean-embedding (DeepSets) critic (Hüttenrauch, Šošić & Neumann, *Deep
  Reinforcement Learning for Swarm Systems*, JMLR 2019): the same encoder on every robot's features,
  pooled over robots, so one set of weights evaluates any swarm size and any robot order; with
  ``per_robot`` it gives one value per robot, Q_i = ρ([φ(f_i), pool_j φ(f_j), g]), for per-robot rewards.

All are fully connected with ELU hidden layers. Initialisation follows the thesis: every hidden
layer's weights and biases from U(±1/√f) with f the layer's input width; the critic's output layer
from U(±3·10⁻⁴), the actor's from U(±3·10⁻³). The actor's output layer is *linear*: its outputs
are kept in [0, 1] by the inverting-gradient rule during learning (see :mod:`learn.magddpg`) and
clipped to [0, 1] when acting, which is what the exported firmware does too.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from sim.config import ACTION_DIM

CRITIC_OUT_INIT = 3e-4
ACTOR_OUT_INIT = 3e-3


class OutputLinear(nn.Linear):
    """The output layer: computed in float32 even inside a bfloat16 autocast (``--precision bf16``), so Q values
    and motor commands keep full precision (a Q of 100 in bfloat16 is only good to ±0.5); outside autocast it is
    ``nn.Linear`` exactly."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_autocast_enabled(x.device.type):
            with torch.autocast(x.device.type, enabled=False):
                return nn.functional.linear(x.float(), self.weight, self.bias)
        return nn.functional.linear(x, self.weight, self.bias)


def mlp(in_dim: int, hidden: tuple[int, ...], out_dim: int, out_init: float) -> nn.Sequential:
    """Linear+ELU hidden layers and a linear output layer, initialised as in thesis §4.3.1."""
    layers: list[nn.Module] = []
    width = in_dim
    for h in hidden:
        lin = nn.Linear(width, h)
        bound = 1.0 / math.sqrt(width)  # f = the layer's input width
        nn.init.uniform_(lin.weight, -bound, bound)
        nn.init.uniform_(lin.bias, -bound, bound)
        layers += [lin, nn.ELU()]
        width = h
    out = OutputLinear(width, out_dim)
    nn.init.uniform_(out.weight, -out_init, out_init)
    nn.init.uniform_(out.bias, -out_init, out_init)
    layers.append(out)
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """μ(h | θ^μ): one robot's flat history (t_prev · tuple_dim) → (u_left, u_right), linear output.

    Shared by all robots: call it on (..., in_dim) histories of any leading shape.
    """

    def __init__(self, in_dim: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        assert in_dim >= 1, f"actor input width must be >= 1, got {in_dim}"
        self.in_dim = in_dim
        self.hidden = tuple(hidden)
        self.net = mlp(in_dim, self.hidden, ACTION_DIM, ACTOR_OUT_INIT)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.net(h)

    def layers(self) -> list[tuple[np.ndarray, np.ndarray, str]]:
        """(W (out, in), b (out,), activation) per linear layer as float32 NumPy, for export."""
        linears = [m for m in self.net if isinstance(m, nn.Linear)]
        acts = ["elu"] * (len(linears) - 1) + ["identity"]
        return [(m.weight.detach().cpu().numpy().astype(np.float32).copy(),
                 m.bias.detach().cpu().numpy().astype(np.float32).copy(), a)
                for m, a in zip(linears, acts)]


class Critic(nn.Module):
    """Q(s, a¹..a^M | θ^Q): full state and joint action, concatenated at the input → scalar."""

    def __init__(self, state_dim: int, n_robots: int, hidden: tuple[int, ...]) -> None:
        super().__init__()
        assert state_dim >= 1 and n_robots >= 1, f"bad critic sizes {state_dim}, {n_robots}"
        self.state_dim = state_dim
        self.n_robots = n_robots
        self.net = mlp(state_dim + ACTION_DIM * n_robots, tuple(hidden), 1, CRITIC_OUT_INIT)

    def forward(self, s: torch.Tensor, a: torch.Tensor, o: torch.Tensor | None = None) -> torch.Tensor:
        """s (N, state_dim), a (N, M, 2) → Q (N,). (``o``, the robots' observations, is not used.)"""
        return self.net(torch.cat([s, a.flatten(1)], dim=1)).squeeze(1)


#: per-robot features of the mean critic: x, y (arena), x − x_t, y − y_t (target), cos φ, sin φ, a_l, a_r
ROBOT_FEATURES = 8


class MeanCritic(nn.Module):
    """Q(s, a¹..a^M) = ρ([pool_i φ(f_i), g]): invariant to the order and the number of robots.

    ``s`` is the simulator's critic state (``SwarmEnv.state()``: target x, y, then every robot's x, y,
    φ/π, positions / arena half-width). Robot i's features f_i are its position (relative to the
    arena), its position relative to the target, cos φ and sin φ, its action and, with ``obs_dim``,
    its observation; φ is a shared ELU encoder, pooled by the mean over robots (``pool="meanmax"``:
    mean and element-wise max), and ρ an ELU MLP on the pooled embedding and the global features
    g = (target x, target y, 1/M).

    ``per_robot``: Q (N, M), robot i's value from its own embedding φ(f_i) beside the pooled one and g (the
    same head for every robot), learned from robot i's own reward (``--reward local``). A robot's own
    features reach its value directly instead of with weight 1/M through the mean, which is what
    credit assignment at 16+ robots needs.
    """

    def __init__(self, embed: tuple[int, ...], hidden: tuple[int, ...], pool: str = "mean", obs_dim: int = 0,
                 per_robot: bool = False) -> None:
        super().__init__()
        assert len(embed) >= 1 and pool in ("mean", "meanmax"), f"bad mean critic {embed}, {pool}"
        self.pool, self.obs_dim, self.per_robot = pool, int(obs_dim), bool(per_robot)
        layers: list[nn.Module] = []
        width = ROBOT_FEATURES + self.obs_dim
        for h in embed:
            lin = nn.Linear(width, h)
            bound = 1.0 / math.sqrt(width)
            nn.init.uniform_(lin.weight, -bound, bound)
            nn.init.uniform_(lin.bias, -bound, bound)
            layers += [lin, nn.ELU()]
            width = h
        self.encoder = nn.Sequential(*layers)
        pooled = width * (2 if pool == "meanmax" else 1) + (width if self.per_robot else 0)
        self.head = mlp(pooled + 3, tuple(hidden), 1, CRITIC_OUT_INIT)

    def features(self, s: torch.Tensor, a: torch.Tensor, o: torch.Tensor | None = None) -> torch.Tensor:
        """Per-robot features (N, M, ROBOT_FEATURES [+ obs_dim])."""
        N, M, _ = a.shape
        assert s.shape[1] == 2 + 3 * M, f"state width {s.shape[1]} does not match {M} robots"
        target = s[:, None, :2]  # (N, 1, 2)
        robots = s[:, 2:].reshape(N, M, 3)
        xy, phi = robots[..., :2], robots[..., 2] * math.pi
        parts = [xy, xy - target, torch.cos(phi)[..., None], torch.sin(phi)[..., None], a]
        if self.obs_dim:
            assert o is not None and o.shape[-1] == self.obs_dim, "this critic needs the robots' observations"
            parts.append(o)
        return torch.cat(parts, dim=-1)

    def forward(self, s: torch.Tensor, a: torch.Tensor, o: torch.Tensor | None = None) -> torch.Tensor:
        """s (N, 2 + 3M), a (N, M, 2)[, o (N, M, obs_dim)] → Q (N,), or (N, M) ``per_robot``, for any M."""
        e = self.encoder(self.features(s, a, o))  # (N, M, E)
        pooled = [e.mean(dim=1)] + ([e.amax(dim=1)] if self.pool == "meanmax" else [])
        g = torch.cat([s[:, :2], torch.full_like(s[:, :1], 1.0 / a.shape[1])], dim=1)
        swarm = torch.cat(pooled + [g], dim=1)  # (N, ·)
        if not self.per_robot:
            return self.head(swarm).squeeze(1)
        shared = swarm[:, None, :].expand(-1, e.shape[1], -1)  # (N, M, ·)
        return self.head(torch.cat([e, shared], dim=2)).squeeze(2)


def make_critic(kind: str, state_dim: int, n_robots: int, hidden: tuple[int, ...], embed: tuple[int, ...] = (64, 64),
                pool: str = "mean", obs_dim: int = 0) -> nn.Module:
    """The critic a config names: ``concat`` (:class:`Critic`, one swarm size), ``mean`` (:class:`MeanCritic`) or
    ``robot`` (:class:`MeanCritic` with one value per robot)."""
    if kind == "concat":
        return Critic(state_dim, n_robots, hidden)
    assert kind in ("mean", "robot"), f"unknown critic {kind!r}"
    return MeanCritic(embed, hidden, pool, obs_dim, per_robot=kind == "robot")


def config_critic(cfg, world) -> nn.Module:
    """The critic of a training config (:mod:`learn.config`) in ``world``."""
    M = cfg.n_robots[0]
    return make_critic(cfg.critic, world.state_dim(M), M, cfg.critic_hidden, cfg.critic_embed, cfg.critic_pool,
                       world.obs_dim if cfg.critic_obs else 0)
