/*
 * fmu_model.h - the example FMUs' model interface (HOST ONLY; docs/fmu.md).
 *
 * fmu_slave.c implements the FMI 2.0 co-simulation functions once; each model (fmu/NAME/
 * model.c) supplies its state and three functions, and fmugen.py writes the model's
 * variable table (vars.c: value references = indices into r[], start values, causality)
 * and modelDescription.xml from the one spec fmu/NAME/model.yaml.
 *
 * All variables are Real; r[] holds every variable's present value (parameters and the
 * input set by the importer, outputs written by the model).
 */
#ifndef FMU_MODEL_H
#define FMU_MODEL_H

#include <math.h>
#include <stddef.h>
#include <stdio.h>

enum { FMU_PARAMETER = 0, FMU_INPUT = 1, FMU_OUTPUT = 2 };

/* vars.c (generated) */
extern const char fmu_guid[];
extern const unsigned fmu_nvars;
extern const double fmu_start[];
extern const unsigned char fmu_causality[];
extern const char *const fmu_names[];

/* model.c */
size_t model_size(void);
/* At fmi2ExitInitializationMode: check the parameters in r, set the state, write the
 * outputs to r. 0, or -1 with a message naming the parameter. */
int model_init(void *m, double *r, char *msg, size_t msglen);
/* Advance from t by h with the input r held; write the outputs. 0, or -1 with a message. */
int model_step(void *m, double *r, double t, double h, char *msg, size_t msglen);

/* ---- helpers the models share (static: each FMU is its own shared object) ---- */

/* Each r[index[i]] finite and > 0 (strictly positive) or >= 0; else -1 with a message
 * naming the first parameter that is not. */
static inline int fmu_check_parameters(const double *r, const unsigned *index, size_t n, int strictly_positive,
                                       char *msg, size_t msglen)
{
    for (size_t i = 0; i < n; i++) {
        double v = r[index[i]];
        if (!isfinite(v) || (strictly_positive ? !(v > 0.0) : !(v >= 0.0))) {
            snprintf(msg, msglen, "parameter %s = %g: must be finite and %s 0", fmu_names[index[i]], v,
                     strictly_positive ? ">" : ">=");
            return -1;
        }
    }
    return 0;
}

/* The substeps parameter: a whole number 1 .. FMU_MAX_SUBSTEPS; else -1 with a message. */
#define FMU_MAX_SUBSTEPS 10000
static inline int fmu_check_substeps(double substeps, char *msg, size_t msglen)
{
    if (!(substeps >= 1.0 && substeps <= (double)FMU_MAX_SUBSTEPS) || substeps != floor(substeps)) {
        snprintf(msg, msglen, "parameter substeps = %g: a whole number 1 .. %d", substeps, FMU_MAX_SUBSTEPS);
        return -1;
    }
    return 0;
}

/* dx/dt of a model's state x (n values) under parameters p and input u. */
typedef void (*fmu_rhs_t)(const double *p, const double *x, double u, double *dx);
#define FMU_MAX_STATES 8

/* Advance x (n <= FMU_MAX_STATES values) from t by h with the input u held, in `substeps`
 * classical Runge-Kutta steps; 0, or -1 with a message when the input or the state is not
 * finite (the state is then not to be used). */
static inline int fmu_rk4_step(fmu_rhs_t rhs, const double *p, double *x, unsigned n, double u, double t,
                               double h, unsigned substeps, char *msg, size_t msglen)
{
    double hs = h / (double)substeps;
    if (!isfinite(u)) {
        snprintf(msg, msglen, "input u = %g is not finite at t = %g s", u, t);
        return -1;
    }
    if (n > FMU_MAX_STATES) {
        snprintf(msg, msglen, "%u states: at most %d", n, FMU_MAX_STATES);
        return -1;
    }
    for (unsigned s = 0; s < substeps; s++) {
        double k1[FMU_MAX_STATES], k2[FMU_MAX_STATES], k3[FMU_MAX_STATES], k4[FMU_MAX_STATES], y[FMU_MAX_STATES];
        rhs(p, x, u, k1);
        for (unsigned i = 0; i < n; i++) {
            y[i] = x[i] + 0.5 * hs * k1[i];
        }
        rhs(p, y, u, k2);
        for (unsigned i = 0; i < n; i++) {
            y[i] = x[i] + 0.5 * hs * k2[i];
        }
        rhs(p, y, u, k3);
        for (unsigned i = 0; i < n; i++) {
            y[i] = x[i] + hs * k3[i];
        }
        rhs(p, y, u, k4);
        for (unsigned i = 0; i < n; i++) {
            x[i] += hs / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
    }
    for (unsigned i = 0; i < n; i++) {
        if (!isfinite(x[i])) {
            snprintf(msg, msglen, "the state diverged at t = %g s (reduce the step or raise substeps)", t + h);
            return -1;
        }
    }
    return 0;
}

#endif /* FMU_MODEL_H */
