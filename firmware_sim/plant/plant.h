/*
 * plant.h - simulated two-mass plant with friction (HOST SIMULATION ONLY, double).
 *
 * The paper's set-up II: motor inertia J1 driven by km * u [N m] (u the input voltage),
 * torsional spring k and damper c to the load inertia J2:
 *   J1 w1' = km u - k (th1 - th2) - c (w1 - w2) - F(w1)
 *   J2 w2' =        k (th1 - th2) + c (w1 - w2) - b2 w2
 * Motor friction while slipping in direction s = sign(w1), with the Coulomb level of that
 * direction Fc_s = Fc (1 + s a) (asymmetry a, 0 = symmetric; a != 0 gives even harmonics):
 *   F = s (Fc_s + (Fs - Fc_s) exp(-(w1/vs)^2)) + bv w1   (Stribeck term only if vs > 0)
 * Position-dependent friction (coulomb_position e, 0 = none): the normal force of the friction
 * contact varies once per revolution (run-out of the friction wheel), so Fc_s and Fs are
 * scaled by g(th1) = 1 + e sin(th1). The part e Fc sin(th1) sign(w1) is EVEN in the motion:
 * even harmonics that a Coulomb feed-forward K_fc sign(.) (odd) leaves as they are.
 * Stiction: while w1 = 0 the motor sticks (th1 fixed, w1 = 0 exactly: no creep) as long as
 * |T| <= Fs, T = km u - k (th1 - th2) + c w2 the net non-friction torque on it.
 *
 * Fast path (no Stribeck term, e = 0): between stick/slip events the plant is LINEAR (friction sign
 * fixed, u held), so a controller step is propagated exactly by the zero-order-hold
 * discretisation x+ = Phi x + Gamma (km u - s Fc) (slip) or of the load-side dynamics with
 * th1 fixed (stick), Phi and Gamma from a matrix exponential (scaling and squaring, Taylor)
 * computed once per step length. A step whose end shows an event (w1 changed sign while
 * slipping, |T| > Fs while sticking) is recomputed from its start on the sub-step path.
 * Assumption of the fast path: at most one such event inside one controller step (w1 does
 * not reverse twice within 1/fs), true when the plant's modes are well below fs/2.
 *
 * Sub-step path (events; Stribeck; e != 0): a fixed number of RK4 sub-steps per controller step
 * (u held). Stick/slip
 * switching is event-driven inside a sub-step: when w1 would change sign (slip) or |T|
 * would exceed Fs (stick), the event time is located by bisection on the RK4 step length
 * (50 halvings, to double precision), the state is advanced to it, the mode switched
 * (stick if |T| <= Fs at w1 = 0, else slip in the direction of T) and the rest of the
 * sub-step integrated in the new mode. So there is no chatter around w1 = 0 and no drift
 * under static friction.
 *
 * Measurement: encoder quantisation to the nearest of counts_per_rev counts per rev
 * (0 = none) plus seeded Gaussian noise (std, rad) on both angles.
 */
#ifndef PLANT_H
#define PLANT_H

#include <stddef.h>
#include <stdint.h>

typedef struct {
    double j1, j2;          /* kg m^2 */
    double k, c;            /* N m/rad, N m s/rad */
    double km;              /* N m/V: torque per input volt */
    double coulomb;         /* Fc, N m (mean of the two directions) */
    double coulomb_asym;    /* a in [-0.9, 0.9]: Fc_+ = Fc (1 + a), Fc_- = Fc (1 - a) */
    double coulomb_pos;     /* e in [-0.9, 0.9]: friction levels x (1 + e sin th1) (run-out) */
    double stat;            /* Fs >= Fc (1 + |a|), N m (static / break-away) */
    double stribeck_vel;    /* vs, rad/s; 0 = no Stribeck term */
    double viscous;         /* bv, N m s/rad (motor side) */
    double load_viscous;    /* b2, N m s/rad */
    uint32_t substeps;      /* per controller step, >= 1 */
    uint32_t counts_per_rev;/* encoder counts per revolution, 0 = no quantisation */
    double noise_std;       /* rad, on both measured angles */
    uint64_t seed;          /* noise seed */
} plant_params_t;

typedef struct {
    plant_params_t p;
    double x[4];            /* th1, w1, th2, w2 */
    int mode;               /* -1 / +1 slipping, 0 sticking */
    double t;               /* simulated time, s */
    uint64_t events;        /* stick/slip switches so far */
    uint64_t slow_steps;    /* controller steps integrated on the sub-step path */
    double fast_dt;         /* step length Phi/Gamma belong to (0 = none) */
    double count, per_count;    /* encoder count [rad] and its inverse (0: no quantisation) */
    double phi[4][4], gam[4];   /* slip: x+ = phi x + gam (km u - s Fc) */
    double phis[2][2], gams[2]; /* stick: (th2, w2)+ = phis (th2, w2) + gams th1 */
    uint64_t rng;
    int has_spare;
    double spare;
} plant_t;

/* 0 if physically valid, else -1 with the offending field named in err. */
int plant_check_params(const plant_params_t *p, char *err, size_t errlen);
/* At rest at the origin, sticking. Returns plant_check_params' result. */
int plant_init(plant_t *pl, const plant_params_t *p, char *err, size_t errlen);
/* Non-finite values: ignored (state kept). Sticking if w1 == 0 (until |T| > Fs). */
void plant_set_state(plant_t *pl, double th1, double w1, double th2, double w2);
void plant_get_state(const plant_t *pl, double x[4]);
int plant_mode(const plant_t *pl);
/* Advance by dt seconds with u [V] held. Non-finite u or dt <= 0: no change. */
void plant_advance(plant_t *pl, double u, double dt);
/* Measured angles (quantised + noise); advances the noise generator. */
void plant_measure(plant_t *pl, double *th1_meas, double *th2_meas);
/* The same sensor (quantisation, noise) applied to angles th1, th2 [rad] from elsewhere (an
 * FMU plant, plant/sim.h sim_plant_ext_t); advances the noise generator as plant_measure. */
void plant_measure_angles(plant_t *pl, double th1, double th2, double *th1_meas, double *th2_meas);
/* Net non-friction torque on the motor [N m]. */
double plant_net_torque(const plant_t *pl, double u);

#endif /* PLANT_H */
