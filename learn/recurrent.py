"""The recurrent actors of MAGRDPG: a GRU or an LSTM cell over ``[a_prev, obs]`` and a linear output layer.

The GRU is PyTorch's (``torch.nn.GRU``, gate order r, z, n: the artifact of :mod:`kiloforge.actors.gru`
holds the same numbers)::

    r = σ(W_ir x + b_ir + W_hr h + b_hr),  z = σ(W_iz x + b_iz + W_hz h + b_hz)
    n = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn)),  h' = (1 − z) ⊙ n + z ⊙ h,  a = W_out h' + b_out

The LSTM (the thesis's MAGRDPG actor) is PyTorch's too (``torch.nn.LSTM``, gate order i, f, g, o:
:mod:`kiloforge.actors.lstm`); its state ``[h, c]`` is kept as one (R, 2H) tensor so that both actors
share one interface (``initial_state``, ``states``, ``forward``, ``step``, ``arrays``, ``policy``).

The output is linear (the inverting-gradient rule keeps it in [0, 1] while learning; acting clips).
Initialisation: the cell as PyTorch's, U(±1/√H); the output layer U(±3·10⁻³) (thesis §4.3.2).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import nn

from kiloforge.actors.gru import GRUPolicy
from kiloforge.actors.lstm import LSTMPolicy
from sim.config import ACTION_DIM, WorldConfig

from .networks import ACTOR_OUT_INIT, OutputLinear


class GRUActor(nn.Module):
    """μ(o_t, a_{t−1}, h_{t−1}): one GRU layer of ``hidden`` units and a linear (hidden → 2) output.

    The recurrence is ``torch.nn.GRU`` (its fused loop; parameters ``weight_ih_l0`` ... in gate
    order r, z, n), so one call unrolls a whole window.
    """

    def __init__(self, in_dim: int, hidden: int) -> None:
        super().__init__()
        assert in_dim >= 1 and hidden >= 1, f"bad GRU actor sizes {in_dim}, {hidden}"
        self.in_dim, self.hidden = int(in_dim), int(hidden)
        self.gru = nn.GRU(self.in_dim, self.hidden, batch_first=True)  # init U(±1/√H)
        self.out = OutputLinear(self.hidden, ACTION_DIM)
        nn.init.uniform_(self.out.weight, -ACTOR_OUT_INIT, ACTOR_OUT_INIT)
        nn.init.uniform_(self.out.bias, -ACTOR_OUT_INIT, ACTOR_OUT_INIT)

    def initial_state(self, n: int) -> torch.Tensor:
        """Zero hidden states (n, H) on the actor's device."""
        return torch.zeros(n, self.hidden, device=self.out.weight.device)

    def states(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """Hidden states after each step: x (R, L, D), h (R, H) -> (R, L, H)."""
        y, _ = self.gru(x, h.unsqueeze(0))
        return y

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unroll a window: x (R, L, D) from states h (R, H) -> (raw actions (R, L, 2), final state (R, H))."""
        y = self.states(x, h)
        return self.out(y), y[:, -1]

    def step(self, x: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One control step: x (R, D), h (R, H) -> (raw action (R, 2), new state)."""
        a, h = self.forward(x.unsqueeze(1), h)
        return a[:, 0], h

    def arrays(self) -> dict[str, np.ndarray]:
        """float32 NumPy copies named as in :mod:`kiloforge.actors.gru` (w_ih, w_hh, b_ih, b_hh, w_out, b_out)."""
        def a(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy().astype(np.float32).copy()
        g = self.gru
        return {"w_ih": a(g.weight_ih_l0), "w_hh": a(g.weight_hh_l0), "b_ih": a(g.bias_ih_l0),
                "b_hh": a(g.bias_hh_l0), "w_out": a(self.out.weight), "b_out": a(self.out.bias)}

    def policy(self, world: WorldConfig, provenance: dict) -> GRUPolicy:
        """The actor as a policy artifact."""
        return GRUPolicy(**self.arrays(), world=world, provenance=provenance)

    @property
    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


class LSTMActor(nn.Module):
    """μ(o_t, a_{t−1}, s_{t−1}): one LSTM layer of ``hidden`` units and a linear (hidden → 2) output.

    The state ``s = [h, c]`` is one (R, 2H) tensor. The recurrence is ``torch.nn.LSTM`` (its fused loop;
    parameters ``weight_ih_l0`` ... in gate order i, f, g, o), so one call unrolls a whole window.
    """

    def __init__(self, in_dim: int, hidden: int) -> None:
        super().__init__()
        assert in_dim >= 1 and hidden >= 1, f"bad LSTM actor sizes {in_dim}, {hidden}"
        self.in_dim, self.hidden = int(in_dim), int(hidden)
        self.lstm = nn.LSTM(self.in_dim, self.hidden, batch_first=True)  # init U(±1/√H)
        self.out = OutputLinear(self.hidden, ACTION_DIM)
        nn.init.uniform_(self.out.weight, -ACTOR_OUT_INIT, ACTOR_OUT_INIT)
        nn.init.uniform_(self.out.bias, -ACTOR_OUT_INIT, ACTOR_OUT_INIT)

    def initial_state(self, n: int) -> torch.Tensor:
        """Zero states [h, c] (n, 2H) on the actor's device."""
        return torch.zeros(n, 2 * self.hidden, device=self.out.weight.device)

    def _split(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        H = self.hidden
        return s[:, :H].unsqueeze(0).contiguous(), s[:, H:].unsqueeze(0).contiguous()

    def states(self, x: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """States [h, c] after each step: x (R, L, D), s (R, 2H) -> (R, L, 2H) (one LSTM call per step:
        the fused call returns c only at the end)."""
        h, c = self._split(s)
        out = []
        for t in range(x.shape[1]):
            _, (h, c) = self.lstm(x[:, t:t + 1], (h, c))
            out.append(torch.cat([h[0], c[0]], -1))
        return torch.stack(out, 1)

    def forward(self, x: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Unroll a window: x (R, L, D) from states s (R, 2H) -> (raw actions (R, L, 2), final state (R, 2H))."""
        y, (h, c) = self.lstm(x, self._split(s))
        return self.out(y), torch.cat([h[0], c[0]], -1)

    def step(self, x: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One control step: x (R, D), s (R, 2H) -> (raw action (R, 2), new state)."""
        a, s = self.forward(x.unsqueeze(1), s)
        return a[:, 0], s

    def arrays(self) -> dict[str, np.ndarray]:
        """float32 NumPy copies named as in :mod:`kiloforge.actors.lstm` (w_ih, w_hh, b_ih, b_hh, w_out, b_out)."""
        def a(t: torch.Tensor) -> np.ndarray:
            return t.detach().cpu().numpy().astype(np.float32).copy()
        m = self.lstm
        return {"w_ih": a(m.weight_ih_l0), "w_hh": a(m.weight_hh_l0), "b_ih": a(m.bias_ih_l0),
                "b_hh": a(m.bias_hh_l0), "w_out": a(self.out.weight), "b_out": a(self.out.bias)}

    def policy(self, world: WorldConfig, provenance: dict) -> LSTMPolicy:
        """The actor as a policy artifact."""
        return LSTMPolicy(**self.arrays(), world=world, provenance=provenance)

    @property
    def n_params(self) -> int:
        return sum(p.numel() for p in self.parameters())


#: the recurrent actors by cell name (RecurrentConfig.cell: the kind of the policy artifact they write)
RECURRENT_ACTORS: dict[str, type[nn.Module]] = {GRUPolicy.kind: GRUActor, LSTMPolicy.kind: LSTMActor}


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
