/* kilolib.h -- kiloforge's own AVR stand-in for the kilolib API, used for exact size builds.
 *
 * Part of kiloforge (MIT). kilolib itself has no licence: nothing here is copied from it. The
 * declarations follow kilolib's documented API (shared/reference/kilobot-platform.md); the code in
 * kilolib_avr.c is ours and deliberately minimal. export/verify/avr.py builds a generated program against
 * this stand-in, measures it with avr-size, and replaces the stand-in's own size (measured as a
 * program with empty setup/loop) by kilolib's (7,028 B flash, 110 B SRAM with empty setup/loop).
 * To build for a robot, use the real kilolib (python -m export ... --kilolib DIR).
 */
#ifndef KILOLIB_H
#define KILOLIB_H

#include <stdint.h>
#include <avr/pgmspace.h>

typedef struct {
    uint8_t data[9];
    uint8_t type;
    uint16_t crc;
} message_t; /* 12 bytes packed: payload, type at offset 9, crc little-endian at offset 10 */

typedef struct {
    int16_t low_gain;
    int16_t high_gain;
} distance_measurement_t;

typedef void (*message_rx_t)(message_t *m, distance_measurement_t *d);
typedef message_t *(*message_tx_t)(void);
typedef void (*message_tx_success_t)(void);

#define RGB(r, g, b) ((r) & 3) | (((g) & 3) << 2) | (((b) & 3) << 4) /* no outer parentheses */
#define TICKS_PER_SEC 31

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
void kilo_start(void (*setup)(void), void (*loop)(void));
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

#endif /* KILOLIB_H */
