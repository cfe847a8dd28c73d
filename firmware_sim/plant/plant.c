/* plant.c - see plant.h. Host simulation only. */
#include "plant.h"

#include <math.h>
#include <stdio.h>

#define PLANT_MAX_EVENTS 8
#define PLANT_BISECT 50
#define PLANT_TWO_PI 6.283185307179586476925

int plant_check_params(const plant_params_t *p, char *err, size_t errlen)
{
    const struct {
        const char *name;
        double v;
        int positive; /* 1: > 0, 0: >= 0 */
    } f[] = {
        {"j1", p->j1, 1}, {"j2", p->j2, 1}, {"k", p->k, 0}, {"c", p->c, 0}, {"km", p->km, 1},
        {"coulomb", p->coulomb, 0}, {"static", p->stat, 0}, {"stribeck_velocity", p->stribeck_vel, 0},
        {"viscous", p->viscous, 0}, {"load_viscous", p->load_viscous, 0}, {"noise_std", p->noise_std, 0},
    };
    for (size_t i = 0; i < sizeof f / sizeof f[0]; i++) {
        if (!isfinite(f[i].v) || f[i].v < 0.0 || (f[i].positive && f[i].v == 0.0)) {
            snprintf(err, errlen, "%s = %g: must be finite and %s", f[i].name, f[i].v,
                     f[i].positive ? "> 0" : ">= 0");
            return -1;
        }
    }
    if (!isfinite(p->coulomb_asym) || fabs(p->coulomb_asym) > 0.9) {
        snprintf(err, errlen, "coulomb_asymmetry = %g: must be in [-0.9, 0.9]", p->coulomb_asym);
        return -1;
    }
    if (!isfinite(p->coulomb_pos) || fabs(p->coulomb_pos) > 0.9) {
        snprintf(err, errlen, "coulomb_position = %g: must be in [-0.9, 0.9]", p->coulomb_pos);
        return -1;
    }
    if (p->stat < p->coulomb * (1.0 + fabs(p->coulomb_asym))) {
        snprintf(err, errlen, "static = %g: must be >= coulomb (1 + |coulomb_asymmetry|) = %g", p->stat,
                 p->coulomb * (1.0 + fabs(p->coulomb_asym)));
        return -1;
    }
    if (p->substeps < 1u || p->substeps > 10000u) {
        snprintf(err, errlen, "substeps = %u: must be 1 .. 10000", (unsigned)p->substeps);
        return -1;
    }
    return 0;
}

int plant_init(plant_t *pl, const plant_params_t *p, char *err, size_t errlen)
{
    if (plant_check_params(p, err, errlen) != 0) {
        return -1;
    }
    pl->p = *p;
    plant_set_state(pl, 0.0, 0.0, 0.0, 0.0);
    pl->t = 0.0;
    pl->events = 0u;
    pl->slow_steps = 0u;
    pl->fast_dt = 0.0;
    pl->count = p->counts_per_rev ? PLANT_TWO_PI / (double)p->counts_per_rev : 0.0;
    pl->per_count = p->counts_per_rev ? (double)p->counts_per_rev / PLANT_TWO_PI : 0.0;
    pl->rng = p->seed;
    pl->has_spare = 0;
    pl->spare = 0.0;
    return 0;
}

void plant_set_state(plant_t *pl, double th1, double w1, double th2, double w2)
{
    if (!isfinite(th1) || !isfinite(w1) || !isfinite(th2) || !isfinite(w2)) {
        return; /* keep the present state */
    }
    pl->x[0] = th1;
    pl->x[1] = w1;
    pl->x[2] = th2;
    pl->x[3] = w2;
    pl->mode = (w1 > 0.0) - (w1 < 0.0);
}

void plant_get_state(const plant_t *pl, double x[4])
{
    for (int i = 0; i < 4; i++) {
        x[i] = pl->x[i];
    }
}

int plant_mode(const plant_t *pl)
{
    return pl->mode;
}

static double plant_net_torque_x(const plant_params_t *p, const double x[4], double u)
{
    return p->km * u - p->k * (x[0] - x[2]) - p->c * (x[1] - x[3]);
}

double plant_net_torque(const plant_t *pl, double u)
{
    return plant_net_torque_x(&pl->p, pl->x, u);
}

/* g(th1) = 1 + e sin(th1): the position-dependent scale of the friction levels (1 if e = 0) */
static double plant_friction_scale(const plant_params_t *p, const double x[4])
{
    return p->coulomb_pos == 0.0 ? 1.0 : 1.0 + p->coulomb_pos * sin(x[0]);
}

/* right-hand side in a fixed mode (the friction sign is the mode, not sign(w1), so the
 * slipping dynamics extend smoothly past w1 = 0 for the event location) */
static void plant_rhs(const plant_params_t *p, int mode, const double x[4], double u, double dx[4])
{
    double spring = p->k * (x[0] - x[2]) + p->c * (x[1] - x[3]);
    if (mode == 0) {
        dx[0] = 0.0;
        dx[1] = 0.0;
    } else {
        double g = plant_friction_scale(p, x);
        double fc = g * p->coulomb * (1.0 + (double)mode * p->coulomb_asym);
        double fr = fc;
        if (p->stribeck_vel > 0.0) {
            double r = x[1] / p->stribeck_vel;
            fr += (g * p->stat - fc) * exp(-r * r);
        }
        double friction = (double)mode * fr + p->viscous * x[1];
        dx[0] = x[1];
        dx[1] = (p->km * u - spring - friction) / p->j1;
    }
    dx[2] = x[3];
    dx[3] = (spring - p->load_viscous * x[3]) / p->j2;
}

static void plant_rk4(const plant_params_t *p, int mode, const double x[4], double u, double h, double out[4])
{
    double k1[4], k2[4], k3[4], k4[4], y[4];
    plant_rhs(p, mode, x, u, k1);
    for (int i = 0; i < 4; i++) {
        y[i] = x[i] + 0.5 * h * k1[i];
    }
    plant_rhs(p, mode, y, u, k2);
    for (int i = 0; i < 4; i++) {
        y[i] = x[i] + 0.5 * h * k2[i];
    }
    plant_rhs(p, mode, y, u, k3);
    for (int i = 0; i < 4; i++) {
        y[i] = x[i] + h * k3[i];
    }
    plant_rhs(p, mode, y, u, k4);
    for (int i = 0; i < 4; i++) {
        out[i] = x[i] + h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
    }
    if (mode == 0) {
        out[1] = 0.0; /* exactly stuck */
    }
}

/* Event function: >= 0 while the mode is valid. Slip: s w1. Stick: Fs - |T|. */
static double plant_event(const plant_params_t *p, int mode, const double x[4], double u)
{
    if (mode == 0) {
        return plant_friction_scale(p, x) * p->stat - fabs(plant_net_torque_x(p, x, u));
    }
    return (double)mode * x[1];
}

/* Mode at w1 = 0: stick if the net torque cannot break away, else slip along it. */
static int plant_mode_at_rest(const plant_params_t *p, const double x[4], double u)
{
    double tn = plant_net_torque_x(p, x, u);
    if (fabs(tn) <= plant_friction_scale(p, x) * p->stat) {
        return 0;
    }
    return tn > 0.0 ? 1 : -1;
}

static void plant_substep(plant_t *pl, double u, double h)
{
    const plant_params_t *p = &pl->p;
    double left = h;
    for (int ev = 0; left > 0.0; ev++) {
        if (pl->mode == 0) {
            int m = plant_mode_at_rest(p, pl->x, u);
            if (m != 0) {
                pl->mode = m; /* break away now */
                pl->events++;
            }
        }
        double x1[4];
        plant_rk4(p, pl->mode, pl->x, u, left, x1);
        double g1 = plant_event(p, pl->mode, x1, u);
        int crossed = (pl->mode == 0) ? (g1 < 0.0) : (g1 <= 0.0);
        if (!crossed || ev >= PLANT_MAX_EVENTS) {
            for (int i = 0; i < 4; i++) {
                pl->x[i] = x1[i];
            }
            return;
        }
        /* locate the event: g(a) >= 0 (mode valid), g(b) crossed */
        double a = 0.0, b = left, xb[4];
        for (int i = 0; i < 4; i++) {
            xb[i] = x1[i];
        }
        for (int it = 0; it < PLANT_BISECT; it++) {
            double m = 0.5 * (a + b), xm[4];
            plant_rk4(p, pl->mode, pl->x, u, m, xm);
            double gm = plant_event(p, pl->mode, xm, u);
            int c = (pl->mode == 0) ? (gm < 0.0) : (gm <= 0.0);
            if (c) {
                b = m;
                for (int i = 0; i < 4; i++) {
                    xb[i] = xm[i];
                }
            } else {
                a = m;
            }
        }
        for (int i = 0; i < 4; i++) {
            pl->x[i] = xb[i];
        }
        left -= b;
        pl->events++;
        if (pl->mode != 0) {
            pl->x[1] = 0.0; /* the velocity reached zero */
            pl->mode = plant_mode_at_rest(p, pl->x, u);
        } else {
            double tn = plant_net_torque_x(p, pl->x, u);
            pl->mode = tn > 0.0 ? 1 : -1;
        }
    }
}

/* e^a for an n x n matrix (n <= 5), row-major: scaling and squaring with a Taylor series
 * (terms until they no longer change the sum; ||a / 2^s|| <= 0.5). */
static void plant_expm(int n, const double a[5][5], double e[5][5])
{
    double norm = 0.0;
    for (int i = 0; i < n; i++) {
        double row = 0.0;
        for (int j = 0; j < n; j++) {
            row += fabs(a[i][j]);
        }
        norm = fmax(norm, row);
    }
    int s = 0;
    while (norm > 0.5) {
        norm *= 0.5;
        s++;
    }
    double sc = ldexp(1.0, -s), as[5][5], term[5][5], tmp[5][5];
    for (int i = 0; i < n; i++) {
        for (int j = 0; j < n; j++) {
            as[i][j] = a[i][j] * sc;
            term[i][j] = (i == j) ? 1.0 : 0.0;
            e[i][j] = term[i][j];
        }
    }
    for (int k = 1; k <= 30; k++) {
        for (int i = 0; i < n; i++) {
            for (int j = 0; j < n; j++) {
                double acc = 0.0;
                for (int l = 0; l < n; l++) {
                    acc += term[i][l] * as[l][j];
                }
                tmp[i][j] = acc / (double)k;
            }
        }
        for (int i = 0; i < n; i++) {
            for (int j = 0; j < n; j++) {
                term[i][j] = tmp[i][j];
                e[i][j] += term[i][j];
            }
        }
    }
    for (int q = 0; q < s; q++) {
        for (int i = 0; i < n; i++) {
            for (int j = 0; j < n; j++) {
                double acc = 0.0;
                for (int l = 0; l < n; l++) {
                    acc += e[i][l] * e[l][j];
                }
                tmp[i][j] = acc;
            }
        }
        for (int i = 0; i < n; i++) {
            for (int j = 0; j < n; j++) {
                e[i][j] = tmp[i][j];
            }
        }
    }
}

/* Zero-order-hold discretisation of both modes for step length dt (augmented exponential). */
static void plant_discretise(plant_t *pl, double dt)
{
    const plant_params_t *p = &pl->p;
    double m[5][5] = {{0}}, e[5][5];
    m[0][1] = 1.0;
    m[1][0] = -p->k / p->j1;
    m[1][1] = -(p->c + p->viscous) / p->j1;
    m[1][2] = p->k / p->j1;
    m[1][3] = p->c / p->j1;
    m[1][4] = 1.0 / p->j1; /* input v = km u - s Fc_s */
    m[2][3] = 1.0;
    m[3][0] = p->k / p->j2;
    m[3][1] = p->c / p->j2;
    m[3][2] = -p->k / p->j2;
    m[3][3] = -(p->c + p->load_viscous) / p->j2;
    for (int i = 0; i < 5; i++) {
        for (int j = 0; j < 5; j++) {
            m[i][j] *= dt;
        }
    }
    plant_expm(5, m, e);
    for (int i = 0; i < 4; i++) {
        for (int j = 0; j < 4; j++) {
            pl->phi[i][j] = e[i][j];
        }
        pl->gam[i] = e[i][4];
    }
    double ms[5][5] = {{0}}, es[5][5];
    ms[0][1] = dt;
    ms[1][0] = -p->k / p->j2 * dt;
    ms[1][1] = -(p->c + p->load_viscous) / p->j2 * dt;
    ms[1][2] = p->k / p->j2 * dt; /* input th1 (held while stuck) */
    plant_expm(3, ms, es);
    for (int i = 0; i < 2; i++) {
        for (int j = 0; j < 2; j++) {
            pl->phis[i][j] = es[i][j];
        }
        pl->gams[i] = es[i][2];
    }
    pl->fast_dt = dt;
}

/* One exact step if no event happens in it; 0 (state untouched) otherwise. */
static int plant_fast_step(plant_t *pl, double u)
{
    const plant_params_t *p = &pl->p;
    double *x = pl->x;
    if (pl->mode != 0) {
        double v = p->km * u - (double)pl->mode * p->coulomb - p->coulomb * p->coulomb_asym, y[4];
        for (int i = 0; i < 4; i++) {
            y[i] = pl->phi[i][0] * x[0] + pl->phi[i][1] * x[1] + pl->phi[i][2] * x[2] +
                   pl->phi[i][3] * x[3] + pl->gam[i] * v;
        }
        if ((double)pl->mode * y[1] <= 0.0) {
            return 0;
        }
        for (int i = 0; i < 4; i++) {
            x[i] = y[i];
        }
        return 1;
    }
    if (fabs(plant_net_torque_x(p, x, u)) > p->stat) {
        return 0;
    }
    double th2 = pl->phis[0][0] * x[2] + pl->phis[0][1] * x[3] + pl->gams[0] * x[0];
    double w2 = pl->phis[1][0] * x[2] + pl->phis[1][1] * x[3] + pl->gams[1] * x[0];
    double y[4] = {x[0], 0.0, th2, w2};
    if (fabs(plant_net_torque_x(p, y, u)) > p->stat) {
        return 0;
    }
    x[2] = th2;
    x[3] = w2;
    return 1;
}

void plant_advance(plant_t *pl, double u, double dt)
{
    if (!isfinite(u) || !isfinite(dt) || !(dt > 0.0)) {
        return; /* documented: no advance on a non-finite input or step */
    }
    if (pl->p.stribeck_vel == 0.0 && pl->p.coulomb_pos == 0.0) {
        if (dt != pl->fast_dt) {
            plant_discretise(pl, dt);
        }
        if (plant_fast_step(pl, u)) {
            pl->t += dt;
            return;
        }
    }
    pl->slow_steps++;
    uint32_t n = pl->p.substeps;
    double h = dt / (double)n;
    for (uint32_t i = 0u; i < n; i++) {
        plant_substep(pl, u, h);
    }
    pl->t += dt;
}

/* splitmix64 -> uniform (0, 1] -> Box-Muller */
static double plant_uniform(plant_t *pl)
{
    uint64_t z = (pl->rng += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    z ^= z >> 31;
    return ((double)(z >> 11) + 1.0) * (1.0 / 9007199254740992.0);
}

static double plant_gauss(plant_t *pl)
{
    if (pl->has_spare) {
        pl->has_spare = 0;
        return pl->spare;
    }
    double r = sqrt(-2.0 * log(plant_uniform(pl)));
    double phi = PLANT_TWO_PI * plant_uniform(pl);
    pl->spare = r * sin(phi);
    pl->has_spare = 1;
    return r * cos(phi);
}

/* nearest count: q floor(th / q + 1/2), the floor by integer conversion (no libm call on
 * the per-step path); beyond +-2^62 counts it saturates, far outside any simulation */
static double plant_quantise(const plant_t *pl, double th)
{
    if (pl->per_count == 0.0) {
        return th;
    }
    double t = th * pl->per_count + 0.5;
    if (!(fabs(t) < 4.0e18)) {
        return th;
    }
    int64_t i = (int64_t)t;
    if ((double)i > t) {
        i--;
    }
    return (double)i * pl->count;
}

void plant_measure(plant_t *pl, double *th1_meas, double *th2_meas)
{
    plant_measure_angles(pl, pl->x[0], pl->x[2], th1_meas, th2_meas);
}

void plant_measure_angles(plant_t *pl, double th1, double th2, double *th1_meas, double *th2_meas)
{
    double m1 = plant_quantise(pl, th1);
    double m2 = plant_quantise(pl, th2);
    if (pl->p.noise_std > 0.0) {
        m1 += pl->p.noise_std * plant_gauss(pl);
        m2 += pl->p.noise_std * plant_gauss(pl);
    }
    *th1_meas = m1;
    *th2_meas = m2;
}
