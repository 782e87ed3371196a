"""Actor and critic networks of MAGDDPG (thesis §4.3.1).

Both are fully connected with ELU hidden layers. Initialisation follows the thesis: every hidden
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
    out = nn.Linear(width, out_dim)
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

    def forward(self, s: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """s (N, state_dim), a (N, M, 2) → Q (N,)."""
        return self.net(torch.cat([s, a.flatten(1)], dim=1)).squeeze(1)
