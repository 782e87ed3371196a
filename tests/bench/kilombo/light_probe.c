/* A Kilombo probe for tests/test_kilombo_phototaxis.py: each robot stands still and, on its first loop() call,
 * prints "KFLIGHT <kilo_uid> <get_ambientlight()>" (the uid as the program sees it, after the adapter's
 * kfUidOffset). Build it like the firmware: -DKILOMBO -Dkilo_start=kfk_kilo_start with kilombo_adapter.c. */
#include <stdint.h>
#include <stdio.h>
#include <kilombo.h>

typedef struct {
    uint8_t done;
} lp_state_t;

REGISTER_USERDATA(lp_state_t)

static void setup(void)
{
    mydata->done = 0u;
    set_motors(0u, 0u);
}

static void loop(void)
{
    if (!mydata->done) {
        printf("KFLIGHT %u %d\n", (unsigned)kilo_uid, (int)get_ambientlight());
        mydata->done = 1u;
    }
}

int main(void)
{
    kilo_init();
    kilo_start(setup, loop);
    return 0;
}
