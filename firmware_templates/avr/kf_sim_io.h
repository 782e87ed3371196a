/* kf_sim_io.h -- the AVR side of export/verify/simavr_run.c's protocol (simavr only; never on a robot).
 * Part of kiloforge (MIT).
 *   kf_sim_in()      next byte of the runner's input file      (reads GPIOR2)
 *   kf_sim_out(b)    append a byte to the runner's output file (writes GPIOR1)
 *   kf_sim_mark(id)  record "M id cycle" (id 1..0xFD)          (writes GPIOR0)
 *   kf_sim_paint()   repaint the free stack region for a new high-water mark
 *   kf_sim_exit()    end the run
 */
#ifndef KF_SIM_IO_H
#define KF_SIM_IO_H

#include <stdint.h>
#include <avr/io.h>

static inline uint8_t kf_sim_in(void) { return GPIOR2; }
static inline uint16_t kf_sim_in16(void)
{
    uint16_t lo = kf_sim_in();
    return (uint16_t)(lo | ((uint16_t)kf_sim_in() << 8));
}
static inline void kf_sim_out(uint8_t b) { GPIOR1 = b; }
static inline void kf_sim_out16(uint16_t v)
{
    kf_sim_out((uint8_t)v);
    kf_sim_out((uint8_t)(v >> 8));
}
static inline void kf_sim_mark(uint8_t id) { __asm__ __volatile__("" ::: "memory"); GPIOR0 = id; __asm__ __volatile__("" ::: "memory"); }
static inline void kf_sim_paint(void) { GPIOR0 = 0xFE; }
static inline void kf_sim_exit(void)
{
    GPIOR0 = 0xFF;
    for (;;) {
    }
}

#endif /* KF_SIM_IO_H */
