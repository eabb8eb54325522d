/*
 * servo_loop: a haptic host in the style of an OpenHaptics scheduler callback, on
 * libhapticrom (include/hapticrom.h).
 *
 * A servo thread steps the model at 1 kHz along a scripted path (press, slide at constant
 * depth, release: like hapticrom.online.play.tool_path): each tick sets the contact, reads
 * the contact normal and asks for the force of a displacement along it. A render thread
 * reads the surface at about 60 Hz into its own buffer meanwhile.
 *
 *   servo_loop MODEL [--seconds S] [--rate HZ] [--render-rate HZ] [--forces FILE.csv]
 *              [--surfaces FILE.bin] [--response anm|curves] [--interpolation transport|podi]
 *   servo_loop MODEL --bench N [--bench-surfaces M] [--cpu K]
 *
 * --forces: one CSV row per tick (tick, contact point mm, depth mm, force N, status, the
 * state's sequence number after the tick's set_contact).
 * --surfaces: per rendered frame, the state's sequence number (uint64) then 3 V doubles
 * (mm), after a header of V (uint64). --bench: no threads; the latency of N set_contact,
 * get_state and step_displacement calls along the path and of M surfaces (clock_gettime,
 * CLOCK_MONOTONIC, per call), as p50 / p99 / p99.9 / max in ns.
 *
 * Exit status 0 if every call succeeded, 1 otherwise (the message on stderr), 2 on usage.
 */
#define _GNU_SOURCE
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
    double *points; /* (ticks, 3) mm */
    double *depths; /* (ticks,) mm */
};

struct run {
    hapticrom_simulator sim;
    hapticrom_info info;
    struct path path;
    double rate, render_rate;
    double *forces;      /* (ticks, 3) N */
    int *statuses;       /* (ticks,) */
    uint64_t *sequences; /* (ticks,): the state's number after each tick's set_contact */
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
        int status = tick(r->sim, &r->path.points[3 * i], r->path.depths[i], &r->forces[3 * i],
                          &r->sequences[i]);
        r->statuses[i] = status;
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
    fprintf(f, "tick,x,y,z,depth,fx,fy,fz,status,sequence\n");
    for (size_t i = 0; i < r->path.ticks; i++) {
        const double *p = &r->path.points[3 * i], *F = &r->forces[3 * i];
        fprintf(f, "%zu,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%.17g,%d,%llu\n", i, p[0], p[1],
                p[2], r->path.depths[i], F[0], F[1], F[2], r->statuses[i],
                (unsigned long long)r->sequences[i]);
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
    for (size_t i = 0; i < r->path.ticks; i++) {
        const double *F = &r->forces[3 * i];
        peak = fmax(peak, sqrt(F[0] * F[0] + F[1] * F[1] + F[2] * F[2]));
    }
    printf("servo: %zu ticks at %.0f Hz in %.3f s; render: %zu surfaces of %llu vertices (%zu "
           "skipped: busy); peak force %.6g N\n", r->path.ticks, r->rate, seconds, r->frames,
           (unsigned long long)r->info.vertex_count, r->skipped, peak);
    if (forces_file && write_forces(r, forces_file)) return 1;
    return r->failed;
}

/* --- latency ------------------------------------------------------------------------------- */
static int compare_u32(const void *a, const void *b) {
    uint32_t x = *(const uint32_t *)a, y = *(const uint32_t *)b;
    return (x > y) - (x < y);
}

static void report(const char *what, uint32_t *ns, size_t n) {
    qsort(ns, n, sizeof *ns, compare_u32);
    printf("%-20s %9zu calls  p50 %7u ns  p99 %7u ns  p99.9 %8u ns  max %9u ns\n", what, n,
           ns[n / 2], ns[(size_t)(0.99 * (double)n)], ns[(size_t)(0.999 * (double)n)],
           ns[n - 1]);
}

static uint32_t elapsed(int64_t t0, int64_t t1) {
    return (uint32_t)(t1 - t0 > UINT32_MAX ? UINT32_MAX : t1 - t0);
}

static int bench(struct run *r, size_t steps, size_t surfaces) {
    uint32_t *contact = malloc(steps * sizeof *contact), *state_ns = malloc(steps * sizeof *contact),
             *step_ns = malloc(steps * sizeof *contact), *timer = malloc(steps * sizeof *contact),
             *surface_ns = malloc((surfaces ? surfaces : 1) * sizeof *contact);
    size_t length = 3 * r->info.vertex_count;
    double *surface = malloc(length * sizeof(double)), force[3];
    if (!contact || !state_ns || !step_ns || !timer || !surface_ns || !surface) return 1;
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
    for (size_t i = 0; i < surfaces; i++) {
        size_t k = (i * 7919) % r->path.ticks; /* states along the path */
        uint64_t sequence;
        if (check(tick(sim, &r->path.points[3 * k], r->path.depths[k], force, &sequence),
                  "bench tick"))
            return 1;
        int64_t t0 = now_ns();
        int status = hapticrom_surface(sim, surface, length, NULL);
        surface_ns[i] = elapsed(t0, now_ns());
        if (check(status, "bench surface")) return 1;
    }
    report("clock_gettime", timer, steps);
    report("set_contact", contact, steps);
    report("get_state", state_ns, steps);
    report("step_displacement", step_ns, steps);
    if (surfaces) report("surface", surface_ns, surfaces);
    free(contact), free(state_ns), free(step_ns), free(timer), free(surface_ns), free(surface);
    return 0;
}

/* --- main ------------------------------------------------------------------------------------ */
static int usage(void) {
    fprintf(stderr, "usage: servo_loop MODEL [--seconds S] [--rate HZ] [--render-rate HZ] "
                    "[--forces FILE.csv] [--surfaces FILE.bin] [--response anm|curves] "
                    "[--interpolation transport|podi]\n"
                    "       servo_loop MODEL --bench N [--bench-surfaces M] [--cpu K]\n");
    return 2;
}

struct arguments {
    const char *model, *forces, *surfaces;
    double seconds, rate, render_rate;
    long bench, bench_surfaces, cpu;
    hapticrom_options options;
};

static int positive(const char *text, double *value) {
    char *end;
    *value = strtod(text, &end);
    return *end == '\0' && isfinite(*value) && *value > 0;
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
        else if (!strcmp(key, "--surfaces")) a->surfaces = value;
        else if (!strcmp(key, "--seconds") && positive(value, &x)) a->seconds = x;
        else if (!strcmp(key, "--rate") && positive(value, &x)) a->rate = x;
        else if (!strcmp(key, "--render-rate") && positive(value, &x)) a->render_rate = x;
        else if (!strcmp(key, "--bench") && positive(value, &x)) a->bench = (long)x;
        else if (!strcmp(key, "--bench-surfaces") && positive(value, &x))
            a->bench_surfaces = (long)x;
        else if (!strcmp(key, "--cpu")) a->cpu = strtol(value, NULL, 10);
        else if (!strcmp(key, "--response"))
            a->options.response = !strcmp(value, "anm") ? HAPTICROM_RESPONSE_ANM
                                  : !strcmp(value, "curves") ? HAPTICROM_RESPONSE_CURVES
                                                             : -1;
        else if (!strcmp(key, "--interpolation"))
            a->options.interpolation = !strcmp(value, "transport") ? HAPTICROM_INTERPOLATION_TRANSPORT
                                       : !strcmp(value, "podi")    ? HAPTICROM_INTERPOLATION_PODI
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
    int64_t t0 = now_ns();
    if (check(hapticrom_load(a.model, &a.options, &r.sim), "load") ||
        check(hapticrom_get_info(r.sim, &r.info), "info"))
        return 1;
    printf("hapticrom %s (ABI %u): %s loaded in %.2f s: %llu vertices, %llu samples, %llu "
           "modes; %s, %s\n", version, abi, a.model, (double)(now_ns() - t0) * 1e-9,
           (unsigned long long)r.info.vertex_count, (unsigned long long)r.info.sample_count,
           (unsigned long long)r.info.mode_count,
           r.info.interpolation == HAPTICROM_INTERPOLATION_TRANSPORT ? "transport" : "podi",
           r.info.response == HAPTICROM_RESPONSE_ANM ? "POD-ANM series" : "stored curves");
    size_t ticks = a.bench ? 2000 : (size_t)llround(a.seconds * a.rate);
    if (ticks < 2 || make_path(r.sim, &r.info, ticks, &r.path)) return 1;
    r.forces = calloc(3 * ticks, sizeof(double));
    r.statuses = calloc(ticks, sizeof(int));
    r.sequences = calloc(ticks, sizeof(uint64_t));
    if (!r.forces || !r.statuses || !r.sequences) return 1;
    int failed = a.bench ? bench(&r, (size_t)a.bench, (size_t)a.bench_surfaces)
                         : play(&r, a.forces, a.surfaces);
    if (check(hapticrom_free(r.sim), "free")) failed = 1;
    free(r.path.points), free(r.path.depths), free(r.forces), free(r.statuses), free(r.sequences);
    return failed ? 1 : 0;
}
