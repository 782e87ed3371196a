/* Kilombo side of tests/bench/bench_kilombo.py: the kilobot world's walls and wall light, a position
 * log, and the options of the comparison. Not part of the firmware.
 *
 * Build the program under test with -DKILOMBO -Dkilo_start=kfk_kilo_start and link this file and
 * Kilombo's headless library: the program's kilo_start() then lands here, which wraps its loop()
 * and hands the wrapper to Kilombo's kilo_start(). Options come from the Kilombo parameter file
 * (keys starting with "kf", see kfk_read_options); every one must be present.
 *
 * Each simulation step Kilombo runs every robot's loop() in index order, then moves the robots,
 * pushes overlapping ones apart and passes messages. Robot 0's wrapper therefore sees the positions
 * at the start of the tick loop() is called in; at every kfLogEvery-th tick it writes one line:
 * "tick x0 y0 d0 x1 y1 d1 ..." (mm, Kilombo's own frame, d = direction in radians).
 */
#undef kilo_start /* this file calls Kilombo's own */
#include <stdio.h>
#include <stdlib.h>
#include <kilombo/skilobot.h>
#include <kilombo/params.h>

void kfk_kilo_start(void (*setup)(void), void (*loop)(void));

static void (*kfk_user_loop)(void);
static FILE *kfk_log;
static int kfk_log_every;
static int kfk_pin_uid = -1; /* robot held in place (a taped-down beacon), -1: none */
static double kfk_pin_x, kfk_pin_y;
static double kfk_wall_lim;  /* robot centres stay in [-lim, lim]^2 */
static double kfk_arena_half, kfk_wall_sense;
static int kfk_light_floor, kfk_light_wall;

static double kfk_option(const char *name)
{
    json_t *v = json_object_get(simparams->root, name);
    if (!json_is_number(v)) {
        fprintf(stderr, "kilombo_adapter: parameter file lacks the number '%s'\n", name);
        exit(2);
    }
    return json_number_value(v);
}

/* Walls: push a centre that left the square back onto its edge (sim/kinematics.py clip_walls). */
static int16_t kfk_walls(double x, double y, double *dx, double *dy)
{
    double cx = x > kfk_wall_lim ? kfk_wall_lim : (x < -kfk_wall_lim ? -kfk_wall_lim : x);
    double cy = y > kfk_wall_lim ? kfk_wall_lim : (y < -kfk_wall_lim ? -kfk_wall_lim : y);
    *dx = cx - x;
    *dy = cy - y;
    return (int16_t)(*dx != 0.0 || *dy != 0.0);
}

/* Ambient light: bright within kfWallSense of a wall (sim/radio.py light_readings, no dropout). */
static int16_t kfk_light(double x, double y)
{
    double ax = x < 0 ? -x : x, ay = y < 0 ? -y : y;
    double wall_d = kfk_arena_half - (ax > ay ? ax : ay);
    return (int16_t)(wall_d <= kfk_wall_sense ? kfk_light_wall : kfk_light_floor);
}

static void kfk_read_options(void)
{
    const char *path = get_string_param("kfLogFile", NULL);
    int tx = (int)kfk_option("kfTxPeriod");
    kfk_arena_half = kfk_option("kfArenaHalf");
    kfk_wall_lim = kfk_arena_half - kfk_option("kfWallRadius");
    kfk_wall_sense = kfk_option("kfWallSense");
    kfk_light_floor = (int)kfk_option("kfLightFloor");
    kfk_light_wall = (int)kfk_option("kfLightWall");
    kfk_log_every = (int)kfk_option("kfLogEvery");
    kfk_pin_uid = (int)kfk_option("kfPinUid");
    if (path == NULL || kfk_log_every < 1 || tx < 1) {
        fprintf(stderr, "kilombo_adapter: need kfLogFile, kfLogEvery >= 1 and kfTxPeriod >= 1\n");
        exit(2);
    }
    kfk_log = fopen(path, "w");
    if (kfk_log == NULL) {
        fprintf(stderr, "kilombo_adapter: cannot write %s\n", path);
        exit(2);
    }
    /* Robots already drew their first send tick as rand() % 15; later sends follow this period. */
    tx_period_ticks = tx;
    set_callback_obstacles(kfk_walls);
    set_callback_lighting(kfk_light);
}

static void kfk_loop(void)
{
    kilobot *me = Me();
    if (me == allbots[0] && kilo_ticks % (uint32_t)kfk_log_every == 0u) {
        int i;
        fprintf(kfk_log, "%lu", (unsigned long)kilo_ticks);
        for (i = 0; i < n_bots; ++i) {
            fprintf(kfk_log, " %.4f %.4f %.5f", allbots[i]->x, allbots[i]->y, allbots[i]->direction);
        }
        fputc('\n', kfk_log);
        fflush(kfk_log);
    }
    if ((int)kilo_uid == kfk_pin_uid) { /* undo any push since the last step */
        me->x = kfk_pin_x;
        me->y = kfk_pin_y;
    }
    kfk_user_loop();
}

void kfk_kilo_start(void (*setup)(void), void (*loop)(void))
{
    if (kfk_log == NULL) {
        kfk_read_options();
    }
    if ((int)kilo_uid == kfk_pin_uid) {
        kfk_pin_x = Me()->x;
        kfk_pin_y = Me()->y;
    }
    kfk_user_loop = loop;
    kilo_start(setup, kfk_loop);
}
