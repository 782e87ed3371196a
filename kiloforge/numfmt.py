"""The fixed-point number format: the single source of truth for quantisers, renderer and emulator.

Everything the firmware computes with is defined here, and the C constants are rendered from here
(:mod:`export.codegen.render`); each actor kind (:mod:`kiloforge.actors`) builds its int8 network
from these pieces.

Format
------
* **Tensors** (inputs, hidden activations) are ``int8`` with a per-tensor power-of-two exponent
  ``e``: real value = ``q * 2**-e``.
* **Weights** are ``int8`` with a per-output-row exponent ``ew[j]`` (per-channel power-of-two scales).
* **Biases** are ``int32`` at the accumulator's exponent ``ew[j] + e_in``.
* **Accumulator**: the reference is ``int32`` (:data:`ACC_BITS_REFERENCE`):
  ``acc = bias[j] + Σ_i W[j, i] * x[i]``. Every row is proven free of overflow for every int8 input
  with the rounding constant included, ``|acc + 2**(s-1)| < 2**31`` (:func:`acc_bound`, the sum the C
  kernel really forms). A narrower 24-bit accumulator (:data:`ACC_BITS_NARROW`) is used on the AVR
  only for layers where the same proof gives ``< 2**23`` (:func:`fits_acc`).
* **Requantisation**: ``y = clamp(rshift_round(acc, s[j]), lo, hi)`` with
  ``s[j] = ew[j] + e_in - e_out >= 0``. Rounding rule **half-up** (towards +inf on ties):
  ``rshift_round(a, s) = (a + half_up_constant(s)) >> s`` with an arithmetic (flooring) shift, where
  ``half_up_constant(s) = 1 << (s - 1)`` for ``s > 0`` and 0 for ``s == 0``. Saturation: clamp to
  ``[lo, hi]``.
* **Hidden layers**: requantise to the pre-activation ``int8`` (``lo, hi = -128, 127``) at exponent
  ``e_z``, then the activation: ReLU is ``max(0, z)`` (same exponent); the :data:`TABLE_ACTIVATIONS`
  (ELU, tanh, sigmoid) are 256-entry ``int8`` tables indexed by ``z + 128`` mapping to exponent
  ``e_a``; identity is nothing.
* **Output layer**: its real output is ``255 * u`` (the quantiser folds the 255 into the float
  weights), at exponent 0, clamped to ``[0, 255]``: the uint8 motor command ``q``, ``u = q / 255``
  (the same map as :func:`sim.motion.action_to_u8`).
* **Observations** are ``int8`` at exponent ``e_in`` (the first layer's input exponent): wall flag
  ``1 << e_in``; target ``-(1 << e_in)`` when not heard, else ``TGT[d]`` from a 256-entry table
  indexed by the uint8 distance; neighbour flag ``1 << e_in``; RBF bin k = saturate_int8(Σ RBF[k][d])
  over table entries (table ``uint8``, 0 beyond the communication radius). Previous actions enter
  the actor's input as ``ACT[q]`` (a 256-entry table of ``round_half_up(q / 255 * 2**e_in)``).
* **Recurrent cells** (GRU, LSTM) keep their state as ``int8`` at :data:`HIDDEN_EXP` and their gates
  as ``uint8`` at :data:`GATE_EXP` from 256-entry tables (:func:`gate_table`); a table's input
  exponent only needs to cover where its function still changes (:data:`SIGMOID_SAT_EXP`,
  :data:`TANH_SAT_EXP`). The cells themselves are defined by their kinds (:mod:`kiloforge.actors.gru`,
  :mod:`kiloforge.actors.lstm`).
* No floats, no division, no malloc in the control step; C uses only ``<stdint.h>`` types and casts
  to ``int32_t`` before every multiply, so it never depends on the width of ``int``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FORMAT_NAME = "kf-int8-pow2-v1"  #: rendered into the C banner and the manifest
ROUNDING = "half-up"  #: the one rounding rule (documented above)
INT8_MIN, INT8_MAX = -128, 127
UINT8_MAX = 255  #: the output layer's clamp and the uint8 gate tables' top
ACC_BITS_REFERENCE = 32  #: the reference accumulator (int32)
ACC_BITS_NARROW = 24  #: the AVR kernel's accumulator, where :func:`fits_acc` proves it exact
DEFAULT_INPUT_EXP = 6  #: observations in [-2, 2) with 1/64 resolution
MAX_SHIFT = 30
ACTIVATIONS = ("elu", "relu", "tanh", "sigmoid", "identity")
TABLE_ACTIVATIONS = ("elu", "tanh", "sigmoid")  #: realised as 256-entry int8 tables (identical ones shared)
OUTPUT_ACTIVATIONS = ("identity", "relu")  #: output activations the uint8 clamp realises exactly
TABLE_SIZE = 256  #: entries of every activation, gate and distance table (index: an int8 + 128 or a uint8)
GATE_EXP = 8  #: recurrent gates: uint8 at exponent 8 (real g / 256)
HIDDEN_EXP = 7  #: recurrent state (and a GRU's candidate, an LSTM's tanh outputs): int8 at exponent 7 (real h / 128)
SIGMOID_SAT_EXP = 4  #: coarsest gate-table exponent needed: ±8 covers σ's uint8 saturation (-6.24, 5.13)
TANH_SAT_EXP = 5  #: coarsest tanh-table exponent needed: ±4 covers tanh's int8 saturation (±3.1)


def acc_limit(bits: int) -> int:
    """Bound that a signed accumulator of ``bits`` bits needs ``|acc|`` to stay below.

    >>> acc_limit(ACC_BITS_REFERENCE), acc_limit(ACC_BITS_NARROW)
    (2147483648, 8388608)
    """
    return 1 << (int(bits) - 1)


ACC32_LIMIT = acc_limit(ACC_BITS_REFERENCE)  #: |acc + rounding| of every row stays below this (the int32 proof)
ACC24_LIMIT = acc_limit(ACC_BITS_NARROW)  #: ... and below this for the AVR's 24-bit kernel


def half_up_constant(shift: np.ndarray | int) -> np.ndarray:
    """The half-up rounding constant added before a right shift: 2^(s-1) for s > 0, 0 for s = 0 (int64).

    >>> half_up_constant(np.array([0, 1, 8])).tolist()
    [0, 1, 128]
    """
    s = np.asarray(shift, np.int64)
    return np.where(s > 0, np.left_shift(np.int64(1), np.maximum(s - 1, 0)), 0)


ROUND_LIMIT = 2.0 ** 62  #: |values| :func:`round_half_up` saturates at (every caller saturates or refuses far below)


def round_half_up(x: np.ndarray | float) -> np.ndarray:
    """Round to nearest integer, ties towards +inf (the format's rounding rule), as int64. A finite value
    beyond ±2^62 (a huge weight times its scale) becomes ±2^62 instead of overflowing the cast.

    >>> round_half_up(np.array([-1.5, -0.5, 0.5, 1.5, 2.4])).tolist()
    [-1, 0, 1, 2, 2]
    >>> round_half_up(np.array([1e30, -1e30])).tolist() == [2 ** 62, -2 ** 62]
    True
    """
    return np.clip(np.floor(np.asarray(x, dtype=np.float64) + 0.5), -ROUND_LIMIT, ROUND_LIMIT).astype(np.int64)


def rshift_round(acc: np.ndarray, shift: np.ndarray | int) -> np.ndarray:
    """Arithmetic right shift with half-up rounding; shift 0 is the identity. int64 in, int64 out.

    >>> rshift_round(np.array([5, -5, 6, -6, 7]), 1).tolist()
    [3, -2, 3, -3, 4]
    >>> rshift_round(np.array([-7]), 0).tolist()
    [-7]
    """
    acc = np.asarray(acc, dtype=np.int64)
    s = np.asarray(shift, dtype=np.int64)
    return np.right_shift(acc + half_up_constant(s), s)


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
    assert np.all(np.abs(acc) < ACC32_LIMIT), "int32 accumulator overflow (the quantiser must prevent this)"
    return saturate(rshift_round(acc, np.asarray(shift, np.int64)), lo, hi)


def acc_bound(w: np.ndarray, b: np.ndarray, shift: np.ndarray | int = 0, x_lo: int = INT8_MIN,
              x_hi: int = INT8_MAX) -> np.ndarray:
    """Largest ``|b + half_up_constant(s) + W x|`` per row over every input in [x_lo, x_hi]^n_in (int64, (n_out,)).

    The sum the kernels form (the rounding constant is folded into the bias), so it is the bound
    both overflow proofs use. ``shift`` 0 (the default) bounds the plain accumulator.

    >>> acc_bound(np.array([[1, -2]]), np.array([10]), np.array([2])).tolist()
    [395]
    """
    w = np.asarray(w, np.int64)
    b = np.asarray(b, np.int64) + half_up_constant(np.broadcast_to(np.asarray(shift, np.int64), (w.shape[0],)))
    hi_part = np.where(w > 0, w * x_hi, w * x_lo).sum(axis=1) + b
    lo_part = np.where(w > 0, w * x_lo, w * x_hi).sum(axis=1) + b
    return np.maximum(np.abs(hi_part), np.abs(lo_part))


def fits_acc(w: np.ndarray, b: np.ndarray, shift: np.ndarray | int, bits: int) -> bool:
    """True when a signed ``bits``-bit accumulator provably cannot overflow for any int8 input,
    rounding constant included (:func:`acc_bound`). The 24-bit test decides the AVR kernel and the
    error report's "acc24" column alike."""
    return bool(np.all(acc_bound(w, b, shift) < acc_limit(bits)))


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
        needs_table = self.activation in TABLE_ACTIVATIONS
        assert (self.table is not None) == needs_table, f"{self.activation}: table presence is wrong"

    @property
    def acc_max(self) -> int:
        """max over rows of :func:`acc_bound` (rounding included): the overflow proof's figure."""
        return int(acc_bound(self.w, self.b, self.shift).max())

    @property
    def acc24_safe(self) -> bool:
        """The 24-bit accumulator is exact for every int8 input (:func:`fits_acc`)."""
        return fits_acc(self.w, self.b, self.shift, ACC_BITS_NARROW)

    def forward(self, x: np.ndarray) -> np.ndarray:
        """Integer forward of this layer (int64 out): requantise, then the activation."""
        z = dense_int(x, self.w, self.b, self.shift, self.lo, self.hi)
        if self.activation == "relu":
            return np.maximum(z, 0)
        if self.table is not None:
            return self.table.astype(np.int64)[z + 128]
        return z


# --- recurrent-cell gate tables (module doc, "Recurrent cells") ------------------------------
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


