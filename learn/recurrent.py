"""The recurrent actor of MAGRDPG: a GRU cell over ``[a_prev, obs]`` and a linear output layer.

The cell is PyTorch's GRU (gate order r, z, n; parameters named as in ``torch.nn.GRUCell`` so the
artifact of :mod:`export.gru` is the same numbers), written out so that a whole window's input
projections are one matrix product and episode starts inside a window can zero the state::

    r = σ(W_ir x + b_ir + W_hr h + b_hr),  z = σ(W_iz x + b_iz + W_hz h + b_hz)
    n = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn)),  h' = (1 − z) ⊙ n + z ⊙ h,  a = W_out h' + b_out

The output is linear (the inverting-gradient rule keeps it in [0, 1] while learning; acting clips).
Initialisation: the cell as PyTorch's GRU, U(±1/√H); the output layer U(±3·10⁻³) (thesis §4.3.2).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from sim.config import ACTION_DIM

from .networks import ACTOR_OUT_INIT


class GRUActor(nn.Module):
    """μ(o_t, a_{t−1}, h_{t−1}): one GRU cell of ``hidden`` units and a linear (hidden → 2) output."""

    def __init__(self, in_dim: int, hidden: int) -> None:
        super().__init__()
        assert in_dim >= 1 and hidden >= 1, f"bad GRU actor sizes {in_dim}, {hidden}"
        self.in_dim, self.hidden = int(in_dim), int(hidden)
        H = self.hidden
        self.weight_ih = nn.Parameter(torch.empty(3 * H, in_dim))
        self.weight_hh = nn.Parameter(torch.empty(3 * H, H))
        self.bias_ih = nn.Parameter(torch.empty(3 * H))
        self.bias_hh = nn.Parameter(torch.empty(3 * H))
        bound = 1.0 / math.sqrt(H)
        for p in (self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh):
            nn.init.uniform_(p, -bound, bound)
        self.out = nn.Linear(H, ACTION_DIM)
        nn.init.uniform_(self.out.weight, -ACTOR_OUT_INIT, ACTOR_OUT_INIT)
        nn.init.uniform_(self.out.bias, -ACTOR_OUT_INIT, ACTOR_OUT_INIT)

    def initial_state(self, n: int) -> torch.Tensor:
        """Zero hidden states (n, H)."""
        return torch.zeros(n, self.hidden)

    def cell(self, gi: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """One step from the input projection ``gi = W_ih x + b_ih`` (R, 3H) and the state h (R, H)."""
        gh = F.linear(h, self.weight_hh, self.bias_hh)  # (R, 3H)
        i_r, i_z, i_n = gi.chunk(3, -1)
        h_r, h_z, h_n = gh.chunk(3, -1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return n + z * (h - n)  # (1 - z) n + z h

    def forward(self, x: torch.Tensor, h: torch.Tensor, reset: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """Unroll over a window: x (R, L, D), h (R, H), ``reset`` (R, L) bool zeroes the state before
        that step (an episode start) -> (raw actions (R, L, 2), final state (R, H))."""
        gi = F.linear(x, self.weight_ih, self.bias_ih)  # (R, L, 3H): every step's input projection at once
        keep = None if reset is None else (~reset).to(x.dtype).unsqueeze(-1)  # (R, L, 1)
        hs = []
        for j in range(x.shape[1]):
            if keep is not None:
                h = h * keep[:, j]
            h = self.cell(gi[:, j], h)
            hs.append(h)
        return self.out(torch.stack(hs, 1)), h

    def step(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One control step: x (R, D), h (R, H) -> (raw action (R, 2), new state)."""
        h = self.cell(F.linear(x, self.weight_ih, self.bias_ih), h)
        return self.out(h), h

    def arrays(self) -> dict[str, np.ndarray]:
        """float32 NumPy copies named as in :mod:`export.gru` (w_ih, w_hh, b_ih, b_hh, w_out, b_out)."""
        def a(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy().astype(np.float32).copy()
        return {"w_ih": a(self.weight_ih), "w_hh": a(self.weight_hh), "b_ih": a(self.bias_ih),
                "b_hh": a(self.bias_hh), "w_out": a(self.out.weight), "b_out": a(self.out.bias)}

    @property
    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


def gru_params(in_dim: int, hidden: int) -> int:
    """Parameters of a GRU actor: 3H(D + H + 2) + 2H + 2.

    >>> gru_params(16, 32)
    4866
    """
    return 3 * hidden * (in_dim + hidden + 2) + ACTION_DIM * hidden + ACTION_DIM


def mlp_params(sizes: list[int]) -> int:
    """Parameters of an MLP with these layer sizes (input first).

    >>> mlp_params([160, 32, 32, 2])
    6274
    """
    return sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))
