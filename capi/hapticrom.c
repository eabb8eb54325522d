/*
 * libhapticrom: the C ABI of include/hapticrom.h over the numba entry points of
 * hapticrom.online.cabi (see that module for the handle it returns).
 *
 * Layout of this file: simulator slots and handles; errors; the embedded interpreter
 * (started once, then the GIL released); load and free (under the GIL); the servo calls
 * (a busy flag and a sequence lock around a call through a function pointer); the render
 * calls (a snapshot of the servo state, then the surface from it); set_friction (checked
 * in Python under the GIL, then written like a servo call).
 *
 * The servo state a snapshot copies is two arrays of doubles this file treats as opaque:
 * the state buffer (all a surface reads) and the head of step_position's proxy state (the
 * proxy and its contact point, for hapticrom_state); only cabi.read_state knows their
 * layouts.
 *
 * Memory orders: a slot's handle is published with release and read with acquire; the busy
 * flags are taken with an acquiring compare-exchange and given back with a release store;
 * the sequence lock is Boehm's (odd while the servo thread writes its state arrays; the
 * renderer copies with relaxed atomic loads and checks the sequence again after an acquire
 * fence). The servo side's writes are the compiled kernels' plain stores: they sit between
 * the release fence and the release store of the sequence in this thread's program order,
 * which is what the lock needs (only the C11 model's letter calls them a race).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <pthread.h>
#include <sched.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "hapticrom.h"

#ifndef HAPTICROM_PACKAGE_VERSION
#define HAPTICROM_PACKAGE_VERSION "unknown"
#endif
#ifndef HAPTICROM_DEFAULT_PYTHON
#define HAPTICROM_DEFAULT_PYTHON ""
#endif

/* The numba entry points' C signatures (hapticrom.online.cabi). */
typedef int32_t (*set_contact_fn)(const double *point, const double *table, int64_t table_size,
                                  double *buf, int64_t buf_size);
typedef int32_t (*step_fn)(const double *input, double *buf, int64_t buf_size, double *output);
typedef int32_t (*read_fn)(const double *buf, int64_t buf_size, double *out);
typedef int32_t (*state_fn)(const double *buf, int64_t buf_size, const double *proxy,
                            int64_t proxy_size, double *out);
typedef int32_t (*position_fn)(const double *tip, const double *sheet, int64_t sheet_size,
                               double *proxy, int64_t proxy_size, const double *table,
                               int64_t table_size, double *buf, int64_t buf_size, double *force);
typedef int32_t (*estimate_fn)(const double *buf, int64_t buf_size, const double *indicator,
                               int64_t samples, double *out);
typedef int32_t (*friction_fn)(const double *values, double *buf, int64_t buf_size);
typedef int32_t (*surface_fn)(void *const *arrays, const int64_t *dims, const double *buf,
                              int64_t buf_size, double *out, int64_t vertices);

/* The handle fields this file reads, by name (cabi.HANDLE_FIELDS gives their positions). */
enum field {
    F_ABI, F_KEY, F_SET_CONTACT, F_STEP_DISPLACEMENT, F_STEP_FORCE, F_CONTACT_STIFFNESS,
    F_ERROR_ESTIMATE, F_READ_STATE, F_SURFACE, F_STEP_POSITION, F_STIFFNESS, F_SET_FRICTION,
    F_BUF, F_BUF_SIZE,
    F_SNAPSHOT, F_TABLE, F_TABLE_SIZE, F_INDICATOR, F_SAMPLES, F_SHEET, F_SHEET_SIZE, F_PROXY,
    F_PROXY_SIZE, F_PROXY_HEAD, F_PROXY_SNAPSHOT, F_SURFACE_ARRAYS, F_SURFACE_DIMS, F_VERTICES,
    F_VERTEX_COUNT, F_TRIANGLES, F_TRIANGLE_COUNT, F_SAMPLE_POINTS, F_MODES, F_INTERPOLATION,
    F_RESPONSE, F_TRAINED_DEPTH, F_TRAINED_FORCE, F_MAX_DISPLACEMENT, F_MAX_FORCE, F_TOOL_RADIUS,
    F_COUNT
};
static const char *const FIELD_NAMES[F_COUNT] = {
    "abi", "key", "set_contact", "step_displacement", "step_force", "contact_stiffness",
    "error_estimate", "read_state", "surface", "step_position", "stiffness", "set_friction",
    "buf", "buf_size",
    "snapshot", "table", "table_size", "indicator", "samples", "sheet", "sheet_size", "proxy",
    "proxy_size", "proxy_head", "proxy_snapshot", "surface_arrays", "surface_dims", "vertices",
    "vertex_count", "triangles", "triangle_count", "sample_points", "modes", "interpolation",
    "response", "trained_depth", "trained_force", "max_displacement", "max_force", "tool_radius",
};
#define STATE_SIZE 21 /* cabi.STATE_SIZE: read_state's doubles */

/* --- slots and handles ---------------------------------------------------------------- */
/* A handle: MAGIC (16 bits) | generation (28 bits) | slot index (20 bits). The slots are a
 * static array that is never freed, so any handle value can be checked without touching
 * memory that may be gone; a freed slot's generation moves on, so old handles stay dead. */
#define MAGIC 0x4852ull /* "HR" */
#define GENERATION_BITS 28
#define INDEX_BITS 20

/* What a live simulator's calls read: set by load, cleared by free (under slots_lock, while
 * free holds both busy flags). */
struct simulator_data {
    int64_t key; /* the Python registry's key */
    set_contact_fn set_contact;
    step_fn step_displacement, step_force;
    position_fn step_position;
    read_fn contact_stiffness, stiffness;
    state_fn read_state;
    estimate_fn error_estimate;
    friction_fn set_friction;
    surface_fn surface;
    double *buf, *snapshot, *proxy, *proxy_snapshot;
    const double *table, *sheet, *indicator, *vertices, *sample_points;
    const int64_t *triangles, *surface_dims;
    void *const *surface_arrays;
    int64_t buf_size, table_size, sheet_size, proxy_size, proxy_head, samples;
    hapticrom_info info;
};

struct slot {
    uint64_t handle;   /* the live handle, 0 while free: atomic */
    int servo_busy;    /* a thread is inside a servo call (or free holds it): atomic */
    uint64_t sequence; /* sequence lock of buf: odd while the servo thread writes: atomic */
    struct simulator_data d;
    /* The render thread's flag, on its own cache line (the servo thread's stays quiet). */
    int render_busy __attribute__((aligned(64)));
    /* Only under slots_lock. */
    uint32_t generation;
    int reserved;
} __attribute__((aligned(64)));

static struct slot slots[HAPTICROM_MAX_SIMULATORS];
static pthread_mutex_t slots_lock = PTHREAD_MUTEX_INITIALIZER;

static struct slot *slot_of(hapticrom_simulator h) {
    if ((h >> (GENERATION_BITS + INDEX_BITS)) != MAGIC) return NULL;
    uint64_t index = h & ((1ull << INDEX_BITS) - 1);
    return index < HAPTICROM_MAX_SIMULATORS ? &slots[index] : NULL;
}

static hapticrom_simulator handle_of(size_t index, uint32_t generation) {
    uint64_t g = generation & ((1ull << GENERATION_BITS) - 1);
    return (MAGIC << (GENERATION_BITS + INDEX_BITS)) | (g << INDEX_BITS) | index;
}

/* --- errors ------------------------------------------------------------------------------- */
static _Thread_local char last_error[1024];

static int fail(int status, const char *format, ...) __attribute__((format(printf, 2, 3)));
static int fail(int status, const char *format, ...) {
    va_list args;
    va_start(args, format);
    vsnprintf(last_error, sizeof last_error, format, args);
    va_end(args);
    return status;
}

const char *hapticrom_last_error(void) { return last_error; }

const char *hapticrom_status_name(int status) {
    static const char *const names[] = {
        "HAPTICROM_OK", "HAPTICROM_E_NULL_ARGUMENT", "HAPTICROM_E_NOT_FINITE",
        "HAPTICROM_E_BEYOND_LIMIT", "HAPTICROM_E_DISPLACEMENT_LIMIT", "HAPTICROM_E_WRONG_SIZE",
        "HAPTICROM_E_NO_CONTACT", "HAPTICROM_E_BUSY", "HAPTICROM_E_BAD_HANDLE",
        "HAPTICROM_E_LOAD_FAILED", "HAPTICROM_E_INVALID_OPTION", "HAPTICROM_E_TOO_MANY",
        "HAPTICROM_E_PYTHON", "HAPTICROM_E_INTERNAL",
    };
    if (status < 0 || (size_t)status >= sizeof names / sizeof names[0]) return "unknown status";
    return names[status];
}

/* The message of an entry point's status (what = the input's name). */
static int fail_status(int status, const char *call, const char *what) {
    switch (status) {
    case HAPTICROM_E_NOT_FINITE:
        return fail(status, "%s: %s is not finite (NaN or infinite); state unchanged", call, what);
    case HAPTICROM_E_BEYOND_LIMIT:
        return fail(status, "%s: %s is longer than the simulator's limit (max_displacement or "
                            "max_force, see hapticrom_get_info); state unchanged", call, what);
    case HAPTICROM_E_DISPLACEMENT_LIMIT:
        return fail(status, "%s: %s would push the tool beyond the displacement limit "
                            "(max_displacement); state unchanged", call, what);
    case HAPTICROM_E_NO_CONTACT:
        return fail(status, "%s: no contact point yet; call hapticrom_set_contact first", call);
    default:
        return fail(HAPTICROM_E_INTERNAL, "%s: unexpected status %d from the entry point", call,
                    status);
    }
}

const char *hapticrom_version(uint32_t *abi_version) {
    if (abi_version) *abi_version = HAPTICROM_ABI_VERSION;
    return HAPTICROM_PACKAGE_VERSION;
}

void hapticrom_options_init(hapticrom_options *options) {
    if (!options) return;
    memset(options, 0, sizeof *options);
    options->size = sizeof *options;
    options->isolate = 1;
}

/* --- the embedded interpreter ----------------------------------------------------------- */
static pthread_once_t python_once = PTHREAD_ONCE_INIT;
static int python_status = HAPTICROM_E_PYTHON;
static char python_error[1024];
/* cabi.open_simulator, free_simulator, validate_friction */
static PyObject *open_function, *free_function, *friction_function;
static Py_ssize_t field_index[F_COUNT];
static Py_ssize_t handle_length;

/* The pending Python exception as one line into python_error (and cleared). */
static void python_exception(const char *what) {
    PyObject *type, *value, *traceback;
    PyErr_Fetch(&type, &value, &traceback);
    PyErr_NormalizeException(&type, &value, &traceback);
    PyObject *text = value ? PyObject_Str(value) : NULL;
    const char *message = text ? PyUnicode_AsUTF8(text) : NULL;
    snprintf(python_error, sizeof python_error, "%s: %s: %s", what,
             type ? ((PyTypeObject *)type)->tp_name : "error", message ? message : "?");
    PyErr_Clear();
    Py_XDECREF(text);
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(traceback);
}

/* Positions of the fields this file reads in cabi.HANDLE_FIELDS; 0 if all are there. */
static int resolve_fields(PyObject *module) {
    PyObject *names = PyObject_GetAttrString(module, "HANDLE_FIELDS");
    if (!names || !PyTuple_Check(names)) {
        Py_XDECREF(names);
        snprintf(python_error, sizeof python_error, "hapticrom.online.cabi has no HANDLE_FIELDS");
        return -1;
    }
    handle_length = PyTuple_GET_SIZE(names);
    for (int f = 0; f < F_COUNT; f++) {
        field_index[f] = -1;
        for (Py_ssize_t i = 0; i < handle_length; i++) {
            const char *name = PyUnicode_AsUTF8(PyTuple_GET_ITEM(names, i));
            if (name && strcmp(name, FIELD_NAMES[f]) == 0) field_index[f] = i;
        }
        if (field_index[f] < 0) {
            Py_DECREF(names);
            snprintf(python_error, sizeof python_error,
                     "hapticrom.online.cabi's handle has no field '%s' (ABI mismatch)",
                     FIELD_NAMES[f]);
            return -1;
        }
    }
    Py_DECREF(names);
    return 0;
}

/* Import hapticrom.online.cabi (compiles or loads the entry points) and check its ABI. */
static int import_cabi(void) {
    PyObject *module = PyImport_ImportModule("hapticrom.online.cabi");
    if (!module) {
        python_exception("cannot import hapticrom.online.cabi");
        return HAPTICROM_E_PYTHON;
    }
    PyObject *abi = PyObject_GetAttrString(module, "ABI_VERSION");
    long version = abi ? PyLong_AsLong(abi) : -1;
    Py_XDECREF(abi);
    PyErr_Clear();
    if (version != HAPTICROM_ABI_VERSION) {
        snprintf(python_error, sizeof python_error,
                 "hapticrom.online.cabi has ABI version %ld, this library %d: rebuild the "
                 "library (make capi) against the installed package", version,
                 HAPTICROM_ABI_VERSION);
        Py_DECREF(module);
        return HAPTICROM_E_PYTHON;
    }
    open_function = PyObject_GetAttrString(module, "open_simulator");
    free_function = PyObject_GetAttrString(module, "free_simulator");
    friction_function = PyObject_GetAttrString(module, "validate_friction");
    int fields = resolve_fields(module);
    Py_DECREF(module);
    if (!open_function || !free_function || !friction_function) {
        python_exception("hapticrom.online.cabi lacks an entry point");
        return HAPTICROM_E_PYTHON;
    }
    return fields == 0 ? HAPTICROM_OK : HAPTICROM_E_PYTHON;
}

/* Start CPython on the environment of HAPTICROM_PYTHON (or the one baked in at build). */
static int start_interpreter(void) {
    const char *python = getenv("HAPTICROM_PYTHON");
    if (!python || !*python) python = HAPTICROM_DEFAULT_PYTHON;
    if (!*python || access(python, X_OK) != 0) {
        snprintf(python_error, sizeof python_error,
                 "no Python executable at '%s': set HAPTICROM_PYTHON to the python of an "
                 "environment where hapticrom is installed (e.g. .venv/bin/python)", python);
        return HAPTICROM_E_PYTHON;
    }
    PyConfig config;
    PyConfig_InitPythonConfig(&config);
    config.install_signal_handlers = 0; /* the host's signals stay the host's */
    config.parse_argv = 0;
    /* The venv is found from its executable (pyvenv.cfg next to it): its site-packages, and
     * a sys.executable that can start the child process of isolate = 1. */
    PyStatus status = PyConfig_SetBytesString(&config, &config.executable, python);
    if (!PyStatus_Exception(status)) status = Py_InitializeFromConfig(&config);
    PyConfig_Clear(&config);
    if (PyStatus_Exception(status)) {
        snprintf(python_error, sizeof python_error, "cannot start Python (%s): %s", python,
                 status.err_msg ? status.err_msg : "?");
        return HAPTICROM_E_PYTHON;
    }
    return HAPTICROM_OK;
}

static void start_python(void) {
    if (Py_IsInitialized()) { /* a host that runs Python already (SofaPython3, ctypes) */
        PyGILState_STATE gil = PyGILState_Ensure();
        python_status = import_cabi();
        PyGILState_Release(gil);
        return;
    }
    python_status = start_interpreter();
    if (python_status != HAPTICROM_OK) return;
    python_status = import_cabi();
    PyEval_SaveThread(); /* the GIL is free from here: servo threads never need it */
}

/* --- load and free ----------------------------------------------------------------------- */
static int reserve_slot(size_t *index) {
    pthread_mutex_lock(&slots_lock);
    for (size_t i = 0; i < HAPTICROM_MAX_SIMULATORS; i++) {
        if (!slots[i].reserved) {
            slots[i].reserved = 1;
            pthread_mutex_unlock(&slots_lock);
            *index = i;
            return HAPTICROM_OK;
        }
    }
    pthread_mutex_unlock(&slots_lock);
    return fail(HAPTICROM_E_TOO_MANY, "hapticrom_load: %d simulators are open already; free "
                                      "one first", HAPTICROM_MAX_SIMULATORS);
}

static void unreserve_slot(size_t index) {
    pthread_mutex_lock(&slots_lock);
    slots[index].reserved = 0;
    pthread_mutex_unlock(&slots_lock);
}

static double bits_to_double(int64_t bits) {
    double x;
    memcpy(&x, &bits, sizeof x);
    return x;
}

/* Fill a reserved slot from the handle's fields. */
static void fill_slot(struct simulator_data *s, const int64_t *h) {
#define FIELD(f) (h[field_index[f]])
#define POINTER(f) ((void *)(intptr_t)FIELD(f))
#define ENTRY(type, f) ((type)(intptr_t)FIELD(f)) /* an address as a function pointer */
    s->key = FIELD(F_KEY);
    s->set_contact = ENTRY(set_contact_fn, F_SET_CONTACT);
    s->step_displacement = ENTRY(step_fn, F_STEP_DISPLACEMENT);
    s->step_force = ENTRY(step_fn, F_STEP_FORCE);
    s->contact_stiffness = ENTRY(read_fn, F_CONTACT_STIFFNESS);
    s->error_estimate = ENTRY(estimate_fn, F_ERROR_ESTIMATE);
    s->read_state = ENTRY(state_fn, F_READ_STATE);
    s->surface = ENTRY(surface_fn, F_SURFACE);
    s->step_position = ENTRY(position_fn, F_STEP_POSITION);
    s->stiffness = ENTRY(read_fn, F_STIFFNESS);
    s->set_friction = ENTRY(friction_fn, F_SET_FRICTION);
    s->buf = POINTER(F_BUF);
    s->buf_size = FIELD(F_BUF_SIZE);
    s->snapshot = POINTER(F_SNAPSHOT);
    s->table = POINTER(F_TABLE);
    s->table_size = FIELD(F_TABLE_SIZE);
    s->sheet = POINTER(F_SHEET);
    s->sheet_size = FIELD(F_SHEET_SIZE);
    s->proxy = POINTER(F_PROXY);
    s->proxy_size = FIELD(F_PROXY_SIZE);
    s->proxy_head = FIELD(F_PROXY_HEAD);
    s->proxy_snapshot = POINTER(F_PROXY_SNAPSHOT);
    s->indicator = POINTER(F_INDICATOR);
    s->samples = FIELD(F_SAMPLES);
    s->surface_arrays = POINTER(F_SURFACE_ARRAYS);
    s->surface_dims = POINTER(F_SURFACE_DIMS);
    s->vertices = POINTER(F_VERTICES);
    s->triangles = POINTER(F_TRIANGLES);
    s->sample_points = POINTER(F_SAMPLE_POINTS);
    s->info = (hapticrom_info){
        .vertex_count = (uint64_t)FIELD(F_VERTEX_COUNT),
        .triangle_count = (uint64_t)FIELD(F_TRIANGLE_COUNT),
        .sample_count = (uint64_t)FIELD(F_SAMPLES),
        .mode_count = (uint64_t)FIELD(F_MODES),
        .interpolation = (int32_t)FIELD(F_INTERPOLATION),
        .response = (int32_t)FIELD(F_RESPONSE),
        .trained_depth = bits_to_double(FIELD(F_TRAINED_DEPTH)),
        .trained_force = bits_to_double(FIELD(F_TRAINED_FORCE)),
        .max_displacement = bits_to_double(FIELD(F_MAX_DISPLACEMENT)),
        .max_force = bits_to_double(FIELD(F_MAX_FORCE)),
        .tool_radius = bits_to_double(FIELD(F_TOOL_RADIUS)),
    };
#undef FIELD
#undef POINTER
#undef ENTRY
}

static void free_in_python(int64_t key) {
    PyGILState_STATE gil = PyGILState_Ensure();
    PyObject *result = PyObject_CallFunction(free_function, "L", (long long)key);
    if (!result) PyErr_Clear();
    Py_XDECREF(result);
    PyGILState_Release(gil);
}

/* cabi.open_simulator's answer: its status; the handle into h (handle_length int64). */
static int open_in_python(const char *path, const hapticrom_options *o, int64_t *h) {
    PyGILState_STATE gil = PyGILState_Ensure();
    int status = HAPTICROM_E_INTERNAL;
    PyObject *name = PyUnicode_DecodeFSDefault(path);
    PyObject *result = name ? PyObject_CallFunction(open_function, "Oiiddid", name,
                                                     o->interpolation, o->response,
                                                     o->max_displacement, o->max_force,
                                                     o->isolate, o->tool_radius)
                            : NULL;
    Py_XDECREF(name);
    int code = 0;
    const char *message = NULL, *bytes = NULL;
    Py_ssize_t length = 0;
    if (!result || !PyArg_ParseTuple(result, "isy#", &code, &message, &bytes, &length)) {
        python_exception("hapticrom.online.cabi.open_simulator");
        fail(HAPTICROM_E_INTERNAL, "hapticrom_load: %s", python_error);
    } else if (code != HAPTICROM_OK) {
        status = fail(code, "hapticrom_load: %s", message);
    } else if (length != handle_length * (Py_ssize_t)sizeof(int64_t)) {
        fail(HAPTICROM_E_INTERNAL, "hapticrom_load: a handle of %zd bytes, %zd expected",
             length, handle_length * (Py_ssize_t)sizeof(int64_t));
    } else {
        memcpy(h, bytes, (size_t)length);
        status = h[field_index[F_ABI]] == HAPTICROM_ABI_VERSION
                     ? HAPTICROM_OK
                     : fail(HAPTICROM_E_PYTHON, "hapticrom_load: a handle of another ABI");
    }
    Py_XDECREF(result);
    PyGILState_Release(gil);
    return status;
}

static int check_options(const hapticrom_options *o) {
    if (o->size < sizeof(hapticrom_options))
        return fail(HAPTICROM_E_INVALID_OPTION, "hapticrom_load: options.size is %u, not "
                                                "sizeof(hapticrom_options) (%zu): fill the "
                                                "options with hapticrom_options_init",
                    o->size, sizeof(hapticrom_options));
    if (o->isolate != 0 && o->isolate != 1)
        return fail(HAPTICROM_E_INVALID_OPTION, "hapticrom_load: options.isolate must be 0 "
                                                "or 1, got %d", o->isolate);
    return HAPTICROM_OK;
}

int hapticrom_load(const char *artifact_path, const hapticrom_options *options,
                   hapticrom_simulator *simulator) {
    if (!simulator) return fail(HAPTICROM_E_NULL_ARGUMENT, "hapticrom_load: simulator is NULL");
    *simulator = 0;
    if (!artifact_path)
        return fail(HAPTICROM_E_NULL_ARGUMENT, "hapticrom_load: artifact_path is NULL");
    hapticrom_options defaults;
    hapticrom_options_init(&defaults);
    const hapticrom_options *o = options ? options : &defaults;
    int status = check_options(o);
    if (status) return status;
    pthread_once(&python_once, start_python);
    if (python_status != HAPTICROM_OK)
        return fail(python_status, "hapticrom_load: %s", python_error);
    size_t index = 0;
    if ((status = reserve_slot(&index))) return status;
    int64_t h[handle_length > 0 ? handle_length : 1];
    if ((status = open_in_python(artifact_path, o, h))) {
        unreserve_slot(index);
        return status;
    }
    struct slot *s = &slots[index];
    pthread_mutex_lock(&slots_lock);
    fill_slot(&s->d, h);
    __atomic_store_n(&s->sequence, 0, __ATOMIC_RELAXED);
    hapticrom_simulator handle = handle_of(index, ++s->generation);
    __atomic_store_n(&s->handle, handle, __ATOMIC_RELEASE);
    pthread_mutex_unlock(&slots_lock);
    *simulator = handle;
    return HAPTICROM_OK;
}

/* Give a busy flag back. */
static inline void leave(int *flag) { __atomic_store_n(flag, 0, __ATOMIC_RELEASE); }

/* Take a busy flag, waiting for the call inside to end (free only). */
static void take_flag_waiting(int *flag) {
    int expected = 0;
    while (!__atomic_compare_exchange_n(flag, &expected, 1, 0, __ATOMIC_ACQUIRE,
                                        __ATOMIC_RELAXED)) {
        expected = 0;
        sched_yield();
    }
}

int hapticrom_free(hapticrom_simulator simulator) {
    struct slot *s = slot_of(simulator);
    if (!s)
        return fail(HAPTICROM_E_BAD_HANDLE, "hapticrom_free: not a simulator handle (never "
                                            "returned by hapticrom_load)");
    pthread_mutex_lock(&slots_lock);
    if (__atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) != simulator) {
        pthread_mutex_unlock(&slots_lock);
        return fail(HAPTICROM_E_BAD_HANDLE, "hapticrom_free: this simulator was freed already");
    }
    __atomic_store_n(&s->handle, 0, __ATOMIC_SEQ_CST); /* new calls are refused from here */
    take_flag_waiting(&s->servo_busy);                  /* calls inside end */
    take_flag_waiting(&s->render_busy);
    int64_t key = s->d.key;
    memset(&s->d, 0, sizeof s->d); /* no pointer into the Python objects survives */
    s->reserved = 0;
    leave(&s->render_busy);
    leave(&s->servo_busy);
    pthread_mutex_unlock(&slots_lock);
    free_in_python(key); /* never under slots_lock: the GIL may be a wait */
    return HAPTICROM_OK;
}

/* --- entering a simulator ------------------------------------------------------------------ */
/* Take the servo or render flag of a live simulator; BAD_HANDLE or BUSY otherwise. */
static int enter(hapticrom_simulator h, int render, struct slot **out, const char *call) {
    struct slot *s = slot_of(h);
    if (!s)
        return fail(HAPTICROM_E_BAD_HANDLE, "%s: not a simulator handle (never returned by "
                                            "hapticrom_load)", call);
    int *flag = render ? &s->render_busy : &s->servo_busy;
    int expected = 0;
    if (!__atomic_compare_exchange_n(flag, &expected, 1, 0, __ATOMIC_ACQUIRE,
                                     __ATOMIC_RELAXED)) {
        if (__atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) != h)
            return fail(HAPTICROM_E_BAD_HANDLE, "%s: the simulator was freed", call);
        return fail(HAPTICROM_E_BUSY, "%s: another thread is inside this simulator's %s calls; "
                                      "one thread at a time (nothing changed)", call,
                    render ? "render" : "servo");
    }
    if (__atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) != h) {
        __atomic_store_n(flag, 0, __ATOMIC_RELEASE);
        return fail(HAPTICROM_E_BAD_HANDLE, "%s: the simulator was freed", call);
    }
    *out = s;
    return HAPTICROM_OK;
}

static inline void write_begin(struct slot *s) {
    uint64_t q = __atomic_load_n(&s->sequence, __ATOMIC_RELAXED);
    __atomic_store_n(&s->sequence, q + 1, __ATOMIC_RELAXED);
    __atomic_thread_fence(__ATOMIC_RELEASE);
}

static inline void write_end(struct slot *s) {
    uint64_t q = __atomic_load_n(&s->sequence, __ATOMIC_RELAXED);
    __atomic_store_n(&s->sequence, q + 1, __ATOMIC_RELEASE);
}

/* --- servo calls --------------------------------------------------------------------------- */
int hapticrom_set_contact(hapticrom_simulator simulator, const double point[3]) {
    static const char call[] = "hapticrom_set_contact";
    if (!point) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: point is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    write_begin(s);
    status = s->d.set_contact(point, s->d.table, s->d.table_size, s->d.buf, s->d.buf_size);
    write_end(s);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, "the contact point (mm)") : HAPTICROM_OK;
}

/* A step through entry point `step` (the displacement or the force one). */
static int step(hapticrom_simulator simulator, int force_control, const double *input,
                double *output, const char *call, const char *what) {
    if (!input) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: %s is NULL", call, what);
    if (!output) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: the output is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    step_fn kernel = force_control ? s->d.step_force : s->d.step_displacement;
    write_begin(s);
    status = kernel(input, s->d.buf, s->d.buf_size, output);
    write_end(s);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, what) : HAPTICROM_OK;
}

int hapticrom_step_displacement(hapticrom_simulator simulator, const double displacement[3],
                                double force[3]) {
    return step(simulator, 0, displacement, force, "hapticrom_step_displacement",
                "the displacement (mm)");
}

int hapticrom_step_force(hapticrom_simulator simulator, const double force[3],
                         double displacement[3]) {
    return step(simulator, 1, force, displacement, "hapticrom_step_force", "the force (N)");
}

int hapticrom_step_position(hapticrom_simulator simulator, const double tip[3],
                            double force[3]) {
    static const char call[] = "hapticrom_step_position";
    if (!tip) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: tip is NULL", call);
    if (!force) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: force is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    struct simulator_data *d = &s->d;
    write_begin(s); /* the proxy's state too: the snapshot copies its head */
    status = d->step_position(tip, d->sheet, d->sheet_size, d->proxy, d->proxy_size, d->table,
                              d->table_size, d->buf, d->buf_size, force);
    write_end(s);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, "the tool tip (mm)") : HAPTICROM_OK;
}

int hapticrom_stiffness(hapticrom_simulator simulator, double stiffness[9]) {
    static const char call[] = "hapticrom_stiffness";
    if (!stiffness) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: stiffness is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    status = s->d.stiffness(s->d.buf, s->d.buf_size, stiffness);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, "") : HAPTICROM_OK;
}

int hapticrom_contact_stiffness(hapticrom_simulator simulator, double *stiffness) {
    static const char call[] = "hapticrom_contact_stiffness";
    if (!stiffness) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: stiffness is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    status = s->d.contact_stiffness(s->d.buf, s->d.buf_size, stiffness);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, "") : HAPTICROM_OK;
}

int hapticrom_error_estimate(hapticrom_simulator simulator, double *estimate) {
    static const char call[] = "hapticrom_error_estimate";
    if (!estimate) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: estimate is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    status = s->d.error_estimate(s->d.buf, s->d.buf_size, s->d.indicator, s->d.samples, estimate);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, "") : HAPTICROM_OK;
}

/* A state from read_state's doubles (cabi.STATE_SIZE: their order). */
static void state_of(const double *values, uint64_t sequence, hapticrom_state *state) {
    memcpy(state->normal, values, 3 * sizeof(double));
    memcpy(state->force, values + 3, 3 * sizeof(double));
    memcpy(state->displacement, values + 6, 3 * sizeof(double));
    state->depth = values[9];
    state->flags = (uint32_t)values[10];
    state->has_contact = values[11] > 0.0;
    state->sequence = sequence;
    state->in_contact = values[12] > 0.0;
    memcpy(state->proxy, values + 13, 3 * sizeof(double));
    memcpy(state->contact_point, values + 16, 3 * sizeof(double));
    state->saturated = values[19] > 0.0;
    state->slipping = values[20] > 0.0;
}

int hapticrom_get_state(hapticrom_simulator simulator, hapticrom_state *state) {
    static const char call[] = "hapticrom_get_state";
    if (!state) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: state is NULL", call);
    struct slot *s;
    int status = enter(simulator, 0, &s, call);
    if (status) return status;
    double values[STATE_SIZE];
    status = s->d.read_state(s->d.buf, s->d.buf_size, s->d.proxy, s->d.proxy_size, values);
    uint64_t sequence = __atomic_load_n(&s->sequence, __ATOMIC_RELAXED) / 2;
    leave(&s->servo_busy);
    if (status) return fail_status(status, call, "");
    state_of(values, sequence, state);
    return HAPTICROM_OK;
}

/* --- render calls -------------------------------------------------------------------------- */
#define SNAPSHOT_ATTEMPTS 100000

static inline void relax(void) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_ia32_pause();
#else
    sched_yield();
#endif
}

/* n doubles from the servo thread's array into the renderer's copy (relaxed atomic loads:
 * the values may be torn mid-write; the sequence check throws such a copy away). */
static inline void copy_relaxed(const double *from, double *to, int64_t n) {
    for (int64_t i = 0; i < n; i++) __atomic_load(&from[i], &to[i], __ATOMIC_RELAXED);
}

/* Copy the servo state (the state buffer and the proxy state's head) into the snapshot
 * unless a servo write overlaps; its sequence / 2. */
static int take_snapshot(struct slot *s, uint64_t *sequence) {
    for (int attempt = 0; attempt < SNAPSHOT_ATTEMPTS; attempt++) {
        uint64_t before = __atomic_load_n(&s->sequence, __ATOMIC_ACQUIRE);
        if (before & 1) { /* the servo thread is writing */
            if (attempt % 64 == 63) sched_yield();
            relax();
            continue;
        }
        copy_relaxed(s->d.buf, s->d.snapshot, s->d.buf_size);
        copy_relaxed(s->d.proxy, s->d.proxy_snapshot, s->d.proxy_head);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if (__atomic_load_n(&s->sequence, __ATOMIC_RELAXED) == before) {
            *sequence = before / 2;
            return HAPTICROM_OK;
        }
    }
    return fail(HAPTICROM_E_BUSY, "hapticrom_surface: the servo thread kept writing during %d "
                                  "snapshots of its state; try again", SNAPSHOT_ATTEMPTS);
}

int hapticrom_surface(hapticrom_simulator simulator, double *displacement, size_t length,
                      hapticrom_state *state) {
    static const char call[] = "hapticrom_surface";
    if (!displacement) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: displacement is NULL", call);
    struct slot *s;
    int status = enter(simulator, 1, &s, call);
    if (status) return status;
    uint64_t vertices = s->d.info.vertex_count, sequence = 0;
    if (length != 3 * vertices) {
        leave(&s->render_busy);
        return fail(HAPTICROM_E_WRONG_SIZE, "%s: length is %zu, must be 3 x %llu vertices = %llu "
                                            "doubles", call, length,
                    (unsigned long long)vertices, (unsigned long long)(3 * vertices));
    }
    status = take_snapshot(s, &sequence);
    if (!status)
        status = s->d.surface(s->d.surface_arrays, s->d.surface_dims, s->d.snapshot, s->d.buf_size,
                            displacement, (int64_t)vertices);
    double values[STATE_SIZE];
    if (!status && state)
        status = s->d.read_state(s->d.snapshot, s->d.buf_size, s->d.proxy_snapshot,
                                 s->d.proxy_head, values);
    leave(&s->render_busy);
    if (status == HAPTICROM_E_BUSY) return status;
    if (status) return fail_status(status, call, "");
    if (state) state_of(values, sequence, state);
    return HAPTICROM_OK;
}

int hapticrom_get_info(hapticrom_simulator simulator, hapticrom_info *info) {
    static const char call[] = "hapticrom_get_info";
    if (!info) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: info is NULL", call);
    struct slot *s;
    int status = enter(simulator, 1, &s, call);
    if (status) return status;
    *info = s->d.info;
    leave(&s->render_busy);
    return HAPTICROM_OK;
}

/* WRONG_SIZE unless length == 3 count. */
static int check_length(size_t length, uint64_t count, const char *call, const char *what) {
    if (length == 3 * count) return HAPTICROM_OK;
    return fail(HAPTICROM_E_WRONG_SIZE, "%s: %s is %zu, must be 3 x %llu = %llu", call, what,
                length, (unsigned long long)count, (unsigned long long)(3 * count));
}

int hapticrom_surface_mesh(hapticrom_simulator simulator, double *vertices,
                           size_t vertices_length, uint32_t *triangles,
                           size_t triangles_length) {
    static const char call[] = "hapticrom_surface_mesh";
    if (!vertices || !triangles)
        return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: %s is NULL", call,
                    vertices ? "triangles" : "vertices");
    struct slot *s;
    int status = enter(simulator, 1, &s, call);
    if (status) return status;
    status = check_length(vertices_length, s->d.info.vertex_count, call, "vertices_length");
    if (!status)
        status = check_length(triangles_length, s->d.info.triangle_count, call,
                              "triangles_length");
    if (!status) {
        memcpy(vertices, s->d.vertices, vertices_length * sizeof(double));
        for (size_t i = 0; i < triangles_length; i++) triangles[i] = (uint32_t)s->d.triangles[i];
    }
    leave(&s->render_busy);
    return status;
}

int hapticrom_sample_points(hapticrom_simulator simulator, double *points, size_t length) {
    static const char call[] = "hapticrom_sample_points";
    if (!points) return fail(HAPTICROM_E_NULL_ARGUMENT, "%s: points is NULL", call);
    struct slot *s;
    int status = enter(simulator, 1, &s, call);
    if (status) return status;
    status = check_length(length, s->d.info.sample_count, call, "length");
    if (!status) memcpy(points, s->d.sample_points, length * sizeof(double));
    leave(&s->render_busy);
    return status;
}

/* --- friction: a setting (the GIL for its check, then written like a servo call) ---------- */
#define ENTER_WAIT_NS 1000000000 /* a second: a servo call takes microseconds */

static int64_t monotonic_ns(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (int64_t)t.tv_sec * 1000000000 + t.tv_nsec;
}

/* Take the servo flag of the live simulator h, waiting for a servo call inside to end
 * (microseconds; longer if the servo thread was preempted inside one): its slot; NULL and
 * *status BAD_HANDLE, or BUSY if the flag stayed taken for ENTER_WAIT_NS. No message is
 * written unless it fails. */
static struct slot *enter_waiting(hapticrom_simulator h, int *status, const char *call) {
    struct slot *s = slot_of(h);
    if (!s) {
        *status = fail(HAPTICROM_E_BAD_HANDLE, "%s: not a simulator handle (never returned by "
                                               "hapticrom_load)", call);
        return NULL;
    }
    int64_t deadline = 0;
    for (unsigned attempt = 0;; attempt++) {
        if (__atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) != h) break;
        int expected = 0;
        if (__atomic_compare_exchange_n(&s->servo_busy, &expected, 1, 0, __ATOMIC_ACQUIRE,
                                        __ATOMIC_RELAXED)) {
            if (__atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) != h) {
                leave(&s->servo_busy);
                break;
            }
            return s;
        }
        if (attempt % 64 == 63) { /* the servo thread may be preempted inside a call */
            int64_t now = monotonic_ns();
            if (!deadline) deadline = now + ENTER_WAIT_NS;
            else if (now > deadline) break;
            sched_yield();
        }
        relax();
    }
    if (__atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) != h)
        *status = fail(HAPTICROM_E_BAD_HANDLE, "%s: the simulator was freed", call);
    else
        *status = fail(HAPTICROM_E_BUSY, "%s: another thread was inside this simulator's servo "
                                         "calls all the time for %d s; try again (nothing "
                                         "changed)", call, ENTER_WAIT_NS / 1000000000);
    return NULL;
}

/* The Python registry's key of the live simulator h into *key (load and free write it under
 * slots_lock); BAD_HANDLE if h is not live. */
static int key_of(hapticrom_simulator h, int64_t *key, const char *call) {
    struct slot *s = slot_of(h);
    if (!s)
        return fail(HAPTICROM_E_BAD_HANDLE, "%s: not a simulator handle (never returned by "
                                            "hapticrom_load)", call);
    pthread_mutex_lock(&slots_lock);
    int live = __atomic_load_n(&s->handle, __ATOMIC_ACQUIRE) == h;
    if (live) *key = s->d.key;
    pthread_mutex_unlock(&slots_lock);
    return live ? HAPTICROM_OK
                : fail(HAPTICROM_E_BAD_HANDLE, "%s: the simulator was freed", call);
}

/* cabi.validate_friction under the GIL: its status; the resolved (static, dynamic, ratio)
 * into values. */
static int friction_in_python(int64_t key, double mu_s, double mu_d, double kt, double values[3],
                              const char *call) {
    PyGILState_STATE gil = PyGILState_Ensure();
    int status = HAPTICROM_E_INTERNAL;
    PyObject *result = PyObject_CallFunction(friction_function, "Lddd", (long long)key, mu_s,
                                             mu_d, kt);
    int code = 0;
    const char *message = NULL;
    if (!result || !PyArg_ParseTuple(result, "is(ddd)", &code, &message, &values[0], &values[1],
                                     &values[2])) {
        python_exception("hapticrom.online.cabi.validate_friction");
        fail(HAPTICROM_E_INTERNAL, "%s: %s", call, python_error);
    } else if (code != HAPTICROM_OK) {
        status = fail(code, "%s: %s (nothing changed)", call, message);
    } else {
        status = HAPTICROM_OK;
    }
    Py_XDECREF(result);
    PyGILState_Release(gil);
    return status;
}

int hapticrom_set_friction(hapticrom_simulator simulator, double static_coefficient,
                           double dynamic_coefficient, double tangential_stiffness) {
    static const char call[] = "hapticrom_set_friction";
    int64_t key = 0;
    int status = key_of(simulator, &key, call);
    if (status) return status;
    /* Simulator.set_friction's own check, never holding the servo flag while the GIL may be
     * a wait (the servo thread gets BUSY only for the write below, and a host that holds
     * the GIL while it frees the simulator cannot deadlock with it). */
    double values[3];
    status = friction_in_python(key, static_coefficient, dynamic_coefficient,
                                tangential_stiffness, values, call);
    if (status) return status;
    struct slot *s = enter_waiting(simulator, &status, call);
    if (!s) return status;
    write_begin(s); /* a renderer's snapshot holds the state buffer whole */
    status = s->d.set_friction(values, s->d.buf, s->d.buf_size);
    write_end(s);
    leave(&s->servo_busy);
    return status ? fail_status(status, call, "") : HAPTICROM_OK;
}
