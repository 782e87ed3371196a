"""The dense-layer kernel's view of a layer: the arrays ``firmware_templates/kf_dense.c`` consumes.

One set of arrays serves the portable C (host, Kilombo) and the AVR assembly kernel, so the host and
the robot compute the same integers. The kernel computes :func:`kiloforge.numfmt.dense_int` exactly,
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

* ``w``: int8, rows in groups of 8 (then of 2, then 1 for the rest, :func:`row_groups`), each group
  interleaved input-major so the AVR streams it with ``lpm Z+`` for 8 rows per loaded input:
  ``w[g0*n + i*k + r] = W[g0+r, i] + 128`` (as a byte: the bit pattern of ``W ^ 0x80``).
* ``b``: int32 folded bias ``b'``; for ``fast`` layers ``(b' mod 2^24) | (code << 24)`` with the
  AVR kernel's requantisation code :func:`avr_shift_code` (the portable C ignores the top byte).
* ``shift``: uint8 ``s`` (the portable C reads it).
* ``fast``: the 24-bit accumulator is exact for every int8 input, the clamp is ``-128..127`` or
  ``0..255``, ``n_in <= FAST_MAX_IN`` and ``n_out <= FAST_MAX_OUT``: the AVR runs the assembly
  kernel. :func:`all_fast` true: the renderer may ``#define KF_DENSE_ALL_FAST`` (drops the portable
  kernel from the AVR build, about 1 KB of flash).

The AVR kernel (:func:`avr_asm_block`, embedded in ``kf_dense.c``): per group of 8 rows the inner
loop costs ``lpm`` 3 + ``mul`` 2 + 3-byte subtract 3 = 8 cycles per MAC plus the input's ``ld`` and
``subi`` (3) and 1 cycle of loop counting (4 inputs per pass) shared by the 8 rows: 8.5 cycles per
MAC. Each row then costs (bias, requantisation, clamp, int16 store) 26 + 4 (s - 8) cycles when it is
int8 with s = 9..15 (inline: 30 at s = 9), 31 at s = 8, 35 at s = 7 and about 50 otherwise (see
:func:`avr_shift_code`); each group of 8 about 66 and each call about 220 plus 5.75 per input
(register saves, the pass over the input for ``S``; a layer of fewer than 8 rows sums x' in its
own MAC loop instead). Measured in simavr (``tests/bench/bench_avr.py``): 9.0 cycles per MAC over
the default 320-32-32-2 policy, 10.1 for a 32x32 layer, 10.5 over a 32-32-32-2 network. The kernel
keeps its state between row groups in a static 20-byte block: it is not reentrant (never call it
from an interrupt).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kiloforge import numfmt
from kiloforge.numfmt import QuantLayer

from .cformat import c_array, c_ident
from .templates import TEMPLATE_DIR

GROUP_SIZES = (8, 2, 1)  #: rows per group, largest first (the AVR kernel has one loop per size)
FAST_MAX_IN = 510  #: widest layer the AVR kernel takes (it counts passes of 4 inputs in 8 bits)
FAST_MAX_OUT = 2047  #: the AVR kernel counts groups of 8 rows in 8 bits
FAST_CLAMPS = ((numfmt.INT8_MIN, numfmt.INT8_MAX), (0, numfmt.UINT8_MAX))  #: clamps the AVR kernel implements


def row_groups(n_out: int) -> list[tuple[int, int]]:
    """(first row, rows) of each group: 8 while 8 are left, then 2 while 2 are left, then 1.

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


def proof(layer: QuantLayer) -> np.ndarray:
    """Largest ``|acc + 2^(s-1)|`` per row over every int8 input (int64, shape (n_out,)): numfmt.acc_bound."""
    return numfmt.acc_bound(layer.w, layer.b, layer.shift)


def is_fast(layer: QuantLayer) -> bool:
    """True when the AVR assembly kernel computes this layer exactly: the 24-bit proof
    (:attr:`QuantLayer.acc24_safe`, rounding included, so a fast row always has s <= 23), a clamp it
    implements and a width it counts."""
    n_out, n_in = layer.w.shape
    return bool(layer.acc24_safe and (layer.lo, layer.hi) in FAST_CLAMPS
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
    if np.any(bound >= numfmt.ACC32_LIMIT):
        j = int(np.argmax(bound))
        raise ValueError(f"row {j}: accumulator plus rounding may reach {int(bound[j])} >= 2^31; "
                         f"requantise with a smaller weight scale")
    wsum = (layer.w.astype(np.int64) + 128).sum(axis=1)  # (n_out,) sum of w'
    b = layer.b.astype(np.int64) + numfmt.half_up_constant(layer.shift) - 128 * wsum + 16384 * n_in
    if is_fast(layer):
        code = np.array([avr_shift_code(int(s), layer.lo == 0) for s in layer.shift], np.int64)
        b = (b & 0xFFFFFF) | (code << 24)
    return (b & 0xFFFFFFFF).astype(np.uint32).view(np.int32)


#: Class bits of the AVR kernel's general requantisation codes (see :func:`avr_shift_code`).
AVR_CODE_CLASSES = {"right16": 0x00, "left16": 0x10, "left24": 0x20}


def avr_shift_code(s: int, unsigned: bool = False) -> int:
    """The AVR kernel's per-row requantisation code (top byte of a fast bias) for shift ``s`` (0..23).

    ``unsigned``: the row clamps to ``0..255`` (else ``-128..127``). With v = h:m:l the row's 24-bit
    value, int8 rows with s = 9..15 take the inline path: code ``s - 8`` shifts ``h:m`` right;
    every other row has bit 7 set: ``0x80 | 0x40 (0..255) | class | n`` with the classes
    (:data:`AVR_CODE_CLASSES`) right16 ``h:m >> n`` (s = 8 + n), left16 ``(E:h:m << n) >> 8``
    (s = 16 - n) and left24 ``(E:h:m:l << n) >> 8`` (s = 8 - n), E being h's sign byte; the
    kernel's row stubs take int8 s = 7 and s = 8 without the general routine.

    >>> [avr_shift_code(s) for s in (9, 10, 15)]
    [1, 2, 7]
    >>> [hex(avr_shift_code(s)) for s in (8, 7, 4, 0, 16, 23)]
    ['0x80', '0xa1', '0xa4', '0xa8', '0x88', '0x8f']
    >>> [hex(avr_shift_code(s, unsigned=True)) for s in (9, 14, 15, 16)]
    ['0xc1', '0xd2', '0xd1', '0xc8']
    """
    assert 0 <= s <= 23, f"shift {s} is never 24-bit exact"
    if not unsigned and 9 <= s <= 15:
        return s - 8
    if s < 8:
        cls, n = "left24", 8 - s
    elif unsigned and 12 <= s <= 15:
        cls, n = "left16", 16 - s
    else:
        cls, n = "right16", s - 8
    return 0x80 | (0x40 if unsigned else 0) | AVR_CODE_CLASSES[cls] | n


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
    b, mod = (b & 0xFFFFFF, 1 << numfmt.ACC_BITS_NARROW) if kl.fast else (b, 1 << numfmt.ACC_BITS_REFERENCE)
    acc = (b - 128 * xo.sum(axis=-1, keepdims=True) + xo @ wo.T) % mod  # (..., n_out)
    acc = np.where(acc >= mod // 2, acc - mod, acc)  # two's complement
    return np.clip(np.right_shift(acc, s), kl.lo, kl.hi)


# --------------------------------------------------------------------------------------------
# The AVR assembly kernel (kf_dense_avr), generated here and embedded in kf_dense.c
# --------------------------------------------------------------------------------------------
#: Accumulator registers of group row r (low, mid, high byte); high bytes are r16..r23 so that
#: ``sbci hi, 0`` can propagate the borrow without a zero register (the inner loop uses all 32).
#: A group of k < 8 rows uses the last k triples, so that every group ends in the same row code.
AVR_ACC = (("r2", "r3", "r16"), ("r4", "r5", "r17"), ("r6", "r7", "r18"), ("r8", "r9", "r19"),
           ("r10", "r11", "r20"), ("r12", "r13", "r21"), ("r14", "r15", "r22"), ("r24", "r25", "r23"))
#: The kernel's state between row groups: a static block (.bss, 20 bytes), read with lds / sts.
#: Per input segment i: X<i> its address, E<i> = n mod 4, Q<i> = ceil(n / 4) (the MAC loop's entry
#: and passes); T = 128 * sum(x') (24 bits); W, B, Y the next group's weights, biases, outputs;
#: P2 = 0xff while a group of 8 runs through the second segment.
AVR_FRAME = {"T": 0, "W": 3, "B": 5, "Y": 7, "X1": 9, "E1": 11, "Q1": 12, "X2": 13, "E2": 15, "Q2": 16,
             "G8": 17, "REM": 18, "P2": 19}
AVR_FRAME_SIZE = 20
ASM_BEGIN = "/* ---- BEGIN kf_dense_avr: generated by export.codegen.kernel.avr_asm_block(), do not edit ---- */"
ASM_END = "/* ---- END kf_dense_avr ---- */"


def _avr_asm_lines() -> list[str]:
    """The assembly of ``void kf_dense_avr(L, x1, n1, x2, y)`` (avr-gcc ABI), one instruction a line.

    Per group of k rows: the accumulators start at T = 128 * sum(x') and *subtract* every unsigned
    product w' * x' (``sub, sbc, sbci 0``: 3 cycles, no zero register), so after the inputs
    A = T - sum; the row's value is ``v = b' - A`` (mod 2^24), then ``floor(v / 2^s)`` (inline for
    int8 rows with s = 9..15, in the row's stub for s = 7 and 8, else in ``.Lkf_post``; see
    :func:`avr_shift_code`), the clamp, and an int16 store. Inner loop:
    ``lpm`` 3 + ``mul`` 2 + 3 per MAC, plus ``ld``/``subi`` and 1 cycle of loop counting per input
    shared by the k rows (4 inputs per pass). Groups of 2 and 1 rows (the last of a layer) sum x'
    in their own loop (a layer of fewer than 8 rows needs no pass for T).
    """
    out: list[str] = []
    a = out.append

    def f(name: str, off: int = 0) -> str:  # a frame byte (static)
        return f".Lkf_f+{AVR_FRAME[name] + off}"

    def std(name: str, reg: str, off: int = 0) -> None:  # through Y = .Lkf_f
        a(f"std Y+{AVR_FRAME[name] + off}, {reg}")

    def lds2(r_lo: str, r_hi: str, name: str) -> None:
        a(f"lds {r_lo}, {f(name)}"); a(f"lds {r_hi}, {f(name, 1)}")

    def sts2(name: str, r_lo: str, r_hi: str) -> None:
        a(f"sts {f(name)}, {r_lo}"); a(f"sts {f(name, 1)}, {r_hi}")

    def seg(i: int) -> None:  # X, r28 (n & 3), r29 (passes) of input segment i
        lds2("r26", "r27", f"X{i}"); a(f"lds r28, {f(f'E{i}')}"); a(f"lds r29, {f(f'Q{i}')}")

    def body(rows, s_sum: bool = False) -> None:  # one input, the group's rows
        a("ld r28, X+"); a("subi r28, 0x80")
        if s_sum:  # r6:r5:r4 += x' (r7 = 0)
            a("add r4, r28"); a("adc r5, r7"); a("adc r6, r7")
        for lo, mid, hi in rows:
            a("lpm r0, Z+"); a("mul r0, r28"); a(f"sub {lo}, r0"); a(f"sbc {mid}, r1"); a(f"sbci {hi}, 0")

    def tt() -> None:  # T = 128 S mod 2^24 = r5:r4:r0 from S = r6:r5:r4
        a("lsr r6"); a("ror r5"); a("ror r4"); a("clr r0"); a("ror r0")

    def dispatch(k: int) -> None:  # enter the MAC loop where the first pass takes n mod 4 (or 4) inputs
        a("sbrc r28, 1"); a(f"rjmp .Lkf_m{k}a"); a("sbrc r28, 0"); a(f"rjmp .Lkf_m{k}e1")

    a(".pushsection .bss"); a(".Lkf_f:"); a(f".skip {AVR_FRAME_SIZE}"); a(".popsection")
    a(".global kf_dense_avr"); a(".type kf_dense_avr, @function"); a("kf_dense_avr:")
    saved = [f"r{i}" for i in range(2, 18)] + ["r28", "r29"]
    for r in saved:
        a(f"push {r}")
    a("ldi r28, lo8(.Lkf_f)"); a("ldi r29, hi8(.Lkf_f)")
    a("movw r30, r24")  # Z = L (SRAM): w 0, b 2, shift 4, n_in 6, n_out 8, lo 10, hi 12, fast 14
    a("ld r24, Z"); a("ldd r25, Z+1"); std("W", "r24"); std("W", "r25", 1)
    a("ldd r24, Z+2"); a("ldd r25, Z+3"); std("B", "r24"); std("B", "r25", 1)
    std("Y", "r16"); std("Y", "r17", 1); std("P2", "r1")
    a("ldd r24, Z+8"); a("ldd r25, Z+9")  # n_out < 2048: G8 = n_out / 8, REM = n_out % 8
    a("mov r11, r24"); a("andi r24, 7"); std("REM", "r24")
    for _ in range(3):
        a("lsr r25"); a("ror r11")
    std("G8", "r11")
    a("ldd r2, Z+6"); a("ldd r3, Z+7"); a("sub r2, r20"); a("sbc r3, r21")  # n2 = n_in - n1 (<= 510)
    # segments x1[n1], x2[n2]; one segment (T clear) when either is empty or they are contiguous
    a("clt"); a("mov r24, r20"); a("or r24, r21"); a("brne .Lkf_s1")
    a("movw r22, r18"); a("movw r20, r2"); a("rjmp .Lkf_s3")
    a(".Lkf_s1:"); a("mov r24, r2"); a("or r24, r3"); a("breq .Lkf_s3")
    a("movw r24, r22"); a("add r24, r20"); a("adc r25, r21"); a("cp r24, r18"); a("cpc r25, r19")
    a("brne .Lkf_s2"); a("add r20, r2"); a("adc r21, r3"); a("rjmp .Lkf_s3")
    a(".Lkf_s2:"); a("set")
    a(".Lkf_s3:"); a("clr r4"); a("clr r5"); a("clr r6")  # S = sum of x' (24 bits); r1 = 0 (ABI)
    a("adiw r28, 9"); a("movw r26, r22"); a("movw r24, r20"); a("rcall .Lkf_segp")  # Y = frame + X1
    a("brtc .Lkf_s4"); a("adiw r28, 4"); a("movw r26, r18"); a("movw r24, r2"); a("rcall .Lkf_segp")
    a(".Lkf_s4:"); tt(); sts2("T", "r0", "r4"); a(f"sts {f('T', 2)}, r5")
    a("rjmp .Lkf_next")
    # the groups left after those of 8 rows: 2, then 1 (export.codegen.kernel.row_groups)
    a(".Lkf_tail:"); a(f"lds r24, {f('REM')}"); a("cpi r24, 2"); a("brlo .Lkf_t1"); a("rjmp .Lkf_g2")
    a(".Lkf_t1:"); a("sbrc r24, 0"); a("rjmp .Lkf_g1"); a("rjmp .Lkf_done")
    # groups of 8 rows: the hot path, MAC loop inline
    a(".Lkf_next:"); a(f"lds r24, {f('G8')}"); a("subi r24, 1"); a("brcs .Lkf_tail"); a(f"sts {f('G8')}, r24")
    a(f"lds r0, {f('T')}"); a(f"lds r1, {f('T', 1)}"); a(f"lds r26, {f('T', 2)}")
    for lo, _, hi in AVR_ACC:
        a(f"movw {lo}, r0"); a(f"mov {hi}, r26")
    lds2("r30", "r31", "W"); seg(1)
    a(".Lkf_m8d:"); dispatch(8)
    for e in (0, 3, 2, 1):
        a(f".Lkf_m8e{e}:"); body(AVR_ACC)
    a("dec r29"); a("breq .Lkf_m8x"); a("rjmp .Lkf_m8e0")
    a(".Lkf_m8a:"); a("sbrc r28, 0"); a("rjmp .Lkf_m8e3"); a("rjmp .Lkf_m8e2")
    a(".Lkf_m8s:"); a(f"lds r28, {f('P2')}"); a("com r28"); a(f"sts {f('P2')}, r28"); a("breq .Lkf_g8b")
    seg(2); a("rjmp .Lkf_m8d")
    a(".Lkf_m8x:"); a("brts .Lkf_m8s")  # two segments: the second, once (P2 toggles)
    a(".Lkf_g8b:"); sts2("W", "r30", "r31"); lds2("r30", "r31", "B"); lds2("r26", "r27", "Y")
    # the rows' epilogue, entered at row 8 - k: v = b' - A, requantise, clamp, store int16 at X+
    _avr_rows(a, [".Lkf_row8:", f"sts {f('B')}, r30", f"sts {f('B', 1)}, r31", f"sts {f('Y')}, r26",
                  f"sts {f('Y', 1)}, r27", "rjmp .Lkf_next"])
    # tail groups (2 and 1 rows, the last of the layer): accumulators from 0, T from their own sum
    for k in (2, 1):
        a(f".Lkf_g{k}:"); a(f"subi r24, {k}"); a(f"sts {f('REM')}, r24"); a(f"rcall .Lkf_tpre{8 - k}")
        a(f"rcall .Lkf_mac{k}"); a(f"brtc .Lkf_g{k}b"); a("rcall .Lkf_seg2"); a(f"rcall .Lkf_mac{k}")
        a(f".Lkf_g{k}b:"); a(f"rcall .Lkf_addt{8 - k}"); a(f"rjmp .Lkf_row{8 - k}")
    for r in (6, 7):  # accumulators of rows r..7 and S = 0, r7 = 0, Z = W, segment 1
        lo, mid, hi = AVR_ACC[r]
        a(f".Lkf_tpre{r}:"); a(f"clr {lo}"); a(f"clr {mid}"); a(f"clr {hi}")
    a("clr r4"); a("clr r5"); a("clr r6"); a("clr r7"); lds2("r30", "r31", "W")
    a(".Lkf_seg1:"); seg(1); a("ret")
    a(".Lkf_seg2:"); seg(2); a("ret")
    for r in (6, 7):  # A += T for rows r..7; W, B, Y for the epilogue
        a(f".Lkf_addt{r}:"); tt()
        for lo, mid, hi in AVR_ACC[r:]:
            a(f"add {lo}, r0"); a(f"adc {mid}, r4"); a(f"adc {hi}, r5")
        if r == 6:
            a("rjmp .Lkf_addt")
    a(".Lkf_addt:"); sts2("W", "r30", "r31"); lds2("r30", "r31", "B"); lds2("r26", "r27", "Y"); a("ret")
    a(".Lkf_done:")
    for r in reversed(saved):
        a(f"pop {r}")
    a("clr r1"); a("ret")
    _avr_sum(a)
    for k in (2, 1):  # tail MAC loops (X, r28 = n & 3, r29 = passes), summing x' too
        rows = AVR_ACC[8 - k:]
        a(f".Lkf_mac{k}:"); dispatch(k)
        for e in (0, 3, 2, 1):
            a(f".Lkf_m{k}e{e}:"); body(rows, s_sum=True)
        a("dec r29"); a(f"brne .Lkf_m{k}e0"); a("ret")
        a(f".Lkf_m{k}a:"); a("sbrc r28, 0"); a(f"rjmp .Lkf_m{k}e3"); a(f"rjmp .Lkf_m{k}e2")
    _avr_post(a)
    a(".size kf_dense_avr, .-kf_dense_avr")
    return out


def _avr_rows(a, after: list[str]) -> None:
    """The 8 rows' epilogue (``.Lkf_row0`` .. ``.Lkf_row7``, then ``after``), then each row's
    out-of-line piece (the rows whose code has bit 7 set), then ``.Lkf_sat``."""
    def row(r: int) -> list[str]:
        lo, mid, hi = AVR_ACC[r]
        return [f".Lkf_row{r}:",
                "lpm r0, Z+", "lpm r1, Z+", "lpm r28, Z+", "lpm r29, Z+",  # b' (24 bits), code
                f"sub r0, {lo}", f"sbc r1, {mid}", f"sbc r28, {hi}",  # v = b' - A = r28:r1:r0
                "sbrc r29, 7", f"rjmp .Lkf_slow{r}",
                f".Lkf_sh{r}:", "asr r28", "ror r1", "dec r29", f"brne .Lkf_sh{r}",  # code 1..7: s = 8 + code
                f".Lkf_chk{r}:", "mov r0, r1", "lsl r0", "sbc r0, r0",  # int8 when r28 = sext(r1)
                "cpse r28, r0", "rcall .Lkf_sat", "st X+, r1", "st X+, r0"]

    def slow(r: int) -> list[str]:
        return [f".Lkf_slow{r}:", f"cpi r29, 0x{avr_shift_code(7):02x}", f"brne .Lkf_s8_{r}",
                "lsl r0", "rol r1", "rol r28", f"brvs .Lkf_ov{r}", f"rjmp .Lkf_chk{r}",  # s = 7: v << 1 >> 8
                f".Lkf_ov{r}:", "sbc r28, r28", "neg r28", "subi r28, 0x81",  # not 16 bits: 0x80 / 0x7f saturate
                f"rjmp .Lkf_chk{r}",
                f".Lkf_s8_{r}:", f"cpi r29, 0x{avr_shift_code(8):02x}", f"brne .Lkf_gen{r}", f"rjmp .Lkf_chk{r}",
                f".Lkf_gen{r}:", "rcall .Lkf_post", f"rjmp .Lkf_row{r + 1}"]

    code = [ln for r in range(8) for ln in row(r)] + after + [ln for r in range(8) for ln in slow(r)]
    code += [".Lkf_sat:", "lsl r28", "sbc r0, r0", "ldi r29, 0x7f", "eor r29, r0", "mov r1, r29", "ret"]
    for ln in code:  # .Lkf_sat: r1:r0 = -128 or 127 (int16) by the sign of r28
        a(ln)


def _avr_sum(a) -> None:
    """``.Lkf_segp``: store segment X = r27:r26, n = r25:r24 (1..510) at Y (X, E, Q); then, when
    the layer has groups of 8 (r11 > 0), ``.Lkf_sum``: r6:r5:r4 += sum (x ^ 0x80) over the
    segment, as 16-bit partial sums r8:r7 over at most 64 passes of 4 inputs; r1 = 0; clobbers
    r7, r8, r9, r17, r24, r25, X."""
    def one() -> None:
        a("ld r17, X+"); a("subi r17, 0x80"); a("add r7, r17"); a("adc r8, r1")
    a(".Lkf_segp:"); a("std Y+0, r26"); a("std Y+1, r27"); a("mov r17, r24"); a("andi r17, 3"); a("std Y+2, r17")
    a("adiw r24, 3"); a("lsr r25"); a("ror r24"); a("lsr r25"); a("ror r24"); a("std Y+3, r24")
    a("tst r11"); a("breq .Lkf_sumx"); a("mov r25, r24"); a("mov r24, r17")  # r24 = E, r25 = Q
    a(".Lkf_sum:"); a("ldi r17, 64"); a("cp r25, r17"); a("brsh .Lkf_sum0"); a("mov r17, r25")
    a(".Lkf_sum0:"); a("sub r25, r17"); a("mov r9, r17"); a("clr r7"); a("clr r8")
    a("sbrc r24, 1"); a("rjmp .Lkf_suma"); a("sbrc r24, 0"); a("rjmp .Lkf_sume1")
    for e in (0, 3, 2, 1):
        a(f".Lkf_sume{e}:"); one()
    a("dec r9"); a("brne .Lkf_sume0")
    a("add r4, r7"); a("adc r5, r8"); a("adc r6, r1")  # fold the chunk into the 24-bit sum
    a("clr r24"); a("tst r25"); a("brne .Lkf_sum")
    a(".Lkf_sumx:"); a("ret")
    a(".Lkf_suma:"); a("sbrc r24, 0"); a("rjmp .Lkf_sume3"); a("rjmp .Lkf_sume2")


def _avr_post(a) -> None:
    """``.Lkf_post``, the general requantisation (codes with bit 7 set, :func:`avr_shift_code`):
    v = r28:r1:r0, code r29; floor(v / 2^s) to the 16-bit r28:r1 (saturated), clamp, int16 store
    at X+; preserves every register but r0, r1, r28, r29."""
    a(".Lkf_post:"); a("sbrs r29, 4"); a("rjmp .Lkf_pg")
    # left16 (only 0..255 rows have it): E:r28:r1 <<= n (>= 1), then E:r28 clamped to 0..255
    a("andi r29, 15"); a("mov r0, r28"); a("lsl r0"); a("sbc r0, r0")
    a(".Lkf_pl16:"); a("lsl r1"); a("rol r28"); a("rol r0"); a("dec r29"); a("brne .Lkf_pl16")
    a("tst r0"); a("breq .Lkf_pl16s"); a("clr r28"); a("sbrs r0, 7"); a("com r28"); a("clr r0")
    a(".Lkf_pl16s:"); a("st X+, r28"); a("st X+, r0"); a("ret")
    a(".Lkf_pg:"); a("push r24"); a("push r25"); a("mov r24, r29"); a("mov r25, r29"); a("andi r25, 15")
    a("sbrc r24, 5"); a("rjmp .Lkf_pl24")
    a("cpi r25, 8"); a("brlo .Lkf_pr8")  # right16: r28:r1 >>= n (a byte at once first)
    a("mov r1, r28"); a("lsl r28"); a("sbc r28, r28"); a("subi r25, 8")
    a(".Lkf_pr8:"); a("tst r25"); a("breq .Lkf_pc16")
    a(".Lkf_pr16:"); a("asr r28"); a("ror r1"); a("dec r25"); a("brne .Lkf_pr16"); a("rjmp .Lkf_pc16")
    a(".Lkf_pl24:"); a("mov r29, r28"); a("lsl r29"); a("sbc r29, r29")  # left24: E:r28:r1:r0 <<= n, keep E:r28:r1
    a(".Lkf_pl24l:"); a("lsl r0"); a("rol r1"); a("rol r28"); a("rol r29"); a("dec r25"); a("brne .Lkf_pl24l")
    a("mov r0, r28"); a("lsl r0"); a("sbc r0, r0"); a("cp r29, r0"); a("breq .Lkf_pc16")  # saturate to 16 bits
    a("lsl r29"); a("sbc r29, r29"); a("mov r28, r29"); a("ldi r25, 0x7f"); a("eor r28, r25"); a("mov r1, r29")
    a("com r1")  # 0x8000 or 0x7fff by the sign of E
    a(".Lkf_pc16:"); a("pop r25"); a("sbrc r24, 6"); a("rjmp .Lkf_pu8")  # clamp the 16-bit r28:r1
    a("pop r24"); a("mov r0, r1"); a("lsl r0"); a("sbc r0, r0")
    a("cpse r28, r0"); a("rcall .Lkf_sat"); a("rjmp .Lkf_pst")
    a(".Lkf_pu8:"); a("pop r24"); a("clr r0"); a("tst r28"); a("breq .Lkf_pst")
    a("mov r1, r0"); a("sbrs r28, 7"); a("com r1")  # 0 below, 255 above
    a(".Lkf_pst:"); a("st X+, r1"); a("st X+, r0"); a("ret")


def avr_asm_block() -> str:
    """The C text (a file-scope ``__asm__``) of the AVR kernel, as embedded in ``kf_dense.c``.

    ``python -m tools.avr_kernel`` puts it there; a test checks the file holds exactly this text.
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


def kf_dense_c_path() -> Path:
    """Path of ``firmware_templates/kf_dense.c``."""
    return TEMPLATE_DIR / "kf_dense.c"

