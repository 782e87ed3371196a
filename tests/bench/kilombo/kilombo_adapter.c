/* Kilombo side of tests/bench/bench_kilombo.py and bench_kilombo_phototaxis.py: the kilobot world's walls, its
 * light (lit walls, lamps, the sensor model of sim/light.py), a position log, and the options of the comparison.
 * Not part of the firmware.
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
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <kilombo/skilobot.h>
#include <kilombo/params.h>

void kfk_kilo_start(void (*setup)(void), void (*loop)(void));

static void (*kfk_user_setup)(void), (*kfk_user_loop)(void);
static int kfk_uid_offset; /* the program sees kilo_uid + this (Kilombo wants IDs 0..n-1; our robots are 1..n) */
static FILE *kfk_log;
static int kfk_log_every;
static int kfk_pin_uid = -1; /* robot held in place (a taped-down beacon), -1: none */
static double kfk_pin_x, kfk_pin_y;
static double kfk_wall_lim;  /* robot centres stay in [-lim, lim]^2 */
static double kfk_arena_half, kfk_wall_sense;
static int kfk_light_floor, kfk_light_wall;
#define KFK_MAX_LAMPS 8  /* sim/light.py MAX_LAMPS */
#define KFK_MAX_BOTS 1024
static int kfk_n_spots, kfk_n_sides;
static double kfk_spot[KFK_MAX_LAMPS][5]; /* x, y, radius, edge, peak (our frame, mm, counts) */
static double kfk_side[KFK_MAX_LAMPS][2]; /* angle_deg, peak */
static int kfk_graded;                    /* lamps, noise or per-robot gains: sim/light.py sensor_readings */
static double kfk_noise;                  /* std of the per-reading noise (counts) */
static double kfk_gain[KFK_MAX_BOTS], kfk_offset[KFK_MAX_BOTS]; /* per Kilombo ID (default 1, 0) */

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

/* A standard normal draw from Kilombo's rand() (Box-Muller). */
static double kfk_normal(void)
{
    double u1 = (rand() + 1.0) / ((double)RAND_MAX + 2.0), u2 = rand() / ((double)RAND_MAX + 1.0);
    return sqrt(-2.0 * log(u1)) * cos(2.0 * M_PI * u2);
}

/* Ambient light (sim/radio.py light_readings without dropout: Kilombo clamps a reading to 0..1023, never -1):
 * bright within kfWallSense of a wall; with lamps or a sensor model, sim/light.py: the lamps' field at the robot's
 * centre, times its gain, plus its offset and the noise, rounded (half to even, as NumPy's rint) and clipped.
 * Kilombo's frame is our mirror image, so (x, y) is (x, -y) in ours (bench_kilombo.py kilombo_bots). */
static int16_t kfk_light(double x, double y)
{
    double ax = x < 0 ? -x : x, ay = y < 0 ? -y : y;
    double wall_d = kfk_arena_half - (ax > ay ? ax : ay);
    double v = wall_d <= kfk_wall_sense ? kfk_light_wall : kfk_light_floor;
    double oy = -y, field = 0.0; /* the lamps' sum first, then added: sim/light.py's order of operations */
    int i, uid;
    if (!kfk_graded) {
        return (int16_t)v;
    }
    for (i = 0; i < kfk_n_spots; ++i) {
        const double *s = kfk_spot[i];
        double d = hypot(x - s[0], oy - s[1]), f;
        if (s[3] <= 0.0) {
            f = d <= s[2] ? 1.0 : 0.0;
        } else {
            f = (s[2] + 0.5 * s[3] - d) / s[3];
            f = f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
        }
        field += s[4] * f;
    }
    for (i = 0; i < kfk_n_sides; ++i) {
        double a = kfk_side[i][0] * (M_PI / 180.0); /* Python's math.radians */
        double t = (x * cos(a) + oy * sin(a)) / kfk_arena_half, f = 0.5 * (1.0 + t);
        field += kfk_side[i][1] * (f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f));
    }
    v += field;
    uid = (int)Me()->ID;
    if (uid >= 0 && uid < KFK_MAX_BOTS) {
        v = v * kfk_gain[uid] + kfk_offset[uid];
    }
    if (kfk_noise > 0.0) {
        v += kfk_noise * kfk_normal();
    }
    v = rint(v);
    return (int16_t)(v < 0.0 ? 0.0 : (v > 1023.0 ? 1023.0 : v));
}

/* kfSpots [[x, y, radius, edge, peak], ...], kfSides [[angle_deg, peak], ...], kfLightNoise, kfLightGain and
 * kfLightOffset (one per Kilombo ID 0.., may be shorter: 1 and 0 beyond). */
static void kfk_read_lamps(void)
{
    const char *names[2] = {"kfSpots", "kfSides"};
    int k, i, j, n;
    json_t *g, *o;
    for (k = 0; k < 2; ++k) {
        json_t *a = json_object_get(simparams->root, names[k]);
        int width = k == 0 ? 5 : 2;
        if (!json_is_array(a) || json_array_size(a) > KFK_MAX_LAMPS) {
            fprintf(stderr, "kilombo_adapter: '%s' must be an array of at most %d lamps\n", names[k], KFK_MAX_LAMPS);
            exit(2);
        }
        n = (int)json_array_size(a);
        for (i = 0; i < n; ++i) {
            json_t *lamp = json_array_get(a, (size_t)i);
            if (!json_is_array(lamp) || (int)json_array_size(lamp) != width) {
                fprintf(stderr, "kilombo_adapter: each of '%s' must hold %d numbers\n", names[k], width);
                exit(2);
            }
            for (j = 0; j < width; ++j) {
                double v = json_number_value(json_array_get(lamp, (size_t)j));
                if (k == 0) {
                    kfk_spot[i][j] = v;
                } else {
                    kfk_side[i][j] = v;
                }
            }
        }
        if (k == 0) {
            kfk_n_spots = n;
        } else {
            kfk_n_sides = n;
        }
    }
    kfk_noise = kfk_option("kfLightNoise");
    g = json_object_get(simparams->root, "kfLightGain");
    o = json_object_get(simparams->root, "kfLightOffset");
    if (!json_is_array(g) || !json_is_array(o) || json_array_size(g) > KFK_MAX_BOTS ||
        json_array_size(o) > KFK_MAX_BOTS) {
        fprintf(stderr, "kilombo_adapter: kfLightGain and kfLightOffset must be arrays (one number per robot ID)\n");
        exit(2);
    }
    for (i = 0; i < KFK_MAX_BOTS; ++i) {
        kfk_gain[i] = i < (int)json_array_size(g) ? json_number_value(json_array_get(g, (size_t)i)) : 1.0;
        kfk_offset[i] = i < (int)json_array_size(o) ? json_number_value(json_array_get(o, (size_t)i)) : 0.0;
    }
    kfk_graded = kfk_n_spots > 0 || kfk_n_sides > 0 || kfk_noise > 0.0 || json_array_size(g) > 0 ||
                 json_array_size(o) > 0;
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
    kfk_uid_offset = (int)kfk_option("kfUidOffset");
    kfk_read_lamps();
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
    kilo_uid = (uint16_t)(kilo_uid + kfk_uid_offset); /* Kilombo sets kilo_uid again before each robot's turn */
    kfk_user_loop();
}

static void kfk_setup(void)
{
    kilo_uid = (uint16_t)(kilo_uid + kfk_uid_offset);
    kfk_user_setup();
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
    kfk_user_setup = setup;
    kfk_user_loop = loop;
    kilo_start(kfk_setup, kfk_loop);
}
