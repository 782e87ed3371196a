"""Actor kind ``"lstm"``: an LSTM cell over one ``[a_prev, obs]`` tuple per step and a linear output (MAGRDPG).

The thesis's MAGRDPG used an LSTM actor. Float actor (PyTorch's ``torch.nn.LSTM``, gate order
i, f, g, o; Algorithm 5: ``a_0 = 0``, hidden state ``h`` and cell state ``c`` zero at the start of an
episode)::

    i  = σ(W_ii x + b_ii + W_hi h + b_hi)        input gate
    f  = σ(W_if x + b_if + W_hf h + b_hf)        forget gate
    g  = tanh(W_ig x + b_ig + W_hg h + b_hg)     candidate
    o  = σ(W_io x + b_io + W_ho h + b_ho)        output gate
    c' = f ⊙ c + i ⊙ g
    h' = o ⊙ tanh(c')
    u  = clip01(W_out h' + b_out)                (u_left, u_right) in [0, 1]

Its state is the pair (h, c), kept as one vector ``[h, c]`` (2H wide).

Artifact arrays: ``w_ih`` (4H, D), ``w_hh`` (4H, H), ``b_ih`` (4H,), ``b_hh`` (4H,), ``w_out`` (2, H),
``b_out`` (2,) float32, rows in gate order i, f, g, o exactly as PyTorch stores them; meta:
``hidden``, ``input_dim``, ``gate_order "ifgo"``, ``input "a_prev+obs"``.

The int8 cell (number format of :mod:`kiloforge.numfmt`), on the int8 tuple ``x`` at ``e_in``:

* **Hidden state** ``h``: ``int8`` at ``HIDDEN_EXP = 7`` (``h = o tanh(c)`` lies in (-1, 1)), zero
  after ``setup()``.
* **Gate pre-activations** ``a_i, a_f, a_g, a_o``: four dense layers over ``[x, h]`` (``kf_dense2``'s
  two segments; the columns of ``h`` quantised from the float weights times ``2**(e_in - HIDDEN_EXP)``,
  as for the GRU), each requantised to int8 at its own exponent, at least ``SIGMOID_SAT_EXP``
  (i, f, o) or ``TANH_SAT_EXP`` (g): only the range where the table still changes needs covering.
* **Gates**: ``i, f, o`` uint8 at ``GATE_EXP = 8`` from σ tables; ``g`` int8 at ``HIDDEN_EXP`` from a
  tanh table (each table indexed by its int8 pre-activation + 128).
* **Cell state** ``c``: ``int32`` at ``CELL_EXP = GATE_EXP + HIDDEN_EXP = 15`` (real ``c / 2**15``),
  zero after ``setup()``, updated as ``c' = rshift_round(f c, GATE_EXP) + i g``: the product ``i g``
  (exponent 8 + 7) is exact, ``f c`` is rounded half-up once per step. *Overflow argument*: with
  ``|c| <= C = 2**23 - 1``, ``|f c| <= 255 C < 2**31`` (the int32 product is exact) and
  ``|rshift_round(f c, 8)| <= floor((255 C + 128) / 256) = 8,355,839`` while ``|i g| <= 255 * 128 =
  32,640``, so ``|c'| <= 8,388,479 <= C``: by induction from ``c = 0`` the state never leaves
  ``±(2**23 - 1)`` (real ±256), whatever the inputs, so the saturation to ±C in the code never acts (it
  is kept for safety, like the GRU's). Because ``f <= 255/256``, the real cell state itself is
  bounded by ``1 / (1 - 255/256) = 256``: the format cannot be driven out of range.
* **Output**: ``p = saturate_int8(rshift_round(c', CELL_EXP - e_c))`` at the tanh table's input
  exponent ``e_c`` (calibrated, at least ``TANH_SAT_EXP``: beyond ±4 tanh is saturated in int8 anyway),
  ``t = TANH_C[p + 128]`` (int8 at 7), ``h' = saturate_int8(rshift_round(o t, GATE_EXP))``:
  ``|o t| <= 255 * 128``, so ``h'`` stays in [-127, 127] and that saturation never acts either.
* The uint8 output layer on ``h'`` (exponent 7).

Firmware: template partial ``firmware_templates/actors/lstm.c.j2`` and ``kf_lstm.h`` between five
``kf_dense`` layers.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from sim.config import ACTION_DIM, WorldConfig

from .. import numfmt
from ..numfmt import GATE_EXP, HIDDEN_EXP, INT8_MAX, INT8_MIN, QuantLayer, choose_exp
from .base import (BudgetItem, BudgetSpec, CDefine, CTable, HiddenArch, RenderSpec,
                   dense_summary, sensing_tables, sigmoid)
from .dense import (check_range_options, input_exponent, is_gate_layer, output_layer,
                    quantize_dense, saturated_fraction, value_range)
from .recurrent import (QuantizedRecurrent, RecurrentErrorReport, RecurrentKind, RecurrentPolicy,
                        SequenceCalibration, random_recurrent, recurrent_error_report)

GATES = ("i", "f", "g", "o")
CELL_EXP = GATE_EXP + HIDDEN_EXP  #: the cell state's exponent: i * g lands on it exactly
CELL_MAX = (1 << 23) - 1  #: |c| never exceeds this (module doc: the overflow argument)
MAX_EXP = 14  #: finest exponent of a gate pre-activation or of the cell-state tanh input


# --------------------------------------------------------------------------------------------
# The float actor
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class LSTMPolicy(RecurrentPolicy):
    """A float LSTM actor (see the module doc): arrays in gate order i, f, g, o; invalid contents raise PolicyError."""

    kind: ClassVar[str] = "lstm"
    GATE_COUNT: ClassVar[int] = 4
    GATE_ORDER: ClassVar[str] = "ifgo"  #: PyTorch's order of the four row blocks of w_ih, w_hh, b_ih, b_hh
    STATE_WIDTH: ClassVar[int] = 2  #: the state is [h, c]

    def gates(self, x: np.ndarray, state: np.ndarray) -> dict[str, np.ndarray]:
        """Every intermediate of one step in float64 (calibration): pre-activations, gates, c', tanh(c'), h', u."""
        x = np.asarray(x, np.float64)
        state = np.asarray(state, np.float64)
        H = self.hidden_size
        assert x.shape[-1] == self.in_dim, f"input width {x.shape[-1]} != {self.in_dim}"
        assert state.shape[-1] == 2 * H, f"state width {state.shape[-1]} != {2 * H}"
        h, c = state[..., :H], state[..., H:]
        a = x @ self.w_ih.astype(np.float64).T + self.b_ih + h @ self.w_hh.astype(np.float64).T + self.b_hh
        a_i, a_f, a_g, a_o = (a[..., k * H:(k + 1) * H] for k in range(4))
        i, f, g, o = sigmoid(a_i), sigmoid(a_f), np.tanh(a_g), sigmoid(a_o)
        c2 = f * c + i * g
        tc = np.tanh(c2)
        h2 = o * tc
        out = h2 @ self.w_out.astype(np.float64).T + self.b_out
        return {"a_i": a_i, "a_f": a_f, "a_g": a_g, "a_o": a_o, "i": i, "f": f, "g": g, "o": o, "c": c2,
                "tanh_c": tc, "h": h2, "state": np.concatenate([h2, c2], -1), "u": np.clip(out, 0.0, 1.0)}

def random_lstm_policy(world: WorldConfig, hidden: int, seed: int = 0, scale: float = 1.0, out_bias: float = 0.5,
                       out_scale: float = 1.0, provenance: dict | None = None) -> LSTMPolicy:
    """A deterministic untrained LSTM policy (tests, benchmarks): :func:`~kiloforge.actors.recurrent.random_recurrent`."""
    return random_recurrent(LSTMPolicy, world, hidden, seed, scale, out_bias, out_scale, provenance)


# --------------------------------------------------------------------------------------------
# The int8 actor
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class QuantLSTMCell:
    """An int8 LSTM cell (module doc); :meth:`gates` is the reference integer semantics."""

    i: QuantLayer  #: (H, D + H) over [x, h] -> a_i int8 at i.e_out
    f: QuantLayer
    g: QuantLayer
    o: QuantLayer
    i_table: np.ndarray  #: (256,) uint8 gate_table(i.e_out)
    f_table: np.ndarray  #: (256,) uint8 gate_table(f.e_out)
    g_table: np.ndarray  #: (256,) int8 act_table("tanh", g.e_out, HIDDEN_EXP)
    o_table: np.ndarray  #: (256,) uint8 gate_table(o.e_out)
    c_table: np.ndarray  #: (256,) int8 act_table("tanh", e_c, HIDDEN_EXP)
    e_c: int  #: exponent of the cell state's tanh input (c is requantised to it)

    def __post_init__(self) -> None:
        H, DH = self.i.w.shape
        assert DH > H >= 1, f"gate layers must be (H, D + H), got {self.i.w.shape}"
        for name in GATES:
            l = getattr(self, name)
            assert l.w.shape == (H, DH) and is_gate_layer(l), f"{name}: an (H, D + H) int8 gate layer"
            assert l.e_in == self.i.e_in, "every gate reads [x, h] at one exponent"
        for name in ("i_table", "f_table", "o_table"):
            t = getattr(self, name)
            assert t.shape == (256,) and t.dtype == np.uint8, f"{name} must be (256,) uint8"
        for name in ("g_table", "c_table"):
            t = getattr(self, name)
            assert t.shape == (256,) and t.dtype == np.int8, f"{name} must be (256,) int8"
        assert numfmt.TANH_SAT_EXP <= self.e_c <= CELL_EXP, f"e_c must be in {numfmt.TANH_SAT_EXP}..{CELL_EXP}"

    @property
    def hidden(self) -> int:
        return int(self.i.w.shape[0])

    @property
    def in_dim(self) -> int:
        return int(self.i.w.shape[1]) - self.hidden

    @property
    def layers(self) -> list[QuantLayer]:
        """The four gate layers in firmware order: i, f, g, o."""
        return [self.i, self.f, self.g, self.o]

    @property
    def c_shift(self) -> int:
        """CELL_EXP - e_c: the cell state -> the tanh table's input."""
        return CELL_EXP - self.e_c

    def gates(self, x: np.ndarray, h: np.ndarray, c: np.ndarray) -> dict[str, np.ndarray]:
        """Every integer of one step (int64): a_*, the gates, the new cell state c, p, tanh(c) and the new h."""
        x, h, c = (np.asarray(v, np.int64) for v in (x, h, c))
        xh = np.concatenate([x, h], -1)  # (..., D + H)
        a = {k: numfmt.dense_int(xh, l.w, l.b, l.shift, INT8_MIN, INT8_MAX)
             for k, l in zip(GATES, (self.i, self.f, self.g, self.o))}
        i = self.i_table.astype(np.int64)[a["i"] + 128]
        f = self.f_table.astype(np.int64)[a["f"] + 128]
        g = self.g_table.astype(np.int64)[a["g"] + 128]
        o = self.o_table.astype(np.int64)[a["o"] + 128]
        c2 = numfmt.saturate(numfmt.rshift_round(f * c, GATE_EXP) + i * g, -CELL_MAX, CELL_MAX)
        p = numfmt.saturate(numfmt.rshift_round(c2, self.c_shift), INT8_MIN, INT8_MAX)
        t = self.c_table.astype(np.int64)[p + 128]
        h2 = numfmt.saturate(numfmt.rshift_round(o * t, GATE_EXP), INT8_MIN, INT8_MAX)
        return {"a_i": a["i"], "a_f": a["f"], "a_g": a["g"], "a_o": a["o"], "i": i, "f": f, "g": g, "o": o,
                "c": c2, "p": p, "tanh_c": t, "h": h2}


#: the dense layers in firmware order
LAYER_NAMES = ("i", "f", "g", "o", "out")


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedLSTM(QuantizedRecurrent):
    """The int8 LSTM actor: state ``[h (int8 at HIDDEN_EXP), c (int32 at CELL_EXP)]``, ``q = out(h')`` uint8."""

    kind: ClassVar[str] = "lstm"
    STATE_WIDTH: ClassVar[int] = 2
    cell: QuantLSTMCell

    def step_int(self, x: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: int8 tuples (R, D) and states [h, c] (R, 2H) -> (uint8 commands (R, 2), new states)."""
        H = self.hidden_size
        v = self.cell.gates(x, state[:, :H], state[:, H:])
        o = self.out
        q = numfmt.dense_int(v["h"], o.w, o.b, o.shift, o.lo, o.hi)
        return q.astype(np.uint8), np.concatenate([v["h"], v["c"]], 1)

    def summary(self) -> dict[str, Any]:
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "hidden": self.hidden_size, "hidden_exp": HIDDEN_EXP, "gate_exp": GATE_EXP, "cell_exp": CELL_EXP,
                "e_c": int(self.cell.e_c), "layer_sizes": self.layer_sizes,
                "layers": [dense_summary(n, l) for n, l in zip(LAYER_NAMES, self.layers)],
                "policy_hash": self.policy_hash, "world": self.world.name}

    def describe(self) -> str:
        c = self.cell
        return (f"LSTM: input {self.in_dim} ([a_prev, obs]), {self.hidden_size} hidden units int8 at exponent "
                f"{HIDDEN_EXP}, cell state int32 at exponent {CELL_EXP}, linear output 2; e_in {self.e_in}, "
                f"e_i {c.i.e_out}, e_f {c.f.e_out}, e_g {c.g.e_out}, e_o {c.o.e_out}, e_c {c.e_c}")


# --------------------------------------------------------------------------------------------
# Calibration, quantisation, error report
# --------------------------------------------------------------------------------------------
def quantize_lstm(policy: LSTMPolicy, calib: SequenceCalibration, *, percentile: float = 100.0, headroom: float = 1.0,
                  e_in: int | None = None) -> QuantizedLSTM:
    """Quantise ``policy`` with exponents from the calibration ranges (see the module doc)."""
    check_range_options(percentile, headroom)
    assert calib.seqs.shape[-1] == policy.in_dim, "calibration was recorded for another input width"
    assert calib.states.shape[-1] == 2 * policy.hidden_size, "calibration was recorded for another hidden size"
    e_in = input_exponent(calib.inputs, percentile, headroom, e_in)
    v = calib.values
    H = policy.hidden_size

    def exp_of(key: str, finest_needed: int) -> int:
        return min(MAX_EXP, max(choose_exp(value_range(v[key], percentile, headroom)), finest_needed))

    W = np.concatenate([policy.w_ih.astype(np.float64),
                        policy.w_hh.astype(np.float64) * 2.0 ** (e_in - HIDDEN_EXP)], 1)  # (4H, D + H)
    b = policy.b_ih.astype(np.float64) + policy.b_hh.astype(np.float64)
    layers = {}
    for k, name in enumerate(GATES):
        need = numfmt.TANH_SAT_EXP if name == "g" else numfmt.SIGMOID_SAT_EXP
        layers[name] = quantize_dense(f"gate {name}", W[k * H:(k + 1) * H], b[k * H:(k + 1) * H], e_in,
                                      exp_of(f"a_{name}", need), may_lower_e_out=True)
    e_c = min(CELL_EXP, exp_of("c", numfmt.TANH_SAT_EXP))
    cell = QuantLSTMCell(**layers, i_table=numfmt.gate_table(layers["i"].e_out),
                         f_table=numfmt.gate_table(layers["f"].e_out),
                         g_table=numfmt.act_table("tanh", layers["g"].e_out, HIDDEN_EXP),
                         o_table=numfmt.gate_table(layers["o"].e_out),
                         c_table=numfmt.act_table("tanh", e_c, HIDDEN_EXP), e_c=e_c)
    out = output_layer("output", policy.w_out, policy.b_out, HIDDEN_EXP)
    return QuantizedLSTM(cell=cell, out=out, e_in=e_in, world=policy.world, policy_hash=policy.hash,
                         **sensing_tables(policy.world, e_in))


def lstm_error_report(policy: LSTMPolicy, qp: QuantizedLSTM, calib: SequenceCalibration) -> RecurrentErrorReport:
    """Compare the float and the integer cell on every calibration step (see :class:`RecurrentErrorReport`)."""
    H = qp.hidden_size

    def teacher(xq: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, float]]:
        st = calib.states.reshape(len(xq), -1)
        hq = numfmt.quantize(st[:, :H], HIDDEN_EXP)
        cq = numfmt.saturate(numfmt.round_half_up(st[:, H:] * 2.0 ** CELL_EXP), -CELL_MAX, CELL_MAX)
        gi = qp.cell.gates(xq, hq, cq)
        v, g8 = calib.values, 2.0 ** GATE_EXP
        err = {"i": np.abs(gi["i"] / g8 - v["i"]), "f": np.abs(gi["f"] / g8 - v["f"]),
               "g": np.abs(gi["g"] / 2.0 ** HIDDEN_EXP - v["g"]), "o": np.abs(gi["o"] / g8 - v["o"]),
               "c'": np.abs(gi["c"] / 2.0 ** CELL_EXP - v["c"]), "h'": np.abs(gi["h"] / 2.0 ** HIDDEN_EXP - v["h"])}
        return gi, err, {**{k: saturated_fraction(gi[f"a_{k}"]) for k in GATES}, "c'": saturated_fraction(gi["p"])}

    return recurrent_error_report(LSTM.name, qp, calib, teacher,
                                  {"h": (slice(None, H), HIDDEN_EXP), "c": (slice(H, None), CELL_EXP)})


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
LSTM_CODE_B = 400  #: code of the LSTM step beyond the dense calls (gate tables, cell and state update); estimate
#: (C name suffix, what the layer computes) of the dense layers in firmware order
C_LAYERS = (("I", "a_i = W_i [x, h] + b_i (h columns scaled by 2^(e_in - 7))"),
            ("F", "a_f = W_f [x, h] + b_f (h columns scaled by 2^(e_in - 7))"),
            ("G", "a_g = W_g [x, h] + b_g (h columns scaled by 2^(e_in - 7))"),
            ("O", "a_o = W_o [x, h] + b_o (h columns scaled by 2^(e_in - 7))"),
            ("OUT", "255 u = W_out h + b_out (the uint8 motor commands)"))


def lstm_sizes(in_dim: int, hidden: int) -> list[tuple[int, int]]:
    """(n_out, n_in) of the five dense layers: i, f, g, o over [x, h]; the output.

    >>> lstm_sizes(16, 32)
    [(32, 48), (32, 48), (32, 48), (32, 48), (2, 32)]
    """
    D, H = int(in_dim), int(hidden)
    return [(H, D + H)] * 4 + [(ACTION_DIM, H)]


class LSTMKind(RecurrentKind):
    """The recurrent LSTM actor (the thesis's MAGRDPG)."""

    name: ClassVar[str] = "lstm"
    template: ClassVar[str] = "actors/lstm.c.j2"
    c_sources: ClassVar[tuple[str, ...]] = ("kf_lstm.h",)
    policy_type: ClassVar[type[RecurrentPolicy]] = LSTMPolicy
    quantizer = staticmethod(quantize_lstm)
    reporter = staticmethod(lstm_error_report)
    sizes = staticmethod(lstm_sizes)
    c_layers = C_LAYERS
    code_b = LSTM_CODE_B

    def budget_spec(self, world: WorldConfig, arch: HiddenArch, e_in: int) -> BudgetSpec:
        D, H, T = world.tuple_dim, arch.hidden, numfmt.TABLE_SIZE
        return self.cell_budget(world, arch, "int8 h, int32 c",
                                BudgetItem("flash", "gate tables", 5 * T, "3 sigmoid (uint8), 2 tanh (int8)"),
                                BudgetItem("sram", "hidden + cell state + input", H + 4 * H + D,
                                           f"{H} int8 + {H} int32 + {D} int8"),
                                BudgetItem("sram", "gate buffers", 2 * H + 2 * H, f"{H} int16 + {H} uint8 + {H} int8"))

    def render_spec(self, qp: QuantizedLSTM) -> RenderSpec:
        H, c = qp.hidden_size, qp.cell
        return self.cell_render(qp, [
            CTable("KF_GATE_I", "uint8_t", c.i_table,
                   f"i = sigmoid(a_i) at exponent {GATE_EXP}; index a_i + 128, a_i at exponent {c.i.e_out}"),
            CTable("KF_GATE_F", "uint8_t", c.f_table,
                   f"f = sigmoid(a_f) at exponent {GATE_EXP}; index a_f + 128, a_f at exponent {c.f.e_out}"),
            CTable("KF_TANH_G", "int8_t", c.g_table,
                   f"g = tanh(a_g) at exponent {HIDDEN_EXP}; index a_g + 128, a_g at exponent {c.g.e_out}"),
            CTable("KF_GATE_O", "uint8_t", c.o_table,
                   f"o = sigmoid(a_o) at exponent {GATE_EXP}; index a_o + 128, a_o at exponent {c.o.e_out}"),
            CTable("KF_TANH_C", "int8_t", c.c_table,
                   f"tanh(c) at exponent {HIDDEN_EXP}; index p + 128, p = c at exponent {c.e_c}"),
        ], f"int8 h at exponent {HIDDEN_EXP}, int32 c at exponent {CELL_EXP}", (
            CDefine("KF_Y_LEN", H, "uint16_t", "scratch: one gate vector (int16)"),
            CDefine("KF_GATE_EXP", GATE_EXP, comment="gates are uint8 at this exponent"),
            CDefine("KF_CELL_MAX", CELL_MAX, "int32_t", "|c| never exceeds this (kiloforge/actors/lstm.py)"),
            CDefine("KF_C_SHIFT", c.c_shift, comment=f"c at exponent {CELL_EXP} -> the tanh input at e_c {c.e_c}")))


LSTM = LSTMKind()
