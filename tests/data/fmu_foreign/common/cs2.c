/* cs2.c - a small hand-written FMI 2.0 co-simulation slave, in the manner of the Modelica
 * Reference FMUs: not fftune's firmware_sim/fmu/fmu_slave.c. Built with FMPy's CMake project
 * (fmpy.build.build_platform_binary), FMI headers from FMPy's c-code/.
 *
 * The model (model.h, model.c) provides:
 *   MODEL_GUID, NR / NI / NB (Real / Integer / Boolean variables, value reference = index),
 *   Model (r[NR], i[NI], b[NB] and its states), model_defaults(), model_settable(),
 *   model_init(), model_step() (returns an fmi2Status, a message for anything but fmi2OK),
 *   optional CS2_CHATTY (log through the logger callback every step, whatever loggingOn says),
 *   optional CS2_ONCE_PER_PROCESS (a second fmi2Instantiate in the process fails, as embedded code).
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

typedef enum { ST_INSTANTIATED = 1, ST_INIT = 2, ST_STEP = 4, ST_TERMINATED = 8, ST_ERROR = 16 } cs2_state_t;

typedef struct {
    fmi2CallbackFunctions cb;
    char name[128];
    int logging;
    cs2_state_t state;
    double t;
    double h0;            /* first communication step (canHandleVariableCommunicationStepSize false) */
    Model m;
} cs2_t;

static void cs2_log(cs2_t *c, fmi2Status s, const char *cat, const char *fmt, ...)
{
    char buf[512];
    va_list ap;
    if (c->cb.logger == NULL) {
        return;
    }
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    c->cb.logger(c->cb.componentEnvironment, c->name, s, cat, "%s", buf);
}

static int cs2_in(cs2_t *c, int allowed, const char *fn)
{
    if (c == NULL) {
        return 0;
    }
    if (!(c->state & allowed)) {
        cs2_log(c, fmi2Error, "logStatusError", "%s: not allowed in state %d", fn, (int)c->state);
        c->state = ST_ERROR;
        return 0;
    }
    return 1;
}

/* file:///a/b%20c/resources -> /a/b c/resources */
static void cs2_uri_to_path(const char *uri, char *out, size_t n)
{
    size_t k = 0;
    out[0] = '\0';
    if (uri == NULL) {
        return;
    }
    if (strncmp(uri, "file://", 7) == 0) {
        uri += 7;
        if (strncmp(uri, "localhost/", 10) == 0) {
            uri += 9;
        }
    } else if (strncmp(uri, "file:", 5) == 0) {
        uri += 5;
    }
    for (; *uri && k + 1 < n; uri++) {
        unsigned v;
        if (uri[0] == '%' && uri[1] && uri[2] && sscanf(uri + 1, "%2x", &v) == 1) {
            out[k++] = (char)v;
            uri += 2;
        } else {
            out[k++] = *uri;
        }
    }
    out[k] = '\0';
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[])
{
    (void)n;
    (void)cats;
    ((cs2_t *)c)->logging = on;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *cb, fmi2Boolean visible, fmi2Boolean logging)
{
    (void)visible;
    if (cb == NULL || cb->allocateMemory == NULL || cb->freeMemory == NULL) {
        return NULL;
    }
    cs2_t *c = cb->allocateMemory(1, sizeof *c);
    if (c == NULL) {
        return NULL;
    }
    c->cb = *cb;
    snprintf(c->name, sizeof c->name, "%s", name ? name : "?");
    c->logging = logging;
    if (type != fmi2CoSimulation) {
        cs2_log(c, fmi2Error, "logStatusError", "this FMU supports co-simulation only");
        cb->freeMemory(c);
        return NULL;
    }
#ifdef CS2_ONCE_PER_PROCESS
    static int ever; /* embedded code: one instance for the life of the process */
    if (ever++) {
        cs2_log(c, fmi2Error, "logStatusError", "only one instance per process (canBeInstantiatedOnlyOncePerProcess)");
        cb->freeMemory(c);
        return NULL;
    }
#endif
    if (guid == NULL || strcmp(guid, MODEL_GUID) != 0) {
        cs2_log(c, fmi2Error, "logStatusError", "wrong GUID %s, expected %s", guid ? guid : "(null)", MODEL_GUID);
        cb->freeMemory(c);
        return NULL;
    }
    model_defaults(&c->m);
    cs2_uri_to_path(resources, c->m.resources, sizeof c->m.resources);
    c->state = ST_INSTANTIATED;
    return c;
}

void fmi2FreeInstance(fmi2Component c)
{
    cs2_t *s = c;
    if (s != NULL) {
        s->cb.freeMemory(s);
    }
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDef, fmi2Real tol, fmi2Real t0, fmi2Boolean stopDef,
                               fmi2Real tstop)
{
    cs2_t *s = c;
    (void)stopDef;
    (void)tstop;
    if (!cs2_in(s, ST_INSTANTIATED, "fmi2SetupExperiment")) {
        return fmi2Error;
    }
    s->m.tolerance = tolDef ? tol : MODEL_DEFAULT_TOLERANCE;
    s->t = t0;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    cs2_t *s = c;
    if (!cs2_in(s, ST_INSTANTIATED, "fmi2EnterInitializationMode")) {
        return fmi2Error;
    }
    s->state = ST_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    cs2_t *s = c;
    char msg[400] = "";
    if (!cs2_in(s, ST_INIT, "fmi2ExitInitializationMode")) {
        return fmi2Error;
    }
    if (model_init(&s->m, msg, sizeof msg) != 0) {
        cs2_log(s, fmi2Error, "logStatusError", "%s", msg);
        s->state = ST_ERROR;
        return fmi2Error;
    }
    s->state = ST_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    cs2_t *s = c;
    if (!cs2_in(s, ST_STEP, "fmi2Terminate")) {
        return fmi2Error;
    }
    s->state = ST_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c)
{
    cs2_t *s = c;
    char res[sizeof s->m.resources];
    memcpy(res, s->m.resources, sizeof res);
    model_defaults(&s->m);
    memcpy(s->m.resources, res, sizeof res);
    s->state = ST_INSTANTIATED;
    s->h0 = 0.0;
    return fmi2OK;
}

#define CS2_ACCESS(Fn, T, arr, N, code, setting)                                                          \
    fmi2Status Fn(fmi2Component c, const fmi2ValueReference vr[], size_t n, T v[])                        \
    {                                                                                                     \
        cs2_t *s = c;                                                                                     \
        if (!cs2_in(s, ST_INSTANTIATED | ST_INIT | ST_STEP, #Fn)) {                                        \
            return fmi2Error;                                                                             \
        }                                                                                                 \
        for (size_t k = 0; k < n; k++) {                                                                  \
            if (vr[k] >= (N)) {                                                                           \
                cs2_log(s, fmi2Error, "logStatusError", #Fn ": unknown value reference %u", vr[k]);       \
                return fmi2Error;                                                                         \
            }                                                                                             \
            if (setting && !model_settable(&s->m, code, vr[k], s->state == ST_STEP)) {                     \
                cs2_log(s, fmi2Error, "logStatusError", #Fn ": variable %u cannot be set now", vr[k]);    \
                return fmi2Error;                                                                         \
            }                                                                                             \
            CS2_COPY_##setting(s->m.arr[vr[k]], v[k]);                                                    \
        }                                                                                                 \
        return fmi2OK;                                                                                    \
    }
#define CS2_COPY_0(field, val) (val) = (field)
#define CS2_COPY_1(field, val) (field) = (val)

CS2_ACCESS(fmi2GetReal, fmi2Real, r, NR, 'r', 0)
CS2_ACCESS(fmi2GetInteger, fmi2Integer, i, NI, 'i', 0)
CS2_ACCESS(fmi2GetBoolean, fmi2Boolean, b, NB, 'b', 0)
CS2_ACCESS(fmi2SetReal, const fmi2Real, r, NR, 'r', 1)
CS2_ACCESS(fmi2SetInteger, const fmi2Integer, i, NI, 'i', 1)
CS2_ACCESS(fmi2SetBoolean, const fmi2Boolean, b, NB, 'b', 1)

fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[])
{
    (void)vr;
    (void)v;
    return n == 0 ? fmi2OK : (cs2_log(c, fmi2Error, "logStatusError", "no String variables"), fmi2Error);
}

fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[])
{
    return fmi2GetString(c, vr, n, (fmi2String *)v);
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean noSetPrior)
{
    cs2_t *s = c;
    char msg[400] = "";
    (void)noSetPrior;
    if (!cs2_in(s, ST_STEP, "fmi2DoStep")) {
        return fmi2Error;
    }
    if (t < s->t - 1e-9 * (1.0 + s->t) || t > s->t + 1e-9 * (1.0 + s->t)) { /* (as the Reference FMUs check) */
        cs2_log(s, fmi2Error, "logStatusError", "Expected currentCommunicationPoint = %.16g but was %.16g.", s->t, t);
        return fmi2Error;
    }
    if (!(h > 0.0)) {
        cs2_log(s, fmi2Error, "logStatusError", "communication step %g s <= 0", h);
        return fmi2Error;
    }
    if (s->h0 == 0.0) {
        s->h0 = h;
    } else if (h < s->h0 * (1 - 1e-9) || h > s->h0 * (1 + 1e-9)) {
        cs2_log(s, fmi2Error, "logStatusError", "communication step %g s differs from the first %g s "
                "(canHandleVariableCommunicationStepSize=false)", h, s->h0);
        return fmi2Error;
    }
    fmi2Status st = (fmi2Status)model_step(&s->m, t, h, msg, sizeof msg);
    if (st != fmi2OK) {
        cs2_log(s, st, st == fmi2Warning ? "logStatusWarning" : "logStatusError", "%s", msg);
    }
#ifdef CS2_CHATTY
    cs2_log(s, fmi2OK, "logAll", "fmi2DoStep(%.9g, %.9g): u = %.17g, %s%%", t, h, s->m.r[0],
            "100");
#endif
    if (st == fmi2OK || st == fmi2Warning) {
        s->t = t + h;
    }
    return st;
}

fmi2Status fmi2CancelStep(fmi2Component c)
{
    (void)c;
    return fmi2Error;
}

fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind k, fmi2Status *v)
{
    (void)c;
    (void)k;
    *v = fmi2OK;
    return fmi2OK;
}

fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind k, fmi2Real *v)
{
    cs2_t *s = c;
    (void)k;
    *v = s->t;
    return fmi2OK;
}

fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind k, fmi2Integer *v)
{
    (void)c;
    (void)k;
    (void)v;
    return fmi2Discard;
}

fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind k, fmi2Boolean *v)
{
    (void)c;
    (void)k;
    *v = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind k, fmi2String *v)
{
    (void)c;
    (void)k;
    (void)v;
    return fmi2Discard;
}

/* not supported (the capability flags say so) */
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer o[], const fmi2Real v[])
{
    (void)c, (void)vr, (void)n, (void)o, (void)v;
    return fmi2Error;
}

fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer o[], fmi2Real v[])
{
    (void)c, (void)vr, (void)n, (void)o, (void)v;
    return fmi2Error;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *st)
{
    (void)c, (void)st;
    return fmi2Error;
}

fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate st)
{
    (void)c, (void)st;
    return fmi2Error;
}

fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *st)
{
    (void)c, (void)st;
    return fmi2Error;
}

fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate st, size_t *n)
{
    (void)c, (void)st, (void)n;
    return fmi2Error;
}

fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate st, fmi2Byte b[], size_t n)
{
    (void)c, (void)st, (void)b, (void)n;
    return fmi2Error;
}

fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *st)
{
    (void)c, (void)b, (void)n, (void)st;
    return fmi2Error;
}

fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real du[], fmi2Real dz[])
{
    (void)c, (void)u, (void)nu, (void)z, (void)nz, (void)du, (void)dz;
    return fmi2Error;
}
