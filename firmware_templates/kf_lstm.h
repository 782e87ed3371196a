/*
 * kf_lstm.h: the gate and state arithmetic of kiloforge's int8 LSTM cell (number format kf-int8-pow2-v1).
 *
 * Part of kiloforge (MIT). The semantics are kiloforge/actors/lstm.py QuantLSTMCell (module doc); the
 * four gate pre-activations and the output are kf_dense calls, this file holds what lies between them:
 *   kf_lstm_cell    c[j] = sat(rshift_round(f[j] * c[j], KF_GATE_EXP) + i[j] * g[j], +-KF_CELL_MAX)
 *                   with f = F[a_f + 128] (uint8 at KF_GATE_EXP), c int32 at KF_GATE_EXP + 7
 *   kf_lstm_hidden  h[j] = sat8(rshift_round(o[j] * TANH_C[sat8(rshift_round(c[j], c_shift)) + 128], KF_GATE_EXP))
 *                   with o = O[a_o + 128]
 * Rules: <stdint.h> types only, a cast to int32_t before every multiply, no floats, no division.
 * The renderer inlines it after kf_runtime.h (kf_rshift_round, kf_sat16, pgm_read_byte) and defines
 * KF_GATE_EXP and KF_CELL_MAX from kiloforge/numfmt.py and kiloforge/actors/lstm.py.
 */
#ifndef KF_LSTM_H
#define KF_LSTM_H

#include <stdint.h>

#ifndef KF_RUNTIME_H
#error "include kf_runtime.h before kf_lstm.h"
#endif
#if !defined(KF_GATE_EXP) || !defined(KF_CELL_MAX)
#error "the renderer defines KF_GATE_EXP and KF_CELL_MAX before kf_lstm.h"
#endif

/* The cell state update with the forget gate f = F[a_f + 128], the input gate i and the candidate g.
 * |f c| <= 255 * KF_CELL_MAX < 2^31 and the result stays within +-KF_CELL_MAX (the module doc's proof). */
static inline void kf_lstm_cell(const uint8_t *f_table, const int16_t *a_f, const uint8_t *i, const int8_t *g,
                                int32_t *c, uint8_t n)
{
    uint8_t j;
    for (j = 0u; j < n; ++j) {
        int32_t f = (int32_t)pgm_read_byte(&f_table[(uint8_t)(a_f[j] + 128)]);
        int32_t v = kf_rshift_round(f * c[j], KF_GATE_EXP) + (int32_t)i[j] * (int32_t)g[j];
        c[j] = v > KF_CELL_MAX ? KF_CELL_MAX : (v < -KF_CELL_MAX ? -KF_CELL_MAX : v);
    }
}

/* The new hidden state h = o tanh(c) with the output gate o = O[a_o + 128]; |o t| <= 255 * 128. */
static inline void kf_lstm_hidden(const uint8_t *o_table, const int16_t *a_o, const int8_t *tanh_table,
                                  const int32_t *c, uint8_t c_shift, int8_t *h, uint8_t n)
{
    uint8_t j;
    for (j = 0u; j < n; ++j) {
        int32_t o = (int32_t)pgm_read_byte(&o_table[(uint8_t)(a_o[j] + 128)]);
        int16_t p = kf_sat16(kf_rshift_round(c[j], c_shift), -128, 127);
        int32_t t = (int32_t)(int8_t)pgm_read_byte(&tanh_table[(uint8_t)(p + 128)]);
        h[j] = (int8_t)kf_sat16(kf_rshift_round(o * t, KF_GATE_EXP), -128, 127);
    }
}

#endif /* KF_LSTM_H */
