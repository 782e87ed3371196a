/*
 * Unit tests of the hand-written C of kiloforge firmware (firmware_templates/kf_runtime.h).
 * Run by tests/test_host_build.py: exit status 0 when every check passes. With the argument
 * "grid" it also prints "a s kf_rshift_round(a, s)" lines that the test compares with
 * kiloforge/numfmt.py's rshift_round.
 */
#include <stdio.h>
#include <string.h>

#include "kf_runtime.h"

static int failures;

#define CHECK(cond, ...)                                                                         \
    do {                                                                                         \
        if (!(cond)) {                                                                           \
            ++failures;                                                                          \
            fprintf(stderr, "FAIL %s:%d: ", __FILE__, __LINE__);                                 \
            fprintf(stderr, __VA_ARGS__);                                                        \
            fputc('\n', stderr);                                                                 \
        }                                                                                        \
    } while (0)

/* floor((a + 2^(s-1)) / 2^s) computed with int64 division (no shifts of negative numbers) */
static int64_t ref_rshift_round(int64_t a, unsigned s)
{
    int64_t d = (int64_t)1 << s, n;
    if (s == 0u) {
        return a;
    }
    n = a + d / 2;
    return n >= 0 ? n / d : -((-n + d - 1) / d);
}

static int64_t ref_floor_shift(int64_t a, unsigned s)
{
    int64_t d = (int64_t)1 << s;
    return a >= 0 ? a / d : -((-a + d - 1) / d);
}

static uint32_t lcg_state = 12345u;
static uint32_t lcg(void)
{
    lcg_state = lcg_state * 1664525u + 1013904223u;
    return lcg_state;
}

/* values around every power of two and at the int32 extremes, then pseudo-random ones */
static int32_t sample(unsigned i)
{
    static const int32_t edges[] = {0, 1, -1, 2, -2, 3, -3, 5, -5, 6, -6, 7, -7, 127, -128,
                                    32767, -32768, 2147483647, -2147483647 - 1, 2147483646,
                                    -2147483647, 1073741824, -1073741824};
    const unsigned n_edges = (unsigned)(sizeof edges / sizeof edges[0]);
    if (i < n_edges) {
        return edges[i];
    }
    i -= n_edges;
    if (i < 31u * 6u) {
        int64_t p = (int64_t)1 << (i / 6u), v;
        switch (i % 6u) {
        case 0: v = p; break;
        case 1: v = p - 1; break;
        case 2: v = p + 1; break;
        case 3: v = -p; break;
        case 4: v = -p - 1; break;
        default: v = -p + 1; break;
        }
        if (v > 2147483647) v = 2147483647;
        return (int32_t)v;
    }
    return (int32_t)lcg();
}

#define N_SAMPLES 1200u

int main(int argc, char **argv)
{
    unsigned i, s;
    int grid = argc > 1 && strcmp(argv[1], "grid") == 0;

    /* CRC-16/MCRF4XX test vectors (platform notes and the CRC catalogue) */
    {
        uint8_t v[10] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 0};
        uint8_t z[10] = {0};
        const uint8_t *check = (const uint8_t *)"123456789";
        CHECK(kf_crc16(v, 10u) == 0xA718u, "crc(01..09, type 0) = %04x", (unsigned)kf_crc16(v, 10u));
        CHECK(kf_crc16(z, 10u) == 0x9C87u, "crc(zeros) = %04x", (unsigned)kf_crc16(z, 10u));
        CHECK(kf_crc16(check, 9u) == 0x6F91u, "crc(\"123456789\") = %04x", (unsigned)kf_crc16(check, 9u));
        CHECK(kf_crc16_update(kf_crc16(v, 9u), v[9]) == kf_crc16(v, 10u), "crc update is not incremental");
    }

    /* rounding shift and flooring shift against int64 references */
    for (i = 0u; i < N_SAMPLES; ++i) {
        int32_t a = sample(i);
        for (s = 0u; s <= 30u; ++s) {
            int32_t got = kf_rshift_round(a, (uint8_t)s);
            CHECK((int64_t)got == ref_rshift_round(a, s), "rshift_round(%ld, %u) = %ld, want %lld", (long)a, s,
                  (long)got, (long long)ref_rshift_round(a, s));
            CHECK((int64_t)kf_asr32(a, (uint8_t)s) == ref_floor_shift(a, s), "asr32(%ld, %u)", (long)a, s);
            if (grid && i < 300u) {
                printf("%ld %u %ld\n", (long)a, s, (long)got);
            }
        }
    }

    /* saturation */
    CHECK(kf_sat16(-300, -128, 127) == -128, "sat16 low");
    CHECK(kf_sat16(300, -128, 127) == 127, "sat16 high");
    CHECK(kf_sat16(5, -128, 127) == 5, "sat16 inside");
    CHECK(kf_sat16(-2147483647 - 1, 0, 255) == 0, "sat16 int32 min");
    CHECK(kf_sat16(2147483647, 0, 255) == 255, "sat16 int32 max");
    CHECK(kf_sat16(255, 0, 255) == 255 && kf_sat16(256, 0, 255) == 255 && kf_sat16(-1, 0, 255) == 0, "sat16 uint8");

    /* activations: table lookup at z + 128, relu, identity */
    {
        int8_t tbl[256];
        int16_t z[256];
        int8_t x[256];
        unsigned k;
        for (k = 0u; k < 256u; ++k) {
            tbl[k] = (int8_t)(127 - (int)k); /* a table whose entries differ everywhere */
            z[k] = (int16_t)((int)k - 128);
        }
        kf_act_table(tbl, z, x, 256u);
        for (k = 0u; k < 256u; ++k) {
            CHECK(x[k] == tbl[k], "table[%d] gave %d, want %d", (int)z[k] + 128, x[k], tbl[k]);
        }
        kf_act_relu(z, x, 256u);
        for (k = 0u; k < 256u; ++k) {
            CHECK(x[k] == (z[k] > 0 ? z[k] : 0), "relu(%d) = %d", z[k], x[k]);
        }
        kf_act_identity(z, x, 256u);
        for (k = 0u; k < 256u; ++k) {
            CHECK(x[k] == z[k], "identity(%d) = %d", z[k], x[k]);
        }
    }

    if (failures != 0) {
        fprintf(stderr, "%d check(s) failed\n", failures);
        return 1;
    }
    return 0;
}
