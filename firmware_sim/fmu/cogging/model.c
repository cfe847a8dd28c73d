/* cogging/model.c - two-mass plant with cogging torque and Dahl friction (model.yaml). */
#include <math.h>
#include <stdio.h>

#include "fmu_model.h"
#include "vars.h"

typedef struct {
    double x[5]; /* th1, w1, th2, w2, z */
    double p[VR_substeps + 1];
    unsigned substeps;
} cogging_t;

size_t model_size(void)
{
    return sizeof(cogging_t);
}

static double cogging_torque(const double *p, double th1)
{
    return p[VR_cogging_amplitude] * sin(p[VR_cogging_periods] * th1);
}

static void cogging_rhs(const double *p, const double *x, double u, double *dx)
{
    double w = x[1];
    double dz = w - p[VR_sigma0] * fabs(w) * x[4] / p[VR_Fc];
    double f = p[VR_sigma0] * x[4] + p[VR_viscous] * w;
    double spring = p[VR_k] * (x[0] - x[2]) + p[VR_c] * (x[1] - x[3]);
    dx[0] = w;
    dx[1] = (p[VR_km] * u - cogging_torque(p, x[0]) - spring - f) / p[VR_j1];
    dx[2] = x[3];
    dx[3] = (spring - p[VR_load_viscous] * x[3]) / p[VR_j2];
    dx[4] = dz;
}

static void cogging_outputs(const cogging_t *m, double *r)
{
    r[VR_theta1] = m->x[0];
    r[VR_omega1] = m->x[1];
    r[VR_theta2] = m->x[2];
    r[VR_omega2] = m->x[3];
    r[VR_cogging] = cogging_torque(m->p, m->x[0]);
}

int model_init(void *mv, double *r, char *msg, size_t msglen)
{
    cogging_t *m = mv;
    static const unsigned positive[] = {VR_j1, VR_j2, VR_km, VR_Fc, VR_sigma0};
    static const unsigned nonneg[] = {VR_k, VR_c, VR_viscous, VR_load_viscous, VR_cogging_amplitude,
                                      VR_cogging_periods};
    if (fmu_check_parameters(r, positive, sizeof positive / sizeof positive[0], 1, msg, msglen) != 0 ||
        fmu_check_parameters(r, nonneg, sizeof nonneg / sizeof nonneg[0], 0, msg, msglen) != 0) {
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
    cogging_outputs(m, r);
    return 0;
}

int model_step(void *mv, double *r, double t, double h, char *msg, size_t msglen)
{
    cogging_t *m = mv;
    if (fmu_rk4_step(cogging_rhs, m->p, m->x, 5, r[VR_u], t, h, m->substeps, msg, msglen) != 0) {
        return -1;
    }
    cogging_outputs(m, r);
    return 0;
}
