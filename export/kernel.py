"""The dense-layer kernel's view of a layer: the arrays ``firmware_templates/kf_dense.c`` consumes.

One set of arrays serves the portable C (host, Kilombo) and the AVR assembly kernel, so the host and
the robot compute the same integers. The kernel computes :func:`export.numfmt.dense_int` exactly,
through this algebra (``n = n_in``, ``x' = x + 128``, ``w' = W + 128``, both ``0..255``)::

    sum_i W[j,i] x[i] = sum_i w'[j,i] x'[i] - 128 sum_i x'[i] - 128 sum_i w'[j,i] + 16384 n
    acc[j] + 2^(s-1)  = b'[j] - 128 S + sum_i w'[j,i] x'[i]        with S = sum_i x'[i] (per input)
    b'[j]             = b[j] + 2^(s[j]-1) - 128 sum_i w'[j,i] + 16384 n   (0 instead of 2^(s-1) if s = 0)
    y[j]              = clamp(floor((acc[j] + 2^(s-1)) / 2^s), lo, hi)    = numfmt's half-up rounding

so the AVR's unsigned 8x8 MUL needs no sign handling and the correction costs one pass over the
input per layer. Everything is computed modulo 2^32 (int32 path) or 2^24 (``fast`` path); the result
is exact because its true value is proven to fit: :func:`proof` bounds ``|acc + 2^(s-1)|`` over every
int8 input with :func:`numfmt.acc_bound`.

Array formats (also in ``kf_dense.h``):

* ``w``: int8, rows in groups of 8 (then 4, 2, 1 for the rest, :func:`row_groups`), each group
  interleaved input-major so the AVR streams it with ``lpm Z+`` for 8 rows per loaded input:
  ``w[g0*n + i*k + r] = W[g0+r, i] + 128`` (as a byte: the bit pattern of ``W ^ 0x80``).
* ``b``: int32 folded bias ``b'``; for ``fast`` layers ``(b' mod 2^24) | (code << 24)`` with the
  AVR kernel's requantisation code :func:`avr_shift_code` (the portable C ignores the top byte).
* ``shift``: uint8 ``s`` (the portable C reads it).
* ``fast``: the 24-bit accumulator is exact for every int8 input, the clamp is ``-128..127`` or
  ``0..255``, ``n_in <= FAST_MAX_IN`` and ``n_out <= FAST_MAX_OUT``: the AVR runs the assembly
  kernel. :func:`all_fast` true: the renderer may ``#define KF_DENSE_ALL_FAST`` (drops the portable
  kernel from the AVR build, about 1 KB of flash).

The AVR kernel (:func:`avr_asm_block`, embedded in ``kf_dense.c``): per group of up to 8 rows the
inner loop costs ``lpm`` 3 + ``mul`` 2 + 3-byte subtract 3 = 8 cycles per MAC plus the input load
and loop counting shared by the rows (8.56 cycles per MAC for 8 rows); each row then costs about
40 cycles (bias, requantisation, clamp, int16 store), each group about 90 and each call about 300
(register saves, the pass over the input for ``S``). Measured in simavr: 9.3 cycles per MAC over
the default 320-32-32-2 policy, 10.7 for a 32x32 layer.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import numfmt
from .numfmt import QuantLayer

GROUP_SIZES = (8, 4, 2, 1)  #: rows per group, largest first (the AVR kernel has one loop per size)
FAST_MAX_IN = 510  #: widest layer the AVR kernel takes (it counts input pairs of a segment in 8 bits)
FAST_MAX_OUT = 2047  #: the AVR kernel counts groups of 8 rows in 8 bits
FAST_CLAMPS = ((numfmt.INT8_MIN, numfmt.INT8_MAX), (0, 255))  #: clamps the AVR kernel implements
ACC24_LIMIT = 2 ** (numfmt.ACC_BITS_NARROW - 1)
ACC32_LIMIT = 2 ** 31


def row_groups(n_out: int) -> list[tuple[int, int]]:
    """(first row, rows) of each group: 8 while 8 are left, then 4, 2, 1.

    >>> row_groups(19)
    [(0, 8), (8, 8), (16, 2), (18, 1)]
    >>> row_groups(2)
    [(0, 2)]
    """
    groups, g0 = [], 0
    while g0 < n_out:
        k = next(k for k in GROUP_SIZES if n_out - g0 >= k)
        groups.append((g0, k))
        g0 += k
    return groups


def kernel_weights(w: np.ndarray) -> np.ndarray:
    """(n_out, n_in) int8 -> flat int8 in kernel order: offset binary (``W ^ 0x80``), groups interleaved.

    >>> kernel_weights(np.array([[1, 2], [3, 4]], np.int8)).view(np.uint8).tolist()
    [129, 131, 130, 132]
    """
    w = np.asarray(w)
    assert w.dtype == np.int8 and w.ndim == 2, "weights must be a 2-D int8 array"
    wo = (w.astype(np.int16) + 128).astype(np.uint8)  # (n_out, n_in) offset binary
    parts = [wo[g0:g0 + k].T.reshape(-1) for g0, k in row_groups(w.shape[0])]  # input-major per group
    return np.concatenate(parts).view(np.int8)


def rounding(shift: np.ndarray) -> np.ndarray:
    """2^(s-1) for s > 0, 0 for s = 0 (int64): the half-up constant folded into the bias.

    >>> rounding(np.array([0, 1, 8])).tolist()
    [0, 1, 128]
    """
    s = np.asarray(shift, np.int64)
    return np.where(s > 0, np.left_shift(np.int64(1), np.maximum(s - 1, 0)), 0)


def proof(layer: QuantLayer) -> np.ndarray:
    """Largest ``|acc + 2^(s-1)|`` per row over every int8 input (int64, shape (n_out,))."""
    return numfmt.acc_bound(layer.w, layer.b.astype(np.int64) + rounding(layer.shift))


def is_fast(layer: QuantLayer) -> bool:
    """True when the AVR assembly kernel computes this layer exactly (24-bit proof, clamp, width).

    The proof includes the rounding constant 2^(s-1), so a fast row always has s <= 23.
    """
    n_out, n_in = layer.w.shape
    return bool(np.all(proof(layer) < ACC24_LIMIT) and (layer.lo, layer.hi) in FAST_CLAMPS
                and 1 <= n_in <= FAST_MAX_IN and n_out <= FAST_MAX_OUT)


def all_fast(layers) -> bool:
    """True when every layer is fast: the renderer may then ``#define KF_DENSE_ALL_FAST`` (saves ~1 KB)."""
    return all(is_fast(l) for l in layers)


def kernel_bias(layer: QuantLayer) -> np.ndarray:
    """The folded int32 bias ``b'`` (see module doc); for fast layers packed with the shift.

    Raises ``ValueError`` when ``acc + 2^(s-1)`` could leave int32 (the quantiser leaves that margin
    in practice; the message says which row).
    """
    n_out, n_in = layer.w.shape
    bound = proof(layer)
    if np.any(bound >= ACC32_LIMIT):
        j = int(np.argmax(bound))
        raise ValueError(f"row {j}: accumulator plus rounding may reach {int(bound[j])} >= 2^31; "
                         f"requantise with a smaller weight scale")
    wsum = (layer.w.astype(np.int64) + 128).sum(axis=1)  # (n_out,) sum of w'
    b = layer.b.astype(np.int64) + rounding(layer.shift) - 128 * wsum + 16384 * n_in
    if is_fast(layer):
        code = np.array([avr_shift_code(int(s)) for s in layer.shift], np.int64)
        b = (b & 0xFFFFFF) | (code << 24)
    return (b & 0xFFFFFFFF).astype(np.uint32).view(np.int32)


def avr_shift_code(s: int) -> int:
    """The AVR kernel's per-row requantisation code (top byte of a fast bias) for shift ``s`` (0..23).

    With v = r28:r1:r0 (24 bits), the value ``v >> 8`` is already in r28:r1, so for 8 <= s <= 11
    the code is just the bit count ``s - 8``; 12..15 shift left ``16 - s`` and drop a byte (0x20);
    16..23 first drop another byte (0x40); below 8 the 24-bit paths (0x80, with 0x20: left).

    >>> [avr_shift_code(s) for s in (9, 12, 15, 17, 23, 2, 6)]
    [1, 36, 33, 65, 97, 130, 162]
    """
    assert 0 <= s <= 23, f"shift {s} is never 24-bit exact"
    if s < 8:
        return 0x80 | s if s < 4 else 0xA0 | (8 - s)
    c = s - 8 if s < 16 else s - 16
    code = c if c < 4 else 0x20 | (8 - c)
    return code | (0x40 if s >= 16 else 0)


@dataclass(frozen=True)
class KernelLayer:
    """Everything the renderer writes for one ``kf_dense_t`` (arrays in PROGMEM, the rest inline)."""

    w: np.ndarray  #: (n_out * n_in,) int8, kernel order
    b: np.ndarray  #: (n_out,) int32, folded (packed with the shift when fast)
    shift: np.ndarray  #: (n_out,) uint8
    n_in: int
    n_out: int
    lo: int
    hi: int
    fast: bool
    acc_bound: int  #: max |acc + rounding| over every int8 input (the proof behind ``fast``)

    def c_initializer(self, w_name: str, b_name: str, shift_name: str) -> str:
        """The ``kf_dense_t`` initializer, e.g. ``{ L0_w, L0_b, L0_shift, 160u, 32u, -128, 127, 1u }``."""
        return (f"{{ {w_name}, {b_name}, {shift_name}, {self.n_in}u, {self.n_out}u, "
                f"{self.lo}, {self.hi}, {int(self.fast)}u }}")

    def c_source(self, prefix: str) -> str:
        """PROGMEM arrays ``<prefix>_w/_b/_shift`` and the descriptor ``static const kf_dense_t <prefix>``."""
        from .cformat import c_array, c_ident
        p = c_ident(prefix)
        path = "AVR assembly (24-bit exact)" if self.fast else "portable int32"
        return "\n".join([
            c_array(f"{p}_w", "int8_t", self.w, comment=f"{p}: {self.n_out}x{self.n_in} weights, kernel order"),
            c_array(f"{p}_b", "int32_t", self.b, per_line=8, comment=f"{p}: folded biases ({path})"),
            c_array(f"{p}_shift", "uint8_t", self.shift, comment=f"{p}: shifts"),
            f"static const kf_dense_t {p} = {self.c_initializer(p + '_w', p + '_b', p + '_shift')};",
        ])


def kernel_layer(layer: QuantLayer) -> KernelLayer:
    """The kernel arrays and descriptor fields of one quantised layer."""
    n_out, n_in = layer.w.shape
    return KernelLayer(w=kernel_weights(layer.w), b=kernel_bias(layer), shift=layer.shift.astype(np.uint8),
                       n_in=int(n_in), n_out=int(n_out), lo=int(layer.lo), hi=int(layer.hi),
                       fast=is_fast(layer), acc_bound=int(proof(layer).max()))


def run(kl: KernelLayer, x: np.ndarray) -> np.ndarray:
    """NumPy model of the kernel's own arithmetic on its arrays (int64 (..., n_out)); tests compare it
    with :func:`numfmt.dense_int`. ``x`` (..., n_in) int8 values."""
    x = np.asarray(x, np.int64)
    xo = x + 128  # (..., n_in) x'
    wo = np.empty((kl.n_out, kl.n_in), np.int64)  # (n_out, n_in) w' back in row order
    flat = kl.w.view(np.uint8).astype(np.int64)
    for g0, k in row_groups(kl.n_out):
        wo[g0:g0 + k] = flat[g0 * kl.n_in:(g0 + k) * kl.n_in].reshape(kl.n_in, k).T
    b = kl.b.astype(np.int64) & 0xFFFFFFFF
    s = kl.shift.astype(np.int64)
    b, mod = (b & 0xFFFFFF, 2 ** 24) if kl.fast else (b, 2 ** 32)
    acc = (b - 128 * xo.sum(axis=-1, keepdims=True) + xo @ wo.T) % mod  # (..., n_out)
    acc = np.where(acc >= mod // 2, acc - mod, acc)  # two's complement
    return np.clip(np.right_shift(acc, s), kl.lo, kl.hi)


# --------------------------------------------------------------------------------------------
# The AVR assembly kernel (kf_dense_avr), generated here and embedded in kf_dense.c
# --------------------------------------------------------------------------------------------
#: Accumulator registers of group row r (low, mid, high byte); high bytes are r16..r23 so that
#: ``sbci hi, 0`` can propagate the borrow without a zero register (the inner loop uses all 32).
AVR_ACC = (("r2", "r3", "r16"), ("r4", "r5", "r17"), ("r6", "r7", "r18"), ("r8", "r9", "r19"),
           ("r10", "r11", "r20"), ("r12", "r13", "r21"), ("r14", "r15", "r22"), ("r24", "r25", "r23"))
#: Stack frame of kf_dense_avr (offsets from Y = SP, so the first byte is Y+1).
AVR_FRAME = {"X1": 1, "ODD1": 3, "PAIRS1": 4, "X2": 5, "ODD2": 7, "PAIRS2": 8, "Y": 9, "B": 11, "W": 13,
             "T": 15, "G8": 18, "REM": 19}
AVR_FRAME_SIZE = 19
ASM_BEGIN = "/* ---- BEGIN kf_dense_avr: generated by export.kernel.avr_asm_block(), do not edit ---- */"
ASM_END = "/* ---- END kf_dense_avr ---- */"


def _avr_asm_lines() -> list[str]:
    """The assembly of ``void kf_dense_avr(L, x1, n1, x2, y)`` (avr-gcc ABI), one instruction a line.

    Per group of k rows: the accumulators start at T = 128 * sum(x') and *subtract* every unsigned
    product w' * x' (``sub, sbc, sbci 0``: 3 cycles, no zero register), so after the inputs
    A = T - sum; the row's value is ``v = b' - A`` (mod 2^24), then ``floor(v / 2^s)`` by byte moves
    and single-bit shifts, the clamp, and an int16 store. Inner loop: ``lpm`` 3 + ``mul`` 2 + 3 per
    MAC, plus ``ld``/``subi``/loop counting shared by the k rows (two inputs per iteration).
    """
    F = AVR_FRAME
    out: list[str] = []
    a = out.append

    def sp_to_y() -> None:
        a("in r28, 0x3d"); a("in r29, 0x3e")

    def body(k: int) -> None:  # one input, k rows
        a("ld r28, X+"); a("subi r28, 0x80")
        for lo, mid, hi in AVR_ACC[:k]:
            a("lpm r0, Z+"); a("mul r0, r28"); a(f"sub {lo}, r0"); a(f"sbc {mid}, r1"); a(f"sbci {hi}, 0")

    def segment(xo: int, k: int) -> None:  # r0 = n & 1, r1 = n >> 1; Y = frame on entry; clobbers Y
        a(f"ldd r26, Y+{xo}"); a(f"ldd r27, Y+{xo + 1}"); a("movw r28, r0")
        a(f"rcall .Lkf_mac{k}")

    def group(k: int) -> None:  # Y = frame on entry and on exit
        a(f"ldd r0, Y+{F['T']}"); a(f"ldd r1, Y+{F['T'] + 1}"); a(f"ldd r26, Y+{F['T'] + 2}")
        for lo, _, hi in AVR_ACC[:k]:
            a(f"movw {lo}, r0"); a(f"mov {hi}, r26")
        a(f"ldd r30, Y+{F['W']}"); a(f"ldd r31, Y+{F['W'] + 1}")
        a(f"ldd r0, Y+{F['ODD1']}"); a(f"ldd r1, Y+{F['PAIRS1']}")
        segment(F["X1"], k)
        sp_to_y()
        a(f"ldd r26, Y+{F['ODD2']}"); a(f"ldd r27, Y+{F['PAIRS2']}"); a("movw r0, r26"); a("or r26, r27")
        a(f"breq .Lkf_noseg2_{k}")
        segment(F["X2"], k)
        sp_to_y()
        a(f".Lkf_noseg2_{k}:")
        a(f"std Y+{F['W']}, r30"); a(f"std Y+{F['W'] + 1}, r31")
        a(f"ldd r30, Y+{F['B']}"); a(f"ldd r31, Y+{F['B'] + 1}")
        a(f"ldd r26, Y+{F['Y']}"); a(f"ldd r27, Y+{F['Y'] + 1}")
        for lo, mid, hi in AVR_ACC[:k]:
            a("lpm r0, Z+"); a("lpm r1, Z+"); a("lpm r28, Z+"); a("lpm r29, Z+")  # b' (24 bits), s
            a(f"sub r0, {lo}"); a(f"sbc r1, {mid}"); a(f"sbc r28, {hi}")  # v = b' - A
            a("rcall .Lkf_post")
        sp_to_y()
        a(f"std Y+{F['B']}, r30"); a(f"std Y+{F['B'] + 1}, r31")
        a(f"std Y+{F['Y']}, r26"); a(f"std Y+{F['Y'] + 1}, r27")

    a(".global kf_dense_avr"); a(".type kf_dense_avr, @function"); a("kf_dense_avr:")
    saved = [f"r{i}" for i in range(2, 18)] + ["r28", "r29"]
    for r in saved:
        a(f"push {r}")
    sp_to_y(); a(f"sbiw r28, {AVR_FRAME_SIZE}")
    a("in r0, 0x3f"); a("cli"); a("out 0x3e, r29"); a("out 0x3f, r0"); a("out 0x3d, r28")
    a(f"std Y+{F['X1']}, r22"); a(f"std Y+{F['X1'] + 1}, r23")
    a(f"std Y+{F['X2']}, r18"); a(f"std Y+{F['X2'] + 1}, r19")
    a(f"std Y+{F['Y']}, r16"); a(f"std Y+{F['Y'] + 1}, r17")
    a("movw r30, r24")  # Z = L (SRAM): w 0, b 2, shift 4, n_in 6, n_out 8, lo 10, hi 12, fast 14
    a("ld r24, Z"); a("ldd r25, Z+1"); a(f"std Y+{F['W']}, r24"); a(f"std Y+{F['W'] + 1}, r25")
    a("ldd r24, Z+2"); a("ldd r25, Z+3"); a(f"std Y+{F['B']}, r24"); a(f"std Y+{F['B'] + 1}, r25")
    a("ldd r24, Z+8"); a("ldd r25, Z+9")  # n_out < 2048: G8 = n_out / 8, REM = n_out % 8
    a("mov r0, r24"); a("andi r24, 7"); a(f"std Y+{F['REM']}, r24")
    for _ in range(3):
        a("lsr r25"); a("ror r0")
    a(f"std Y+{F['G8']}, r0")
    a("clt"); a("ldd r24, Z+10"); a("ldd r25, Z+11"); a("or r24, r25"); a("brne 1f"); a("set"); a("1:")  # T: clamp 0..255
    a("ldd r2, Z+6"); a("ldd r3, Z+7"); a("sub r2, r20"); a("sbc r3, r21")  # n2 = n_in - n1 (<= 510)
    for n, odd, pairs in (("r20", "ODD1", "PAIRS1"), ("r2", "ODD2", "PAIRS2")):
        a(f"movw r24, {n}"); a("lsr r25"); a("ror r24"); a("rol r25")  # r24 = n >> 1, r25 = n & 1
        a(f"std Y+{F[odd]}, r25"); a(f"std Y+{F[pairs]}, r24")
    # S = sum of x' over both segments (24 bits), T = 128 * S (mod 2^24)
    a("movw r26, r18"); a("movw r24, r2"); a("clr r1"); a("clr r2"); a("clr r3"); a("clr r4"); a("rcall .Lkf_sum")
    a("movw r26, r22"); a("movw r24, r20"); a("rcall .Lkf_sum")
    a("lsr r4"); a("ror r3"); a("ror r2"); a("clr r0"); a("ror r0")
    a(f"std Y+{F['T']}, r0"); a(f"std Y+{F['T'] + 1}, r2"); a(f"std Y+{F['T'] + 2}, r3")
    # groups of 8 rows, then 4, 2, 1 (export.kernel.row_groups)
    a(".Lkf_loop8:")
    a(f"ldd r24, Y+{F['G8']}"); a("subi r24, 1"); a("brcc 1f"); a("rjmp .Lkf_tail"); a("1:")
    a(f"std Y+{F['G8']}, r24")
    group(8)
    a("rjmp .Lkf_loop8")
    a(".Lkf_tail:")
    a(f"ldd r24, Y+{F['REM']}")
    for k, bit in ((4, 2), (2, 1), (1, 0)):
        a(f"sbrs r24, {bit}"); a(f"rjmp .Lkf_skip{k}")
        group(k)
        a(f"ldd r24, Y+{F['REM']}")
        a(f".Lkf_skip{k}:")
    sp_to_y(); a(f"adiw r28, {AVR_FRAME_SIZE}")
    a("in r0, 0x3f"); a("cli"); a("out 0x3e, r29"); a("out 0x3f, r0"); a("out 0x3d, r28")
    for r in reversed(saved):
        a(f"pop {r}")
    a("clr r1"); a("ret")
    # r4:r3:r2 += sum (x ^ 0x80) over X[0..r25:r24-1]; r1 = 0; clobbers r17, r24, r25, X
    a(".Lkf_sum:")

    def one() -> None:
        a("ld r17, X+"); a("subi r17, 0x80"); a("add r2, r17"); a("adc r3, r1"); a("adc r4, r1")
    a("sbrs r24, 0"); a("rjmp 1f"); one()
    a("1:"); a("sbrs r24, 1"); a("rjmp 2f"); one(); one()
    a("2:"); a("lsr r25"); a("ror r24"); a("lsr r25"); a("ror r24"); a("sbiw r24, 0"); a("breq 4f")
    a("3:"); one(); one(); one(); one(); a("sbiw r24, 1"); a("brne 3b")
    a("4:"); a("ret")
    # MAC loops: X = inputs, Z = weights, r28 = n & 1, r29 = n >> 1
    for k in (8, 4, 2, 1):
        a(f".Lkf_mac{k}:")
        a("sbrs r28, 0"); a("rjmp 1f")
        body(k)
        a("1:"); a("tst r29"); a("brne 2f"); a("ret")
        a("2:")
        body(k); body(k)
        if k <= 4:  # the loop fits a conditional branch (+-64 words)
            a("dec r29"); a("brne 2b"); a("ret")
        else:
            a("dec r29"); a("breq 3f"); a("rjmp 2b")
            a("3:"); a("ret")
    # requantise: v = r28:r1:r0 (24-bit), s = r29; y = clamp(floor(v / 2^s)) -> X+ (int16);
    # SREG.T set: clamp 0..255, clear: -128..127
    a(".Lkf_post:")  # the value v >> 8 is r28:r1; the code says how to finish (avr_shift_code)
    a("cpi r29, 4"); a("brsh .Lkf_p_other")
    a(".Lkf_p_right:")  # 16-bit r28:r1 shifted right by r29 (0..3)
    a("tst r29"); a("breq 4f")
    a("2:"); a("asr r28"); a("ror r1"); a("dec r29"); a("brne 2b")
    # clamp and store the 16-bit r28:r1; SREG.T set: 0..255, clear: -128..127
    a("4:"); a("brts 6f")
    a("mov r0, r1"); a("lsl r0"); a("sbc r0, r0"); a("cp r28, r0"); a("brne 5f")
    a("st X+, r1"); a("st X+, r0"); a("ret")
    a("5:"); a("ldi r29, 0x7f"); a("sbrc r28, 7"); a("ldi r29, 0x80"); a("st X+, r29")
    a("lsl r28"); a("sbc r28, r28"); a("st X+, r28"); a("ret")
    a("6:"); a("tst r28"); a("brne 7f")
    a("st X+, r1"); a("st X+, r28"); a("ret")
    a("7:"); a("ldi r29, 0xff"); a("sbrc r28, 7"); a("ldi r29, 0"); a("st X+, r29")
    a("clr r29"); a("st X+, r29"); a("ret")
    a(".Lkf_p_other:")
    a("sbrc r29, 7"); a("rjmp .Lkf_p_small")
    a("sbrs r29, 6"); a("rjmp .Lkf_p_left")
    a("mov r1, r28"); a("lsl r28"); a("sbc r28, r28")  # s >= 16: drop another byte
    a("andi r29, 0x3f"); a("cpi r29, 4"); a("brlo .Lkf_p_right")
    a(".Lkf_p_left:")  # shift r28:r1 left by t = r29 & 7 (1..4) into a sign byte r0, keep r0:r28
    a("andi r29, 7"); a("mov r0, r28"); a("lsl r0"); a("sbc r0, r0")
    a("3:"); a("lsl r1"); a("rol r28"); a("rol r0"); a("dec r29"); a("brne 3b")
    a("mov r1, r28"); a("mov r28, r0"); a("rjmp 4b")
    a(".Lkf_p_small:")  # s < 8: the 24-bit v; 0x80 | s (s < 4) right, 0xA0 | t left by t = 8 - s
    a("sbrc r29, 5"); a("rjmp .Lkf_p_left24")
    a("andi r29, 7"); a("breq 1f")
    a("3:"); a("asr r28"); a("ror r1"); a("ror r0"); a("dec r29"); a("brne 3b")
    a("1:"); a("mov r29, r28"); a("mov r28, r1"); a("mov r1, r0"); a("rjmp .Lkf_p_fix")
    a(".Lkf_p_left24:")  # E:r28:r1:r0 <<= t with E = r29 (a count-free chain), keep E:r28:r1
    a("andi r29, 7"); a("cpi r29, 2"); a("brlo .Lkf_p_t1"); a("breq .Lkf_p_t2"); a("cpi r29, 3"); a("breq .Lkf_p_t3")
    sign = ("mov r29, r28", "lsl r29", "sbc r29, r29")  # r29 = sign extension of r28
    for t in (4, 3, 2, 1):
        if t < 4:
            a(f".Lkf_p_t{t}:")
        for ln in sign:
            a(ln)
        a(f"rjmp .Lkf_p_sh{t}")
    for t in (4, 3, 2, 1):  # falls through: entering at sh<t> shifts t bits left
        a(f".Lkf_p_sh{t}:"); a("lsl r0"); a("rol r1"); a("rol r28"); a("rol r29")
    a(".Lkf_p_fix:")  # 24-bit r29:r28:r1 -> 16-bit r28:r1, saturated when it does not fit
    a("mov r0, r28"); a("lsl r0"); a("sbc r0, r0"); a("cp r29, r0"); a("brne 8f"); a("rjmp 4b")
    a("8:"); a("ldi r28, 0x7f"); a("sbrc r29, 7"); a("ldi r28, 0x80"); a("rjmp 4b")
    a(".size kf_dense_avr, .-kf_dense_avr")
    return out


def avr_asm_block() -> str:
    """The C text (a file-scope ``__asm__``) of the AVR kernel, as embedded in ``kf_dense.c``.

    ``write_avr_asm()`` puts it there; a test checks the file holds exactly this text.
    """
    rows: list[str] = []
    cur: list[str] = []
    for ln in _avr_asm_lines():  # labels start a line; instructions packed up to ~90 columns
        if ln.endswith(":") or sum(len(c) + 4 for c in cur) + len(ln) > 80:
            if cur:
                rows.append("\\n\\t".join(cur))
            cur = []
        if ln.endswith(":"):
            rows.append(ln)
        else:
            cur.append(ln)
    if cur:
        rows.append("\\n\\t".join(cur))
    body = "\n".join(f'    "{r}\\n"' if r.endswith(":") else f'    "\\t{r}\\n"' for r in rows)
    return (f"{ASM_BEGIN}\n#if defined(__AVR__) && !defined(KF_DENSE_PORTABLE)\n__asm__(\n"
            f"    \".pushsection .text\\n\"\n{body}\n    \".popsection\\n\"\n);\n#endif\n{ASM_END}")


def kf_dense_c_path():
    """Path of ``firmware_templates/kf_dense.c``."""
    from pathlib import Path
    return Path(__file__).resolve().parent.parent / "firmware_templates" / "kf_dense.c"


def write_avr_asm() -> None:
    """Replace the generated block of ``kf_dense.c`` with :func:`avr_asm_block` (a developer tool)."""
    path = kf_dense_c_path()
    text = path.read_text()
    i, j = text.index(ASM_BEGIN), text.index(ASM_END) + len(ASM_END)
    path.write_text(text[:i] + avr_asm_block() + text[j:])
