/*
 * harness.c: kilo_start() of kiloforge's kilolib stand-in: replays a binary event stream through a
 * generated Kilobot program, one robot after another, and writes every per-tick output byte.
 * Part of kiloforge (MIT). The stream formats are written and read by export/verify/hostbuild.py.
 *
 * Tick model (export/verify/emulator.py models exactly this): for robot r, setup() once, then for every
 * global tick T = 0 .. n_ticks-1 (control ticks are T = k * period, k >= 1: the program listens
 * during its first period):
 *   0. (host build only, before setup()) the robot's state is fresh garbage (KF_HOST_FILL: a byte,
 *      0xA5 when unset, or random:SEED, different bytes per robot), then, as kilolib may, the rx
 *      callback gets 512 messages of every user type and version bytes 0..3 and the tx callback is
 *      asked for a message: it must return NULL (else the harness fails), and none of the 512 may
 *      count (the emulator hears nothing before setup());
 *   1. kilo_ticks = T; at control ticks the next light reading is loaded;
 *   2. loop() runs once;
 *   3. the tick record is written: duties, spinup flag, colour, the message kilo_message_tx()
 *      returns; at control ticks followed by the step record (what KF_TRACE_STEP reported);
 *   4. the messages of tick T are delivered to kilo_message_rx in stream order (types >= 0x80 are
 *      kilolib's and never reach the program).
 *
 * Input (little-endian):
 *   header 16 B: "KFS1", u16 n_robots, u8 period_ticks, u8 obs_dim, u32 n_ticks, u32 0
 *   per robot: u16 uid, u8 straight_left, u8 straight_right, u8 turn_left, u8 turn_right, u16 0
 *     then per tick: [i16 light at control ticks] u8 n, n x (u16 uid, u8 role, u8 flag, u8 type,
 *     u8 version, u8 distance_mm, u8 0, u16 light: message data[4..5])
 * Output per robot and tick: 16 B (left, right, spinup, colour, message_t bytes with the crc
 * little-endian), at control ticks then 2 + obs_dim B (q_left, q_right, obs as int8).
 *
 * I/O goes through the kf_io_* functions below; define KF_HARNESS_CUSTOM_IO and provide them to
 * run elsewhere (e.g. on an AVR under simavr); the default uses stdin/stdout. kf_io_finish and
 * kf_io_fail must not return.
 */
#include "kilolib.h"
#include "../kf_runtime.h"

#define KF_STEP_MAX (2u + 255u)

void kf_io_open(void);
void kf_io_read(void *buf, uint16_t n);
void kf_io_write(const void *buf, uint16_t n);
void kf_io_finish(void);
void kf_io_fail(const char *why);

#ifndef KF_HARNESS_CUSTOM_IO
#include <stdio.h>
#include <stdlib.h>

static char kf_in_buffer[1 << 16];
static char kf_out_buffer[1 << 16];

void kf_io_open(void)
{
    setvbuf(stdin, kf_in_buffer, _IOFBF, sizeof kf_in_buffer);
    setvbuf(stdout, kf_out_buffer, _IOFBF, sizeof kf_out_buffer);
}

void kf_io_read(void *buf, uint16_t n)
{
    if (n != 0u && fread(buf, 1u, n, stdin) != n) {
        kf_io_fail("event stream ended early");
    }
}

void kf_io_write(const void *buf, uint16_t n)
{
    if (n != 0u && fwrite(buf, 1u, n, stdout) != n) {
        kf_io_fail("cannot write the output stream");
    }
}

void kf_io_finish(void)
{
    if (fflush(stdout) != 0) {
        kf_io_fail("cannot write the output stream");
    }
    exit(0);
}

void kf_io_fail(const char *why)
{
    fprintf(stderr, "harness: %s\n", why);
    exit(2);
}
#endif

#ifdef KF_HOST_USERDATA
#include <stdlib.h>
#include <string.h>

void *kf_host_userdata;
static int kf_fill_random; /* 1: random bytes from kf_fill_seed, 0: every byte kf_fill_byte */
static uint8_t kf_fill_byte = 0xA5u;
static uint32_t kf_fill_seed;

/* KF_HOST_FILL: "0xA5" (any byte value) or "random:SEED"; unset means 0xA5. */
static void kf_fill_parse(void)
{
    const char *spec = getenv("KF_HOST_FILL");
    char *end = 0;
    unsigned long v;
    if (spec == 0 || *spec == '\0') {
        return;
    }
    kf_fill_random = strncmp(spec, "random:", 7u) == 0;
    v = strtoul(kf_fill_random ? spec + 7 : spec, &end, 0);
    if (end == spec || *end != '\0' || (!kf_fill_random && v > 0xFFu)) {
        kf_io_fail("KF_HOST_FILL must be a byte value (e.g. 0xA5) or random:SEED");
    }
    kf_fill_byte = (uint8_t)v;
    kf_fill_seed = (uint32_t)v;
}

/* A fresh garbage state for robot r (the previous robot's is freed). */
static void kf_fill_state(uint16_t r)
{
    uint8_t *p;
    uint16_t i;
    uint32_t x = (kf_fill_seed ^ ((uint32_t)r << 16)) * 2654435761u | 1u; /* xorshift32, never 0 */
    free(kf_host_userdata);
    p = (uint8_t *)malloc(kf_host_userdata_size);
    if (p == 0) {
        kf_io_fail("out of memory");
    }
    for (i = 0u; i < kf_host_userdata_size; ++i) {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        p[i] = kf_fill_random ? (uint8_t)(x >> 24) : kf_fill_byte;
    }
    kf_host_userdata = p;
}

/* What kilolib may do before setup(): deliver messages and ask for one to send. */
static void kf_before_setup(void)
{
    message_t m;
    distance_measurement_t d;
    uint16_t k;
    memset(&m, 0, sizeof m);
    for (k = 0u; k < 512u; ++k) {
        m.type = (uint8_t)(k & 0x7Fu);
        m.data[0] = (uint8_t)(k >> 7); /* version bytes 0..3 */
        m.data[1] = (uint8_t)k;
        m.data[2] = (uint8_t)(k >> 8);
        m.data[3] = (uint8_t)(k & 3u);
        m.crc = message_crc(&m);
        d.low_gain = (int16_t)(k & 0xFFu);
        d.high_gain = d.low_gain;
        if (kilo_message_rx != 0) {
            kilo_message_rx(&m, &d);
        }
    }
    if (kilo_message_tx != 0 && kilo_message_tx() != 0) {
        kf_io_fail("the program offers a message before setup() has run");
    }
}
#endif

static uint8_t kf_trace[KF_STEP_MAX];
static uint8_t kf_trace_len; /* 2 + obs_dim from the stream header */
static uint8_t kf_traced;

void kf_host_trace_step(uint8_t q_left, uint8_t q_right, const int8_t *obs, uint8_t n)
{
    uint8_t i;
    if ((uint16_t)n + 2u != kf_trace_len) {
        kf_io_fail("the program traced an observation of another width than the stream header's obs_dim");
    }
    kf_trace[0] = q_left;
    kf_trace[1] = q_right;
    for (i = 0u; i < n; ++i) {
        kf_trace[2u + i] = (uint8_t)obs[i];
    }
    kf_traced = 1u;
}

static uint16_t kf_u16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

static uint32_t kf_u32(const uint8_t *p)
{
    return (uint32_t)kf_u16(p) | ((uint32_t)kf_u16(p + 2) << 16);
}

static void kf_deliver(void)
{
    uint8_t ev[10];
    uint8_t n, k, i;
    message_t m;
    distance_measurement_t d;
    kf_io_read(&n, 1u);
    for (k = 0u; k < n; ++k) {
        kf_io_read(ev, 10u);
        m.data[0] = ev[5];                    /* version byte */
        m.data[1] = ev[0];                    /* uid, little-endian */
        m.data[2] = ev[1];
        m.data[3] = (uint8_t)((ev[2] & 1u) | ((ev[3] & 1u) << 1)); /* role | sensing << 1 */
        m.data[4] = ev[8];                    /* light (an emitter's reading), little-endian */
        m.data[5] = ev[9];
        for (i = 6u; i < 9u; ++i) {
            m.data[i] = 0u;
        }
        m.type = ev[4];
        m.crc = message_crc(&m);
        d.low_gain = (int16_t)ev[6];
        d.high_gain = (int16_t)ev[6];
        if (m.type < 0x80u && kilo_message_rx != 0) {
            kilo_message_rx(&m, &d);
        }
    }
}

void kilo_start(void (*setup)(void), void (*loop)(void))
{
    uint8_t hdr[16];
    uint8_t rec[16];
    uint16_t n_robots, r;
    uint8_t period, phase, i, control;
    uint32_t n_ticks, t;

    kf_io_open();
#ifdef KF_HOST_USERDATA
    kf_fill_parse();
#endif
    kf_io_read(hdr, 16u);
    if (hdr[0] != 'K' || hdr[1] != 'F' || hdr[2] != 'S' || hdr[3] != '1') {
        kf_io_fail("not a kiloforge event stream (bad magic)");
    }
    n_robots = kf_u16(hdr + 4);
    period = hdr[6];
    kf_trace_len = (uint8_t)(2u + hdr[7]);
    n_ticks = kf_u32(hdr + 8);
    if (period == 0u || hdr[7] > 253u) {
        kf_io_fail("bad stream header (period 0 or obs_dim > 253)");
    }
    for (r = 0u; r < n_robots; ++r) {
        kf_io_read(rec, 8u);
        kf_host_reset(kf_u16(rec), rec[2], rec[3], rec[4], rec[5]);
#ifdef KF_HOST_USERDATA
        kf_fill_state(r);
        kf_before_setup();
#endif
        setup();
        phase = 0u;
        for (t = 0u; t < n_ticks; ++t) {
            kilo_ticks = t;
            control = (uint8_t)(phase == 0u && t != 0u);
            if (control) {
                uint8_t lb[2];
                kf_io_read(lb, 2u);
                kf_host_state.light = (int16_t)kf_u16(lb);
            }
            kf_host_state.spinup = 0u;
            kf_traced = 0u;
            loop();
            rec[0] = kf_host_state.duty_left;
            rec[1] = kf_host_state.duty_right;
            rec[2] = kf_host_state.spinup;
            rec[3] = kf_host_state.color;
            if (kilo_message_tx != 0) {
                const message_t *m = kilo_message_tx();
                for (i = 0u; i < 9u; ++i) {
                    rec[4u + i] = m != 0 ? m->data[i] : 0u;
                }
                rec[13] = m != 0 ? m->type : 0u;
                rec[14] = m != 0 ? (uint8_t)(m->crc & 0xFFu) : 0u;
                rec[15] = m != 0 ? (uint8_t)(m->crc >> 8) : 0u;
            } else {
                for (i = 4u; i < 16u; ++i) {
                    rec[i] = 0u;
                }
            }
            kf_io_write(rec, 16u);
            if (control) {
                if (!kf_traced) {
                    for (i = 0u; i < kf_trace_len; ++i) {
                        kf_trace[i] = 0u;
                    }
                }
                kf_io_write(kf_trace, kf_trace_len);
            }
            kf_deliver();
            phase = (uint8_t)(phase + 1u == period ? 0u : phase + 1u);
        }
    }
    kf_io_finish();
}
