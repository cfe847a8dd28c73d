/* bls_cs. Motor: Jm wm' = km u - Fm - Ts; Fm Coulomb Fc sign(wm) + bm wm while sliding; the
 * motor sticks (wm = 0) when wm crosses zero or rests while |km u - Ts| <= Fs (Karnopp).
 * Shaft through a backlash of total width gap: Ts = k dz(qm - ql) + d (wm - wl) in contact,
 * dz the dead zone of half width gap/2. Load: Jl wl' = Ts - bl wl. Explicit sub-steps of at
 * most hMax. Every step with a new contact returns fmi2Warning (warnOnImpact true). */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

void model_defaults(Model *m)
{
    memset(m, 0, sizeof *m);
    m->r[R_JM] = 1.0e-4;
    m->r[R_JL] = 2.0e-4;
    m->r[R_K] = 0.5;
    m->r[R_D] = 3.0e-4;
    m->r[R_GAP] = 1.0e-3;
    m->r[R_KM] = 0.05;
    m->r[R_FC] = 5.5e-3;
    m->r[R_FS] = 7.0e-3;
    m->r[R_BM] = 1.0e-4;
    m->r[R_BL] = 5.0e-5;
    m->r[R_HMAX] = 1.0e-5;
    m->b[B_WARN] = 1;
}

int model_settable(const Model *m, int type, unsigned vr, int stepping)
{
    (void)m;
    if (type == 'r' && vr == R_U) {
        return 1;
    }
    if (type == 'i' || (type == 'r' && vr <= R_WL)) {
        return 0;
    }
    return !stepping;
}

int model_init(Model *m, char *msg, unsigned long n)
{
    double *r = m->r;
    if (!(r[R_JM] > 0 && r[R_JL] > 0 && r[R_GAP] >= 0 && r[R_FC] >= 0 && r[R_FS] >= r[R_FC] && r[R_HMAX] > 0)) {
        snprintf(msg, n, "Jm, Jl, hMax > 0, gap >= 0, 0 <= Fc <= Fs needed");
        return -1;
    }
    r[R_QM] = r[R_QL] = r[R_WM] = r[R_WL] = 0.0;
    m->i[I_IMPACTS] = 0;
    m->contact = 0;
    return 0;
}

static double sgn(double x) { return (x > 0) - (x < 0); }

int model_step(Model *m, double t, double h, char *msg, unsigned long n)
{
    double *r = m->r;
    int sub = (int)ceil(h / r[R_HMAX]), impacts = 0;
    double hs = h / sub, half = 0.5 * r[R_GAP];
    for (int s = 0; s < sub; s++) {
        double z = r[R_QM] - r[R_QL], dz = 0.0;
        int contact = fabs(z) > half;
        if (contact) {
            dz = z - sgn(z) * half;
        }
        if (contact && !m->contact) {
            impacts++;
        }
        m->contact = contact;
        double ts = contact ? r[R_K] * dz + r[R_D] * (r[R_WM] - r[R_WL]) : 0.0;
        double ta = r[R_KM] * r[R_U] - ts, wm = r[R_WM], wn;
        if (wm == 0.0) {
            wn = fabs(ta) > r[R_FS] ? hs * (ta - r[R_FC] * sgn(ta)) / r[R_JM] : 0.0;
        } else {
            wn = wm + hs * (ta - r[R_FC] * sgn(wm) - r[R_BM] * wm) / r[R_JM];
            if (wn * wm < 0.0 && fabs(ta) <= r[R_FS]) {
                wn = 0.0;
            }
        }
        r[R_WM] = wn;
        r[R_QM] += hs * wn;
        r[R_WL] += hs * (ts - r[R_BL] * r[R_WL]) / r[R_JL];
        r[R_QL] += hs * r[R_WL];
    }
    m->i[I_IMPACTS] += impacts;
    if (impacts && m->b[B_WARN]) {
        snprintf(msg, n, "backlash impact #%d at t = %.6f s", m->i[I_IMPACTS], t);
        return fmi2Warning;
    }
    return fmi2OK;
}
