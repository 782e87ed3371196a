/* kf_avr_io.c -- the I/O of firmware_templates/host/harness.c on an AVR under simavr.
 *
 * Part of kiloforge (MIT). Compiled with -DKF_HARNESS_CUSTOM_IO next to host/kilolib_host.c and
 * host/harness.c: the event stream comes in through GPIOR2, the output records go out through
 * GPIOR1 (export/verify/simavr_run.c). Control steps are measured without touching the harness: the
 * harness reads the 2-byte light value right before calling loop() at a control tick and writes
 * the 16-byte tick record right after it, so
 *   - the light read repaints the free stack (0xFE) and marks KF_MARK_STEP_BEGIN,
 *   - the next record write marks KF_MARK_STEP_END and scans the stack (0xFD).
 * kf_io_read uses only call-clobbered registers (no pushes), so SP at the paint is the harness's
 * SP minus the 2-byte return address: export/verify/avr.py adds those bytes back.
 */
#include <stdint.h>

#include "kf_sim_io.h"

#if !defined(KF_MARK_STEP_BEGIN) || !defined(KF_MARK_STEP_END) || !defined(KF_MARK_FAIL)
#error "export/verify/avr.py defines the marks (KF_MARK_STEP_BEGIN, KF_MARK_STEP_END, KF_MARK_FAIL)"
#endif

static uint8_t kf_in_step;

void kf_io_open(void)
{
}

void kf_io_read(void *buf, uint16_t n)
{
    uint8_t *p = (uint8_t *)buf;
    uint16_t i;
    if (n == 2u) { /* the light value of a control tick: loop() runs next */
        kf_sim_paint();
        kf_in_step = 1u;
    }
    for (i = 0u; i < n; ++i) {
        p[i] = kf_sim_in();
    }
    if (n == 2u) {
        kf_sim_mark(KF_MARK_STEP_BEGIN);
    }
}

void kf_io_write(const void *buf, uint16_t n)
{
    const uint8_t *p = (const uint8_t *)buf;
    uint16_t i;
    if (kf_in_step) {
        kf_sim_mark(KF_MARK_STEP_END);
        GPIOR0 = 0xFDu; /* stack scan */
        kf_in_step = 0u;
    }
    for (i = 0u; i < n; ++i) {
        kf_sim_out(p[i]);
    }
}

void kf_io_finish(void)
{
    kf_sim_exit();
}

void kf_io_fail(const char *why)
{
    (void)why;
    kf_sim_mark(KF_MARK_FAIL);
    kf_sim_exit();
}
