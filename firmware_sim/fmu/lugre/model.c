/* lugre/model.c - two-mass plant with LuGre friction at the motor (model.yaml). */
#include <math.h>
#include <stdio.h>

#include "fmu_model.h"
#include "vars.h"

typedef struct {
    double x[5]; /* th1, w1, th2, w2, z */
    double p[VR_substeps + 1];
    unsigned substeps;
} lugre_t;

size_t model_size(void)
{
    return sizeof(lugre_t);
}

static double lugre_g(const double *p, double w)
{
    double r = p[VR_vs] > 0.0 ? w / p[VR_vs] : 0.0;
    return p[VR_Fc] + (p[VR_Fs] - p[VR_Fc]) * exp(-r * r);
}

/* dz/dt and the friction torque at state x */
static double lugre_friction(const double *p, const double x[5], double *dz)
{
    double w = x[1];
    *dz = w - p[VR_sigma0] * fabs(w) * x[4] / lugre_g(p, w);
    return p[VR_sigma0] * x[4] + p[VR_sigma1] * *dz + p[VR_sigma2] * w;
}

static void lugre_rhs(const double *p, const double x[5], double u, double dx[5])
{
    double dz, f = lugre_friction(p, x, &dz);
    double spring = p[VR_k] * (x[0] - x[2]) + p[VR_c] * (x[1] - x[3]);
    dx[0] = x[1];
    dx[1] = (p[VR_km] * u - spring - f) / p[VR_j1];
    dx[2] = x[3];
    dx[3] = (spring - p[VR_load_viscous] * x[3]) / p[VR_j2];
    dx[4] = dz;
}

static void lugre_outputs(const lugre_t *m, double *r)
{
    double dz;
    r[VR_theta1] = m->x[0];
    r[VR_omega1] = m->x[1];
    r[VR_theta2] = m->x[2];
    r[VR_omega2] = m->x[3];
    r[VR_friction] = lugre_friction(m->p, m->x, &dz);
}

int model_init(void *mv, double *r, char *msg, size_t msglen)
{
    lugre_t *m = mv;
    static const unsigned positive[] = {VR_j1, VR_j2, VR_km, VR_Fc, VR_sigma0};
    static const unsigned nonneg[] = {VR_k, VR_c, VR_vs, VR_sigma1, VR_sigma2, VR_load_viscous};
    for (unsigned i = 0; i < sizeof positive / sizeof positive[0]; i++) {
        if (!(r[positive[i]] > 0.0) || !isfinite(r[positive[i]])) {
            snprintf(msg, msglen, "parameter %s = %g: must be finite and > 0", fmu_names[positive[i]], r[positive[i]]);
            return -1;
        }
    }
    for (unsigned i = 0; i < sizeof nonneg / sizeof nonneg[0]; i++) {
        if (!(r[nonneg[i]] >= 0.0) || !isfinite(r[nonneg[i]])) {
            snprintf(msg, msglen, "parameter %s = %g: must be finite and >= 0", fmu_names[nonneg[i]], r[nonneg[i]]);
            return -1;
        }
    }
    if (!(r[VR_Fs] >= r[VR_Fc]) || !isfinite(r[VR_Fs])) {
        snprintf(msg, msglen, "parameter Fs = %g: must be >= Fc = %g", r[VR_Fs], r[VR_Fc]);
        return -1;
    }
    double sub = r[VR_substeps];
    if (!(sub >= 1.0 && sub <= 10000.0) || sub != floor(sub)) {
        snprintf(msg, msglen, "parameter substeps = %g: a whole number 1 .. 10000", sub);
        return -1;
    }
    for (unsigned i = 0; i <= VR_substeps; i++) {
        m->p[i] = r[i];
    }
    m->substeps = (unsigned)sub;
    for (int i = 0; i < 5; i++) {
        m->x[i] = 0.0;
    }
    lugre_outputs(m, r);
    return 0;
}

int model_step(void *mv, double *r, double t, double h, char *msg, size_t msglen)
{
    lugre_t *m = mv;
    double u = r[VR_u], hs = h / (double)m->substeps;
    if (!isfinite(u)) {
        snprintf(msg, msglen, "input u = %g is not finite at t = %g s", u, t);
        return -1;
    }
    for (unsigned s = 0; s < m->substeps; s++) {
        double k1[5], k2[5], k3[5], k4[5], y[5];
        lugre_rhs(m->p, m->x, u, k1);
        for (int i = 0; i < 5; i++) {
            y[i] = m->x[i] + 0.5 * hs * k1[i];
        }
        lugre_rhs(m->p, y, u, k2);
        for (int i = 0; i < 5; i++) {
            y[i] = m->x[i] + 0.5 * hs * k2[i];
        }
        lugre_rhs(m->p, y, u, k3);
        for (int i = 0; i < 5; i++) {
            y[i] = m->x[i] + hs * k3[i];
        }
        lugre_rhs(m->p, y, u, k4);
        for (int i = 0; i < 5; i++) {
            m->x[i] += hs / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
    }
    for (int i = 0; i < 5; i++) {
        if (!isfinite(m->x[i])) {
            snprintf(msg, msglen, "the state diverged at t = %g s (reduce the step or raise substeps)", t + h);
            return -1;
        }
    }
    lugre_outputs(m, r);
    return 0;
}
