/* kilolib_avr.c -- kiloforge's minimal AVR stand-in for kilolib (see kilolib.h). Part of kiloforge
 * (MIT); our own code. It only has to link and behave plausibly: export/verify/avr.py subtracts its size
 * (an empty-setup/loop program built with it) and adds kilolib's measured size instead.
 * Timer0 overflow advances kilo_ticks (8 MHz / 1024 / 256 = 30.52 Hz, as on a Kilobot).
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <util/crc16.h>

#include "kilolib.h"

volatile uint32_t kilo_ticks;
uint16_t kilo_uid;
uint8_t kilo_straight_left;
uint8_t kilo_straight_right;
uint8_t kilo_turn_left;
uint8_t kilo_turn_right;
message_rx_t kilo_message_rx;
message_tx_t kilo_message_tx;
message_tx_success_t kilo_message_tx_success;
static uint8_t kf_rand = 0xA5u;

ISR(TIMER0_OVF_vect)
{
    kilo_ticks++;
}

void kilo_init(void)
{
    TCCR0A = 0u;
    TCCR0B = (uint8_t)((1u << CS02) | (1u << CS00)); /* clk / 1024 */
    TIMSK0 = (uint8_t)(1u << TOIE0);
}

void kilo_start(void (*setup)(void), void (*loop)(void))
{
    sei();
    setup();
    for (;;) {
        loop();
    }
}

uint8_t estimate_distance(const distance_measurement_t *d)
{
    return (uint8_t)d->low_gain;
}

void set_motors(uint8_t left, uint8_t right)
{
    OCR0A = left; /* stand-in: the robot drives the vibration motors from two PWM channels */
    OCR0B = right;
}

void spinup_motors(void)
{
    set_motors(255u, 255u);
}

void set_color(uint8_t color)
{
    PORTD = color;
}

int16_t get_ambientlight(void)
{
    return (int16_t)(ADC & 0x3FFu);
}

int16_t get_voltage(void)
{
    return (int16_t)(ADC & 0x3FFu);
}

int16_t get_temperature(void)
{
    return 25;
}

uint8_t rand_soft(void)
{
    uint8_t x = kf_rand;
    x ^= (uint8_t)(x << 3);
    x ^= (uint8_t)(x >> 5);
    x ^= (uint8_t)(x << 4);
    kf_rand = x;
    return x;
}

uint8_t rand_hard(void)
{
    return rand_soft();
}

void rand_seed(uint8_t seed)
{
    kf_rand = seed ? seed : 1u;
}

void delay(uint16_t ms)
{
    while (ms--) {
        uint16_t i;
        for (i = 0u; i < 2000u; ++i) {
            __asm__ __volatile__("nop");
        }
    }
}

uint16_t message_crc(const message_t *m)
{
    uint16_t crc = 0xFFFFu;
    uint8_t i;
    for (i = 0u; i < 9u; ++i) {
        crc = _crc_ccitt_update(crc, m->data[i]);
    }
    return _crc_ccitt_update(crc, m->type);
}
