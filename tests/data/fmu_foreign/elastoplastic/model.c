/* EPStage. Elasto-plastic friction (Dupont, Hayward, Armstrong, Altpeter 2002):
 *   z' = w (1 - alpha(z, w) sigma0 z sgn(w) / fss(w)),  F = sigma0 z + sigma1 z' + sigma2 w,
 *   fss(w) = Fc + (Fs - Fc) exp(-(w/vs)^2), zmax = fss / sigma0, zba = zbaRatio zmax;
 *   alpha = 0 for |z| <= zba or sgn(z) != sgn(w), 1 for |z| >= zmax, a half sine between
 *   (true stiction: no drift below break-away).
 * J1 w' = km u - F - Ts, J2 wl' = Ts, Ts = k (phi - phil) + d (w - wl); semi-implicit Euler,
 * nSub sub-steps. Embedded code: one instance per process (fmi2Reset restarts it). */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

void model_defaults(Model *m)
{
    memset(m, 0, sizeof *m);
    m->r[R_J1] = 1.0e-4;
    m->r[R_J2] = 2.0e-4;
    m->r[R_K] = 0.5;
    m->r[R_D] = 2.0e-4;
    m->r[R_KM] = 0.05;
    m->r[R_FC] = 6.2e-3;
    m->r[R_FS] = 8.5e-3;
    m->r[R_VS] = 0.08;
    m->r[R_S0] = 25.0;
    m->r[R_S1] = 0.03;
    m->r[R_S2] = 1.5e-4;
    m->r[R_ZBA] = 0.7;
    m->i[I_NSUB] = 40;
}

int model_settable(const Model *m, int type, unsigned vr, int stepping)
{
    (void)m;
    if (type == 'r' && vr == R_U) {
        return 1;
    }
    return !stepping && !(type == 'r' && vr <= R_F);
}

int model_init(Model *m, char *msg, unsigned long n)
{
    double *r = m->r;
    if (!(r[R_J1] > 0 && r[R_J2] > 0 && r[R_S0] > 0 && r[R_VS] > 0 && r[R_FC] > 0 && r[R_FS] >= r[R_FC] &&
          r[R_ZBA] > 0 && r[R_ZBA] < 1 && m->i[I_NSUB] >= 1)) {
        snprintf(msg, n, "need J1, J2, sigma0, vs, Fc > 0, Fs >= Fc, 0 < zbaRatio < 1, nSub >= 1");
        return -1;
    }
    r[R_PHI] = r[R_W] = r[R_LPHI] = r[R_LW] = r[R_Z] = r[R_F] = 0.0;
    return 0;
}

static double sgn(double x) { return (x > 0) - (x < 0); }

int model_step(Model *m, double t, double h, char *msg, unsigned long n)
{
    double *r = m->r;
    double hs = h / m->i[I_NSUB];
    (void)t;
    (void)msg;
    (void)n;
    for (int s = 0; s < m->i[I_NSUB]; s++) {
        double w = r[R_W], z = r[R_Z];
        double v = w / r[R_VS];
        double fss = r[R_FC] + (r[R_FS] - r[R_FC]) * exp(-v * v);
        double zmax = fss / r[R_S0], zba = r[R_ZBA] * zmax, alpha = 0.0;
        if (sgn(z) == sgn(w) && fabs(z) > zba) {
            alpha = fabs(z) >= zmax ? 1.0 : 0.5 * sin(M_PI * (fabs(z) - 0.5 * (zmax + zba)) / (zmax - zba)) + 0.5;
        }
        double dz = w * (1.0 - alpha * r[R_S0] * z * sgn(w) / fss);
        double f = r[R_S0] * z + r[R_S1] * dz + r[R_S2] * w;
        double ts = r[R_K] * (r[R_PHI] - r[R_LPHI]) + r[R_D] * (w - r[R_LW]);
        r[R_W] += hs * (r[R_KM] * r[R_U] - f - ts) / r[R_J1];
        r[R_LW] += hs * ts / r[R_J2];
        r[R_PHI] += hs * r[R_W];
        r[R_LPHI] += hs * r[R_LW];
        r[R_Z] += hs * dz;
        r[R_F] = f;
    }
    return fmi2OK;
}
