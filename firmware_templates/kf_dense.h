/* kf_dense.h -- the int8 dense-layer kernel of kiloforge firmware (number format kf-int8-pow2-v1).
 *
 * Semantics (bit-exact with kiloforge/numfmt.py dense_int, int32 reference accumulator):
 *     y[j] = clamp(rshift_round_half_up(b[j] + sum_i W[j][i] * x[i], s[j]), lo, hi)
 *
 * The arrays in a kf_dense_t are NOT the plain W / b / s of a numfmt.QuantLayer: they are what
 * export/codegen/kernel.py renders for this kernel (KernelLayer.w / .b / .shift / .fast), and ONE set of
 * arrays serves both the portable C below (host, Kilombo) and the AVR assembly kernel:
 *   w      PROGMEM int8, n_out * n_in bytes: offset-binary weights (W + 128, stored as W ^ 0x80),
 *          rows in groups of 8 (then of 2, then 1 for the rest), each group interleaved input-major:
 *          group rows g0..g0+k-1 hold w[g0*n_in + i*k + r] = W[g0+r][i] ^ 0x80.
 *   b      PROGMEM int32, n_out: the bias with the rounding constant and the offset-binary
 *          corrections folded in; for `fast` layers the low 24 bits hold it and the top byte
 *          holds the AVR kernel's requantisation code for the row (export.codegen.kernel.avr_shift_code).
 *   shift  PROGMEM uint8, n_out: s[j] in 0..30 (the portable code's shift).
 *   fast   1 when export/codegen/kernel.py proved that a 24-bit accumulator is exact for this layer
 *          (every int8 input, rounding included), the clamp is int8 or uint8, n_in <= 510
 *          and n_out <= 2047: the AVR uses its assembly kernel (8.5 cycles per MAC in its inner
 *          loop, 9 to 10.5 per MAC over a whole layer); 0: the portable int32 code everywhere.
 *   lo, hi the saturation bounds (hidden layers -128..127, the output layer 0..255).
 * The descriptor itself lives in SRAM (plain `static const kf_dense_t`, 15 bytes), e.g.
 *     static const kf_dense_t L0 = { L0_w, L0_b, L0_shift, 160, 32, -128, 127, 1 };
 * export.codegen.kernel.KernelLayer.c_initializer(...) renders exactly this initializer.
 *
 * KF_DENSE_ALL_FAST: define it (before this code) when every layer's `fast` is 1
 * (export.codegen.kernel.all_fast); the AVR build then omits the portable kernel (about 1 KB of flash).
 *
 * Inputs x are int8 in SRAM; outputs y are int16 in SRAM (already clamped to [lo, hi]).
 * kf_dense2 reads its input as the concatenation of two SRAM segments (x1[0..n1-1] then
 * x2[0..n_in-n1-1]) without copying: the ring-buffer history, oldest tuple first, is
 *     kf_dense2(&L0, &hist[head * TUPLE], (T_PREV - head) * TUPLE, &hist[0], z0);
 * (segment 2 may be empty: n1 == n_in).
 *
 * The AVR assembly kernel keeps its state between row groups in a static 20-byte block: the
 * kernel is not reentrant (call it from the main loop only, never from an interrupt).
 *
 * Include this header (or paste it) before kf_dense.c; off AVR it shims PROGMEM / pgm_read_*.
 */
#ifndef KF_DENSE_H
#define KF_DENSE_H

#include <stdint.h>

#ifdef __AVR__
#include <avr/pgmspace.h>
#else
#ifndef PROGMEM
#define PROGMEM
#endif
#ifndef pgm_read_byte
#define pgm_read_byte(p) (*(const uint8_t *)(p))
#endif
#ifndef pgm_read_dword
#define pgm_read_dword(p) (*(const uint32_t *)(p))
#endif
#endif

typedef struct {
    const int8_t *w;      /* PROGMEM, kernel order (export.codegen.kernel.KernelLayer.w) */
    const int32_t *b;     /* PROGMEM, folded bias (export.codegen.kernel.KernelLayer.b) */
    const uint8_t *shift; /* PROGMEM, per-row shift 0..30 */
    uint16_t n_in;
    uint16_t n_out;
    int16_t lo;
    int16_t hi;
    uint8_t fast;         /* 1: 24-bit exact, AVR assembly path allowed (export.codegen.kernel proves it) */
} kf_dense_t;

/* y = layer(x); x has L->n_in int8 entries, y receives L->n_out int16 entries. */
void kf_dense(const kf_dense_t *L, const int8_t *x, int16_t *y);

/* The same, input = x1[0..n1-1] followed by x2[0..L->n_in-n1-1] (ring buffer, no copy). */
void kf_dense2(const kf_dense_t *L, const int8_t *x1, uint16_t n1, const int8_t *x2, int16_t *y);
#define kf_dense_2seg kf_dense2 /* the name an early firmware draft used */

#endif /* KF_DENSE_H */
