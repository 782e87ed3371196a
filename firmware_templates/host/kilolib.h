/*
 * kilolib.h: kiloforge's own host stand-in for the kilolib API (kilolib itself has no licence, so
 * nothing here is copied from it: the declarations follow the documented API, the code is ours).
 * Part of kiloforge (MIT). Lets a generated Kilobot program build and run on a PC (and, with
 * kilolib_host.c, on the AVR under simavr) driven by firmware_templates/host/harness.c.
 *
 * Stand-in behaviour (what differs from a robot):
 *   - kilo_ticks, kilo_uid and the calibration values are set by the harness per robot;
 *   - estimate_distance() returns the distance the harness put into the measurement:
 *     low_gain holds it in mm (0..255), high_gain a copy;
 *   - set_motors/spinup_motors/set_color only record what was asked (kf_host_state);
 *   - get_ambientlight() returns the reading the harness set for the current control period;
 *   - the harness calls kilo_message_rx (only for types < 0x80, as kilolib does) after loop(),
 *     and on the host also before setup(), as kilolib may;
 *   - on the host the per-robot state is garbage before setup() (KF_HOST_USERDATA below).
 */
#ifndef KILOLIB_H
#define KILOLIB_H

#include <stdint.h>

typedef struct {
    uint8_t data[9];
    uint8_t type;
    uint16_t crc;
} message_t; /* 12 bytes: payload, type at offset 9, crc (little-endian on the robot) at offset 10 */

typedef struct {
    int16_t low_gain;
    int16_t high_gain;
} distance_measurement_t;

typedef void (*message_rx_t)(message_t *m, distance_measurement_t *d);
typedef message_t *(*message_tx_t)(void);
typedef void (*message_tx_success_t)(void);

/* 2 bits per channel; like kilolib's macro it has no outer parentheses */
#define RGB(r, g, b) ((r) & 3) | (((g) & 3) << 2) | (((b) & 3) << 4)

extern volatile uint32_t kilo_ticks;
extern uint16_t kilo_uid;
extern uint8_t kilo_straight_left;
extern uint8_t kilo_straight_right;
extern uint8_t kilo_turn_left;
extern uint8_t kilo_turn_right;
extern message_rx_t kilo_message_rx;
extern message_tx_t kilo_message_tx;
extern message_tx_success_t kilo_message_tx_success;

void kilo_init(void);
void kilo_start(void (*setup)(void), void (*loop)(void)); /* the harness: never returns */
uint8_t estimate_distance(const distance_measurement_t *d);
void set_motors(uint8_t left, uint8_t right);
void spinup_motors(void);
void set_color(uint8_t color);
int16_t get_ambientlight(void);
int16_t get_voltage(void);
int16_t get_temperature(void);
uint8_t rand_soft(void);
uint8_t rand_hard(void);
void rand_seed(uint8_t seed);
void delay(uint16_t ms);
uint16_t message_crc(const message_t *m);

/* --- stand-in only: what the harness reads and sets ------------------------------------------- */
typedef struct {
    uint8_t duty_left;    /* last set_motors values */
    uint8_t duty_right;
    uint8_t spinup;       /* set by spinup_motors(); the harness clears it every tick */
    uint8_t color;        /* last set_color value */
    int16_t light;        /* what get_ambientlight() returns */
    uint8_t rand_state;
} kf_host_state_t;
extern kf_host_state_t kf_host_state;
void kf_host_reset(uint16_t uid, uint8_t straight_left, uint8_t straight_right, uint8_t turn_left,
                   uint8_t turn_right);

#ifndef __AVR__
/* On the host the harness owns each robot's per-robot state, as Kilombo does: a program declares it
 * with KF_HOST_USERDATA(type) and reaches it through `mydata`; before each robot's setup() the
 * harness allocates kf_host_userdata_size bytes and fills them with garbage (harness.c). The AVR
 * build under simavr keeps the program's own static state. */
extern void *kf_host_userdata;
extern const uint16_t kf_host_userdata_size;
#define KF_HOST_USERDATA(T)                                                                       \
    const uint16_t kf_host_userdata_size = (uint16_t)sizeof(T);                                   \
    static T *kf_host_mydata(void) { return (T *)kf_host_userdata; }
#define mydata (kf_host_mydata())
#endif

/* Generated programs call KF_TRACE_STEP(q_left, q_right, obs, obs_dim) once per control step; the
 * stand-in records it so the harness can compare commands and observations with the emulator. */
void kf_host_trace_step(uint8_t q_left, uint8_t q_right, const int8_t *obs, uint8_t n);
#define KF_TRACE_STEP(ql, qr, obs, n) kf_host_trace_step((ql), (qr), (obs), (n))

#endif /* KILOLIB_H */
