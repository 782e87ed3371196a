"""Actor kind ``"gru"``: a GRU cell over one ``[a_prev, obs]`` tuple per step and a linear output (MAGRDPG).

Float actor (PyTorch's ``torch.nn.GRUCell``, gate order r, z, n; Algorithm 5: ``a_0 = 0``, the
hidden state ``h`` zero at the start of an episode)::

    r  = σ(W_ir x + b_ir + W_hr h + b_hr)
    z  = σ(W_iz x + b_iz + W_hz h + b_hz)
    n  = tanh(W_in x + b_in + r ⊙ (W_hn h + b_hn))
    h' = (1 − z) ⊙ n + z ⊙ h
    u  = clip01(W_out h' + b_out)                        (u_left, u_right) in [0, 1]

Artifact arrays: ``w_ih`` (3H, D), ``w_hh`` (3H, H), ``b_ih`` (3H,), ``b_hh`` (3H,), ``w_out`` (2, H),
``b_out`` (2,) float32, rows in gate order r, z, n exactly as PyTorch stores them; meta: ``hidden``,
``input_dim``, ``gate_order "rzn"``, ``input "a_prev+obs"``.

The int8 cell (number format of :mod:`kiloforge.numfmt`), on the int8 tuple ``x`` at ``e_in`` and
the int8 hidden state ``h``:

* **Hidden state**: ``int8`` at ``HIDDEN_EXP = 7`` (real ``h / 128``), kept in SRAM between control
  steps, zero after ``setup()``. The candidate ``n`` (a tanh) is at the same exponent, so the state
  never leaves ``[-128, 127]``.
* **Gate pre-activations** are dense layers (int8 weights with per-row exponents, int32 bias and
  accumulator, half-up requantisation, saturation to int8): ``a_r`` and ``a_z`` read the
  concatenation ``[x, h]`` (``kf_dense2``'s two segments, no copy); the columns of ``h`` are
  quantised from the float weights times ``2**(e_in - HIDDEN_EXP)``, so one accumulator exponent
  serves both parts. ``a_r`` has its exponent ``e_r``, ``a_z`` its ``e_z``; ``nx = W_in x + b_in``
  and ``nh = W_hn h + b_hn`` are requantised to ``e_nx`` and ``e_nh``.
* **Gates**: ``r = R[a_r + 128]`` and ``k = K[a_z + 128]`` from 256-entry **uint8** tables at
  ``GATE_EXP = 8`` (real ``g / 256``; :func:`~kiloforge.numfmt.gate_table`): ``R`` is σ, ``K`` is
  ``1 - σ`` (``k = 1 - z``: a saturated "keep" gate is exactly 0, so a GRU that holds its state holds
  it bit for bit; 1.0 itself saturates to 255/256).
* **Candidate**: ``p = saturate_int8(nx * 2**s_nx + rshift_round(r * nh, s_rn))`` at the table's
  exponent ``e_n = e_nx + s_nx`` (``s_nx >= 0``: an exact left shift, written as a multiply in C),
  with ``s_rn = GATE_EXP + e_nh - e_n >= 0`` (the gate × state product at exponent ``8 + e_nh``,
  rounded half-up to ``e_n``), then ``n = TANH[p + 128]`` (``act_table("tanh", e_n, 7)``).
* **Table exponents**: a table's input exponent need not cover the whole calibrated range, only
  where the function still changes (``SIGMOID_SAT_EXP``, ``TANH_SAT_EXP``); the quantiser takes the
  finer of that and the calibrated exponent, and larger values saturate to the same entry.
* **State update**: ``h' = saturate_int8(h + rshift_round(k * (n - h), GATE_EXP))``, i.e.
  ``(1 - z) n + z h`` with one gate × state product rounded half-up. ``|k (n - h)| / 256 < |n - h|``,
  so ``h'`` lies between ``h`` and ``n`` and the saturation never acts (kept for safety).
* **Output**: the uint8 output layer on ``h'`` (exponent 7).

Every product is formed in int32 (``|r * nh| <= 32,640``, ``|k (n - h)| <= 65,025``). Firmware:
template partial ``firmware_templates/actors/gru.c.j2`` and ``kf_gru.h`` between five ``kf_dense``
layers.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from sim.config import ACTION_DIM, WorldConfig

from .. import numfmt
from ..errors import QuantizeError
from ..numfmt import GATE_EXP, HIDDEN_EXP, INT8_MAX, INT8_MIN, MAX_SHIFT, QuantLayer, choose_exp
from .base import (BudgetItem, BudgetSpec, CDefine, CTable, HiddenArch, RenderSpec,
                   dense_summary, sensing_tables, sigmoid)
from .dense import (check_range_options, input_exponent, is_gate_layer, output_layer,
                    quantize_dense, saturated_fraction, value_range)
from .recurrent import (QuantizedRecurrent, RecurrentErrorReport, RecurrentKind, RecurrentPolicy,
                        SequenceCalibration, random_recurrent, recurrent_error_report)

MAX_NX_SHIFT = 7  #: nx -> e_n is a multiply by 2^nx_shift of an int8 value (fits int16)


# --------------------------------------------------------------------------------------------
# The float actor
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GRUPolicy(RecurrentPolicy):
    """A float GRU actor (see the module doc): arrays in gate order r, z, n; invalid contents raise PolicyError."""

    kind: ClassVar[str] = "gru"
    GATE_COUNT: ClassVar[int] = 3
    GATE_ORDER: ClassVar[str] = "rzn"  #: PyTorch's order of the three row blocks of w_ih, w_hh, b_ih, b_hh
    STATE_WIDTH: ClassVar[int] = 1  #: the state is h

    def gates(self, x: np.ndarray, h: np.ndarray) -> dict[str, np.ndarray]:
        """Every intermediate of one step in float64 (calibration): pre-activations and gates, h' and u."""
        x = np.asarray(x, np.float64)
        h = np.asarray(h, np.float64)
        assert x.shape[-1] == self.in_dim, f"input width {x.shape[-1]} != {self.in_dim}"
        assert h.shape[-1] == self.hidden_size, f"hidden width {h.shape[-1]} != {self.hidden_size}"
        H = self.hidden_size
        gi = x @ self.w_ih.astype(np.float64).T + self.b_ih  # (..., 3H)
        gh = h @ self.w_hh.astype(np.float64).T + self.b_hh  # (..., 3H)
        a_r = gi[..., :H] + gh[..., :H]
        a_z = gi[..., H:2 * H] + gh[..., H:2 * H]
        nx, nh = gi[..., 2 * H:], gh[..., 2 * H:]
        r, z = sigmoid(a_r), sigmoid(a_z)
        pre_n = nx + r * nh
        n = np.tanh(pre_n)
        h2 = (1.0 - z) * n + z * h
        out = h2 @ self.w_out.astype(np.float64).T + self.b_out  # (..., 2)
        return {"a_r": a_r, "a_z": a_z, "nx": nx, "nh": nh, "r": r, "z": z, "pre_n": pre_n, "n": n,
                "h": h2, "state": h2, "out": out, "u": np.clip(out, 0.0, 1.0)}


def random_gru_policy(world: WorldConfig, hidden: int, seed: int = 0, scale: float = 1.0, out_bias: float = 0.5,
                      out_scale: float = 1.0, provenance: dict | None = None) -> GRUPolicy:
    """A deterministic untrained GRU policy (tests, benchmarks): :func:`~kiloforge.actors.recurrent.random_recurrent`."""
    return random_recurrent(GRUPolicy, world, hidden, seed, scale, out_bias, out_scale,
                            provenance or {"notes": f"random_gru_policy seed {seed}"})


# --------------------------------------------------------------------------------------------
# The int8 actor
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class QuantGRUCell:
    """An int8 GRU cell (module doc); :meth:`gates` is the reference integer semantics."""

    r: QuantLayer  #: (H, D + H) over [x, h] -> a_r int8 at r.e_out
    z: QuantLayer  #: (H, D + H) over [x, h] -> a_z int8 at z.e_out
    nx: QuantLayer  #: (H, D) over x -> W_in x + b_in int8 at e_nx
    nh: QuantLayer  #: (H, H) over h -> W_hn h + b_hn int8 at e_nh
    r_table: np.ndarray  #: (256,) uint8 gate_table(r.e_out)
    k_table: np.ndarray  #: (256,) uint8 gate_table(z.e_out, complement=True): 1 - z
    n_table: np.ndarray  #: (256,) int8 act_table("tanh", e_n, HIDDEN_EXP), e_n = nx.e_out + nx_shift
    rn_shift: int  #: GATE_EXP + nh.e_out - e_n: r * nh -> exponent e_n
    nx_shift: int = 0  #: e_n - nx.e_out >= 0: nx -> exponent e_n (exact left shift)

    def __post_init__(self) -> None:
        H, DH = self.r.w.shape
        D = DH - H
        assert D >= 1 and self.z.w.shape == (H, DH), f"r and z must be (H, D + H), got {self.r.w.shape}, {self.z.w.shape}"
        assert self.nx.w.shape == (H, D) and self.nh.w.shape == (H, H), "nx must be (H, D), nh (H, H)"
        for name in ("r", "z", "nx", "nh"):
            assert is_gate_layer(getattr(self, name)), f"{name}: gate layers requantise to int8 with no activation of their own"
        assert self.nh.e_in == HIDDEN_EXP, f"nh reads h at exponent {HIDDEN_EXP}, not {self.nh.e_in}"
        assert self.r.e_in == self.z.e_in == self.nx.e_in, "r, z and nx read x at one exponent"
        for name in ("r_table", "k_table"):
            t = getattr(self, name)
            assert t.shape == (256,) and t.dtype == np.uint8, f"{name} must be (256,) uint8"
        assert self.n_table.shape == (256,) and self.n_table.dtype == np.int8, "n_table must be (256,) int8"
        assert 0 <= self.nx_shift <= MAX_NX_SHIFT, f"nx_shift must be in 0..{MAX_NX_SHIFT}, got {self.nx_shift}"
        assert self.rn_shift == GATE_EXP + self.nh.e_out - self.e_n and 0 <= self.rn_shift <= MAX_SHIFT, \
            f"rn_shift {self.rn_shift} != {GATE_EXP} + e_nh {self.nh.e_out} - e_n {self.e_n} (or out of range)"

    @property
    def layers(self) -> list[QuantLayer]:
        """The four dense layers in firmware order: r, z, nx, nh."""
        return [self.r, self.z, self.nx, self.nh]

    @property
    def e_n(self) -> int:
        """Exponent of the candidate's pre-activation (the tanh table's input)."""
        return self.nx.e_out + self.nx_shift

    @property
    def hidden(self) -> int:
        return int(self.r.w.shape[0])

    @property
    def in_dim(self) -> int:
        return int(self.nx.w.shape[1])

    def gates(self, x: np.ndarray, h: np.ndarray) -> dict[str, np.ndarray]:
        """Every integer of one step (int64): a_r, a_z, r, k, nx, nh, pre_n, n and the new state h."""
        x = np.asarray(x, np.int64)
        h = np.asarray(h, np.int64)
        xh = np.concatenate([x, h], -1)  # (..., D + H)
        a_r = numfmt.dense_int(xh, self.r.w, self.r.b, self.r.shift, INT8_MIN, INT8_MAX)
        a_z = numfmt.dense_int(xh, self.z.w, self.z.b, self.z.shift, INT8_MIN, INT8_MAX)
        r = self.r_table.astype(np.int64)[a_r + 128]
        k = self.k_table.astype(np.int64)[a_z + 128]
        nx = numfmt.dense_int(x, self.nx.w, self.nx.b, self.nx.shift, INT8_MIN, INT8_MAX)
        nh = numfmt.dense_int(h, self.nh.w, self.nh.b, self.nh.shift, INT8_MIN, INT8_MAX)
        pre = numfmt.saturate(nx * (1 << self.nx_shift) + numfmt.rshift_round(r * nh, self.rn_shift),
                              INT8_MIN, INT8_MAX)
        n = self.n_table.astype(np.int64)[pre + 128]
        h2 = numfmt.saturate(h + numfmt.rshift_round(k * (n - h), GATE_EXP), INT8_MIN, INT8_MAX)
        return {"a_r": a_r, "a_z": a_z, "r": r, "k": k, "nx": nx, "nh": nh, "pre_n": pre, "n": n, "h": h2}

    def step(self, x: np.ndarray, h: np.ndarray) -> np.ndarray:
        """The new hidden state (int64, same shape as h) for int8 inputs x (..., D) and states h (..., H)."""
        return self.gates(x, h)["h"]


#: which float value each dense layer's exponent must cover, in firmware order
LAYER_NAMES = ("r", "z", "nx", "nh", "out")


@dataclass(frozen=True, eq=False, kw_only=True)
class QuantizedGRU(QuantizedRecurrent):
    """The int8 GRU actor: ``h' = cell.step(x, h)``, ``q = out(h')`` uint8; ``h`` int8 at HIDDEN_EXP."""

    kind: ClassVar[str] = "gru"
    STATE_WIDTH: ClassVar[int] = 1
    cell: QuantGRUCell

    def step_int(self, x: np.ndarray, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One control step: int8 tuples (R, D) and states (R, H) -> (uint8 commands (R, 2), new states)."""
        h2 = self.cell.step(x, h)
        o = self.out
        q = numfmt.dense_int(h2, o.w, o.b, o.shift, o.lo, o.hi)
        return q.astype(np.uint8), h2

    def summary(self) -> dict[str, Any]:
        c = self.cell
        return {"kind": self.kind, "format": self.format_name, "rounding": self.rounding, "e_in": int(self.e_in),
                "hidden": self.hidden_size, "hidden_exp": HIDDEN_EXP, "gate_exp": GATE_EXP,
                "rn_shift": int(c.rn_shift), "nx_shift": int(c.nx_shift), "e_n": int(c.e_n),
                "layer_sizes": self.layer_sizes,
                "layers": [dense_summary(n, l) for n, l in zip(LAYER_NAMES, self.layers)],
                "policy_hash": self.policy_hash, "world": self.world.name}

    def describe(self) -> str:
        c = self.cell
        return (f"GRU: input {self.in_dim} ([a_prev, obs]), {self.hidden_size} hidden units int8 at exponent "
                f"{HIDDEN_EXP}, linear output 2; e_in {self.e_in}, e_r {c.r.e_out}, e_z {c.z.e_out}, "
                f"e_nx {c.nx.e_out}, e_nh {c.nh.e_out}, e_n {c.e_n}")


# --------------------------------------------------------------------------------------------
# Calibration, quantisation, error report
# --------------------------------------------------------------------------------------------
def quantize_gru(policy: GRUPolicy, calib: SequenceCalibration, *, percentile: float = 100.0, headroom: float = 1.0,
                 e_in: int | None = None, gate_exp_max: int | None = None) -> QuantizedGRU:
    """Quantise ``policy`` with exponents from the calibration ranges (see the module doc).

    The input exponent as for every kind; one exponent per gate pre-activation (``e_r``, ``e_z``,
    ``e_nx``, ``e_nh``, ``e_n``; the table inputs at least SIGMOID_SAT_EXP / TANH_SAT_EXP) and per row
    the weight exponent with the overflow proof. ``gate_exp_max`` caps the gate pre-activation
    exponents (a smaller exponent covers a wider range of the tables at a coarser step).
    """
    check_range_options(percentile, headroom)
    assert calib.seqs.shape[-1] == policy.in_dim, "calibration was recorded for another input width"
    assert calib.states.shape[-1] == policy.hidden_size, "calibration was recorded for another hidden size"
    e_in = input_exponent(calib.inputs, percentile, headroom, e_in)
    v = calib.values
    H = policy.hidden_size
    cap = 14 if gate_exp_max is None else int(gate_exp_max)

    def exp_of(*keys: str, finest_needed: int | None = None) -> int:
        e = choose_exp(max(value_range(v[k], percentile, headroom) for k in keys))
        if finest_needed is not None:  # a table input: beyond its saturation every value reads the same entry
            e = max(e, finest_needed)
        return min(cap, e)

    W_ih, W_hh = policy.w_ih.astype(np.float64), policy.w_hh.astype(np.float64)
    b_ih, b_hh = policy.b_ih.astype(np.float64), policy.b_hh.astype(np.float64)
    h_scale = 2.0 ** (e_in - HIDDEN_EXP)  # h columns: real h = h_int 2^-7, read at the nominal exponent e_in
    blk = [slice(0, H), slice(H, 2 * H), slice(2 * H, 3 * H)]
    r, z = (quantize_dense(f"gate {name}", np.concatenate([W_ih[blk[g]], W_hh[blk[g]] * h_scale], 1),
                           b_ih[blk[g]] + b_hh[blk[g]], e_in,
                           exp_of(f"a_{name}", finest_needed=numfmt.SIGMOID_SAT_EXP), may_lower_e_out=True)
            for g, name in ((0, "r"), (1, "z")))
    e_n = exp_of("pre_n", finest_needed=numfmt.TANH_SAT_EXP)  # the tanh table's input
    l_nx = quantize_dense("n (input part)", W_ih[blk[2]], b_ih[blk[2]], e_in, min(exp_of("nx"), e_n),
                          may_lower_e_out=True)
    e_n = max(e_n, l_nx.e_out)  # nx_shift = e_n - e_nx >= 0 (l_nx may have chosen a coarser grid)
    if e_n - l_nx.e_out > MAX_NX_SHIFT:  # pragma: no cover - weights far larger than any trained GRU's
        raise QuantizeError("the candidate's input part needs a much coarser exponent than its table")
    e_nh = max(exp_of("nh"), e_n - GATE_EXP)  # rn_shift = 8 + e_nh - e_n >= 0
    l_nh = quantize_dense("n (hidden part)", W_hh[blk[2]], b_hh[blk[2]], HIDDEN_EXP, e_nh, may_lower_e_out=True)
    if l_nh.e_out < e_n - GATE_EXP:  # pragma: no cover - needs weights ~2^8 larger than the input part's
        raise QuantizeError("the candidate's hidden part needs a coarser exponent than the format allows")
    cell = QuantGRUCell(r=r, z=z, nx=l_nx, nh=l_nh, r_table=numfmt.gate_table(r.e_out),
                        k_table=numfmt.gate_table(z.e_out, complement=True),
                        n_table=numfmt.act_table("tanh", e_n, HIDDEN_EXP),
                        rn_shift=GATE_EXP + l_nh.e_out - e_n, nx_shift=e_n - l_nx.e_out)
    out = output_layer("output", policy.w_out, policy.b_out, HIDDEN_EXP)
    return QuantizedGRU(cell=cell, out=out, e_in=e_in, world=policy.world, policy_hash=policy.hash,
                        **sensing_tables(policy.world, e_in))


def gru_error_report(policy: GRUPolicy, qp: QuantizedGRU, calib: SequenceCalibration) -> RecurrentErrorReport:
    """Compare the float and the integer cell on every calibration step (see :class:`RecurrentErrorReport`)."""
    def teacher(xq: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, float]]:
        gi = qp.cell.gates(xq, numfmt.quantize(calib.states.reshape(len(xq), -1), HIDDEN_EXP))
        v = calib.values
        err = {"r": np.abs(gi["r"] / 2.0 ** GATE_EXP - v["r"]),
               "1-z": np.abs(gi["k"] / 2.0 ** GATE_EXP - (1.0 - v["z"])),
               "n": np.abs(gi["n"] / 2.0 ** HIDDEN_EXP - v["n"]), "h'": np.abs(gi["h"] / 2.0 ** HIDDEN_EXP - v["h"])}
        return gi, err, {k: saturated_fraction(gi[a]) for k, a in (("r", "a_r"), ("1-z", "a_z"), ("n", "pre_n"))}

    return recurrent_error_report(GRU.name, qp, calib, teacher, {"h": (slice(None), HIDDEN_EXP)})


# --------------------------------------------------------------------------------------------
# The kind
# --------------------------------------------------------------------------------------------
GRU_CODE_B = 300  #: code of the GRU step beyond the dense calls (gate tables, n, state update); estimate
#: (C name suffix, what the layer computes) of the dense layers in firmware order
C_LAYERS = (("R", "a_r = W_r [x, h] + b_r (h columns scaled by 2^(e_in - 7))"),
            ("Z", "a_z = W_z [x, h] + b_z (h columns scaled by 2^(e_in - 7))"),
            ("NX", "W_in x + b_in"),
            ("NH", "W_hn h + b_hn"),
            ("OUT", "255 u = W_out h + b_out (the uint8 motor commands)"))


def gru_sizes(in_dim: int, hidden: int) -> list[tuple[int, int]]:
    """(n_out, n_in) of the five dense layers: r, z over [x, h]; n over x; n over h; the output.

    >>> gru_sizes(16, 32)
    [(32, 48), (32, 48), (32, 16), (32, 32), (2, 32)]
    """
    D, H = int(in_dim), int(hidden)
    return [(H, D + H), (H, D + H), (H, D), (H, H), (ACTION_DIM, H)]


class GRUKind(RecurrentKind):
    """The recurrent GRU actor (MAGRDPG)."""

    name: ClassVar[str] = "gru"
    template: ClassVar[str] = "actors/gru.c.j2"
    c_sources: ClassVar[tuple[str, ...]] = ("kf_gru.h",)
    policy_type: ClassVar[type[RecurrentPolicy]] = GRUPolicy
    quantizer = staticmethod(quantize_gru)
    reporter = staticmethod(gru_error_report)
    sizes = staticmethod(gru_sizes)
    c_layers = C_LAYERS
    code_b = GRU_CODE_B

    def budget_spec(self, world: WorldConfig, arch: HiddenArch, e_in: int) -> BudgetSpec:
        D, H, T = world.tuple_dim, arch.hidden, numfmt.TABLE_SIZE
        return self.cell_budget(world, arch, "int8 state",
                                BudgetItem("flash", "gate tables", 3 * T, "sigmoid, 1 - sigmoid (uint8), tanh (int8)"),
                                BudgetItem("sram", "hidden state + input", H + D, f"{H} + {D} int8"),
                                BudgetItem("sram", "gate buffers", 2 * 2 * H + H, f"{2 * H} int16 + {H} uint8"))

    def render_spec(self, qp: QuantizedGRU) -> RenderSpec:
        H, c = qp.hidden_size, qp.cell
        return self.cell_render(qp, [
            CTable("KF_GATE_R", "uint8_t", c.r_table,
                   f"r = sigmoid(a_r) at exponent {GATE_EXP}; index a_r + 128, a_r at exponent {c.r.e_out}"),
            CTable("KF_GATE_K", "uint8_t", c.k_table,
                   f"k = 1 - sigmoid(a_z) at exponent {GATE_EXP}; index a_z + 128, a_z at exponent {c.z.e_out}"),
            CTable("KF_TANH", "int8_t", c.n_table,
                   f"n = tanh(p) at exponent {HIDDEN_EXP}; index p + 128, p at exponent {c.e_n}"),
        ], f"int8 state at exponent {HIDDEN_EXP}", (
            CDefine("KF_Y_LEN", 2 * H, "uint16_t", "scratch: two gate vectors (int16)"),
            CDefine("KF_GATE_EXP", GATE_EXP, comment="gates are uint8 at this exponent"),
            CDefine("KF_RN_SHIFT", c.rn_shift, comment=f"r * (W_hn h + b_hn): exponent {GATE_EXP} + e_nh "
                                                       f"{c.nh.e_out} -> e_n {c.e_n}"),
            CDefine("KF_NX_SHIFT", c.nx_shift, comment=f"W_in x + b_in: exponent e_nx {c.nx.e_out} -> e_n {c.e_n} "
                                                       "(left shift)")))


GRU = GRUKind()
