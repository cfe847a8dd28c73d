/* fmu_plant.c - see fmu_plant.h. Host only (dlopen). */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE /* dlfcn */
#endif
#include "fmu_plant.h"

#include <ctype.h>
#include <dlfcn.h>
#include <errno.h>
#include <math.h>
#include <signal.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/time.h>
#include <unistd.h>

/* ---- the part of the FMI 2.0 standard used here (fmi2TypesPlatform.h, fmi2FunctionTypes.h) */
typedef void *fmi2Component;
typedef void *fmi2ComponentEnvironment;
typedef unsigned int fmi2ValueReference;
typedef double fmi2Real;
typedef int fmi2Integer;
typedef int fmi2Boolean;
typedef const char *fmi2String;
typedef enum { fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal, fmi2Pending } fmi2Status;
typedef enum { fmi2ModelExchange, fmi2CoSimulation } fmi2Type;
typedef struct {
    void (*logger)(fmi2ComponentEnvironment, fmi2String, fmi2Status, fmi2String, fmi2String, ...);
    void *(*allocateMemory)(size_t, size_t);
    void (*freeMemory)(void *);
    void (*stepFinished)(fmi2ComponentEnvironment, fmi2Status);
    fmi2ComponentEnvironment componentEnvironment;
} fmi2CallbackFunctions;

typedef const char *fmi2GetVersionTYPE(void);
typedef const char *fmi2GetTypesPlatformTYPE(void);
typedef fmi2Component fmi2InstantiateTYPE(fmi2String, fmi2Type, fmi2String, fmi2String,
                                          const fmi2CallbackFunctions *, fmi2Boolean, fmi2Boolean);
typedef void fmi2FreeInstanceTYPE(fmi2Component);
typedef fmi2Status fmi2SetupExperimentTYPE(fmi2Component, fmi2Boolean, fmi2Real, fmi2Real, fmi2Boolean, fmi2Real);
typedef fmi2Status fmi2ModeTYPE(fmi2Component);
typedef fmi2Status fmi2SetRealTYPE(fmi2Component, const fmi2ValueReference[], size_t, const fmi2Real[]);
typedef fmi2Status fmi2GetRealTYPE(fmi2Component, const fmi2ValueReference[], size_t, fmi2Real[]);
typedef fmi2Status fmi2SetIntegerTYPE(fmi2Component, const fmi2ValueReference[], size_t, const fmi2Integer[]);
typedef fmi2Status fmi2SetBooleanTYPE(fmi2Component, const fmi2ValueReference[], size_t, const fmi2Boolean[]);
typedef fmi2Status fmi2DoStepTYPE(fmi2Component, fmi2Real, fmi2Real, fmi2Boolean);
typedef fmi2Status fmi2ResetTYPE(fmi2Component);

/* ---- the part of the FMI 3.0 standard used here (fmi3PlatformTypes.h, fmi3FunctionTypes.h);
 * fmi3Status has fmi2Status' first five values */
typedef void *fmi3Instance;
typedef void *fmi3InstanceEnvironment;
typedef uint32_t fmi3ValueReference;
typedef void fmi3LogMessageCallback(fmi3InstanceEnvironment, int, const char *, const char *);
typedef const char *fmi3GetVersionTYPE(void);
typedef fmi3Instance fmi3InstantiateCoSimulationTYPE(const char *, const char *, const char *, bool, bool, bool, bool,
                                                     const fmi3ValueReference[], size_t, fmi3InstanceEnvironment,
                                                     fmi3LogMessageCallback *, void *);
typedef void fmi3FreeInstanceTYPE(fmi3Instance);
typedef int fmi3EnterInitializationModeTYPE(fmi3Instance, bool, double, double, bool, double);
typedef int fmi3ModeTYPE(fmi3Instance);
typedef int fmi3SetFloat64TYPE(fmi3Instance, const fmi3ValueReference[], size_t, const double[], size_t);
typedef int fmi3GetFloat64TYPE(fmi3Instance, const fmi3ValueReference[], size_t, double[], size_t);
typedef int fmi3SetInt32TYPE(fmi3Instance, const fmi3ValueReference[], size_t, const int32_t[], size_t);
typedef int fmi3SetBooleanTYPE(fmi3Instance, const fmi3ValueReference[], size_t, const bool[], size_t);
typedef int fmi3DoStepTYPE(fmi3Instance, double, double, bool, bool *, bool *, bool *, double *);

struct fmup {
    fmup_cfg_t cfg;
    double dt;
    void *lib;
    fmi2GetVersionTYPE *get_version;
    fmi2GetTypesPlatformTYPE *get_types_platform;
    fmi2InstantiateTYPE *instantiate;
    fmi2FreeInstanceTYPE *free_instance;
    fmi2SetupExperimentTYPE *setup_experiment;
    fmi2ModeTYPE *enter_init, *exit_init, *terminate;
    fmi2SetRealTYPE *set_real;
    fmi2GetRealTYPE *get_real;
    fmi2SetIntegerTYPE *set_integer;
    fmi2SetBooleanTYPE *set_boolean;
    fmi2DoStepTYPE *do_step;
    fmi2ResetTYPE *reset; /* (fmi3Reset has the same shape) */
    /* FMI 3.0 (cfg.fmi_version 3) */
    fmi3GetVersionTYPE *get_version3;
    fmi3InstantiateCoSimulationTYPE *instantiate3;
    fmi3FreeInstanceTYPE *free_instance3;
    fmi3EnterInitializationModeTYPE *enter_init3;
    fmi3ModeTYPE *exit_init3, *terminate3;
    fmi3SetFloat64TYPE *set_float64;
    fmi3GetFloat64TYPE *get_float64;
    fmi3SetInt32TYPE *set_int32;
    fmi3SetBooleanTYPE *set_boolean3;
    fmi3DoStepTYPE *do_step3;
    char resource_path[FMUP_STR + 16]; /* FMI 3.0: unzipdir/resources/ */
    fmi2CallbackFunctions cb;
    fmi2Component c;
    int ok;                 /* the instance answered every call so far (fmi2Terminate allowed) */
    int fatal;              /* it returned fmi2Fatal: no further call, not even fmi2FreeInstance */
    double t;
    double y1, y2;          /* motor, load angle after the last step */
    char resource_uri[3 * FMUP_STR + 16];
    char log[400];          /* the FMU's last warning or error message */
    char err[2600];         /* the last failure (fmup_error) */
    sim_plant_ext_t ext;
};

/* ---- the plant file's fmu: section ---- */

typedef enum { K_STR, K_INT } fmup_kind_t;

#define FMUP_KEYS 14u /* the named keys of fmup_key; pN_* follow */

static int fmup_parse_string(const char *text, char *out, size_t outlen, char *msg, size_t msglen)
{
    size_t n = strlen(text);
    if (n < 2 || text[0] != '"' || text[n - 1] != '"') {
        snprintf(msg, msglen, "expected a string in double quotes, got '%s'", text);
        return -1;
    }
    if (n - 2 >= outlen) {
        snprintf(msg, msglen, "string longer than %u characters", (unsigned)(outlen - 1));
        return -1;
    }
    for (size_t i = 1; i + 1 < n; i++) {
        if (text[i] == '"' || text[i] == '\\' || (unsigned char)text[i] < 0x20) {
            snprintf(msg, msglen, "a quote, backslash or control character inside the string");
            return -1;
        }
    }
    memcpy(out, text + 1, n - 2);
    out[n - 2] = '\0';
    return 0;
}

static int fmup_parse_uint(const char *text, unsigned *out, char *msg, size_t msglen)
{
    char *end;
    errno = 0;
    unsigned long v = strtoul(text, &end, 10);
    if (end == text || *end != '\0' || errno == ERANGE || text[0] == '-' || v > 0xFFFFFFFFul) {
        snprintf(msg, msglen, "'%s' is not an unsigned 32-bit integer", text);
        return -1;
    }
    *out = (unsigned)v;
    return 0;
}

static char *fmup_trim(char *s)
{
    while (*s == ' ' || *s == '\t') {
        s++;
    }
    char *e = s + strlen(s);
    while (e > s && (e[-1] == ' ' || e[-1] == '\t' || e[-1] == '\r' || e[-1] == '\n')) {
        *--e = '\0';
    }
    return s;
}

/* value text of one line: a quoted string is taken whole (a '#' inside it is no comment) */
static void fmup_strip_comment(char *value)
{
    int quoted = 0;
    for (char *p = value; *p; p++) {
        if (*p == '"') {
            quoted = !quoted;
        } else if (*p == '#' && !quoted) {
            *p = '\0';
            return;
        }
    }
}

static int fmup_key(fmup_cfg_t *c, const char *key, const char *value, unsigned seen[], char *msg, size_t msglen)
{
    static const char *const names[] = {"source", "path", "fmi_version", "unzipdir", "model_identifier", "guid",
                                        "input", "input_vr", "output", "output_vr", "load_output", "load_output_vr", "tolerance",
                                        "once_per_process"};
    for (unsigned i = 0; i < sizeof names / sizeof names[0]; i++) {
        if (strcmp(key, names[i]) != 0) {
            continue;
        }
        if (seen[i]++) {
            snprintf(msg, msglen, "duplicate key 'fmu.%s'", key);
            return -1;
        }
        switch (i) {
        case 0: return fmup_parse_string(value, c->source, sizeof c->source, msg, msglen);
        case 1: return fmup_parse_string(value, c->path, sizeof c->path, msg, msglen);
        case 2: {
            unsigned v;
            if (fmup_parse_uint(value, &v, msg, msglen) != 0) {
                return -1;
            }
            c->fmi_version = (int)v;
            return 0;
        }
        case 3: return fmup_parse_string(value, c->unzipdir, sizeof c->unzipdir, msg, msglen);
        case 4: return fmup_parse_string(value, c->model_identifier, sizeof c->model_identifier, msg, msglen);
        case 5: return fmup_parse_string(value, c->guid, sizeof c->guid, msg, msglen);
        case 6: return fmup_parse_string(value, c->input, sizeof c->input, msg, msglen);
        case 7: return fmup_parse_uint(value, &c->input_vr, msg, msglen);
        case 8: return fmup_parse_string(value, c->output, sizeof c->output, msg, msglen);
        case 9: return fmup_parse_uint(value, &c->output_vr, msg, msglen);
        case 10:
            c->has_load_output = 1;
            return fmup_parse_string(value, c->load_output, sizeof c->load_output, msg, msglen);
        case 11: return fmup_parse_uint(value, &c->load_output_vr, msg, msglen);
        case 13: {
            unsigned v;
            if (fmup_parse_uint(value, &v, msg, msglen) != 0 || v > 1u) {
                snprintf(msg, msglen, "fmu.once_per_process: '%s' is not 0 or 1", value);
                return -1;
            }
            c->once_per_process = (int)v;
            return 0;
        }
        default: {
            char *end;
            errno = 0;
            c->tolerance = strtod(value, &end);
            if (end == value || *end != '\0' || errno == ERANGE || !isfinite(c->tolerance) || c->tolerance <= 0.0) {
                snprintf(msg, msglen, "fmu.tolerance: '%s' is not a positive finite number", value);
                return -1;
            }
            c->has_tolerance = 1;
            return 0;
        }
        }
    }
    /* pN_name / pN_vr / pN_type / pN_value */
    unsigned idx;
    int used = 0;
    char field[16];
    if (sscanf(key, "p%u_%15[a-z]%n", &idx, field, &used) != 2 || key[used] != '\0') {
        snprintf(msg, msglen, "unknown key 'fmu.%s'", key);
        return -1;
    }
    if (idx >= FMUP_PARAMS_MAX) {
        snprintf(msg, msglen, "fmu.%s: at most %d start values (p0 .. p%d)", key, FMUP_PARAMS_MAX, FMUP_PARAMS_MAX - 1);
        return -1;
    }
    fmup_param_t *p = &c->param[idx];
    if ((int)idx >= c->n_params) {
        c->n_params = (int)idx + 1;
    }
    unsigned slot = FMUP_KEYS + 4u * idx;
    if (strcmp(field, "name") == 0) {
        if (seen[slot]++) {
            snprintf(msg, msglen, "duplicate key 'fmu.%s'", key);
            return -1;
        }
        return fmup_parse_string(value, p->name, sizeof p->name, msg, msglen);
    }
    if (strcmp(field, "vr") == 0) {
        if (seen[slot + 1]++) {
            snprintf(msg, msglen, "duplicate key 'fmu.%s'", key);
            return -1;
        }
        return fmup_parse_uint(value, &p->vr, msg, msglen);
    }
    if (strcmp(field, "type") == 0) {
        char t[16];
        if (seen[slot + 2]++) {
            snprintf(msg, msglen, "duplicate key 'fmu.%s'", key);
            return -1;
        }
        if (fmup_parse_string(value, t, sizeof t, msg, msglen) != 0) {
            return -1;
        }
        if (strcmp(t, "real") == 0) {
            p->type = FMUP_REAL;
        } else if (strcmp(t, "integer") == 0) {
            p->type = FMUP_INTEGER;
        } else if (strcmp(t, "boolean") == 0) {
            p->type = FMUP_BOOLEAN;
        } else {
            snprintf(msg, msglen, "fmu.%s = %s: real, integer or boolean", key, value);
            return -1;
        }
        return 0;
    }
    if (strcmp(field, "value") == 0) {
        char *end;
        if (seen[slot + 3]++) {
            snprintf(msg, msglen, "duplicate key 'fmu.%s'", key);
            return -1;
        }
        errno = 0;
        p->value = strtod(value, &end);
        if (end == value || *end != '\0' || errno == ERANGE || !isfinite(p->value)) {
            snprintf(msg, msglen, "fmu.%s: '%s' is not a finite number", key, value);
            return -1;
        }
        return 0;
    }
    snprintf(msg, msglen, "unknown key 'fmu.%s'", key);
    return -1;
}

int fmup_config_load(const char *path, fmup_cfg_t *out, char *err, size_t errlen)
{
    FILE *f = fopen(path, "r");
    if (f == NULL) {
        snprintf(err, errlen, "%s: cannot open: %s", path, strerror(errno));
        return -1;
    }
    fmup_cfg_t *c = calloc(1, sizeof *c);
    unsigned seen[FMUP_KEYS + 4 * FMUP_PARAMS_MAX];
    memset(seen, 0, sizeof seen);
    char line[1200], msg[700] = "";
    int lineno = 0, rc = c ? 0 : -1, in_fmu = 0, found = 0;
    if (c == NULL) {
        snprintf(msg, sizeof msg, "out of memory");
    }
    while (rc == 0 && fgets(line, sizeof line, f) != NULL) {
        lineno++;
        if (strchr(line, '\n') == NULL && !feof(f)) {
            snprintf(msg, sizeof msg, "line too long");
            rc = -1;
            break;
        }
        size_t indent = strspn(line, " ");
        char *colon = strchr(line, ':');
        if (colon == NULL || line[indent] == '#') {
            continue; /* blank, comment (plant_config_load checks the rest) */
        }
        *colon = '\0';
        char *key = fmup_trim(line);
        char *value = colon + 1;
        fmup_strip_comment(value);
        value = fmup_trim(value);
        if (indent == 0) {
            in_fmu = strcmp(key, "fmu") == 0;
            found |= in_fmu;
            if (in_fmu && *value != '\0') {
                snprintf(msg, sizeof msg, "'fmu:' must be a section of one 'key: value' a line (drive_sim "
                         "reads the file fftune writes from a plant file naming an FMU: fftune sim|demo --plant FILE)");
                rc = -1;
            }
            continue;
        }
        if (in_fmu) {
            if (*value == '\0') {
                snprintf(msg, sizeof msg, "fmu.%s: missing value (drive_sim reads the file fftune writes from "
                         "a plant file naming an FMU: fftune sim|demo --plant FILE)", key);
                rc = -1;
                break;
            }
            rc = fmup_key(c, key, value, seen, msg, sizeof msg);
        }
    }
    fclose(f);
    if (rc != 0) {
        snprintf(err, errlen, "%s:%d: %s (a plant file naming an FMU goes to fftune sim|demo --plant FILE, "
                 "which hands drive_sim its checked view: docs/fmu.md)", path, lineno, msg);
        free(c);
        return -1;
    }
    static const char *const required[] = {"source", "path", "fmi_version", "unzipdir", "model_identifier", "guid",
                                           "input", "input_vr", "output", "output_vr"};
    for (unsigned i = 0; i < sizeof required / sizeof required[0]; i++) {
        if (!found || !seen[i]) {
            snprintf(err, errlen, "%s: fmu.%s missing (the file fftune writes from a plant file naming an FMU "
                     "has it: fftune sim|demo --plant FILE)", path, required[i]);
            free(c);
            return -1;
        }
    }
    if (c->has_load_output != (seen[11] != 0)) {
        snprintf(err, errlen, "%s: fmu.load_output and fmu.load_output_vr go together", path);
        free(c);
        return -1;
    }
    for (int i = 0; i < c->n_params; i++) {
        unsigned s = FMUP_KEYS + 4u * (unsigned)i;
        if (!seen[s] || !seen[s + 1] || !seen[s + 2] || !seen[s + 3]) {
            snprintf(err, errlen, "%s: fmu.p%d: name, vr, type and value go together", path, i);
            free(c);
            return -1;
        }
    }
    if (c->fmi_version != 2 && c->fmi_version != 3) {
        snprintf(err, errlen, "%s: FMU %s: FMI version %d: drive_sim co-simulates FMI 2.0 and 3.0 (docs/fmu.md)",
                 c->source, c->path, c->fmi_version);
        free(c);
        return -1;
    }
    *out = *c;
    free(c);
    return 0;
}

/* ---- the FMU ---- */

/* A crash inside the FMU (SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT while one of its functions
 * runs) is one "drive_sim: error:" line naming the plant file, the FMU and the function, and
 * exit status 2, instead of a bare signal. The one piece of process state here: a signal
 * handler has no other way to know which FMU call was running (set around each call, cleared
 * when drive_sim's own code runs again, so its own crashes stay crashes). */
static fmup_t *volatile fmup_crash_f;
static const char *volatile fmup_crash_fn;
static volatile unsigned long fmup_calls; /* FMU calls begun (the hang watchdog's progress) */
static volatile unsigned fmup_patience;   /* seconds a call may take: 1 (to 2) a step, 8 loading / initialising */

#define FMUP_PATIENCE_STEP 1u
#define FMUP_PATIENCE_INIT 8u
#define FMUP_AT_P(f, name, p)   \
    do {                        \
        fmup_crash_fn = (name); \
        fmup_patience = (p);    \
        fmup_calls++;           \
        fmup_crash_f = (f);     \
    } while (0)
#define FMUP_AT(f, name) FMUP_AT_P(f, name, FMUP_PATIENCE_STEP)
#define FMUP_AT_INIT(f, name) FMUP_AT_P(f, name, FMUP_PATIENCE_INIT)
#define FMUP_DONE() (fmup_crash_f = NULL)

static void fmup_on_crash(int sig)
{
    fmup_t *f = fmup_crash_f;
    if (f != NULL) {
        static char line[2 * FMUP_STR + 400];
        const char *name = sig == SIGSEGV ? "SIGSEGV" : sig == SIGBUS ? "SIGBUS" : sig == SIGFPE ? "SIGFPE"
                           : sig == SIGILL ? "SIGILL" : "SIGABRT";
        int n = snprintf(line, sizeof line, "drive_sim: error: %s: FMU %s: the FMU crashed (%s) in %s at t = %.9g s; "
                         "drive_sim stops\n", f->cfg.source, f->cfg.path, name, fmup_crash_fn, f->t);
        if (n > 0) {
            size_t len = (size_t)n < sizeof line ? (size_t)n : sizeof line - 1;
            ssize_t w = write(STDERR_FILENO, line, len);
            (void)w;
        }
        _exit(2);
    }
    signal(sig, SIG_DFL);
    raise(sig);
}

/* The hang watchdog: SIGALRM every second (wall clock; installed only with an FMU plant; the
 * bus code takes EINTR as "nothing yet", file reads restart); an FMU call that has not
 * returned after its patience is one line and exit status 2 (fftune waits 10 s for drive_sim
 * to start and 2 x 2 s for an SDO answer: without this a hung FMU is a bare timeout naming no
 * FMU). CPU time would not do: on a loaded machine it runs slower than fftune's timeouts. */
static void fmup_on_tick(int sig)
{
    static unsigned long last;
    static unsigned ticks;
    fmup_t *f = fmup_crash_f;
    (void)sig;
    if (f == NULL || fmup_calls != last) {
        last = fmup_calls;
        ticks = 0;
        return;
    }
    if (++ticks >= fmup_patience) {
        static char line[2 * FMUP_STR + 400];
        int n = snprintf(line, sizeof line, "drive_sim: error: %s: FMU %s: %s did not return within %u s "
                         "(t = %.9g s; the FMU hangs?); drive_sim stops\n", f->cfg.source, f->cfg.path, fmup_crash_fn,
                         ticks, f->t);
        if (n > 0) {
            size_t len = (size_t)n < sizeof line ? (size_t)n : sizeof line - 1;
            ssize_t w = write(STDERR_FILENO, line, len);
            (void)w;
        }
        _exit(2);
    }
}

static void fmup_guard_install(void)
{
    static int installed;
    static char alt[64 * 1024]; /* (a stack overflow in the FMU still reaches the handler) */
    static const int sigs[] = {SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT};
    if (installed) {
        return;
    }
    installed = 1;
    stack_t st;
    memset(&st, 0, sizeof st);
    st.ss_sp = alt;
    st.ss_size = sizeof alt;
    (void)sigaltstack(&st, NULL);
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = fmup_on_crash;
    sa.sa_flags = SA_ONSTACK;
    sigemptyset(&sa.sa_mask);
    for (unsigned i = 0; i < sizeof sigs / sizeof sigs[0]; i++) {
        (void)sigaction(sigs[i], &sa, NULL);
    }
    struct sigaction tick;
    memset(&tick, 0, sizeof tick);
    tick.sa_handler = fmup_on_tick;
    tick.sa_flags = SA_RESTART;
    sigemptyset(&tick.sa_mask);
    (void)sigaction(SIGALRM, &tick, NULL);
    struct itimerval every = {{1, 0}, {1, 0}};
    (void)setitimer(ITIMER_REAL, &every, NULL);
}

static void fmup_logger(fmi2ComponentEnvironment env, fmi2String instance, fmi2Status status, fmi2String category,
                        fmi2String message, ...)
{
    (void)instance;
    (void)category;
    fmup_t *f = env;
    if (f == NULL || status < fmi2Warning || message == NULL) {
        return;
    }
    va_list ap;
    va_start(ap, message);
    vsnprintf(f->log, sizeof f->log, message, ap);
    va_end(ap);
    for (char *p = f->log; *p; p++) {
        if (*p == '\n' || *p == '\r') {
            *p = ' '; /* one line */
        }
    }
}

static void *fmup_calloc(size_t n, size_t size)
{
    return calloc(n, size);
}

static void fmup_fail(fmup_t *f, char *err, size_t errlen, const char *fmt, ...)
{
    char what[600];
    f->ok = 0;
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(what, sizeof what, fmt, ap);
    va_end(ap);
    snprintf(f->err, sizeof f->err, "%s: FMU %s: %s%s%s%s", f->cfg.source, f->cfg.path, what,
             f->log[0] ? " (the FMU's log: " : "", f->log, f->log[0] ? ")" : "");
    if (err != NULL) {
        snprintf(err, errlen, "%s", f->err);
    }
}

/* the FMU's folder of this platform's binary: FMI 2.0 "linux64", FMI 3.0 "<arch>-linux" */
static const char *fmup_binary_dir(const fmup_cfg_t *c)
{
    if (c->fmi_version == 2) {
        return "binaries/linux64";
    }
#if defined(__aarch64__)
    return "binaries/aarch64-linux";
#else
    return "binaries/x86_64-linux";
#endif
}

static const char *fmup_version_of(const fmup_t *f);

static void *fmup_sym(fmup_t *f, const char *name, char *err, size_t errlen)
{
    void *p = dlsym(f->lib, name);
    if (p == NULL) {
        fmup_fail(f, err, errlen, "%s/%s.so has no function %s (not an FMI %s co-simulation binary)",
                  fmup_binary_dir(&f->cfg), f->cfg.model_identifier, name, fmup_version_of(f));
    }
    return p;
}

#define FMUP_BIND(field, name)                                    \
    do {                                                          \
        void *sym_ = fmup_sym(f, name, err, errlen);              \
        if (sym_ == NULL) {                                       \
            return -1;                                            \
        }                                                         \
        memcpy(&f->field, &sym_, sizeof f->field);                \
    } while (0)

static const char *fmup_version_of(const fmup_t *f)
{
    return f->cfg.fmi_version == 3 ? "3.0" : "2.0";
}

static int fmup_bind(fmup_t *f, char *err, size_t errlen)
{
    const char *v;
    if (f->cfg.fmi_version == 3) {
        FMUP_BIND(get_version3, "fmi3GetVersion");
        FMUP_BIND(instantiate3, "fmi3InstantiateCoSimulation");
        FMUP_BIND(free_instance3, "fmi3FreeInstance");
        FMUP_BIND(enter_init3, "fmi3EnterInitializationMode");
        FMUP_BIND(exit_init3, "fmi3ExitInitializationMode");
        FMUP_BIND(terminate3, "fmi3Terminate");
        FMUP_BIND(set_float64, "fmi3SetFloat64");
        FMUP_BIND(get_float64, "fmi3GetFloat64");
        FMUP_BIND(set_int32, "fmi3SetInt32");
        FMUP_BIND(set_boolean3, "fmi3SetBoolean");
        FMUP_BIND(do_step3, "fmi3DoStep");
        if (f->cfg.once_per_process) {
            FMUP_BIND(reset, "fmi3Reset");
        }
        FMUP_AT(f, "fmi3GetVersion");
        v = f->get_version3();
    } else {
        FMUP_BIND(get_version, "fmi2GetVersion");
        FMUP_BIND(get_types_platform, "fmi2GetTypesPlatform");
        FMUP_BIND(instantiate, "fmi2Instantiate");
        FMUP_BIND(free_instance, "fmi2FreeInstance");
        FMUP_BIND(setup_experiment, "fmi2SetupExperiment");
        FMUP_BIND(enter_init, "fmi2EnterInitializationMode");
        FMUP_BIND(exit_init, "fmi2ExitInitializationMode");
        FMUP_BIND(terminate, "fmi2Terminate");
        FMUP_BIND(set_real, "fmi2SetReal");
        FMUP_BIND(get_real, "fmi2GetReal");
        FMUP_BIND(set_integer, "fmi2SetInteger");
        FMUP_BIND(set_boolean, "fmi2SetBoolean");
        FMUP_BIND(do_step, "fmi2DoStep");
        if (f->cfg.once_per_process) {
            FMUP_BIND(reset, "fmi2Reset");
        }
        FMUP_AT(f, "fmi2GetVersion");
        v = f->get_version();
        FMUP_AT(f, "fmi2GetTypesPlatform");
        const char *tp = f->get_types_platform();
        if (tp == NULL || strcmp(tp, "default") != 0) {
            fmup_fail(f, err, errlen, "fmi2GetTypesPlatform() = '%s': drive_sim uses the standard's \"default\"",
                      tp ? tp : "(null)");
            return -1;
        }
    }
    if (v == NULL || v[0] != (f->cfg.fmi_version == 3 ? '3' : '2') || v[1] != '.') {
        fmup_fail(f, err, errlen, "fmi%dGetVersion() = '%s': not FMI %s", f->cfg.fmi_version, v ? v : "(null)",
                  fmup_version_of(f));
        return -1;
    }
    return 0;
}

/* "fmi2Error" / "fmi3Error" ...; notes a fatal status (no further call then) */
static const char *fmup_status_name(fmup_t *f, int s)
{
    static const char *const n2[] = {"fmi2OK", "fmi2Warning", "fmi2Discard", "fmi2Error", "fmi2Fatal", "fmi2Pending"};
    static const char *const n3[] = {"fmi3OK", "fmi3Warning", "fmi3Discard", "fmi3Error", "fmi3Fatal", "?"};
    f->fatal |= s == (int)fmi2Fatal;
    if ((unsigned)s >= 6u) {
        return "an unknown status";
    }
    return f->cfg.fmi_version == 3 ? n3[s] : n2[s];
}

static void fmup_free_instance_in(fmup_t *f)
{
    if (f->c != NULL && !f->fatal) {
        if (f->cfg.fmi_version == 3) {
            if (f->ok) {
                FMUP_AT(f, "fmi3Terminate");
                (void)f->terminate3(f->c);
            }
            FMUP_AT(f, "fmi3FreeInstance");
            f->free_instance3(f->c);
        } else {
            if (f->ok) {
                FMUP_AT(f, "fmi2Terminate");
                (void)f->terminate(f->c);
            }
            FMUP_AT(f, "fmi2FreeInstance");
            f->free_instance(f->c);
        }
    }
    f->c = NULL;
    f->ok = 0;
    f->fatal = 0;
}

static void fmup_free_instance(fmup_t *f)
{
    fmup_free_instance_in(f);
    FMUP_DONE();
}

/* fmi2SetReal / fmi3SetFloat64 of one variable */
static int fmup_set_f64(fmup_t *f, unsigned vr, double v)
{
    if (f->cfg.fmi_version == 3) {
        fmi3ValueReference r = vr;
        FMUP_AT(f, "fmi3SetFloat64");
        return f->set_float64(f->c, &r, 1, &v, 1);
    }
    fmi2ValueReference r = vr;
    FMUP_AT(f, "fmi2SetReal");
    return (int)f->set_real(f->c, &r, 1, &v);
}

static const char *fmup_fn(const fmup_t *f, const char *fmi2_name, const char *fmi3_name)
{
    return f->cfg.fmi_version == 3 ? fmi3_name : fmi2_name;
}

/* read the angles into y1, y2 (0, or -1 with the failure recorded) */
static int fmup_read(fmup_t *f, char *err, size_t errlen)
{
    unsigned vr[2] = {f->cfg.output_vr, f->cfg.has_load_output ? f->cfg.load_output_vr : f->cfg.output_vr};
    double y[2] = {NAN, NAN};
    int s;
    if (f->cfg.fmi_version == 3) {
        fmi3ValueReference r[2] = {vr[0], vr[1]};
        FMUP_AT(f, "fmi3GetFloat64");
        s = f->get_float64(f->c, r, 2, y, 2);
    } else {
        fmi2ValueReference r[2] = {vr[0], vr[1]};
        FMUP_AT(f, "fmi2GetReal");
        s = (int)f->get_real(f->c, r, 2, y);
    }
    FMUP_DONE();
    if (s > (int)fmi2Warning) {
        fmup_fail(f, err, errlen, "%s of output '%s' at t = %.9g s returned %s", fmup_fn(f, "fmi2GetReal", "fmi3GetFloat64"),
                  f->cfg.output, f->t, fmup_status_name(f, s));
        return -1;
    }
    if (!isfinite(y[0]) || !isfinite(y[1])) {
        fmup_fail(f, err, errlen, "output '%s' is %g at t = %.9g s (not finite)",
                  isfinite(y[0]) ? f->cfg.load_output : f->cfg.output, isfinite(y[0]) ? y[1] : y[0], f->t);
        return -1;
    }
    f->y1 = y[0];
    f->y2 = y[1];
    return 0;
}

static void fmup_log3(fmi3InstanceEnvironment env, int status, const char *category, const char *message)
{
    fmup_logger(env, "fftune", (fmi2Status)status, category, "%s", message ? message : "");
}

/* a new instance at t = 0 with the start values, initialised (0, or -1) */
/* a new instance, or (canBeInstantiatedOnlyOncePerProcess) the one instance back to its
 * instantiated state by fmi2Reset / fmi3Reset (0, or -1 with the failure recorded) */
static int fmup_new_instance(fmup_t *f, char *err, size_t errlen)
{
    f->log[0] = '\0';
    f->t = 0.0;
    if (f->cfg.once_per_process && f->c != NULL) {
        if (f->fatal) {
            fmup_fail(f, err, errlen, "it returned %sFatal and can be instantiated only once per process "
                      "(canBeInstantiatedOnlyOncePerProcess): no restart", f->cfg.fmi_version == 3 ? "fmi3" : "fmi2");
            return -1;
        }
        FMUP_AT_INIT(f, fmup_fn(f, "fmi2Reset", "fmi3Reset"));
        int s = (int)f->reset(f->c);
        f->ok = s <= (int)fmi2Warning;
        if (!f->ok) {
            fmup_fail(f, err, errlen, "%s (its restart: it can be instantiated only once per process) returned %s",
                      fmup_fn(f, "fmi2Reset", "fmi3Reset"), fmup_status_name(f, s));
            return -1;
        }
        return 0;
    }
    fmup_free_instance(f);
    FMUP_AT_INIT(f, fmup_fn(f, "fmi2Instantiate", "fmi3InstantiateCoSimulation"));
    if (f->cfg.fmi_version == 3) {
        f->c = f->instantiate3("fftune", f->cfg.guid, f->resource_path, false, false, false, false, NULL, 0, f,
                               fmup_log3, NULL);
    } else {
        f->c = f->instantiate("fftune", fmi2CoSimulation, f->cfg.guid, f->resource_uri, &f->cb, 0, 0);
    }
    f->ok = f->c != NULL;
    if (f->c == NULL) {
        fmup_fail(f, err, errlen, "%s (co-simulation, %s %s) returned NULL",
                  fmup_fn(f, "fmi2Instantiate", "fmi3InstantiateCoSimulation"),
                  fmup_fn(f, "GUID", "instantiation token"), f->cfg.guid);
        return -1;
    }
    return 0;
}

static int fmup_instantiate_in(fmup_t *f, char *err, size_t errlen)
{
    int s;
    if (fmup_new_instance(f, err, errlen) != 0) {
        return -1;
    }
    if (f->cfg.fmi_version == 2) {
        FMUP_AT(f, "fmi2SetupExperiment");
        s = (int)f->setup_experiment(f->c, f->cfg.has_tolerance, f->cfg.tolerance, 0.0, 0, 0.0);
        if (s > (int)fmi2Warning) {
            fmup_fail(f, err, errlen, "fmi2SetupExperiment returned %s", fmup_status_name(f, s));
            return -1;
        }
    }
    for (int i = 0; i < f->cfg.n_params; i++) {
        const fmup_param_t *p = &f->cfg.param[i];
        FMUP_AT(f, "setting a start value (fmu.parameters)");
        if (p->type == FMUP_REAL) {
            s = fmup_set_f64(f, p->vr, p->value);
        } else if (f->cfg.fmi_version == 3) {
            fmi3ValueReference vr = p->vr;
            if (p->type == FMUP_INTEGER) {
                int32_t v = (int32_t)p->value;
                s = f->set_int32(f->c, &vr, 1, &v, 1);
            } else {
                bool v = p->value != 0.0;
                s = f->set_boolean3(f->c, &vr, 1, &v, 1);
            }
        } else {
            fmi2ValueReference vr = p->vr;
            if (p->type == FMUP_INTEGER) {
                fmi2Integer v = (fmi2Integer)p->value;
                s = (int)f->set_integer(f->c, &vr, 1, &v);
            } else {
                fmi2Boolean v = p->value != 0.0;
                s = (int)f->set_boolean(f->c, &vr, 1, &v);
            }
        }
        if (s > (int)fmi2Warning) {
            fmup_fail(f, err, errlen, "setting parameter '%s' = %g (fmu.parameters) returned %s", p->name, p->value,
                      fmup_status_name(f, s));
            return -1;
        }
    }
    s = fmup_set_f64(f, f->cfg.input_vr, 0.0);
    if (s > (int)fmi2Warning) {
        fmup_fail(f, err, errlen, "%s of input '%s' returned %s", fmup_fn(f, "fmi2SetReal", "fmi3SetFloat64"),
                  f->cfg.input, fmup_status_name(f, s));
        return -1;
    }
    FMUP_AT_INIT(f, fmup_fn(f, "fmi2EnterInitializationMode", "fmi3EnterInitializationMode"));
    s = f->cfg.fmi_version == 3 ? f->enter_init3(f->c, f->cfg.has_tolerance != 0, f->cfg.tolerance, 0.0, false, 0.0) : (int)f->enter_init(f->c);
    if (s > (int)fmi2Warning) {
        fmup_fail(f, err, errlen, "fmi%dEnterInitializationMode returned %s", f->cfg.fmi_version,
                  fmup_status_name(f, s));
        return -1;
    }
    FMUP_AT_INIT(f, fmup_fn(f, "fmi2ExitInitializationMode", "fmi3ExitInitializationMode"));
    s = f->cfg.fmi_version == 3 ? f->exit_init3(f->c) : (int)f->exit_init(f->c);
    if (s > (int)fmi2Warning) {
        fmup_fail(f, err, errlen, "fmi%dExitInitializationMode returned %s", f->cfg.fmi_version,
                  fmup_status_name(f, s));
        return -1;
    }
    return fmup_read(f, err, errlen);
}

static int fmup_instantiate(fmup_t *f, char *err, size_t errlen)
{
    int rc = fmup_instantiate_in(f, err, errlen);
    FMUP_DONE();
    return rc;
}

static int fmup_step_in(fmup_t *f, double u, double dt, char *err, size_t errlen)
{
    if (f->c == NULL || !f->ok) {
        if (err != NULL) {
            snprintf(err, errlen, "%s", f->err); /* (the restart or an earlier call failed: said there) */
        }
        return -1;
    }
    int s = fmup_set_f64(f, f->cfg.input_vr, u);
    if (s > (int)fmi2Warning) {
        fmup_fail(f, err, errlen, "%s of input '%s' = %g at t = %.9g s returned %s",
                  fmup_fn(f, "fmi2SetReal", "fmi3SetFloat64"), f->cfg.input, u, f->t, fmup_status_name(f, s));
        return -1;
    }
    if (f->cfg.fmi_version == 3) {
        bool event = false, terminate = false, early = false;
        double last = f->t;
        FMUP_AT(f, "fmi3DoStep");
        s = f->do_step3(f->c, f->t, dt, true, &event, &terminate, &early, &last);
        if (s <= (int)fmi2Warning && (terminate || early)) {
            fmup_fail(f, err, errlen, "fmi3DoStep(t = %.9g s, h = %.9g s) with input '%s' = %g: the FMU %s", f->t, dt,
                      f->cfg.input, u, terminate ? "asked to terminate the simulation" : "returned early");
            return -1;
        }
    } else {
        FMUP_AT(f, "fmi2DoStep");
        s = (int)f->do_step(f->c, f->t, dt, 1);
    }
    if (s > (int)fmi2Warning) {
        fmup_fail(f, err, errlen, "fmi%dDoStep(t = %.9g s, h = %.9g s) with input '%s' = %g returned %s",
                  f->cfg.fmi_version, f->t, dt, f->cfg.input, u, fmup_status_name(f, s));
        return -1;
    }
    f->t += dt;
    return fmup_read(f, err, errlen);
}

static int fmup_step(fmup_t *f, double u, double dt, char *err, size_t errlen)
{
    int rc = fmup_step_in(f, u, dt, err, errlen);
    FMUP_DONE();
    return rc;
}

static int fmup_ext_advance(void *ctx, double u, double dt)
{
    fmup_t *f = ctx;
    if (fmup_step(f, u, dt, NULL, 0) != 0) {
        fprintf(stderr, "drive_sim: error: %s; the drive is disabled, the plant holds until an NMT reset\n", f->err);
        return -1;
    }
    return 0;
}

static void fmup_ext_angles(void *ctx, double *motor, double *load)
{
    fmup_t *f = ctx;
    *motor = f->y1;
    *load = f->y2;
}

/* file:// URI of unzipdir/resources (RFC 3986: unreserved characters and '/' kept) */
static void fmup_uri(fmup_t *f)
{
    char *o = f->resource_uri;
    size_t cap = sizeof f->resource_uri, n = (size_t)snprintf(o, cap, "file://");
    char dir[FMUP_STR + 16];
    snprintf(dir, sizeof dir, "%s/resources", f->cfg.unzipdir);
    for (const char *p = dir; *p && n + 4 < cap; p++) {
        unsigned char ch = (unsigned char)*p;
        if (isalnum(ch) || strchr("-._~/", ch)) {
            o[n++] = (char)ch;
        } else {
            n += (size_t)snprintf(o + n, cap - n, "%%%02X", ch);
        }
    }
    o[n] = '\0';
}

fmup_t *fmup_open(const fmup_cfg_t *cfg, double dt_s, char *err, size_t errlen)
{
    fmup_t *f = calloc(1, sizeof *f);
    if (f == NULL) {
        snprintf(err, errlen, "%s: out of memory", cfg->source);
        return NULL;
    }
    f->cfg = *cfg;
    f->dt = dt_s;
    f->cb.logger = fmup_logger;
    f->cb.allocateMemory = fmup_calloc;
    f->cb.freeMemory = free;
    f->cb.componentEnvironment = f;
    f->ext.ctx = f;
    f->ext.advance = fmup_ext_advance;
    f->ext.angles = fmup_ext_angles;
    fmup_uri(f);
    char so[2 * FMUP_STR + 32];
    snprintf(f->resource_path, sizeof f->resource_path, "%s/resources/", cfg->unzipdir);
    snprintf(so, sizeof so, "%s/%s/%s.so", cfg->unzipdir, fmup_binary_dir(cfg), cfg->model_identifier);
    fmup_guard_install();
    if (cfg->once_per_process) {
        void *loaded = dlopen(so, RTLD_NOW | RTLD_NOLOAD);
        if (loaded != NULL) {
            dlclose(loaded);
            fmup_fail(f, err, errlen, "another axis of this drive_sim runs it already, and it can be instantiated "
                      "only once per process (canBeInstantiatedOnlyOncePerProcess): one drive_sim per such axis");
            free(f);
            return NULL;
        }
    }
    FMUP_AT_INIT(f, "loading the binary (its constructors)");
    f->lib = dlopen(so, RTLD_NOW | RTLD_LOCAL);
    FMUP_DONE();
    if (f->lib == NULL) {
        const char *why = dlerror();
        fmup_fail(f, err, errlen, "cannot load %s/%s.so: %s", fmup_binary_dir(cfg), cfg->model_identifier,
                  why ? why : "dlopen failed");
        free(f);
        return NULL;
    }
    int bound = fmup_bind(f, err, errlen);
    FMUP_DONE();
    if (bound != 0 || fmup_instantiate(f, err, errlen) != 0 || fmup_step(f, 0.0, dt_s, err, errlen) != 0) {
        /* trial (an FMU that cannot take a step fails before the drive exists) */
        fmup_close(f);
        return NULL;
    }
    if (fmup_instantiate(f, err, errlen) != 0) {
        fmup_close(f);
        return NULL;
    }
    return f;
}

fmup_t *fmup_open_file(const char *path, double dt_s, char *err, size_t errlen)
{
    fmup_cfg_t *c = calloc(1, sizeof *c);
    if (c == NULL) {
        snprintf(err, errlen, "%s: out of memory", path);
        return NULL;
    }
    fmup_t *f = fmup_config_load(path, c, err, errlen) == 0 ? fmup_open(c, dt_s, err, errlen) : NULL;
    free(c);
    return f;
}

int fmup_restart(fmup_t *f, char *err, size_t errlen)
{
    return fmup_instantiate(f, err, errlen);
}

const sim_plant_ext_t *fmup_ext(fmup_t *f)
{
    return &f->ext;
}

const char *fmup_error(const fmup_t *f)
{
    return f->err;
}

double fmup_time(const fmup_t *f)
{
    return f->t;
}

void fmup_close(fmup_t *f)
{
    if (f == NULL) {
        return;
    }
    if (f->lib != NULL && f->free_instance != NULL) {
        fmup_free_instance(f);
    }
    /* the library stays loaded: an FMU's atexit handlers or threads may still refer to it */
    free(f);
}
