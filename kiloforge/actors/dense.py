"""The dense-layer quantiser every actor kind builds on, with the int32 overflow proof.

:func:`quantize_dense` turns a float layer ``W x + b`` (already scaled to its real output) into a
:class:`~kiloforge.numfmt.QuantLayer`: per output row the weight exponent ``ew[j]`` (the largest
that keeps the row in int8 and the shift ``ew[j] + e_in - e_out`` in ``0..MAX_SHIFT``), int32
biases at the accumulator exponent ``ew[j] + e_in``, and the proof that no int8 input can make
``|acc + 2**(s-1)|`` reach ``2**31`` (:func:`kiloforge.numfmt.acc_bound`, the sum the C kernel
forms); rows that fail it get a coarser weight scale until they pass.
"""
from __future__ import annotations

import numpy as np

from .. import numfmt
from ..errors import QuantizeError
from ..numfmt import ACC32_LIMIT, DEFAULT_INPUT_EXP, INT8_MAX, INT8_MIN, MAX_SHIFT, QuantLayer, choose_exp

WEIGHT_EXP_LO = -16  #: smallest per-row weight exponent tried (|w| up to 127 * 2**16)


def value_range(a: np.ndarray, percentile: float, headroom: float) -> float:
    """max |a| (or its ``percentile``), times ``headroom``: the range an exponent must cover."""
    v = np.abs(np.asarray(a, np.float64)).ravel()
    if v.size == 0:
        return 0.0
    m = float(v.max()) if percentile >= 100.0 else float(np.percentile(v, percentile))
    return m * headroom


def check_range_options(percentile: float, headroom: float) -> None:
    """Raise QuantizeError for a percentile outside (0, 100] or a headroom <= 0."""
    if not 0.0 < percentile <= 100.0:
        raise QuantizeError(f"percentile must be in (0, 100], got {percentile}")
    if headroom <= 0.0:
        raise QuantizeError(f"headroom must be > 0, got {headroom}")


def input_exponent(inputs: np.ndarray, percentile: float, headroom: float, e_in: int | None) -> int:
    """The observation exponent: from the calibrated inputs unless given, at most DEFAULT_INPUT_EXP
    (so that the 0/1 flags are exact) and at least 0."""
    if e_in is None:
        e_in = min(DEFAULT_INPUT_EXP, max(0, choose_exp(value_range(inputs, percentile, headroom))))
    if not 0 <= e_in <= DEFAULT_INPUT_EXP:
        raise QuantizeError(f"input exponent must be in 0..{DEFAULT_INPUT_EXP} (flags are 1 << e_in), got {e_in}")
    return int(e_in)


def quantize_dense(name: str, W: np.ndarray, b: np.ndarray, e_in: int, e_out: int, *, may_lower_e_out: bool,
                   lo: int = INT8_MIN, hi: int = INT8_MAX, activation: str = "identity", e_act: int | None = None,
                   table: np.ndarray | None = None) -> QuantLayer:
    """The quantised layer of float ``W`` (n_out, n_in) and ``b`` (n_out,), scaled to the real output.

    ``e_out`` is lowered (a coarser output grid) when some row would need a negative shift and
    ``may_lower_e_out``; otherwise that is a QuantizeError. ``activation``, ``e_act`` (default: the
    final ``e_out``) and ``table`` complete the layer (a table must match the final ``e_out``: pass
    a table only with ``may_lower_e_out=False``, or use :func:`dense_weights` and build it after).
    """
    wq, bq, shift, e_out = dense_weights(name, W, b, e_in, e_out, may_lower_e_out=may_lower_e_out)
    return QuantLayer(w=wq, b=bq, shift=shift, lo=lo, hi=hi, activation=activation, e_in=e_in, e_out=e_out,
                      e_act=e_out if e_act is None else e_act, table=table)


def dense_weights(name: str, W: np.ndarray, b: np.ndarray, e_in: int, e_out: int, *, may_lower_e_out: bool
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(int8 weights, int32 biases, uint8 shifts, final e_out) of :func:`quantize_dense`."""
    W = np.asarray(W, np.float64)
    b = np.asarray(b, np.float64)
    row_max = np.abs(W).max(axis=1)  # (n_out,)
    ew = np.array([choose_exp(float(m), lo=WEIGHT_EXP_LO, hi=MAX_SHIFT + e_out - e_in) for m in row_max],
                  dtype=np.int64)  # largest exponent keeping each row in int8 and the shift <= MAX_SHIFT
    over = row_max * np.ldexp(1.0, ew) > INT8_MAX + 0.5  # not in int8 even at the coarsest weight scale
    if over.any():
        j = int(np.flatnonzero(over)[0])
        raise QuantizeError(f"{name} row {j}: weights up to {row_max[j]:.4g} exceed the int8 format's range "
                            f"(|w| <= {INT8_MAX} x 2^{-WEIGHT_EXP_LO} = {INT8_MAX * 2.0 ** -WEIGHT_EXP_LO:.4g}); the "
                            f"policy has weights too large for the int8 format")
    if np.any(ew + e_in - e_out < 0):
        if not may_lower_e_out:
            j = int(np.argmin(ew))
            raise QuantizeError(
                f"{name} row {j}: weights up to {row_max[j]:.4g} are too large for the output exponent "
                f"{e_out} (needs a negative shift); retrain with smaller output weights")
        e_out = int((ew + e_in).min())  # coarser output grid so that every shift is >= 0
    for _ in range(64):
        shift = ew + e_in - e_out
        wq = numfmt.quantize(W * np.ldexp(1.0, ew)[:, None], 0)  # (n_out, n_in), in int8 by choice of ew
        bq = numfmt.round_half_up(b * np.ldexp(1.0, ew + e_in))  # (n_out,) int64 at the accumulator exponent
        bound = numfmt.acc_bound(wq, bq, shift)  # (n_out,) max |acc + 2^(s-1)| over every int8 input
        # the bias alone must be an int32 too: a rounding constant can pull |b + 2^(s-1)| under 2^31 while b is not
        bound = np.maximum(bound, np.abs(bq))
        bad = bound >= ACC32_LIMIT
        if not bad.any():
            return wq.astype(np.int8), bq.astype(np.int32), shift.astype(np.uint8), int(e_out)
        stuck = bad & (shift <= 0)
        if stuck.any():
            j = int(np.flatnonzero(stuck)[0])
            raise QuantizeError(
                f"{name} row {j}: the int32 accumulator could overflow (|acc| up to {int(bound[j])} "
                f">= 2^31, bias {b[j]:.4g}) even at the coarsest weight scale; the policy has weights or "
                f"biases too large for the int8 format")
        ew = np.where(bad, ew - 1, ew)  # halve the scale of the offending rows only
    raise QuantizeError(f"{name}: could not remove a possible int32 overflow")  # pragma: no cover


def output_layer(name: str, W: np.ndarray, b: np.ndarray, e_in: int) -> QuantLayer:
    """The output layer: real output ``255 u`` (255 folded into the float weights), exponent 0,
    clamped to 0..255: the uint8 motor commands."""
    return quantize_dense(name, np.asarray(W, np.float64) * 255.0, np.asarray(b, np.float64) * 255.0, e_in, 0,
                          may_lower_e_out=False, lo=0, hi=numfmt.UINT8_MAX)


def is_output_layer(l: QuantLayer) -> bool:
    """True for the uint8 output layer: identity, exponent 0, clamp 0..255."""
    return (l.lo, l.hi, l.e_out, l.e_act, l.activation) == (0, numfmt.UINT8_MAX, 0, 0, "identity")


def is_gate_layer(l: QuantLayer) -> bool:
    """True for a layer that requantises to int8 with no activation of its own (a recurrent gate)."""
    return (l.lo, l.hi, l.activation, l.table) == (INT8_MIN, INT8_MAX, "identity", None)


def saturated_fraction(z: np.ndarray, lo: int = INT8_MIN, hi: int = INT8_MAX) -> float:
    """Fraction of values at ``lo`` or ``hi`` (a requantised layer's saturation)."""
    z = np.asarray(z)
    return float(np.mean((z == lo) | (z == hi))) if z.size else 0.0
