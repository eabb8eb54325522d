/*
 * hapticrom.h: the C ABI of the hapticrom online runtime (C99; usable from C++).
 *
 * A host (an OpenHaptics scheduler callback, a CHAI3D or Force Dimension haptic thread, a
 * Unity native plugin, a SOFA component) loads a reduced-model artifact, then drives one
 * tool on it from its servo thread, position in, force out:
 *
 *     hapticrom_simulator sim;
 *     if (hapticrom_load("cornea.h5", NULL, &sim) != HAPTICROM_OK)
 *         fprintf(stderr, "%s\n", hapticrom_last_error());
 *     hapticrom_set_friction(sim, 0.5, 0.3, 0);          // optional: Coulomb friction
 *     hapticrom_step_position(sim, tip, force);          // tip centre mm in, N out, every tick
 *     hapticrom_surface(sim, vertex_displacement, 3 * V, &state);  // render thread, mm;
 *                                                        // draw the tool at state.proxy
 *     hapticrom_free(sim);
 *
 * or, with the host's own collision detection, contact point and displacement in:
 *
 *     hapticrom_set_contact(sim, point);                 // mm, on or near the surface
 *     hapticrom_step_displacement(sim, d, force);        // mm in, N out (force on the tool)
 *
 * Units: lengths and displacements mm, forces N, stiffness N/mm.
 *
 * The library embeds CPython: hapticrom_load starts the interpreter at its first call (or
 * uses the host's, if the host already runs one), imports hapticrom.online.cabi and takes
 * the addresses of its numba-compiled entry points; the physics is the Python runtime's own
 * kernels, compiled once. The servo and render calls below then call machine code only:
 * they never take the GIL, never allocate, never lock (a busy flag, not a mutex: see
 * "Threads").
 *
 * Finding Python: the interpreter is the environment of the executable named by the
 * environment variable HAPTICROM_PYTHON (e.g. /path/to/.venv/bin/python; its venv's
 * site-packages must hold hapticrom), else the one baked in at build time (the project's
 * .venv/bin/python). NUMBA_CACHE_DIR, if set, is where the compiled kernels are cached.
 *
 * Threads (per simulator; different simulators are independent and may run in parallel):
 *   - servo calls (step_position, stiffness, set_contact, step_displacement, step_force,
 *     contact_stiffness, error_estimate, get_state): one thread at a time. A call while
 *     another thread is inside one returns HAPTICROM_E_BUSY at once (never waits, changes
 *     nothing).
 *   - render calls (surface, get_info, surface_mesh, sample_points): one thread at a time,
 *     concurrently with the servo calls. hapticrom_surface computes from a consistent
 *     snapshot of the servo state (a sequence lock: the servo thread never waits for the
 *     renderer; the renderer retries a copy that a servo write overlapped) and reports
 *     which state it rendered (hapticrom_state.sequence).
 *   - hapticrom_load, hapticrom_free and hapticrom_set_friction may be called from any
 *     thread; they take the GIL (and may wait for it). hapticrom_free waits for calls inside
 *     the simulator to end; later calls with the freed handle return HAPTICROM_E_BAD_HANDLE.
 *     hapticrom_set_friction checks its arguments under the GIL without holding the
 *     simulator, then waits for a servo call inside to end (up to a second) and writes
 *     (nanoseconds: a servo call in that window gets HAPTICROM_E_BUSY, as from any second
 *     thread).
 *
 * Errors: every function but the string ones returns a hapticrom_status; on an error
 * nothing is changed and hapticrom_last_error() returns a message naming the call and
 * the problem (a buffer of the calling thread, valid until its next failing call).
 * Handles are checked on every call (a magic number, a slot and a generation): a freed,
 * doubly freed or made-up handle is refused, never dereferenced.
 *
 * Not in this ABI yet: cutting (the scalpel), the Grassmann surface, sharing one loaded
 * model between several simulators (each hapticrom_load loads its own copy).
 */
#ifndef HAPTICROM_H
#define HAPTICROM_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Bumped on any incompatible change; hapticrom_load refuses a Python package whose entry
 * points are of another ABI version (HAPTICROM_E_PYTHON). */
#define HAPTICROM_ABI_VERSION 3

/* Simulators open at once, at most (HAPTICROM_E_TOO_MANY beyond). */
#define HAPTICROM_MAX_SIMULATORS 256

/* A simulator: an opaque value from hapticrom_load (0 is never valid). */
typedef uint64_t hapticrom_simulator;

/* What every call returns. */
typedef enum hapticrom_status {
    HAPTICROM_OK = 0,
    HAPTICROM_E_NULL_ARGUMENT = 1,      /* a pointer argument is NULL */
    HAPTICROM_E_NOT_FINITE = 2,         /* an input is NaN or infinite */
    HAPTICROM_E_BEYOND_LIMIT = 3,       /* an input is longer than max_displacement/max_force */
    HAPTICROM_E_DISPLACEMENT_LIMIT = 4, /* a force step would push past max_displacement */
    HAPTICROM_E_WRONG_SIZE = 5,         /* a buffer's length argument is not what it must be */
    HAPTICROM_E_NO_CONTACT = 6,         /* a step (or query) before any hapticrom_set_contact */
    HAPTICROM_E_BUSY = 7,               /* another thread is inside this simulator */
    HAPTICROM_E_BAD_HANDLE = 8,         /* not a live simulator: freed, or never loaded */
    HAPTICROM_E_LOAD_FAILED = 9,        /* the artifact is missing, damaged or refused */
    HAPTICROM_E_INVALID_OPTION = 10,    /* a hapticrom_options field or a setting (friction)
                                           is out of its range */
    HAPTICROM_E_TOO_MANY = 11,          /* HAPTICROM_MAX_SIMULATORS are open */
    HAPTICROM_E_PYTHON = 12,            /* the interpreter or the package could not start */
    HAPTICROM_E_INTERNAL = 13           /* a bug: please report it with the message */
} hapticrom_status;

/* hapticrom_state.flags: bits of the last step (and of the contact point). */
enum hapticrom_flag {
    HAPTICROM_FLAG_BEYOND_DEPTH = 1,   /* deeper than the trained range (extrapolated) */
    HAPTICROM_FLAG_NO_CONTACT = 2,     /* the tool pulled away: zero force */
    HAPTICROM_FLAG_OUTSIDE_REGION = 4  /* contact point outside the trained region (clamped) */
};

/* hapticrom_options.interpolation: how the rendered surface follows the tool. */
enum hapticrom_interpolation {
    HAPTICROM_INTERPOLATION_DEFAULT = 0,   /* transport where the model has a chart, else
                                              compliance where it has contact fields, else podi */
    HAPTICROM_INTERPOLATION_TRANSPORT = 1, /* each neighbour's field carried to the contact */
    HAPTICROM_INTERPOLATION_PODI = 2,      /* the fields blended where each was trained */
    HAPTICROM_INTERPOLATION_COMPLIANCE = 3 /* the tool's linear dent at the contact added
                                              (artifact 2.2 contact fields; any organ). New
                                              in hapticrom 0.1 at ABI 3: a host built before
                                              it can see this value in info.interpolation */
};

/* hapticrom_options.response: where the force comes from. */
enum hapticrom_response {
    HAPTICROM_RESPONSE_DEFAULT = 0, /* the POD-ANM series if the artifact has them */
    HAPTICROM_RESPONSE_ANM = 1,     /* the POD-ANM series */
    HAPTICROM_RESPONSE_CURVES = 2   /* the stored full-order force curves */
};

/* Options of hapticrom_load: fill with hapticrom_options_init, then change fields. */
typedef struct hapticrom_options {
    uint32_t size;           /* sizeof(hapticrom_options) (set by hapticrom_options_init) */
    int32_t interpolation;   /* enum hapticrom_interpolation */
    int32_t response;        /* enum hapticrom_response */
    int32_t isolate;         /* 1 (default): HDF5 parses the file in a child process first,
                                so that a crafted file cannot crash the host; 0: in-process */
    double max_displacement; /* mm, the longest step input/output; 0: the model's default */
    double max_force;        /* N, the longest force step input; 0: the model's default */
    double tool_radius;      /* mm, step_position's spherical tip; 0: the artifact's training
                                radius (hapticrom_info.tool_radius says which) */
} hapticrom_options;

/* What a loaded simulator is (hapticrom_get_info). */
typedef struct hapticrom_info {
    uint64_t vertex_count;   /* V: surface vertices (hapticrom_surface fills 3 V doubles) */
    uint64_t triangle_count; /* T: surface triangles */
    uint64_t sample_count;   /* P: trained tool positions */
    uint64_t mode_count;     /* n: reduced modes per sample */
    int32_t interpolation;   /* what HAPTICROM_INTERPOLATION_DEFAULT resolved to */
    int32_t response;        /* what HAPTICROM_RESPONSE_DEFAULT resolved to */
    double trained_depth;    /* mm, the depth every sample was trained to (the shallowest) */
    double trained_force;    /* N, the smallest of the samples' forces at trained_depth */
    double max_displacement; /* mm, this simulator's limit */
    double max_force;        /* N, this simulator's limit */
    double tool_radius;      /* mm, step_position's spherical tip */
} hapticrom_info;

/* The contact state (hapticrom_get_state; hapticrom_surface's snapshot: all its fields are
 * of the state the surface was computed from). */
typedef struct hapticrom_state {
    double normal[3];        /* outward unit surface normal at the contact */
    double force[3];         /* N, on the tool: the last displacement or position step's */
    double displacement[3];  /* mm: the last force step's output */
    double depth;            /* mm: the last step's indentation */
    uint32_t flags;          /* enum hapticrom_flag bits */
    uint32_t has_contact;    /* 1 once a contact point was set (by set_contact or by a
                                step_position that touched) */
    uint64_t sequence;       /* the state's number: writing calls (set_contact, steps;
                                refused ones too; set_friction's that succeeded) since load */
    /* Since ABI 2; step_position's, zeros before the first one: */
    double proxy[3];         /* mm: where the tool tip's centre would be if the tissue did not
                                yield (on the surface offset by the tool radius in contact, the
                                tip itself when free): draw the tool here */
    double contact_point[3]; /* mm: where the tool touches the undeformed surface (the proxy's
                                foot: the point the contact model is evaluated at) */
    uint32_t in_contact;     /* 1 if the last step pressed the tissue (a force), 0 if free */
    uint32_t saturated;      /* 1 if the last step_position held the depth at max_displacement */
    /* Since ABI 3: */
    uint32_t slipping;       /* 1 if the last step_position slid with friction (the tangential
                                force was dynamic_coefficient x the normal one); 0 if it stuck,
                                was free or is frictionless (hapticrom_set_friction) */
} hapticrom_state;

/* The package version this library was built with ("0.1.0"); *abi_version (if not NULL)
 * receives HAPTICROM_ABI_VERSION. Needs no interpreter; any thread. */
const char *hapticrom_version(uint32_t *abi_version);

/* The message of this thread's last failing call ("" if none); any thread. */
const char *hapticrom_last_error(void);

/* A status's name ("HAPTICROM_E_BUSY"), "unknown status" for other values; any thread. */
const char *hapticrom_status_name(int status);

/* Fill *options with the defaults (size set; everything else the model's default, isolate 1). */
void hapticrom_options_init(hapticrom_options *options);

/* Load and verify the artifact at artifact_path (a file name, the file system's encoding)
 * and create a simulator on it into *simulator (0 on failure). options may be NULL (the
 * defaults). Seconds (the first call also starts Python and loads the compiled kernels).
 * Errors: NULL_ARGUMENT, INVALID_OPTION, LOAD_FAILED (missing file, damaged or refused
 * artifact: the message names the dataset), TOO_MANY, PYTHON. Any thread; takes the GIL. */
int hapticrom_load(const char *artifact_path, const hapticrom_options *options,
                   hapticrom_simulator *simulator);

/* Free a simulator: waits for calls inside it to end, then releases its memory. The handle
 * is dead afterwards (BAD_HANDLE, also for a second free). Any thread; takes the GIL. */
int hapticrom_free(hapticrom_simulator simulator);

/* Coulomb friction for hapticrom_step_position (none after load): the proxy sticks while the
 * tangential force is at most static_coefficient x the normal force, and slides with
 * dynamic_coefficient x it otherwise (stick-slip: it needs the static cone again to slide
 * after it stuck). While stuck the tangential force is a spring from the tip to the proxy,
 * tangential_stiffness x the normal contact stiffness (d force / d depth); 0 means the
 * default, 2/3 (Mindlin's 2 (1 - nu) / (2 - nu) for incompressible tissue). The rendered
 * surface stays the normal indentation: the drag is in the force only. Coefficients: finite,
 * 0 <= dynamic_coefficient <= static_coefficient <= 10 (pass the same value twice for one
 * coefficient; 0, 0, 0 turns friction off); tangential_stiffness 0 or in (0, 10]. The checks
 * are the Python runtime's (Simulator.set_friction, under the GIL: not a servo call, see
 * "Threads"); the setting holds from the next step on. Errors: NOT_FINITE (an argument is
 * NaN or infinite), INVALID_OPTION (out of range, dynamic above static; the message says
 * which), BUSY (a thread stayed inside the servo calls for a whole second), BAD_HANDLE,
 * INTERNAL; nothing changes on an error. */
int hapticrom_set_friction(hapticrom_simulator simulator, double static_coefficient,
                           double dynamic_coefficient, double tangential_stiffness);

/* --- servo calls (one thread at a time per simulator; no GIL, no allocation, no lock) --- */

/* Put (or slide) the tool's contact at point[3] (mm, on or near the surface); outside the
 * trained region it is clamped (HAPTICROM_FLAG_OUTSIDE_REGION). Microseconds; every tick is
 * fine. Errors: NULL_ARGUMENT, NOT_FINITE, BUSY, BAD_HANDLE. */
int hapticrom_set_contact(hapticrom_simulator simulator, const double point[3]);

/* Position in, force out: the tool tip's centre tip[3] (mm; a sphere of
 * hapticrom_info.tool_radius) in, the reaction force[3] on the tool (N) out; zero when the
 * tool is free. The proxy finds the contact (however fast the tip moves), slides it over the
 * surface, releases it when the tip leaves and never lets it pass through the organ;
 * hapticrom_get_state then gives in_contact, the proxy, the contact point and whether the
 * depth was held at max_displacement (saturated: a finite tip is never refused, a servo loop
 * gets a force every tick). It sets the contact itself (at the proxy's contact point): a
 * host that uses it calls no set_contact. With friction (hapticrom_set_friction) the force
 * has a tangential part: the proxy sticks and a spring pulls the tool back to it, or it
 * slides and the drag is dynamic_coefficient x the normal force (hapticrom_state.slipping).
 * Microseconds; every tick. Errors: NULL_ARGUMENT, NOT_FINITE (nothing changed), BUSY,
 * BAD_HANDLE. */
int hapticrom_step_position(hapticrom_simulator simulator, const double tip[3],
                            double force[3]);

/* The 3x3 contact stiffness K (N/mm, row-major: stiffness[3 i + j] = K[i][j]) of the last
 * step into stiffness[9]: near the tip x, the force on the tool is F(x + dx) ~ F - K dx (for
 * a host that steps the physics slower than its device loop and extrapolates, or tunes its
 * coupling). Frictionless: K = k n n^T, k = d force / d depth, n the contact normal; zero
 * when not in contact (also before any step). With friction, k_t = tangential_stiffness x k:
 * stuck, K + k_t (I - n n^T); slipping along the unit s (against the tangential force),
 * K + k_t (I - n n^T - s s^T) - dynamic_coefficient k s n^T (not symmetric). Errors:
 * NULL_ARGUMENT, BUSY, BAD_HANDLE. */
int hapticrom_stiffness(hapticrom_simulator simulator, double stiffness[9]);

/* Tool displacement[3] (mm, from the contact point) in, reaction force[3] on the tool (N)
 * out, along the outward normal (frictionless). Errors: NULL_ARGUMENT, NOT_FINITE,
 * BEYOND_LIMIT (longer than max_displacement), NO_CONTACT, BUSY, BAD_HANDLE. */
int hapticrom_step_displacement(hapticrom_simulator simulator, const double displacement[3],
                                double force[3]);

/* Force[3] the tool applies to the tissue (N) in, tool displacement[3] (mm) out. Errors:
 * NULL_ARGUMENT, NOT_FINITE, BEYOND_LIMIT (longer than max_force), DISPLACEMENT_LIMIT (the
 * tool would pass max_displacement), NO_CONTACT, BUSY, BAD_HANDLE. */
int hapticrom_step_force(hapticrom_simulator simulator, const double force[3],
                         double displacement[3]);

/* d force / d depth (N/mm) at the last step's depth, for the haptic loop's stability.
 * Errors: NULL_ARGUMENT, NO_CONTACT, BUSY, BAD_HANDLE. */
int hapticrom_contact_stiffness(hapticrom_simulator simulator, double *stiffness);

/* The error indicator at the contact (relative force error): the samples' leave-one-out
 * errors blended with the contact's weights. Errors: NULL_ARGUMENT, NO_CONTACT, BUSY,
 * BAD_HANDLE. */
int hapticrom_error_estimate(hapticrom_simulator simulator, double *estimate);

/* The current state (normal, force, displacement, depth, flags; step_position's proxy,
 * contact point, in_contact, saturated and slipping). Errors: NULL_ARGUMENT, BUSY,
 * BAD_HANDLE. */
int hapticrom_get_state(hapticrom_simulator simulator, hapticrom_state *state);

/* --- render calls (one thread at a time per simulator, alongside the servo thread) --- */

/* The surface vertices' displacement (mm) into displacement[length], length = 3 V (x, y, z
 * per vertex, hapticrom_info.vertex_count vertices), at a consistent snapshot of the servo
 * state; *state (if not NULL) receives that snapshot's state (its sequence says which).
 * Allocates nothing. Errors: NULL_ARGUMENT, WRONG_SIZE, BUSY (another render call is
 * inside, or the servo thread kept writing while a snapshot was taken), BAD_HANDLE. */
int hapticrom_surface(hapticrom_simulator simulator, double *displacement, size_t length,
                      hapticrom_state *state);

/* Sizes, limits and the resolved options. Errors: NULL_ARGUMENT, BUSY, BAD_HANDLE. */
int hapticrom_get_info(hapticrom_simulator simulator, hapticrom_info *info);

/* The surface to render: vertices[3 V] (mm) and triangles[3 T] (vertex indices). Errors:
 * NULL_ARGUMENT, WRONG_SIZE, BUSY, BAD_HANDLE. */
int hapticrom_surface_mesh(hapticrom_simulator simulator, double *vertices,
                           size_t vertices_length, uint32_t *triangles, size_t triangles_length);

/* The trained tool positions points[3 P] (mm): where the model is valid. Errors:
 * NULL_ARGUMENT, WRONG_SIZE, BUSY, BAD_HANDLE. */
int hapticrom_sample_points(hapticrom_simulator simulator, double *points, size_t length);

#ifdef __cplusplus
} /* extern "C" */
#endif

#endif /* HAPTICROM_H */
