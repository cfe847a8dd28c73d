/* msm_plant. Motor torque T: tau_i T' = km u_d - T, u_d the input of the previous
 * communication step (delay true) or the present one. Maxwell-slip friction: element i is a
 * spring k_i whose end slips when |k_i z_i| reaches Fmax_i; F = sum k_i z_i + b w1.
 * J1 w1' = T - F - k (phi1 - phi2) - d (w1 - w2); J2 w2' = k (...) + d (...).
 * Semi-implicit Euler, sub-steps of at most 0.2 sqrt(tolerance) s (the tolerance of
 * fmi2SetupExperiment, else 1e-4: 2 ms; the DefaultExperiment's 1e-8: 20 us). Elements from resources/elements.csv
 * (the first nElem rows). failMode 1 / 2 / 3: fmi2DoStep returns fmi2Discard / fmi2Pending /
 * fmi2Fatal from t >= failTime, 4: it crashes, 5: it never returns (tests of the importer). */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "fmi2Functions.h"
#include "model.h"

void model_defaults(Model *m)
{
    memset(m, 0, sizeof *m);
    m->r[R_TAUI] = 5.0e-4;
    m->r[R_J1] = 1.2e-4;
    m->r[R_J2] = 2.0e-4;
    m->r[R_K] = 0.5;
    m->r[R_D] = 2.0e-4;
    m->r[R_KM] = 0.05;
    m->r[R_B] = 1.0e-4;
    m->r[R_FAILT] = 1.0e9;
    m->i[I_NELEM] = 3;
    m->b[B_DELAY] = 1;
}

int model_settable(const Model *m, int type, unsigned vr, int stepping)
{
    (void)m;
    if (type == 'r' && vr == R_U) {
        return 1;
    }
    if (type == 'r' && (vr == R_PHI1 || vr == R_PHI2 || vr == R_W1 || vr == R_W2 || vr == R_TAU || vr == R_FTOT)) {
        return 0;
    }
    return !stepping;
}

static int read_elements(Model *m, char *msg, unsigned long n)
{
    char path[1100], line[256];
    snprintf(path, sizeof path, "%s/elements.csv", m->resources);
    FILE *f = fopen(path, "r");
    if (f == NULL) {
        snprintf(msg, n, "cannot open %s (the resource location given to fmi2Instantiate)", path);
        return -1;
    }
    m->n_file = 0;
    while (fgets(line, sizeof line, f) != NULL && m->n_file < MSM_MAX) {
        double k, fm;
        if (line[0] == '#' || sscanf(line, "%lf,%lf", &k, &fm) != 2) {
            continue;
        }
        m->k[m->n_file] = k;
        m->fmax[m->n_file] = fm;
        m->n_file++;
    }
    fclose(f);
    return 0;
}

int model_init(Model *m, char *msg, unsigned long n)
{
    if (read_elements(m, msg, n) != 0) {
        return -1;
    }
    if (m->i[I_NELEM] < 1 || m->i[I_NELEM] > m->n_file) {
        snprintf(msg, n, "nElem = %d: resources/elements.csv has %d elements", m->i[I_NELEM], m->n_file);
        return -1;
    }
    if (!(m->r[R_TAUI] > 0 && m->r[R_J1] > 0 && m->r[R_J2] > 0)) {
        snprintf(msg, n, "tau_i, J1, J2 must be > 0");
        return -1;
    }
    m->r[R_FTOT] = 0.0;
    for (int i = 0; i < m->i[I_NELEM]; i++) {
        m->z[i] = 0.0;
        m->r[R_FTOT] += m->fmax[i];
    }
    m->r[R_PHI1] = m->r[R_PHI2] = m->r[R_W1] = m->r[R_W2] = m->r[R_TAU] = 0.0;
    m->u_prev = m->r[R_U];
    return 0;
}

int model_step(Model *m, double t, double h, char *msg, unsigned long n)
{
    double *r = m->r;
    if (m->i[I_FAILMODE] != 0 && t + 0.5 * h >= r[R_FAILT]) {
        static const int st[] = {fmi2OK, fmi2Discard, fmi2Pending, fmi2Fatal};
        while (m->i[I_FAILMODE] == 5) {
            r[R_PHI1] += 1.0; /* a hang (an endless solver loop), on purpose */
        }
        if (m->i[I_FAILMODE] == 4) {
            volatile double *nowhere = NULL;
            r[R_PHI1] = *nowhere; /* a crash (SIGSEGV), on purpose */
        }
        int mode = m->i[I_FAILMODE] >= 1 && m->i[I_FAILMODE] <= 3 ? m->i[I_FAILMODE] : 1;
        snprintf(msg, n, "failMode %d at t = %g s (on purpose)", mode, t);
        return st[mode];
    }
    double ud = m->b[B_DELAY] ? m->u_prev : r[R_U];
    m->u_prev = r[R_U];
    int sub = (int)ceil(h / (0.2 * sqrt(m->tolerance)));
    double hs = h / sub;
    for (int s = 0; s < sub; s++) {
        r[R_TAU] += hs / r[R_TAUI] * (r[R_KM] * ud - r[R_TAU]);
        double f = r[R_B] * r[R_W1];
        for (int i = 0; i < m->i[I_NELEM]; i++) {
            f += m->k[i] * m->z[i];
        }
        double sh = r[R_K] * (r[R_PHI1] - r[R_PHI2]) + r[R_D] * (r[R_W1] - r[R_W2]);
        r[R_W1] += hs * (r[R_TAU] - f - sh) / r[R_J1];
        r[R_W2] += hs * sh / r[R_J2];
        double dphi = hs * r[R_W1];
        r[R_PHI1] += dphi;
        r[R_PHI2] += hs * r[R_W2];
        for (int i = 0; i < m->i[I_NELEM]; i++) {
            double zmax = m->fmax[i] / m->k[i];
            m->z[i] += dphi;
            if (m->z[i] > zmax) m->z[i] = zmax;
            if (m->z[i] < -zmax) m->z[i] = -zmax;
        }
    }
    return fmi2OK;
}
