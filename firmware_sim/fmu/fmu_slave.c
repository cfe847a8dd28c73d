/*
 * fmu_slave.c - FMI 2.0 co-simulation slave around one model of fmu_model.h (HOST ONLY).
 *
 * States: instantiated -> (EnterInitializationMode) initialisation -> (Exit...) stepping ->
 * (Terminate) terminated; a model error puts the instance in the error state (only
 * Reset / FreeInstance then). Parameters may be set before the end of initialisation, the
 * input at any time before Terminate. Model exchange, FMU states, directional and input
 * derivatives, Integer/Boolean/String variables: not provided (fmi2Error, said in the log).
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"
#include "fmu_model.h"

typedef enum { S_INSTANTIATED, S_INIT, S_STEP, S_TERMINATED, S_ERROR } slave_state_t;

typedef struct {
    fmi2CallbackFunctions cb;
    char name[128];
    slave_state_t state;
    int logging;
    double t;
    double *r;
    void *model;
} slave_t;

static void slave_log(slave_t *s, fmi2Status st, const char *fmt, ...)
{
    if (s == NULL || s->cb.logger == NULL) {
        return;
    }
    char msg[512];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    s->cb.logger(s->cb.componentEnvironment, s->name, st, st == fmi2OK ? "logAll" : "logStatusError", "%s", msg);
}

static fmi2Status slave_error(slave_t *s, const char *fmt, const char *what)
{
    slave_log(s, fmi2Error, fmt, what);
    return fmi2Error;
}

const char *fmi2GetTypesPlatform(void)
{
    return fmi2TypesPlatform;
}

const char *fmi2GetVersion(void)
{
    return fmi2Version;
}

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[])
{
    (void)n;
    (void)cats;
    ((slave_t *)c)->logging = on;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String resources,
                              const fmi2CallbackFunctions *cb, fmi2Boolean visible, fmi2Boolean logging)
{
    (void)resources;
    (void)visible;
    if (cb == NULL || cb->allocateMemory == NULL || cb->freeMemory == NULL) {
        return NULL;
    }
    slave_t *s = cb->allocateMemory(1, sizeof *s);
    if (s == NULL) {
        return NULL;
    }
    s->cb = *cb;
    snprintf(s->name, sizeof s->name, "%s", name ? name : "");
    s->logging = logging;
    if (type != fmi2CoSimulation) {
        slave_log(s, fmi2Error, "fmi2Instantiate: this FMU is co-simulation only");
        cb->freeMemory(s);
        return NULL;
    }
    if (guid == NULL || strcmp(guid, fmu_guid) != 0) {
        slave_log(s, fmi2Error, "fmi2Instantiate: GUID %s does not match the FMU's %s", guid ? guid : "(null)",
                  fmu_guid);
        cb->freeMemory(s);
        return NULL;
    }
    s->r = cb->allocateMemory(fmu_nvars, sizeof(double));
    s->model = cb->allocateMemory(1, model_size());
    if (s->r == NULL || s->model == NULL) {
        if (s->r) {
            cb->freeMemory(s->r);
        }
        if (s->model) {
            cb->freeMemory(s->model);
        }
        cb->freeMemory(s);
        return NULL;
    }
    memcpy(s->r, fmu_start, fmu_nvars * sizeof(double));
    s->state = S_INSTANTIATED;
    return s;
}

void fmi2FreeInstance(fmi2Component c)
{
    slave_t *s = c;
    if (s == NULL) {
        return;
    }
    void (*fr)(void *) = s->cb.freeMemory;
    fr(s->r);
    fr(s->model);
    fr(s);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tol_defined, fmi2Real tol, fmi2Real t0,
                               fmi2Boolean stop_defined, fmi2Real stop)
{
    (void)tol_defined;
    (void)tol;
    (void)stop_defined;
    (void)stop;
    slave_t *s = c;
    if (s->state != S_INSTANTIATED) {
        return slave_error(s, "fmi2SetupExperiment: only after fmi2Instantiate%s", "");
    }
    s->t = t0;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c)
{
    slave_t *s = c;
    if (s->state != S_INSTANTIATED) {
        return slave_error(s, "fmi2EnterInitializationMode: only after fmi2Instantiate%s", "");
    }
    s->state = S_INIT;
    return fmi2OK;
}

fmi2Status fmi2ExitInitializationMode(fmi2Component c)
{
    slave_t *s = c;
    char msg[300];
    if (s->state != S_INIT) {
        return slave_error(s, "fmi2ExitInitializationMode: not in initialisation mode%s", "");
    }
    if (model_init(s->model, s->r, msg, sizeof msg) != 0) {
        s->state = S_ERROR;
        return slave_error(s, "%s", msg);
    }
    s->state = S_STEP;
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c)
{
    ((slave_t *)c)->state = S_TERMINATED;
    return fmi2OK;
}

fmi2Status fmi2Reset(fmi2Component c)
{
    slave_t *s = c;
    memcpy(s->r, fmu_start, fmu_nvars * sizeof(double));
    memset(s->model, 0, model_size());
    s->state = S_INSTANTIATED;
    s->t = 0.0;
    return fmi2OK;
}

static fmi2Status slave_check_vr(slave_t *s, const fmi2ValueReference vr[], size_t n, const char *fn)
{
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= fmu_nvars) {
            slave_log(s, fmi2Error, "%s: no variable with value reference %u", fn, vr[i]);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Real v[])
{
    slave_t *s = c;
    if (slave_check_vr(s, vr, n, "fmi2GetReal") != fmi2OK) {
        return fmi2Error;
    }
    for (size_t i = 0; i < n; i++) {
        v[i] = s->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Real v[])
{
    slave_t *s = c;
    if (slave_check_vr(s, vr, n, "fmi2SetReal") != fmi2OK) {
        return fmi2Error;
    }
    for (size_t i = 0; i < n; i++) {
        unsigned char k = fmu_causality[vr[i]];
        if (k == FMU_OUTPUT || (k == FMU_PARAMETER && s->state != S_INSTANTIATED && s->state != S_INIT) ||
            s->state == S_TERMINATED || s->state == S_ERROR) {
            slave_log(s, fmi2Error, "fmi2SetReal: variable '%s' cannot be set now", fmu_names[vr[i]]);
            return fmi2Error;
        }
        s->r[vr[i]] = v[i];
    }
    return fmi2OK;
}

/* the body of a function this FMU does not provide; args: (void) casts of its arguments */
#define SLAVE_UNSUPPORTED(args, what)                                  \
    {                                                                   \
        slave_log((slave_t *)c, fmi2Error, "%s: not supported", what); \
        args;                                                           \
        return fmi2Error;                                               \
    }
#define V(x) (void)(x)

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Integer v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(v)), "fmi2GetInteger (every variable is Real)")
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(v)), "fmi2GetBoolean (every variable is Real)")
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(v)), "fmi2GetString (every variable is Real)")
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Integer v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(v)), "fmi2SetInteger (every variable is Real)")
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(v)), "fmi2SetBoolean (every variable is Real)")
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(v)), "fmi2SetString (every variable is Real)")
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *st) SLAVE_UNSUPPORTED((V(st)), "fmi2GetFMUstate")
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate st) SLAVE_UNSUPPORTED((V(st)), "fmi2SetFMUstate")
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *st) SLAVE_UNSUPPORTED((V(st)), "fmi2FreeFMUstate")
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate st, size_t *n)
    SLAVE_UNSUPPORTED((V(st), V(n)), "fmi2SerializedFMUstateSize")
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate st, fmi2Byte b[], size_t n)
    SLAVE_UNSUPPORTED((V(st), V(b), V(n)), "fmi2SerializeFMUstate")
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *st)
    SLAVE_UNSUPPORTED((V(b), V(n), V(st)), "fmi2DeSerializeFMUstate")
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference z[], size_t nz, const fmi2Real dv[], fmi2Real dz[])
    SLAVE_UNSUPPORTED((V(u), V(nu), V(z), V(nz), V(dv), V(dz)), "fmi2GetDirectionalDerivative")
fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer order[], const fmi2Real v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(order), V(v)), "fmi2SetRealInputDerivatives")
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer order[], fmi2Real v[])
    SLAVE_UNSUPPORTED((V(vr), V(n), V(order), V(v)), "fmi2GetRealOutputDerivatives")
fmi2Status fmi2CancelStep(fmi2Component c) SLAVE_UNSUPPORTED((void)0, "fmi2CancelStep")
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind k, fmi2Status *v)
    SLAVE_UNSUPPORTED((V(k), V(v)), "fmi2GetStatus")
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind k, fmi2Real *v)
    SLAVE_UNSUPPORTED((V(k), V(v)), "fmi2GetRealStatus")
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind k, fmi2Integer *v)
    SLAVE_UNSUPPORTED((V(k), V(v)), "fmi2GetIntegerStatus")
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind k, fmi2Boolean *v)
    SLAVE_UNSUPPORTED((V(k), V(v)), "fmi2GetBooleanStatus")
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind k, fmi2String *v)
    SLAVE_UNSUPPORTED((V(k), V(v)), "fmi2GetStringStatus")

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real h, fmi2Boolean no_set_prior)
{
    (void)no_set_prior;
    slave_t *s = c;
    char msg[300];
    if (s->state != S_STEP) {
        return slave_error(s, "fmi2DoStep: not initialised (or terminated, or failed before)%s", "");
    }
    if (!(h > 0.0)) {
        return slave_error(s, "fmi2DoStep: the step size must be > 0%s", "");
    }
    if (model_step(s->model, s->r, t, h, msg, sizeof msg) != 0) {
        s->state = S_ERROR;
        return slave_error(s, "%s", msg);
    }
    s->t = t + h;
    return fmi2OK;
}
