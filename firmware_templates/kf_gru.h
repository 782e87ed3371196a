/*
 * kf_gru.h: the gate and state arithmetic of kiloforge's int8 GRU cell (number format kf-int8-pow2-v1).
 *
 * Part of kiloforge (MIT). The semantics are kiloforge/actors/gru.py QuantGRUCell (module doc, "The GRU
 * cell"); the four dense products are kf_dense calls and the gates r = R[a_r + 128], k = K[a_z + 128]
 * kf_act_gate lookups (kf_runtime.h); this file holds the rest of what lies between them:
 *   kf_gru_rn      t[j] = rshift_round(r[j] * nh[j], s): gate x (W_hn h + b_hn), half-up, at e_n
 *   kf_gru_update  p = sat8(nx[j] * 2^s_nx + t[j]); n = TANH[p + 128];
 *                  h[j] = sat8(h[j] + rshift_round(k[j] * (n - h[j]), KF_GATE_EXP))   ((1 - z) n + z h)
 * Rules: <stdint.h> types only, a cast to int32_t before every multiply, no floats, no division.
 * The renderer inlines it after kf_runtime.h (kf_rshift_round, kf_sat16, pgm_read_byte) and defines
 * KF_GATE_EXP (kiloforge/numfmt.py GATE_EXP) before it.
 */
#ifndef KF_GRU_H
#define KF_GRU_H

#include <stdint.h>

#ifndef KF_RUNTIME_H
#error "include kf_runtime.h before kf_gru.h"
#endif

#ifndef KF_GATE_EXP
#error "the renderer defines KF_GATE_EXP before kf_gru.h"
#endif

/* In place: nh[j] = rshift_round(r[j] * nh[j], s); |r * nh| <= 255 * 128, so the result fits int16. */
static inline void kf_gru_rn(const uint8_t *r, int16_t *nh, uint8_t n, uint8_t s)
{
    uint8_t j;
    for (j = 0u; j < n; ++j) {
        nh[j] = (int16_t)kf_rshift_round((int32_t)r[j] * (int32_t)nh[j], s);
    }
}

/* The candidate n = TANH[sat8(nx * 2^nx_shift + rn) + 128] and the state update h += rshift_round(k (n - h), 8).
 * The exact left shift of nx is a multiply (a left shift of a negative value is undefined in C). */
static inline void kf_gru_update(const int8_t *tanh_table, const int16_t *nx, uint8_t nx_shift, const int16_t *rn,
                                 const uint8_t *k, int8_t *h, uint8_t n)
{
    const int32_t scale = (int32_t)1 << nx_shift; /* nx_shift <= 7 */
    uint8_t j;
    for (j = 0u; j < n; ++j) {
        int16_t p = kf_sat16((int32_t)nx[j] * scale + (int32_t)rn[j], -128, 127);
        int32_t c = (int32_t)(int8_t)pgm_read_byte(&tanh_table[(uint8_t)(p + 128)]);
        int32_t d = (int32_t)k[j] * (c - (int32_t)h[j]); /* |d| <= 255 * 255 */
        h[j] = (int8_t)kf_sat16((int32_t)h[j] + kf_rshift_round(d, KF_GATE_EXP), -128, 127);
    }
}

#endif /* KF_GRU_H */
