/*
 * servo_loop: a haptic host in the style of an OpenHaptics scheduler callback, on
 * libhapticrom (include/hapticrom.h).
 *
 * A servo thread steps the model at 1 kHz while a render thread reads the surface at about
 * 60 Hz into its own buffer. Two ways of driving the tool:
 *
 * - position in, force out (--tips FILE): each tick hands the tool tip's centre, the next
 *   row of FILE, to hapticrom_step_position and reads the state (in contact, the proxy where
 *   a renderer draws the tool). FILE is a CSV of rows t, x, y, z (s, mm; a header line
 *   "t,x,y,z" and # comments allowed: the format of `hapticrom play --path`); the loop
 *   paces one row per tick at --rate (t is not used). examples/c/scripted_tips.py writes
 *   the scripted path of `hapticrom play` (approach, press at 30 degrees, slide, lift) so.
 * - contact point and displacement in (the default): a scripted path (press, slide at
 *   constant depth, release: like hapticrom.online.play.tool_path) computed here from the
 *   trained points; each tick sets the contact, reads the contact normal and asks for the
 *   force of a displacement along it.
 *
 *   servo_loop MODEL [--tips FILE.csv] [--seconds S] [--rate HZ] [--render-rate HZ]
 *              [--forces FILE.csv] [--surfaces FILE.bin] [--response anm|curves]
 *              [--interpolation transport|podi|compliance] [--tool-radius MM]
 *              [--friction MU_S,MU_D[,K_T]]
 *   servo_loop MODEL [--tips FILE.csv] [--friction MU_S,MU_D[,K_T]] --bench N
 *              [--bench-surfaces M] [--cpu K]
 *
 * --friction: Coulomb friction for step_position (hapticrom_set_friction, before the loop):
 * the static and dynamic coefficients and, optionally, the tangential stiffness as a multiple
 * of the normal one (default 2/3); the contact-point mode (no --tips) is frictionless.
 * --forces: one CSV row per tick: tick, the contact point (or the tip) mm, depth mm, force
 * N, status, the state's sequence number after the tick's set_contact (after its
 * step_position); with --tips also in_contact, saturated, the proxy (mm) and slipping.
 * --surfaces: per rendered frame, the state's sequence number (uint64) then 3 V doubles
 * (mm), after a header of V (uint64). --bench: no threads; the latency of N set_contact,
 * get_state and step_displacement calls along the path (with --tips: step_position,
 * stiffness and get_state along the tips, round and round) and of M surfaces (clock_gettime,
 * CLOCK_MONOTONIC, per call), as p50 / p99 / p99.9 / max in ns; each surface is followed by
 * a call of constant work as long as their median, timed too (the host's floor).
 *
 * Exit status 0 if every call succeeded, 1 otherwise (the message on stderr), 2 on usage.
 */
#define _GNU_SOURCE
#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <sched.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "hapticrom.h"

struct path {
    size_t ticks;
    int position;   /* 1: points are tool tips (step_position); 0: contact points */
    double *points; /* (ticks, 3) mm */
    double *depths; /* (ticks,) mm; contact points only */
};

/* What one servo tick gave. */
struct record {
    double force[3]; /* N */
    double depth;    /* mm, the state's after the tick */
    double proxy[3]; /* mm (step_position) */
    uint64_t sequence; /* the state's number after the tick's set_contact (its step_position) */
    int status;
    uint32_t in_contact, saturated, slipping;
};

struct run {
    hapticrom_simulator sim;
    hapticrom_info info;
    struct path path;
    double rate, render_rate;
    struct record *records; /* (ticks,) */
    FILE *surfaces;
    int servo_started; /* atomic: the first tick is in (the render thread starts) */
    int servo_done;    /* atomic: the render thread stops */
    int failed;     /* atomic */
    size_t frames, skipped; /* surfaces rendered, and not (BUSY) */
};

static int check(int status, const char *what) {
    if (status != HAPTICROM_OK)
        fprintf(stderr, "servo_loop: %s: %s (%s)\n", what, hapticrom_last_error(),
                hapticrom_status_name(status));
    return status;
}

static int64_t now_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000 + t.tv_nsec;
}

/* --- the scripted path ----------------------------------------------------------------- */
/* A unit vector in the plane normal to n. */
static void tangent(const double n[3], double u[3]) {
    int axis = fabs(n[0]) <= fabs(n[1]) && fabs(n[0]) <= fabs(n[2]) ? 0
               : fabs(n[1]) <= fabs(n[2])                            ? 1
                                                                     : 2;
    double e[3] = {0, 0, 0};
    e[axis] = 1.0;
    u[0] = n[1] * e[2] - n[2] * e[1];
    u[1] = n[2] * e[0] - n[0] * e[2];
    u[2] = n[0] * e[1] - n[1] * e[0];
    double length = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    for (int c = 0; c < 3; c++) u[c] /= length;
}

/* Press (25 %), slide (50 %), release (25 %) through the samples' centre along a tangent,
 * over 70 % of the samples' extent, at 80 % of the trained depth. */
static int make_path(hapticrom_simulator sim, const hapticrom_info *info, size_t ticks,
                     struct path *path) {
    size_t P = info->sample_count;
    double *samples = malloc(3 * P * sizeof(double));
    if (!samples || check(hapticrom_sample_points(sim, samples, 3 * P), "sample points")) {
        free(samples);
        return 1;
    }
    double centre[3] = {0, 0, 0}, u[3], lo = INFINITY, hi = -INFINITY;
    for (size_t i = 0; i < P; i++)
        for (int c = 0; c < 3; c++) centre[c] += samples[3 * i + c] / (double)P;
    hapticrom_state state;
    if (check(hapticrom_set_contact(sim, centre), "set_contact at the centre") ||
        check(hapticrom_get_state(sim, &state), "get_state")) {
        free(samples);
        return 1;
    }
    tangent(state.normal, u);
    for (size_t i = 0; i < P; i++) {
        double x = 0;
        for (int c = 0; c < 3; c++) x += (samples[3 * i + c] - centre[c]) * u[c];
        lo = fmin(lo, x);
        hi = fmax(hi, x);
    }
    free(samples);
    double half = 0.35 * (hi - lo), depth = 0.8 * info->trained_depth;
    path->ticks = ticks;
    path->points = malloc(3 * ticks * sizeof(double));
    path->depths = malloc(ticks * sizeof(double));
    if (!path->points || !path->depths) return 1;
    for (size_t i = 0; i < ticks; i++) {
        double t = ticks > 1 ? (double)i / (double)(ticks - 1) : 0.0;
        double x = t < 0.25 ? -half : t > 0.75 ? half : -half + 2 * half * (t - 0.25) / 0.5;
        double d = t < 0.25 ? t / 0.25 : t > 0.75 ? (1 - t) / 0.25 : 1.0;
        for (int c = 0; c < 3; c++) path->points[3 * i + c] = centre[c] + x * u[c];
        path->depths[i] = d * depth;
    }
    return 0;
}

/* --- a tool path from a file: rows t, x, y, z ------------------------------------------------ */
#define MAX_LINE 4096           /* characters in a line, as hapticrom play --path */
#define MAX_TIPS 3600000        /* rows: an hour at 1 kHz */
#define MAX_COORDINATE 1e4      /* mm: a tip 10 m away is a unit mistake */
#define STRINGIFY_(x) #x
#define STRINGIFY(x) STRINGIFY_(x)

/* The line without its comment and surrounding blanks (in place). */
static char *stripped(char *line) {
    char *hash = strchr(line, '#');
    if (hash) *hash = '\0';
    while (isspace((unsigned char)*line)) line++;
    size_t n = strlen(line);
    while (n > 0 && isspace((unsigned char)line[n - 1])) line[--n] = '\0';
    return line;
}

/* Whether line is the header "t,x,y,z" (blanks allowed, any case). */
static int is_header(const char *line) {
    const char *expected = "t,x,y,z";
    for (; *line; line++) {
        if (*line == ' ' || *line == '\t') continue;
        if (tolower((unsigned char)*line) != *expected++) return 0;
    }
    return *expected == '\0';
}

/* Four comma-separated finite numbers of line into v; 0 if they are, 1 if not. */
static int parse_row(const char *line, double v[4]) {
    const char *p = line;
    for (int i = 0; i < 4; i++) {
        char *end;
        errno = 0;
        v[i] = strtod(p, &end);
        if (end == p || errno == ERANGE || !isfinite(v[i])) return 1;
        p = end;
        while (*p == ' ' || *p == '\t') p++;
        if (i < 3 && *p++ != ',') return 1;
    }
    return *p != '\0';
}

/* Append the tip v[1..3] to path (grown by doubling); 0 on success. */
static int append_tip(struct path *path, size_t *capacity, const double v[4]) {
    if (path->ticks == *capacity) {
        size_t grown = *capacity ? 2 * *capacity : 1024;
        double *points = realloc(path->points, 3 * grown * sizeof(double));
        if (!points) return 1;
        path->points = points;
        *capacity = grown;
    }
    memcpy(&path->points[3 * path->ticks++], &v[1], 3 * sizeof(double));
    return 0;
}

enum line_read { LINE_END, LINE_OK, LINE_TOO_LONG, LINE_NUL };

/* The next line of f (without its '\n') into line[MAX_LINE + 1], NUL-terminated: LINE_OK,
 * LINE_END at the end of the file, LINE_TOO_LONG beyond MAX_LINE characters (its '\n'
 * included, as hapticrom play counts), LINE_NUL for a NUL byte (not text). */
static enum line_read read_line(FILE *f, char *line) {
    size_t n = 0;
    int c = getc(f);
    if (c == EOF) return LINE_END;
    for (; c != EOF && c != '\n'; c = getc(f)) {
        if (c == '\0') return LINE_NUL;
        if (n == MAX_LINE - 1) return LINE_TOO_LONG; /* the '\n' still to come */
        line[n++] = (char)c;
    }
    line[n] = '\0';
    return LINE_OK;
}

/* The tips of the CSV file into path (position mode); 0 on success, else 1 and a message
 * naming the file and line. Every row is checked: a host must not feed the device loop a
 * position it did not mean (a NaN, a coordinate in metres). */
static int read_tips(const char *file, struct path *path) {
    FILE *f = fopen(file, "r");
    if (!f) {
        fprintf(stderr, "servo_loop: --tips %s: %s\n", file, strerror(errno));
        return 1;
    }
    *path = (struct path){.position = 1};
    char line[MAX_LINE + 1];
    size_t number = 0, capacity = 0;
    int failed = 0;
    enum line_read got;
    while (!failed && (got = read_line(f, line)) != LINE_END) {
        number++;
        if (got != LINE_OK) {
            fprintf(stderr, "servo_loop: --tips %s, line %zu: %s\n", file, number,
                    got == LINE_NUL ? "a NUL byte (not a text file)"
                                    : "longer than " STRINGIFY(MAX_LINE) " characters");
            failed = 1;
            break;
        }
        /* a UTF-8 byte-order mark before the first line, as hapticrom play accepts */
        char *row = stripped(number == 1 && !strncmp(line, "\xEF\xBB\xBF", 3) ? line + 3 : line);
        if (!*row || (path->ticks == 0 && is_header(row))) continue;
        double v[4];
        if (parse_row(row, v) || fmax(fabs(v[1]), fmax(fabs(v[2]), fabs(v[3]))) > MAX_COORDINATE) {
            fprintf(stderr, "servo_loop: --tips %s, line %zu: expected 4 finite numbers t, x, "
                            "y, z (s, mm; |x|, |y|, |z| <= %g), got '%.80s'\n", file, number,
                    MAX_COORDINATE, row);
            failed = 1;
        } else if (path->ticks == MAX_TIPS) {
            fprintf(stderr, "servo_loop: --tips %s: more than %d rows\n", file, MAX_TIPS);
            failed = 1;
        } else if (append_tip(path, &capacity, v)) {
            fprintf(stderr, "servo_loop: --tips %s: out of memory\n", file);
            failed = 1;
        }
    }
    if (!failed && ferror(f)) {
        fprintf(stderr, "servo_loop: --tips %s: read error\n", file);
        failed = 1;
    }
    fclose(f);
    if (!failed && path->ticks == 0) {
        fprintf(stderr, "servo_loop: --tips %s: no rows (t, x, y, z)\n", file);
        failed = 1;
    }
    return failed;
}

/* --- one servo tick: what an OpenHaptics callback would do ------------------------------- */
/* The contact at point, then the force of a push `depth` (mm) along the normal into force;
 * *sequence receives the state's number after the contact (the step's is one more). */
static int tick(hapticrom_simulator sim, const double point[3], double depth, double force[3],
                uint64_t *sequence) {
    hapticrom_state state;
    int status = hapticrom_set_contact(sim, point);
    if (!status) status = hapticrom_get_state(sim, &state);
    if (status) return status;
    *sequence = state.sequence;
    double d[3];
    for (int c = 0; c < 3; c++) d[c] = -depth * state.normal[c]; /* into the tissue */
    return hapticrom_step_displacement(sim, d, force);
}

/* Position in, force out: the tip to step_position, then the state a host draws from. */
static int tick_position(hapticrom_simulator sim, const double tip[3], struct record *out) {
    hapticrom_state state;
    int status = hapticrom_step_position(sim, tip, out->force);
    if (!status) status = hapticrom_get_state(sim, &state);
    if (status) return status;
    out->depth = state.depth;
    out->sequence = state.sequence;
    out->in_contact = state.in_contact;
    out->saturated = state.saturated;
    out->slipping = state.slipping;
    memcpy(out->proxy, state.proxy, sizeof out->proxy);
    return HAPTICROM_OK;
}

/* Tick i of the run's path, in its mode, into r->records[i]. */
static int run_tick(struct run *r, size_t i) {
    struct record *out = &r->records[i];
    const double *p = &r->path.points[3 * i];
    if (r->path.position) return tick_position(r->sim, p, out);
    out->depth = r->path.depths[i];
    return tick(r->sim, p, out->depth, out->force, &out->sequence);
}

static void sleep_until(int64_t t) {
    struct timespec ts = {.tv_sec = t / 1000000000, .tv_nsec = t % 1000000000};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
    }
}

static void *servo_thread(void *arg) {
    struct run *r = arg;
    int64_t period = (int64_t)(1e9 / r->rate), start = now_ns();
    for (size_t i = 0; i < r->path.ticks; i++) {
        sleep_until(start + (int64_t)i * period);
        int status = run_tick(r, i);
        r->records[i].status = status;
        __atomic_store_n(&r->servo_started, 1, __ATOMIC_RELEASE);
        if (status) {
            check(status, "servo tick");
            __atomic_store_n(&r->failed, 1, __ATOMIC_RELAXED);
            break;
        }
    }
    __atomic_store_n(&r->servo_done, 1, __ATOMIC_RELEASE);
    return NULL;
}

static void *render_thread(void *arg) {
    struct run *r = arg;
    size_t length = 3 * r->info.vertex_count;
    double *surface = malloc(length * sizeof(double)); /* the renderer's own buffer */
    if (!surface) {
        __atomic_store_n(&r->failed, 1, __ATOMIC_RELAXED);
        return NULL;
    }
    /* From the servo's first tick on: every frame is then a state of the path (the test
     * replays the path; a real renderer need not wait). */
    while (!__atomic_load_n(&r->servo_started, __ATOMIC_ACQUIRE)) sched_yield();
    int64_t period = (int64_t)(1e9 / r->render_rate), next = now_ns();
    while (!__atomic_load_n(&r->servo_done, __ATOMIC_ACQUIRE)) {
        hapticrom_state state;
        int status = hapticrom_surface(r->sim, surface, length, &state);
        if (status == HAPTICROM_E_BUSY) { /* a servo loop writing without a pause: show the */
            r->skipped++;                 /* last frame again, try at the next one */
        } else if (check(status, "surface")) {
            __atomic_store_n(&r->failed, 1, __ATOMIC_RELAXED);
            break;
        } else {
            r->frames++;
            if (r->surfaces) {
                fwrite(&state.sequence, sizeof state.sequence, 1, r->surfaces);
                fwrite(surface, sizeof(double), length, r->surfaces);
            }
        }
        next += period;
        sleep_until(next);
    }
    free(surface);
    return NULL;
}

static int write_forces(const struct run *r, const char *file) {
    FILE *f = fopen(file, "w");
    if (!f) {
        perror(file);
        return 1;
    }
    fprintf(f, "tick,x,y,z,depth,fx,fy,fz,status,sequence%s\n",
            r->path.position ? ",in_contact,saturated,px,py,pz,slipping" : "");
    for (size_t i = 0; i < r->path.ticks; i++) {
        const double *p = &r->path.points[3 * i];
        const struct record *t = &r->records[i];
        fprintf(f, "%zu,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%d,%llu", i, p[0], p[1], p[2],
                t->depth, t->force[0], t->force[1], t->force[2], t->status,
                (unsigned long long)t->sequence);
        if (r->path.position)
            fprintf(f, ",%u,%u,%.17g,%.17g,%.17g,%u", t->in_contact, t->saturated,
                    t->proxy[0], t->proxy[1], t->proxy[2], t->slipping);
        fputc('\n', f);
    }
    return fclose(f) != 0;
}

static int play(struct run *r, const char *forces_file, const char *surfaces_file) {
    if (surfaces_file) {
        r->surfaces = fopen(surfaces_file, "wb");
        if (!r->surfaces) {
            perror(surfaces_file);
            return 1;
        }
        uint64_t v = r->info.vertex_count;
        fwrite(&v, sizeof v, 1, r->surfaces);
    }
    pthread_t servo, render;
    int64_t start = now_ns();
    pthread_create(&render, NULL, render_thread, r);
    pthread_create(&servo, NULL, servo_thread, r);
    pthread_join(servo, NULL);
    pthread_join(render, NULL);
    double seconds = (double)(now_ns() - start) * 1e-9;
    if (r->surfaces && fclose(r->surfaces) != 0) r->failed = 1;
    double peak = 0;
    size_t touching = 0, saturated = 0, slipping = 0;
    for (size_t i = 0; i < r->path.ticks; i++) {
        const double *F = r->records[i].force;
        peak = fmax(peak, sqrt(F[0] * F[0] + F[1] * F[1] + F[2] * F[2]));
        touching += r->records[i].in_contact;
        saturated += r->records[i].saturated;
        slipping += r->records[i].slipping;
    }
    printf("servo: %zu ticks at %.0f Hz in %.3f s; render: %zu surfaces of %llu vertices (%zu "
           "skipped: busy); peak force %.6g N\n", r->path.ticks, r->rate, seconds, r->frames,
           (unsigned long long)r->info.vertex_count, r->skipped, peak);
    if (r->path.position)
        printf("position in, force out: %zu ticks in contact, %zu saturated, %zu slipping\n",
               touching, saturated, slipping);
    if (forces_file && write_forces(r, forces_file)) return 1;
    return r->failed;
}

/* --- latency ------------------------------------------------------------------------------- */
static int compare_u32(const void *a, const void *b) {
    uint32_t x = *(const uint32_t *)a, y = *(const uint32_t *)b;
    return (x > y) - (x < y);
}

static void report(const char *what, uint32_t *ns, size_t n) {
    double total = 0;
    for (size_t i = 0; i < n; i++) total += ns[i];
    qsort(ns, n, sizeof *ns, compare_u32);
    printf("%-20s %9zu calls  p50 %7u ns  p99 %7u ns  p99.9 %8u ns  max %9u ns  mean %7.0f ns\n",
           what, n, ns[n / 2], ns[(size_t)(0.99 * (double)n)], ns[(size_t)(0.999 * (double)n)],
           ns[n - 1], total / (double)n);
}

static uint32_t elapsed(int64_t t0, int64_t t1) {
    return (uint32_t)(t1 - t0 > UINT32_MAX ? UINT32_MAX : t1 - t0);
}

/* n dependent multiply-adds: a call whose work never varies, so its p99 is what the
 * machine itself (timer ticks, the hypervisor) adds to a call that long. */
static double constant_work(size_t n, double x) {
    for (size_t i = 0; i < n; i++) x = x * 0.999999 + 1e-7;
    return x;
}

/* The n for which constant_work lasts about median_ns (the least of three timings). */
static size_t constant_work_count(uint32_t median_ns, volatile double *sink) {
    int64_t best = INT64_MAX;
    for (int k = 0; k < 3; k++) {
        int64_t t0 = now_ns();
        *sink += constant_work(1000000, 1.0);
        int64_t took = now_ns() - t0;
        if (took < best) best = took;
    }
    size_t n = (size_t)(1e6 * (double)median_ns / (double)(best > 0 ? best : 1));
    return n ? n : 1;
}

/* One surface after tick k of the path (contact points: spread along it; tips: in order, the
 * proxy follows them); its latency in ns, or UINT32_MAX if a call failed. */
static uint32_t timed_surface(struct run *r, size_t i, double *surface, size_t length) {
    size_t k = r->path.position ? i % r->path.ticks : (i * 7919) % r->path.ticks;
    if (check(run_tick(r, k), "bench tick")) return UINT32_MAX;
    int64_t t0 = now_ns();
    int status = hapticrom_surface(r->sim, surface, length, NULL);
    uint32_t ns = elapsed(t0, now_ns());
    return check(status, "bench surface") ? UINT32_MAX : ns;
}

static double share_over(const uint32_t *ns, size_t n, uint32_t limit) {
    size_t over = 0;
    for (size_t i = 0; i < n; i++) over += ns[i] > limit;
    return (double)over / (double)n;
}

/* M surfaces, each after a tick of the path (states along it), each followed by a call of
 * constant work as long as the surfaces' median (measured on 200 first): the floor the host
 * puts under the surface's tail, met in the same milliseconds. */
static int bench_surfaces(struct run *r, size_t surfaces) {
    if (!surfaces) return 0;
    enum { PROBE = 200 };
    uint32_t *ns = malloc(surfaces * sizeof *ns), *floor_ns = malloc(surfaces * sizeof *ns);
    uint32_t probe[PROBE];
    size_t length = 3 * r->info.vertex_count;
    double *surface = malloc(length * sizeof(double));
    volatile double sink = 0.0;
    int failed = !ns || !floor_ns || !surface;
    for (size_t i = 0; i < PROBE && !failed; i++)
        failed = (probe[i] = timed_surface(r, i, surface, length)) == UINT32_MAX;
    if (!failed) qsort(probe, PROBE, sizeof *probe, compare_u32);
    size_t n = failed ? 0 : constant_work_count(probe[PROBE / 2], &sink);
    for (size_t i = 0; i < surfaces && !failed; i++) {
        failed = (ns[i] = timed_surface(r, i, surface, length)) == UINT32_MAX;
        int64_t t0 = now_ns();
        sink += constant_work(n, 1.0);
        floor_ns[i] = elapsed(t0, now_ns());
    }
    if (!failed) {
        printf("surface over 50 us: %.2f %% of calls, the constant work beside it %.2f %%\n",
               100 * share_over(ns, surfaces, 50000), 100 * share_over(floor_ns, surfaces, 50000));
        report("surface", ns, surfaces);
        report("  constant work", floor_ns, surfaces);
    }
    free(ns), free(floor_ns), free(surface);
    return failed;
}

/* Position in, force out: N step_position, stiffness and get_state calls along the tips
 * (round and round); step_position's latency also split by whether the tool touched. */
static int bench_position(struct run *r, size_t steps) {
    uint32_t *position = malloc(steps * sizeof *position), *touching = malloc(steps * sizeof *position),
             *free_ns = malloc(steps * sizeof *position), *stiffness = malloc(steps * sizeof *position),
             *state_ns = malloc(steps * sizeof *position), *timer = malloc(steps * sizeof *position);
    int failed = !position || !touching || !free_ns || !stiffness || !state_ns || !timer;
    size_t in_contact = 0, out_of_contact = 0;
    double force[3], K[9];
    for (size_t i = 0; i < steps && !failed; i++) {
        hapticrom_state state;
        int64_t t0 = now_ns();
        int status = hapticrom_step_position(r->sim, &r->path.points[3 * (i % r->path.ticks)], force);
        int64_t t1 = now_ns();
        status |= hapticrom_stiffness(r->sim, K);
        int64_t t2 = now_ns();
        status |= hapticrom_get_state(r->sim, &state);
        int64_t t3 = now_ns();
        if (check(status, "bench step_position")) {
            failed = 1;
            break;
        }
        position[i] = elapsed(t0, t1), stiffness[i] = elapsed(t1, t2);
        state_ns[i] = elapsed(t2, t3), timer[i] = elapsed(t3, now_ns());
        if (state.in_contact) touching[in_contact++] = position[i];
        else free_ns[out_of_contact++] = position[i];
    }
    if (!failed) {
        report("clock_gettime", timer, steps);
        report("step_position", position, steps);
        if (in_contact) report("  in contact", touching, in_contact);
        if (out_of_contact) report("  free", free_ns, out_of_contact);
        report("stiffness", stiffness, steps);
        report("get_state", state_ns, steps);
    }
    free(position), free(touching), free(free_ns), free(stiffness), free(state_ns), free(timer);
    return failed;
}

static int bench(struct run *r, size_t steps, size_t surfaces) {
    if (r->path.position)
        return bench_position(r, steps) || bench_surfaces(r, surfaces);
    uint32_t *contact = malloc(steps * sizeof *contact), *state_ns = malloc(steps * sizeof *contact),
             *step_ns = malloc(steps * sizeof *contact), *timer = malloc(steps * sizeof *contact);
    double force[3];
    if (!contact || !state_ns || !step_ns || !timer) return 1;
    hapticrom_simulator sim = r->sim;
    for (size_t i = 0; i < steps; i++) {
        size_t k = i % r->path.ticks;
        hapticrom_state state;
        int64_t t0 = now_ns();
        int status = hapticrom_set_contact(sim, &r->path.points[3 * k]);
        int64_t t1 = now_ns();
        status |= hapticrom_get_state(sim, &state);
        int64_t t2 = now_ns();
        double d[3];
        for (int c = 0; c < 3; c++) d[c] = -r->path.depths[k] * state.normal[c];
        int64_t t3 = now_ns();
        status |= hapticrom_step_displacement(sim, d, force);
        int64_t t4 = now_ns();
        if (check(status, "bench step")) return 1;
        contact[i] = elapsed(t0, t1), state_ns[i] = elapsed(t1, t2), step_ns[i] = elapsed(t3, t4);
        timer[i] = elapsed(t4, now_ns());
    }
    report("clock_gettime", timer, steps);
    report("set_contact", contact, steps);
    report("get_state", state_ns, steps);
    report("step_displacement", step_ns, steps);
    free(contact), free(state_ns), free(step_ns), free(timer);
    return bench_surfaces(r, surfaces);
}

/* --- main ------------------------------------------------------------------------------------ */
static int usage(void) {
    fprintf(stderr, "usage: servo_loop MODEL [--tips FILE.csv] [--seconds S] [--rate HZ] "
                    "[--render-rate HZ] [--forces FILE.csv] [--surfaces FILE.bin] "
                    "[--response anm|curves] [--interpolation transport|podi|compliance] "
                    "[--tool-radius MM] [--friction MU_S,MU_D[,K_T]]\n"
                    "       servo_loop MODEL [--tips FILE.csv] [--friction MU_S,MU_D[,K_T]] "
                    "--bench N [--bench-surfaces M] [--cpu K]\n");
    return 2;
}

struct arguments {
    const char *model, *forces, *surfaces, *tips;
    double seconds, rate, render_rate;
    long bench, bench_surfaces, cpu;
    int friction;       /* --friction given */
    double mu[3];       /* its static, dynamic coefficient, tangential stiffness (0: default) */
    hapticrom_options options;
};

static int positive(const char *text, double *value) {
    char *end;
    *value = strtod(text, &end);
    return *end == '\0' && isfinite(*value) && *value > 0;
}

/* Whether text is 2 or 3 comma-separated numbers (into mu; the third 0 if absent). The
 * library checks their ranges: a refusal there is its message, not a usage error. */
static int coefficients(const char *text, double mu[3]) {
    const char *p = text;
    int n = 0;
    mu[2] = 0.0;
    for (; n < 3; n++) {
        char *end;
        mu[n] = strtod(p, &end);
        if (end == p) return 0;
        p = end;
        if (*p != ',') break;
        p++;
    }
    return *p == '\0' && n >= 1 && n < 3;
}

/* Whether text is a whole number >= 0 (then it goes into *value). */
static int count(const char *text, long *value) {
    char *end;
    errno = 0;
    long n = strtol(text, &end, 10);
    if (end == text || *end != '\0' || errno || n < 0) return 0;
    *value = n;
    return 1;
}

static int parse(int argc, char **argv, struct arguments *a) {
    if (argc < 2) return 1;
    *a = (struct arguments){.model = argv[1], .seconds = 2, .rate = 1000, .render_rate = 60,
                            .bench_surfaces = 2000, .cpu = -1};
    hapticrom_options_init(&a->options);
    for (int i = 2; i < argc; i++) {
        const char *key = argv[i], *value = i + 1 < argc ? argv[i + 1] : NULL;
        double x;
        if (!value) return 1;
        i++;
        if (!strcmp(key, "--forces")) a->forces = value;
        else if (!strcmp(key, "--tips")) a->tips = value;
        else if (!strcmp(key, "--tool-radius") && positive(value, &x)) a->options.tool_radius = x;
        else if (!strcmp(key, "--surfaces")) a->surfaces = value;
        else if (!strcmp(key, "--seconds") && positive(value, &x)) a->seconds = x;
        else if (!strcmp(key, "--rate") && positive(value, &x)) a->rate = x;
        else if (!strcmp(key, "--render-rate") && positive(value, &x)) a->render_rate = x;
        else if (!strcmp(key, "--bench") && positive(value, &x)) a->bench = (long)x;
        else if (!strcmp(key, "--bench-surfaces")) {
            if (!count(value, &a->bench_surfaces)) return 1;
        }
        else if (!strcmp(key, "--cpu")) a->cpu = strtol(value, NULL, 10);
        else if (!strcmp(key, "--friction")) {
            if (!coefficients(value, a->mu)) return 1;
            a->friction = 1;
        }
        else if (!strcmp(key, "--response"))
            a->options.response = !strcmp(value, "anm") ? HAPTICROM_RESPONSE_ANM
                                  : !strcmp(value, "curves") ? HAPTICROM_RESPONSE_CURVES
                                                             : -1;
        else if (!strcmp(key, "--interpolation"))
            a->options.interpolation = !strcmp(value, "transport") ? HAPTICROM_INTERPOLATION_TRANSPORT
                                       : !strcmp(value, "podi")    ? HAPTICROM_INTERPOLATION_PODI
                                       : !strcmp(value, "compliance")
                                           ? HAPTICROM_INTERPOLATION_COMPLIANCE
                                           : -1;
        else return 1;
    }
    return 0;
}

int main(int argc, char **argv) {
    struct arguments a;
    if (parse(argc, argv, &a)) return usage();
    if (a.cpu >= 0) {
        cpu_set_t set;
        CPU_ZERO(&set);
        CPU_SET((int)a.cpu, &set);
        pthread_setaffinity_np(pthread_self(), sizeof set, &set);
    }
    uint32_t abi;
    const char *version = hapticrom_version(&abi);
    struct run r = {.rate = a.rate, .render_rate = a.render_rate};
    if (a.tips && read_tips(a.tips, &r.path)) { /* refused before seconds of loading */
        free(r.path.points);
        return 1;
    }
    int64_t t0 = now_ns();
    if (check(hapticrom_load(a.model, &a.options, &r.sim), "load") ||
        check(hapticrom_get_info(r.sim, &r.info), "info")) {
        free(r.path.points);
        return 1;
    }
    printf("hapticrom %s (ABI %u): %s loaded in %.2f s: %llu vertices, %llu samples, %llu "
           "modes; %s, %s; tool radius %g mm\n", version, abi, a.model,
           (double)(now_ns() - t0) * 1e-9, (unsigned long long)r.info.vertex_count,
           (unsigned long long)r.info.sample_count, (unsigned long long)r.info.mode_count,
           r.info.interpolation == HAPTICROM_INTERPOLATION_TRANSPORT    ? "transport"
           : r.info.interpolation == HAPTICROM_INTERPOLATION_COMPLIANCE ? "compliance"
                                                                         : "podi",
           r.info.response == HAPTICROM_RESPONSE_ANM ? "POD-ANM series" : "stored curves",
           r.info.tool_radius);
    int failed = 0;
    if (a.friction) {
        failed = check(hapticrom_set_friction(r.sim, a.mu[0], a.mu[1], a.mu[2]), "friction") != 0;
        if (!failed)
            printf("friction: static %g, dynamic %g, tangential stiffness %g x normal%s\n",
                   a.mu[0], a.mu[1], a.mu[2] != 0.0 ? a.mu[2] : 2.0 / 3.0,
                   a.tips ? "" : " (step_position only: this contact-point run is frictionless)");
    }
    if (!failed && !a.tips) {
        size_t ticks = a.bench ? 2000 : (size_t)llround(a.seconds * a.rate);
        failed = ticks < 2 || make_path(r.sim, &r.info, ticks, &r.path);
    }
    r.records = failed ? NULL : calloc(r.path.ticks, sizeof *r.records);
    if (!failed && !r.records) failed = 1;
    if (!failed)
        failed = a.bench ? bench(&r, (size_t)a.bench, (size_t)a.bench_surfaces)
                         : play(&r, a.forces, a.surfaces);
    if (check(hapticrom_free(r.sim), "free")) failed = 1;
    free(r.path.points), free(r.path.depths), free(r.records);
    return failed ? 1 : 0;
}
