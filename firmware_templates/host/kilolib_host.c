/*
 * kilolib_host.c: the state and functions of kiloforge's kilolib stand-in (see kilolib.h).
 * Part of kiloforge (MIT). Portable C99 without stdio or malloc, so it also builds for the AVR.
 */
#include "kilolib.h"
#include "../kf_runtime.h"

volatile uint32_t kilo_ticks;
uint16_t kilo_uid;
uint8_t kilo_straight_left;
uint8_t kilo_straight_right;
uint8_t kilo_turn_left;
uint8_t kilo_turn_right;
message_rx_t kilo_message_rx;
message_tx_t kilo_message_tx;
message_tx_success_t kilo_message_tx_success;
kf_host_state_t kf_host_state;

void kilo_init(void)
{
    kilo_message_rx = 0;
    kilo_message_tx = 0;
    kilo_message_tx_success = 0;
    kf_host_reset(0u, 0u, 0u, 0u, 0u);
}

void kf_host_reset(uint16_t uid, uint8_t straight_left, uint8_t straight_right, uint8_t turn_left,
                   uint8_t turn_right)
{
    kilo_ticks = 0u;
    kilo_uid = uid;
    kilo_straight_left = straight_left;
    kilo_straight_right = straight_right;
    kilo_turn_left = turn_left;
    kilo_turn_right = turn_right;
    kf_host_state.duty_left = 0u;
    kf_host_state.duty_right = 0u;
    kf_host_state.spinup = 0u;
    kf_host_state.color = 0u;
    kf_host_state.light = 0;
    kf_host_state.rand_state = (uint8_t)(uid ^ 0xA5u) | 1u;
}

uint8_t estimate_distance(const distance_measurement_t *d)
{
    return (uint8_t)d->low_gain;
}

void set_motors(uint8_t left, uint8_t right)
{
    kf_host_state.duty_left = left;
    kf_host_state.duty_right = right;
}

void spinup_motors(void)
{
    kf_host_state.spinup = 1u;
}

void set_color(uint8_t color)
{
    kf_host_state.color = color;
}

int16_t get_ambientlight(void)
{
    return kf_host_state.light;
}

int16_t get_voltage(void)
{
    return 4000; /* mV-ish placeholder: a charged battery */
}

int16_t get_temperature(void)
{
    return 25;
}

uint8_t rand_soft(void)
{
    uint8_t x = kf_host_state.rand_state; /* a small 8-bit xorshift */
    x ^= (uint8_t)(x << 7);
    x ^= (uint8_t)(x >> 5);
    x ^= (uint8_t)(x << 3);
    kf_host_state.rand_state = x;
    return x;
}

uint8_t rand_hard(void)
{
    return rand_soft();
}

void rand_seed(uint8_t seed)
{
    kf_host_state.rand_state = seed ? seed : 1u;
}

void delay(uint16_t ms)
{
    (void)ms;
}

uint16_t message_crc(const message_t *m)
{
    uint16_t crc = kf_crc16(m->data, 9u);
    return kf_crc16_update(crc, m->type);
}
