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

static void lugre_rhs(const double *p, const double *x, double u, double *dx)
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
    if (fmu_check_parameters(r, positive, sizeof positive / sizeof positive[0], 1, msg, msglen) != 0 ||
        fmu_check_parameters(r, nonneg, sizeof nonneg / sizeof nonneg[0], 0, msg, msglen) != 0) {
        return -1;
    }
    if (!(r[VR_Fs] >= r[VR_Fc]) || !isfinite(r[VR_Fs])) {
        snprintf(msg, msglen, "parameter Fs = %g: must be >= Fc = %g", r[VR_Fs], r[VR_Fc]);
        return -1;
    }
    double sub = r[VR_substeps];
    if (fmu_check_substeps(sub, msg, msglen) != 0) {
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
    if (fmu_rk4_step(lugre_rhs, m->p, m->x, 5, r[VR_u], t, h, m->substeps, msg, msglen) != 0) {
        return -1;
    }
    lugre_outputs(m, r);
    return 0;
}
