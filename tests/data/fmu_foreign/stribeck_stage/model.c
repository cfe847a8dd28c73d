/* StribeckStage: J1 phi'' = km u - k (phi - phi_l) - d (w - w_l) - F(w),  J2 phi_l'' = k (...) + d (...)
 * F(w) = (Fc + (Fs - Fc) exp(-(w/vs)^2)) tanh(w/vEps) + b w  (b only if viscous)
 * classical RK4, nSub sub-steps per communication step. */
#include <math.h>
#include <stdio.h>

#include "fmi2Functions.h"
#include "model.h"

void model_defaults(Model *m)
{
    static const double r0[NR] = {[R_J1] = 1.0e-4, [R_J2] = 2.5e-4, [R_K] = 0.6, [R_D] = 3.0e-4, [R_KM] = 0.05,
                                  [R_FC] = 6.0e-3, [R_FS] = 9.0e-3, [R_VS] = 0.05, [R_VEPS] = 2.0e-3,
                                  [R_B] = 2.0e-4, [R_RATIO] = 1.5};
    for (int k = 0; k < NR; k++) {
        m->r[k] = r0[k];
    }
    m->i[I_NSUB] = 16;
    m->b[B_VISCOUS] = 1;
}

int model_settable(const Model *m, int type, unsigned vr, int stepping)
{
    (void)m;
    if (type == 'r') {
        if (vr == R_U) {
            return 1;
        }
        if (vr == R_FC || vr == R_FS || vr == R_B) {
            return 1; /* tunable */
        }
        return !stepping && vr >= R_J1 && vr <= R_B; /* fixed parameters */
    }
    return !stepping; /* nSub, viscous: fixed */
}

static void rhs(const Model *m, const double x[4], double dx[4])
{
    const double *r = m->r;
    double w = x[1];
    double g = r[R_FC] + (r[R_FS] - r[R_FC]) * exp(-(w / r[R_VS]) * (w / r[R_VS]));
    double f = g * tanh(w / r[R_VEPS]) + (m->b[B_VISCOUS] ? r[R_B] * w : 0.0);
    double s = r[R_K] * (x[0] - x[2]) + r[R_D] * (x[1] - x[3]);
    dx[0] = x[1];
    dx[1] = (r[R_KM] * r[R_U] - s - f) / r[R_J1];
    dx[2] = x[3];
    dx[3] = s / r[R_J2];
}

int model_init(Model *m, char *msg, unsigned long n)
{
    double *r = m->r;
    if (!(r[R_J1] > 0 && r[R_J2] > 0 && r[R_VS] > 0 && r[R_VEPS] > 0 && r[R_FC] >= 0 && r[R_FS] >= r[R_FC])) {
        snprintf(msg, n, "parameters out of range (J1, J2, friction.vs, friction.vEps > 0, 0 <= Fc <= Fs)");
        return -1;
    }
    if (m->i[I_NSUB] < 1 || m->i[I_NSUB] > 1000) {
        snprintf(msg, n, "nSub = %d: expected 1 .. 1000", m->i[I_NSUB]);
        return -1;
    }
    r[R_RATIO] = r[R_FC] > 0 ? r[R_FS] / r[R_FC] : 0.0;
    r[R_PHI] = r[R_W] = r[R_LPHI] = r[R_LW] = r[R_DPHI] = r[R_TM] = 0.0;
    return 0;
}

int model_step(Model *m, double t, double h, char *msg, unsigned long n)
{
    double *r = m->r;
    double x[4] = {r[R_PHI], r[R_W], r[R_LPHI], r[R_LW]};
    int sub = m->i[I_NSUB];
    double hs = h / sub;
    (void)t;
    for (int s = 0; s < sub; s++) {
        double k1[4], k2[4], k3[4], k4[4], y[4];
        rhs(m, x, k1);
        for (int i = 0; i < 4; i++) y[i] = x[i] + 0.5 * hs * k1[i];
        rhs(m, y, k2);
        for (int i = 0; i < 4; i++) y[i] = x[i] + 0.5 * hs * k2[i];
        rhs(m, y, k3);
        for (int i = 0; i < 4; i++) y[i] = x[i] + hs * k3[i];
        rhs(m, y, k4);
        for (int i = 0; i < 4; i++) x[i] += hs / 6.0 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i]);
    }
    if (!isfinite(x[0]) || !isfinite(x[1])) {
        snprintf(msg, n, "the integration diverged (nSub = %d too small?)", sub);
        return fmi2Error;
    }
    r[R_PHI] = x[0];
    r[R_W] = x[1];
    r[R_DPHI] = x[1];
    r[R_LPHI] = x[2];
    r[R_LW] = x[3];
    r[R_TM] = r[R_KM] * r[R_U];
    return fmi2OK;
}
