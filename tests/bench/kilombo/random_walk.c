/* The random floor for tests/bench/bench_kilombo.py, as a kilolib program: every control period
 * (31 kilo_ticks) a searcher draws u_left, u_right uniformly from 0..255 and realises them with the
 * kilobot world's straight / pivot schedule (sim/motion.py: turn ticks first, then straight ticks),
 * as sim.baselines.RandomPolicy does in our simulator. kilo_uid 0 is the beacon: it never moves and
 * sends one message for ever (the searchers ignore it). Builds for kilolib, or Kilombo with -DKILOMBO. */
#include <stdint.h>
#ifdef KILOMBO
#include <kilombo.h>
#else
#include <kilolib.h>
#endif

#define RW_PERIOD 31u
#define RW_BEACON_UID 0u

typedef struct {
    message_t msg;
    uint32_t period_start;
    uint8_t turn, straight, turn_left;
    uint8_t mode; /* 0 stop, 1 straight, 2 left, 3 right: what the motors do now */
} rw_state_t;

#ifdef KILOMBO
REGISTER_USERDATA(rw_state_t)
#else
static rw_state_t rw_state;
static rw_state_t *const mydata = &rw_state;
#endif

static void rw_draw(rw_state_t *s)
{
    uint8_t ql = rand_soft(), qr = rand_soft();
    uint16_t diff = ql > qr ? (uint16_t)(ql - qr) : (uint16_t)(qr - ql);
    uint16_t turn = (uint16_t)((diff * RW_PERIOD + 127u) / 255u);
    uint16_t straight = (uint16_t)(((uint16_t)ql + qr) * RW_PERIOD / 510u);
    if (straight > RW_PERIOD - turn) {
        straight = (uint16_t)(RW_PERIOD - turn);
    }
    s->turn = (uint8_t)turn;
    s->straight = (uint8_t)straight;
    s->turn_left = (uint8_t)(ql > qr);
}

static message_t *rw_tx(void)
{
    return kilo_uid == RW_BEACON_UID ? &mydata->msg : 0;
}

static void setup(void)
{
    rw_state_t *s = mydata;
    uint8_t i;
    for (i = 0u; i < 9u; ++i) {
        s->msg.data[i] = 0u;
    }
    s->msg.type = NORMAL;
    s->msg.crc = message_crc(&s->msg);
    s->period_start = kilo_ticks;
    s->mode = 0u;
    s->turn = s->straight = s->turn_left = 0u;
    rand_seed(rand_hard());
    set_motors(0u, 0u);
    rw_draw(s);
}

static void loop(void)
{
    rw_state_t *s = mydata;
    uint32_t t;
    uint8_t mode;
    if (kilo_uid == RW_BEACON_UID) {
        return;
    }
    t = kilo_ticks - s->period_start;
    if (t >= RW_PERIOD) {
        s->period_start += RW_PERIOD;
        t -= RW_PERIOD;
        rw_draw(s);
    }
    mode = t < s->turn ? (s->turn_left ? 2u : 3u) : (t < (uint32_t)s->turn + s->straight ? 1u : 0u);
    if (mode == s->mode) {
        return;
    }
    if (mode != 0u && s->mode == 0u) {
        spinup_motors();
    }
    if (mode == 1u) {
        set_motors(kilo_straight_left, kilo_straight_right);
    } else if (mode == 2u) {
        set_motors(kilo_turn_left, 0u);
    } else if (mode == 3u) {
        set_motors(0u, kilo_turn_right);
    } else {
        set_motors(0u, 0u);
    }
    s->mode = mode;
}

int main(void)
{
    kilo_init();
    kilo_message_tx = rw_tx;
    kilo_start(setup, loop);
    return 0;
}
