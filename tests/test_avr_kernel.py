"""The int8 dense kernel (firmware_templates/kf_dense.c, export/codegen/kernel.py): bit-exact with numfmt.

Pure-Python checks of the kernel's algebra and layout run everywhere; the portable C runs on the
host; the AVR assembly kernel and the portable C on the AVR run in simavr (marked ``avr``).
"""
from __future__ import annotations

import doctest
from dataclasses import replace

import numpy as np
import pytest

from tests.avr_tools import require_avr
from export.codegen import kernel
from export.verify import avr, tools
from kiloforge import numfmt
from kiloforge.numfmt import QuantLayer


def _layer(rng: np.random.Generator, n_out: int, n_in: int, *, clamp=(-128, 127), shifts=None,
           bias_bits: int = 14, extreme: bool = False) -> QuantLayer:
    w = rng.integers(-128, 128, size=(n_out, n_in))
    if extreme:  # only the int8 extremes
        w = rng.choice(np.array([-128, 127]), size=(n_out, n_in))
    s = rng.integers(0, numfmt.MAX_SHIFT + 1, n_out) if shifts is None else np.resize(np.asarray(shifts), n_out)
    b = rng.integers(-(1 << bias_bits), 1 << bias_bits, n_out)
    return QuantLayer(w=w.astype(np.int8), b=b.astype(np.int32), shift=s.astype(np.uint8), lo=clamp[0],
                      hi=clamp[1], activation="identity", e_in=0, e_out=0, e_act=0, table=None)


def _inputs(rng: np.random.Generator, n_in: int, k: int) -> np.ndarray:
    x = rng.integers(-128, 128, size=(k, n_in))
    x[0], x[1] = -128, 127  # extreme inputs
    if k > 2:
        x[2] = rng.choice(np.array([-128, 127]), n_in)
    return x


def _suite(seed: int) -> tuple[list[QuantLayer], list[tuple[int, int, np.ndarray]], list[np.ndarray]]:
    """Layers covering every group size (8, 2, 1), odd/even widths, every shift, both clamps,
    extreme weights and inputs, 24-bit and int32 paths; requests with random ring-buffer splits."""
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    layers = [
        _layer(rng, 32, 32, shifts=[9]),
        _layer(rng, 15, 33, shifts=rng.integers(0, 24, 15)),  # groups 8, 2, 2, 2, 1; odd width
        _layer(rng, 2, 40, clamp=(0, 255), shifts=[14, 15]),  # the output layer's clamp
        _layer(rng, 31, 1, shifts=np.arange(31)),  # every shift 0..30 (s > 23 is never 24-bit exact)
        _layer(rng, 9, 64, extreme=True, shifts=[0, 7, 8, 15, 16, 23, 12, 9, 1]),
        _layer(rng, 5, 7, bias_bits=29),  # large biases: the int32 path (not fast)
        _layer(rng, 3, 300, clamp=(0, 255), shifts=[13, 14, 15]),  # a wide first layer
        _layer(rng, 6, 10, clamp=(-300, 400)),  # a clamp the assembly does not implement
        _layer(rng, 24, 3, shifts=np.arange(24), bias_bits=4),  # every shift the assembly can get
    ]
    reqs, refs = [], []
    for li, L in enumerate(layers):
        n = L.w.shape[1]
        for x in _inputs(rng, n, 6):
            n1 = int(rng.integers(0, n + 1))
            reqs.append((li, n1, x))
            refs.append(numfmt.dense_int(x, L.w, L.b, L.shift, L.lo, L.hi))
    return layers, reqs, refs


def test_kernel_doctests():
    """The doctests of export.codegen.kernel (layout and rounding helpers) pass."""
    res = doctest.testmod(kernel)
    assert res.failed == 0 and res.attempted >= 4


def test_row_groups_cover_rows_in_order():
    """Row groups are 8 while 8 are left, then 2 while 2 are left, then 1, contiguous and complete."""
    for n in range(1, 70):
        g = kernel.row_groups(n)
        assert [g0 for g0, _ in g] == list(np.cumsum([0] + [k for _, k in g])[:-1])
        assert sum(k for _, k in g) == n
        assert all(k == 8 for _, k in g[:n // 8]) and all(k < 8 for _, k in g[n // 8:])
        assert [k for _, k in g[n // 8:]] == [2] * (n % 8 // 2) + [1] * (n % 2)


def test_kernel_arithmetic_matches_numfmt():
    """The kernel's folded-bias, offset-binary, modular arithmetic (export.codegen.kernel.run) equals dense_int."""
    layers, reqs, refs = _suite(1)
    kls = [kernel.kernel_layer(L) for L in layers]
    for (li, _, x), ref in zip(reqs, refs):
        np.testing.assert_array_equal(kernel.run(kls[li], x), ref)


def test_fast_flag_is_the_24bit_proof():
    """A layer is fast exactly when |acc + rounding| < 2^23 for every int8 input (and the clamp fits)."""
    w = np.full((1, 4), 127, np.int8)
    edge = 2 ** 23 - 2 - 4 * 127 * 127  # |acc + 1| <= edge + 4 * 127 * 127 + 1 = 2^23 - 1
    for b, want in ((edge, True), (edge + 1, False)):
        L = QuantLayer(w=w, b=np.array([b], np.int32), shift=np.array([1], np.uint8), lo=-128, hi=127,
                       activation="identity", e_in=0, e_out=0, e_act=0, table=None)
        assert kernel.is_fast(L) is want, b
        assert int(kernel.proof(L)[0]) == b + 4 * 127 * 127 + 1
    L = _layer(np.random.default_rng(0), 4, 8, clamp=(-300, 400))
    assert not kernel.is_fast(L)


def test_int32_overflow_with_rounding_is_refused():
    """A row whose accumulator fits int32 but plus rounding (2^4 here) may not raises a ValueError."""
    L = QuantLayer(w=np.full((1, 2), 127, np.int8), b=np.array([2 ** 31 - 16 - 2 * 127 * 127], np.int32),
                   shift=np.array([5], np.uint8), lo=-128, hi=127, activation="identity", e_in=0, e_out=0,
                   e_act=0, table=None)
    with pytest.raises(ValueError, match="row 0"):
        kernel.kernel_bias(L)


def test_generated_asm_block_is_current():
    """kf_dense.c holds exactly the assembly export.codegen.kernel generates (no hand edits, no drift)."""
    text = kernel.kf_dense_c_path().read_text()
    assert kernel.avr_asm_block() in text


def test_portable_c_on_host_is_bit_exact():
    """The portable C kernel compiled for the host (-Wall -Wextra -Werror) equals dense_int."""
    why = tools.host_cc_problem()
    if why:
        pytest.skip(why)
    layers, reqs, refs = _suite(2)
    outs = avr.run_kernel_host([kernel.kernel_layer(L) for L in layers], reqs)
    for o, ref in zip(outs, refs):
        np.testing.assert_array_equal(o, ref)


@pytest.mark.avr
@pytest.mark.parametrize("portable", [False, True], ids=["asm", "portable-c"])
def test_avr_kernel_bit_exact_in_simavr(portable):
    """On the simulated ATmega328P both kernels equal dense_int on every layer of the suite."""
    require_avr(simulate=True)
    layers, reqs, refs = _suite(3)
    kls = [kernel.kernel_layer(L) for L in layers]
    assert [k.fast for k in kls] == [True, True, True, False, True, False, True, False, True]
    run = avr.run_kernel(kls, reqs, portable=portable)
    assert len(run.outputs) == len(refs) and run.cycles.size == len(refs)
    for (li, n1, _), o, ref in zip(reqs, run.outputs, refs):
        np.testing.assert_array_equal(o, ref, err_msg=f"layer {li} split {n1}")


@pytest.mark.avr
def test_avr_kernel_random_layers_bit_exact():
    """Random fast layers (random shapes, shifts, biases near the 24-bit bound) are exact in simavr."""
    require_avr(simulate=True)
    rng = np.random.default_rng(np.random.SeedSequence(4))
    layers = []
    for _ in range(6):
        n_out, n_in = int(rng.integers(1, 40)), int(rng.integers(1, 200))
        L = _layer(rng, n_out, n_in, clamp=[(-128, 127), (0, 255)][int(rng.integers(0, 2))],
                   shifts=rng.integers(0, 21, n_out))
        room = (2 ** 23 - 1) - int(kernel.proof(replace(L, b=np.zeros_like(L.b))).max())
        b = rng.integers(-room, room + 1, n_out).astype(np.int32)  # biases up to the proof's limit
        layers.append(replace(L, b=b))
    kls = [kernel.kernel_layer(L) for L in layers]
    assert all(k.fast for k in kls)
    reqs, refs = [], []
    for li, L in enumerate(layers):
        for x in _inputs(rng, L.w.shape[1], 5):
            reqs.append((li, int(rng.integers(0, L.w.shape[1] + 1)), x))
            refs.append(numfmt.dense_int(x, L.w, L.b, L.shift, L.lo, L.hi))
    run = avr.run_kernel(kls, reqs)
    for o, ref in zip(run.outputs, refs):
        np.testing.assert_array_equal(o, ref)


@pytest.mark.avr
def test_avr_kernel_requantisation_edges_bit_exact():
    """Every shift 0..23 and both clamps, with values at the saturation edges and near +-2^23, are exact in simavr."""
    require_avr(simulate=True)
    layers, reqs, refs = [], [], []
    for lo, hi in kernel.FAST_CLAMPS:
        for s in range(24):
            r = (1 << s) >> 1  # the rounding constant: acc + r = b + r when every weight is 0
            ys = (-32769, -257, -129, -128, -1, 0, 1, 127, 128, 255, 256, 32768)
            b = [y * (1 << s) - r + d for y in ys for d in (0, -1) if abs(y * (1 << s) + d) < 2 ** 23]
            b += [2 ** 23 - 1 - r, 1 - 2 ** 23 - r]  # the 24-bit limits of acc + r
            b = np.clip(b, np.iinfo(np.int32).min, np.iinfo(np.int32).max)
            layers.append(QuantLayer(w=np.zeros((len(b), 1), np.int8), b=np.asarray(b, np.int32),
                                     shift=np.full(len(b), s, np.uint8), lo=lo, hi=hi, activation="identity",
                                     e_in=0, e_out=0, e_act=0, table=None))
            x = np.array([[-128], [5]])
            for xi in x:
                reqs.append((len(layers) - 1, 1, xi))
                refs.append(numfmt.dense_int(xi, layers[-1].w, layers[-1].b, layers[-1].shift, lo, hi))
    kls = [kernel.kernel_layer(L) for L in layers]
    assert all(k.fast for k in kls)
    run = avr.run_kernel(kls, reqs)
    for (li, _, _), o, ref in zip(reqs, run.outputs, refs):
        np.testing.assert_array_equal(o, ref, err_msg=f"shift {layers[li].shift[0]} clamp {layers[li].lo}")
