/*
 * kf_runtime.h: the hand-written fixed-point and message helpers of kiloforge firmware.
 *
 * Part of kiloforge (MIT). The renderer inlines this file into every generated program; it is also
 * compiled on its own by tests/c/test_runtime.c. Rules: <stdint.h> types only, never the width of
 * `int`, a cast to int32_t before every multiply, no floats, no division. Everything is `static
 * inline`, so a program pays only for what it calls.
 */
#ifndef KF_RUNTIME_H
#define KF_RUNTIME_H

#include <stdint.h>

/* --- flash tables: PROGMEM on AVR, plain const memory elsewhere (host build, Kilombo) ---------- */
#ifdef __AVR__
#include <avr/pgmspace.h>
#else
#ifndef PROGMEM
#define PROGMEM
#endif
#ifndef pgm_read_byte
#define pgm_read_byte(addr) (*(const uint8_t *)(addr))
#endif
#ifndef pgm_read_word
#define pgm_read_word(addr) (*(const uint16_t *)(addr))
#endif
#ifndef pgm_read_dword
#define pgm_read_dword(addr) (*(const uint32_t *)(addr))
#endif
#endif

/* --- integer helpers (kiloforge/numfmt.py defines the semantics) ---------------------------------- */

/* Arithmetic (flooring) right shift of a signed value, without relying on the implementation-defined
 * behaviour of >> on negative numbers: for a < 0, ~a >= 0 and floor(a / 2^s) == ~(~a >> s). */
static inline int32_t kf_asr32(int32_t a, uint8_t s)
{
    return a >= 0 ? (int32_t)(a >> s) : (int32_t)~((~a) >> s);
}

/* numfmt.rshift_round: (a + 2^(s-1)) >> s with half-up rounding, s = 0 is the identity. Written as
 * floor(a / 2^s) + bit (s-1) of a, which is the same number and cannot overflow. s <= 30. */
static inline int32_t kf_rshift_round(int32_t a, uint8_t s)
{
    if (s == 0u) {
        return a;
    }
    return kf_asr32(a, s) + (int32_t)(((uint32_t)a >> (uint8_t)(s - 1u)) & 1u);
}

/* numfmt.saturate to [lo, hi], result fits int16_t. */
static inline int16_t kf_sat16(int32_t a, int16_t lo, int16_t hi)
{
    if (a < (int32_t)lo) {
        return lo;
    }
    if (a > (int32_t)hi) {
        return hi;
    }
    return (int16_t)a;
}

/* --- activations: int16 requantised layer output (already clamped to int8) -> int8 input -------- */

/* ReLU: max(0, z), same exponent. */
static inline void kf_act_relu(const int16_t *z, int8_t *x, uint16_t n)
{
    uint16_t i;
    for (i = 0u; i < n; ++i) {
        x[i] = (int8_t)(z[i] > 0 ? z[i] : 0);
    }
}

/* Identity: the value itself (z is already in -128..127). */
static inline void kf_act_identity(const int16_t *z, int8_t *x, uint16_t n)
{
    uint16_t i;
    for (i = 0u; i < n; ++i) {
        x[i] = (int8_t)z[i];
    }
}

/* Table activation (ELU, tanh, sigmoid; a recurrent cell's tanh): x = table[z + 128], a 256-entry int8
 * table in flash. */
static inline void kf_act_table(const int8_t *table, const int16_t *z, int8_t *x, uint16_t n)
{
    uint16_t i;
    for (i = 0u; i < n; ++i) {
        x[i] = (int8_t)pgm_read_byte(&table[(uint8_t)(z[i] + 128)]);
    }
}

/* Gate: g = table[z + 128], a 256-entry uint8 table in flash (a recurrent cell's sigmoid gates). */
static inline void kf_act_gate(const uint8_t *table, const int16_t *z, uint8_t *g, uint16_t n)
{
    uint16_t i;
    for (i = 0u; i < n; ++i) {
        g[i] = pgm_read_byte(&table[(uint8_t)(z[i] + 128)]);
    }
}

/* --- CRC-16/MCRF4XX (export/contract/crc.py): reflected poly KF_CRC_POLY, init KF_CRC_INIT, no final xor */

#if !defined(KF_CRC_POLY) || !defined(KF_CRC_INIT)
#error "define KF_CRC_POLY and KF_CRC_INIT (export/contract/crc.py; the renderer does) before kf_runtime.h"
#endif

#ifdef __AVR__
#include <util/crc16.h>
/* avr-libc's _crc_ccitt_update is exactly this update (reflected 0x8408), in a few instructions */
static inline uint16_t kf_crc16_update(uint16_t crc, uint8_t byte)
{
    return _crc_ccitt_update(crc, byte);
}
#else
static inline uint16_t kf_crc16_update(uint16_t crc, uint8_t byte)
{
    uint8_t bit;
    crc ^= byte;
    for (bit = 0u; bit < 8u; ++bit) {
        crc = (crc & 1u) ? (uint16_t)((crc >> 1) ^ KF_CRC_POLY) : (uint16_t)(crc >> 1);
    }
    return crc;
}
#endif

static inline uint16_t kf_crc16(const uint8_t *p, uint8_t n)
{
    uint16_t crc = KF_CRC_INIT;
    uint8_t i;
    for (i = 0u; i < n; ++i) {
        crc = kf_crc16_update(crc, p[i]);
    }
    return crc;
}

/* --- hand-off to the interrupt handlers ------------------------------------------------------- */

/* A compiler barrier: every store before it is emitted before every store after it. The flag or index
 * that hands data to an ISR is volatile, but the data itself need not be; this keeps its stores from
 * being moved past the hand-off (the AVR itself never reorders memory accesses). */
#define KF_BARRIER() __asm__ __volatile__("" ::: "memory")

#endif /* KF_RUNTIME_H */
