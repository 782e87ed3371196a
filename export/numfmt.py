"""The fixed-point number format: the single source of truth for quantiser, renderer and emulator.

Everything the firmware computes with is defined here, and the C constants are rendered from here.

Format
------
* **Tensors** (inputs, hidden activations) are ``int8`` with a per-tensor power-of-two exponent
  ``e``: real value = ``q * 2**-e``.
* **Weights** are ``int8`` with a per-output-row exponent ``ew[j]`` (per-channel power-of-two scales).
* **Biases** are ``int32`` at the accumulator's exponent ``ew[j] + e_in``.
* **Accumulator**: the reference is ``int32``: ``acc = bias[j] + Σ_i W[j, i] * x[i]``. A narrower
  (24-bit) accumulator may be used on AVR only for layers where :func:`acc_bound` proves
  ``|acc| < 2**23`` for every input.
* **Requantisation**: ``y = clamp(rshift_round(acc, s[j]), lo, hi)`` with
  ``s[j] = ew[j] + e_in - e_out >= 0``. Rounding rule **half-up** (towards +inf on ties):
  ``rshift_round(a, s) = (a + (1 << (s - 1))) >> s`` for ``s > 0`` with an arithmetic
  (flooring) shift, and ``a`` for ``s == 0``. Saturation: clamp to ``[lo, hi]``.
* **Hidden layers**: requantise to the pre-activation ``int8`` (``lo, hi = -128, 127``) at exponent
  ``e_z``, then the activation: ReLU is ``max(0, z)`` (same exponent); ELU, tanh and sigmoid are
  256-entry ``int8`` tables indexed by ``z + 128`` mapping to exponent ``e_a``; identity is nothing.
* **Output layer**: its real output is ``255 * u`` (the quantiser folds the 255 into the float
  weights), at exponent 0, clamped to ``[0, 255]``: the uint8 motor command ``q``, ``u = q / 255``
  (the same map as :func:`sim.motion.action_to_u8`).
* **Observations** are ``int8`` at exponent ``e_in`` (the first layer's input exponent): wall flag
  ``1 << e_in``; target ``-(1 << e_in)`` when not heard, else ``TGT[d]`` from a 256-entry table
  indexed by the uint8 distance; neighbour flag ``1 << e_in``; RBF bin k = saturate_int8(Σ RBF[k][d])
  over table entries (table ``uint8``, 0 beyond the communication radius). Previous actions enter
  the history as ``ACT[q]`` (a 256-entry table of ``round_half_up(q / 255 * 2**e_in)``).
* No floats, no division, no malloc in the control step; C uses only ``<stdint.h>`` types and casts
  to ``int32_t`` before every multiply, so it never depends on the width of ``int``.

The GRU cell (recurrent actors, :class:`QuantGRUCell`)
-----------------------------------------------------
PyTorch's GRU (gate order r, z, n) on one int8 input tuple ``x`` (exponent ``e_x``, the
observation exponent: ``[ACT[q_l], ACT[q_r], obs]``) and the int8 hidden state ``h``:

* **Hidden state**: ``int8`` at the fixed exponent ``HIDDEN_EXP = 7`` (real ``h / 128``), kept in
  SRAM between control steps, zero after ``setup()``. The candidate ``n`` (a tanh) is at the same
  exponent, so the state never leaves ``[-128, 127]``.
* **Gate pre-activations** are dense layers of the format above (int8 weights with per-row
  exponents, int32 bias and accumulator, half-up requantisation, saturation to int8):
  ``a_r`` and ``a_z`` read the concatenation ``[x, h]`` (``kf_dense2``'s two segments, no copy);
  the columns of ``h`` are quantised from the float weights times ``2**(e_x - HIDDEN_EXP)``, so one
  accumulator exponent serves both parts. ``a_r`` has its exponent ``e_r``, ``a_z`` its ``e_z``;
  ``nx = W_in x + b_in`` and ``nh = W_hn h + b_hn`` are requantised to ``e_nx`` and ``e_nh``.
* **Gates**: ``r = R[a_r + 128]`` and ``k = K[a_z + 128]`` from 256-entry **uint8** tables at
  ``GATE_EXP = 8`` (real ``g / 256``; :func:`gate_table`): ``R`` is σ, ``K`` is ``1 - σ``
  (``k = 1 - z``: a saturated "keep" gate is exactly 0, so a GRU that holds its state holds it
  bit for bit; 1.0 itself saturates to 255/256).
* **Candidate**: ``p = saturate_int8(nx * 2**s_nx + rshift_round(r * nh, s_rn))`` at the table's
  exponent ``e_n = e_nx + s_nx`` (``s_nx >= 0``: an exact left shift, written as a multiply in C),
  with ``s_rn = GATE_EXP + e_nh - e_n >= 0`` (the gate × state product at exponent ``8 + e_nh``,
  rounded half-up to ``e_n``), then ``n = TANH[p + 128]`` (:func:`act_table` ``("tanh", e_n, 7)``).
* **Table exponents**: a table's input exponent need not cover the whole calibrated range, only the
  part where the function still changes: ``SIGMOID_SAT_EXP = 4`` (±8 covers where the uint8 σ table
  reaches 0 and 255) and ``TANH_SAT_EXP = 5`` (±4 covers where the int8 tanh reaches ±127/128). The
  quantiser takes the finer of that and the calibrated exponent; larger values saturate to the same
  table entry the exact value would give.
* **State update**: ``h' = saturate_int8(h + rshift_round(k * (n - h), GATE_EXP))``, i.e.
  ``(1 - z) n + z h`` with one gate × state product rounded half-up. ``|k (n - h)| / 256 < |n - h|``,
  so ``h'`` lies between ``h`` and ``n`` and the saturation never acts (kept for safety).
* **Output**: the output layer of the MLP format on ``h'`` (exponent 7): ``q = clamp(..., 0, 255)``.

Every product is formed in int32 (``|r * nh| <= 32,640``, ``|k (n - h)| <= 65,025``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FORMAT_NAME = "kf-int8-pow2-v1"  #: rendered into the C banner and the manifest
ROUNDING = "half-up"  #: the one rounding rule (documented above)
INT8_MIN, INT8_MAX = -128, 127
ACC_BITS_REFERENCE = 32
ACC_BITS_NARROW = 24
DEFAULT_INPUT_EXP = 6  #: observations in [-2, 2) with 1/64 resolution
MAX_SHIFT = 30
ACTIVATIONS = ("elu", "relu", "tanh", "sigmoid", "identity")


def round_half_up(x: np.ndarray | float) -> np.ndarray:
    """Round to nearest integer, ties towards +inf (the format's rounding rule), as int64.

    >>> round_half_up(np.array([-1.5, -0.5, 0.5, 1.5, 2.4])).tolist()
    [-1, 0, 1, 2, 2]
    """
    return np.floor(np.asarray(x, dtype=np.float64) + 0.5).astype(np.int64)


def rshift_round(acc: np.ndarray, shift: np.ndarray | int) -> np.ndarray:
    """Arithmetic right shift with half-up rounding; shift 0 is the identity. int64 in, int64 out.

    >>> rshift_round(np.array([5, -5, 6, -6, 7]), 1).tolist()
    [3, -2, 3, -3, 4]
    >>> rshift_round(np.array([-7]), 0).tolist()
    [-7]
    """
    acc = np.asarray(acc, dtype=np.int64)
    s = np.asarray(shift, dtype=np.int64)
    rounding = np.where(s > 0, np.left_shift(np.int64(1), np.maximum(s - 1, 0)), 0)
    return np.right_shift(acc + rounding, s)


def saturate(x: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Clamp to [lo, hi] (int64).

    >>> saturate(np.array([-300, 5, 300]), -128, 127).tolist()
    [-128, 5, 127]
    """
    return np.clip(np.asarray(x, dtype=np.int64), lo, hi)


def quantize(x: np.ndarray, exp: int, lo: int = INT8_MIN, hi: int = INT8_MAX) -> np.ndarray:
    """Real values → integers at exponent ``exp`` (half-up, saturating).

    >>> quantize(np.array([0.5, -1.0, 3.0]), 6).tolist()
    [32, -64, 127]
    """
    return saturate(round_half_up(np.asarray(x, np.float64) * (2.0 ** exp)), lo, hi)


def dequantize(q: np.ndarray, exp: int) -> np.ndarray:
    """Integers at exponent ``exp`` → float64."""
    return np.asarray(q, np.float64) * (2.0 ** -exp)


def dense_int(x: np.ndarray, w: np.ndarray, b: np.ndarray, shift: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """The reference integer layer: ``clamp(rshift_round(b + W @ x, shift), lo, hi)``.

    ``x`` (..., n_in) ints; ``w`` (n_out, n_in) int8; ``b`` (n_out,) int32; ``shift`` (n_out,).
    Computed in int64, then checked to fit the int32 reference accumulator.
    """
    acc = np.asarray(x, np.int64) @ np.asarray(w, np.int64).T + np.asarray(b, np.int64)  # (..., n_out)
    assert np.all(np.abs(acc) < 2 ** 31), "int32 accumulator overflow (the quantiser must prevent this)"
    return saturate(rshift_round(acc, np.asarray(shift, np.int64)), lo, hi)


def acc_bound(w: np.ndarray, b: np.ndarray, x_lo: int = INT8_MIN, x_hi: int = INT8_MAX) -> np.ndarray:
    """Largest |acc| per row over every input in [x_lo, x_hi]^n_in (int64, shape (n_out,))."""
    w = np.asarray(w, np.int64)
    hi_part = np.where(w > 0, w * x_hi, w * x_lo).sum(axis=1) + np.asarray(b, np.int64)
    lo_part = np.where(w > 0, w * x_lo, w * x_hi).sum(axis=1) + np.asarray(b, np.int64)
    return np.maximum(np.abs(hi_part), np.abs(lo_part))


def fits_acc24(w: np.ndarray, b: np.ndarray) -> bool:
    """True when a 24-bit signed accumulator provably cannot overflow for any int8 input."""
    return bool(np.all(acc_bound(w, b) < 2 ** (ACC_BITS_NARROW - 1)))


# --- activation functions and their tables ---------------------------------------------------
def act_float(name: str, z: np.ndarray) -> np.ndarray:
    """The float activation (float64)."""
    z = np.asarray(z, np.float64)
    if name == "elu":
        return np.where(z > 0, z, np.expm1(np.minimum(z, 0.0)))
    if name == "relu":
        return np.maximum(z, 0.0)
    if name == "tanh":
        return np.tanh(z)
    if name == "sigmoid":
        return 1.0 / (1.0 + np.exp(-z))
    if name == "identity":
        return z
    raise ValueError(f"unsupported activation '{name}'; supported: {', '.join(ACTIVATIONS)}")


def act_table(name: str, e_z: int, e_a: int) -> np.ndarray:
    """256-entry int8 table: index ``z + 128`` (z int8 at exponent e_z) → activation at exponent e_a.

    >>> t = act_table("tanh", 5, 7)
    >>> int(t[128]), int(t[255]), int(t[0])
    (0, 127, -128)
    """
    z = np.arange(-128, 128, dtype=np.float64) * (2.0 ** -e_z)
    return quantize(act_float(name, z), e_a).astype(np.int8)


# --- sensing tables (indexed by the uint8 distance in mm) ------------------------------------
def rbf_table(rbf_centres_mm: np.ndarray, sigma_mm: float, norm: float, comm_radius_mm: float,
              e_in: int) -> np.ndarray:
    """(n_rbf, 256) uint8: ψ_k(d) / norm at exponent e_in for d = 0..255 mm; 0 beyond the radius."""
    d = np.arange(256, dtype=np.float64)[None, :]
    mu = np.asarray(rbf_centres_mm, np.float64)[:, None]
    psi = np.exp(-((d - mu) ** 2) / (2.0 * sigma_mm ** 2)) / norm
    q = quantize(psi, e_in, 0, 255)
    q[:, d[0] > comm_radius_mm] = 0
    return q.astype(np.uint8)


def target_table(comm_radius_mm: float, e_in: int) -> np.ndarray:
    """(256,) int8: min(d / comm_radius, 1) at exponent e_in for d = 0..255 mm."""
    d = np.arange(256, dtype=np.float64)
    return quantize(np.minimum(d / comm_radius_mm, 1.0), e_in).astype(np.int8)


def action_table(e_in: int) -> np.ndarray:
    """(256,) int8: the uint8 motor command q as (q / 255) at exponent e_in (history entries)."""
    return quantize(np.arange(256) / 255.0, e_in).astype(np.int8)


def distance_u8(d_mm: np.ndarray) -> np.ndarray:
    """Measured distance (float mm) → the uint8 mm the firmware sees (half-up, clamp 0..255)."""
    return saturate(round_half_up(d_mm), 0, 255).astype(np.uint8)


# --- per-layer exponent choice ---------------------------------------------------------------
def choose_exp(max_abs: float, lo: int = -8, hi: int = 14, limit: int = INT8_MAX) -> int:
    """Largest exponent e in [lo, hi] with round(max_abs * 2**e) <= limit (power-of-two scale).

    >>> choose_exp(1.0), choose_exp(0.3), choose_exp(100.0)
    (6, 8, 0)
    """
    if not math.isfinite(max_abs):
        raise ValueError(f"cannot choose an exponent for max |x| = {max_abs}")
    if max_abs <= 0:
        return hi
    e = math.floor(math.log2(limit / max_abs))
    while e > lo and round_half_up(max_abs * 2.0 ** e) > limit:
        e -= 1
    return int(max(lo, min(hi, e)))


@dataclass(frozen=True)
class QuantLayer:
    """One quantised dense layer (see the module doc for the semantics of every field)."""

    w: np.ndarray  # (n_out, n_in) int8
    b: np.ndarray  # (n_out,) int32
    shift: np.ndarray  # (n_out,) uint8, requantisation shift per row
    lo: int  # saturation bounds of the requantised output
    hi: int
    activation: str  # applied after requantisation ("identity" for the output layer)
    e_in: int  # exponent of the input tensor
    e_out: int  # exponent of the requantised output (pre-activation for table activations)
    e_act: int  # exponent after the activation (== e_out for relu/identity)
    table: np.ndarray | None  # (256,) int8 activation table for elu/tanh/sigmoid, else None

    def __post_init__(self) -> None:
        n_out, n_in = self.w.shape
        assert self.w.dtype == np.int8, f"weights must be int8, got {self.w.dtype}"
        assert self.b.shape == (n_out,) and self.b.dtype == np.int32, "bias must be int32 (n_out,)"
        assert self.shift.shape == (n_out,), "one shift per output row"
        assert np.all((self.shift >= 0) & (self.shift <= MAX_SHIFT)), f"shifts must be in 0..{MAX_SHIFT}"
        assert self.activation in ACTIVATIONS, f"unsupported activation '{self.activation}'"
        needs_table = self.activation in ("elu", "tanh", "sigmoid")
        assert (self.table is not None) == needs_table, f"{self.activation}: table presence is wrong"

    def forward(self, x: np.ndarray) -> np.ndarray:
        """Integer forward of this layer (int64 out): requantise, then the activation."""
        z = dense_int(x, self.w, self.b, self.shift, self.lo, self.hi)
        if self.activation == "relu":
            return np.maximum(z, 0)
        if self.table is not None:
            return self.table.astype(np.int64)[z + 128]
        return z


# --- the GRU cell (module doc, "The GRU cell") --------------------------------------------
GATE_EXP = 8  #: gates r and k = 1 - z: uint8 at exponent 8 (real g / 256)
HIDDEN_EXP = 7  #: hidden state h and candidate n: int8 at exponent 7 (real h / 128)
SIGMOID_SAT_EXP = 4  #: coarsest gate-table exponent needed: ±8 covers σ's uint8 saturation (-6.24, 5.13)
TANH_SAT_EXP = 5  #: coarsest tanh-table exponent needed: ±4 covers tanh's int8 saturation (±3.1)


def gate_table(e_a: int, complement: bool = False) -> np.ndarray:
    """256-entry uint8: index ``a + 128`` (a int8 at exponent e_a) -> σ(a), or 1 - σ(a), at GATE_EXP.

    >>> t = gate_table(4)
    >>> int(t[128]), int(t[255]), int(t[0])
    (128, 255, 0)
    >>> int(gate_table(4, complement=True)[255])
    0
    """
    a = np.arange(-128, 128, dtype=np.float64) * (2.0 ** -e_a)
    g = act_float("sigmoid", -a if complement else a)
    return quantize(g, GATE_EXP, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class QuantGRUCell:
    """An int8 GRU cell (module doc, "The GRU cell"); ``step`` is the reference integer semantics."""

    r: QuantLayer  #: (H, D + H) over [x, h] -> a_r int8 at r.e_out
    z: QuantLayer  #: (H, D + H) over [x, h] -> a_z int8 at z.e_out
    nx: QuantLayer  #: (H, D) over x -> W_in x + b_in int8 at e_n
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
            l = getattr(self, name)
            assert (l.lo, l.hi, l.activation, l.table) == (INT8_MIN, INT8_MAX, "identity", None), \
                f"{name}: gate layers requantise to int8 with no activation of their own"
        assert self.nh.e_in == HIDDEN_EXP, f"nh reads h at exponent {HIDDEN_EXP}, not {self.nh.e_in}"
        assert self.r.e_in == self.z.e_in == self.nx.e_in, "r, z and nx read x at one exponent"
        for name in ("r_table", "k_table"):
            t = getattr(self, name)
            assert t.shape == (256,) and t.dtype == np.uint8, f"{name} must be (256,) uint8"
        assert self.n_table.shape == (256,) and self.n_table.dtype == np.int8, "n_table must be (256,) int8"
        assert 0 <= self.nx_shift <= 7, f"nx_shift must be in 0..7, got {self.nx_shift}"
        assert self.rn_shift == GATE_EXP + self.nh.e_out - self.e_n and 0 <= self.rn_shift <= MAX_SHIFT, \
            f"rn_shift {self.rn_shift} != {GATE_EXP} + e_nh {self.nh.e_out} - e_n {self.e_n} (or out of range)"

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
        a_r = dense_int(xh, self.r.w, self.r.b, self.r.shift, INT8_MIN, INT8_MAX)
        a_z = dense_int(xh, self.z.w, self.z.b, self.z.shift, INT8_MIN, INT8_MAX)
        r = self.r_table.astype(np.int64)[a_r + 128]
        k = self.k_table.astype(np.int64)[a_z + 128]
        nx = dense_int(x, self.nx.w, self.nx.b, self.nx.shift, INT8_MIN, INT8_MAX)
        nh = dense_int(h, self.nh.w, self.nh.b, self.nh.shift, INT8_MIN, INT8_MAX)
        pre = saturate(nx * (1 << self.nx_shift) + rshift_round(r * nh, self.rn_shift), INT8_MIN, INT8_MAX)
        n = self.n_table.astype(np.int64)[pre + 128]
        h2 = saturate(h + rshift_round(k * (n - h), GATE_EXP), INT8_MIN, INT8_MAX)
        return {"a_r": a_r, "a_z": a_z, "r": r, "k": k, "nx": nx, "nh": nh, "pre_n": pre, "n": n, "h": h2}

    def step(self, x: np.ndarray, h: np.ndarray) -> np.ndarray:
        """The new hidden state (int64, same shape as h) for int8 inputs x (..., D) and states h (..., H)."""
        return self.gates(x, h)["h"]
