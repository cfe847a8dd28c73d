/*
 * ctl.h - the position controller of the drive (deployable, float32, no OS call).
 *
 *   u = Kp e + D + FF + u_add,  saturated to +-u_max
 *   FF = sgn(v_r) (K_fc + K_ps sin(theta_r) + K_pc cos(theta_r)) + K_fa |sgn(v_r)| + K_v v_r
 *
 * e = theta_r - theta_1 [rad], theta_r the reference angle, v_r the reference velocity
 * [rad/s] (from the generator). The friction feed-forward (issue 35): the Coulomb level K_fc
 * (the mean of the two directions' levels Fc+ and Fc-), its direction asymmetry
 * K_fa = (Fc+ - Fc-) / 2 (FF = Fc+ moving forward, -Fc- moving back), the first harmonic of
 * the level's variation over one revolution as sine and cosine gains K_ps, K_pc of the
 * reference angle (linear in the gains: a Gauss-Newton step is exact in them and no phase
 * wraps; amplitude sqrt(K_ps^2 + K_pc^2)), and viscous K_v.
 * The angle-dependent level K_fc + K_ps sin + K_pc cos is tabulated by the setters over one
 * revolution (CTL_FF_N entries with their slopes) and read per step by a first-order
 * interpolation (ctl_ff_level): no sin/cos, no libm in the step, about a dozen instructions;
 * error < (2 pi / CTL_FF_N)^2 / 2 = 1.2e-3 of sqrt(K_ps^2 + K_pc^2). A setter running while
 * the control interrupt reads the table may give that one step a mix of old and new entries
 * (a value between the two levels).
 * D the first-order filtered derivative Kd s / (tau_d s + 1) e, discretised with
 * BACKWARD EULER: D[n] = tau/(tau+T) D[n-1] + Kd/(tau+T) (e[n] - e[n-1]).
 * Why not Tustin: Tustin puts the filter pole at -(T - 2 tau)/(T + 2 tau), which is
 * negative (ringing at fs/2) for tau < T/2 and on the unit circle for tau = 0 (an
 * undamped Nyquist oscillation). Backward Euler keeps the pole tau/(tau+T) in [0, 1) for
 * every tau >= 0, and tau = 0 gives the plain backward difference. The price is T/2 of
 * extra phase lag, negligible at the loop bandwidths used here.
 *
 * sgn: pure sign with sgn(0) = 0 (width 0, as in the paper), or clamp(v / width, -1, 1).
 * Setters reject NaN/inf/negative values and leave the old value (CTL_E_*).
 */
#ifndef CTL_H
#define CTL_H

#include <stdbool.h>
#include <stdint.h>

#define CTL_FF_N 128u /* entries of the level table over one revolution (a power of two) */

typedef enum {
    CTL_OK = 0,
    CTL_E_NOT_FINITE,
    CTL_E_RANGE_LOW,
    CTL_E_RANGE_HIGH
} ctl_status_t;

typedef struct {
    /* parameters (SI; V, rad, s) */
    float kp, kd, tau_d, kfc, kv, fc_smooth, u_max;
    float ts; /* sample time [s] */
    /* derived, updated by the setters */
    float d_pole;     /* tau/(tau+T) */
    float d_gain;     /* Kd/(tau+T) */
    float inv_smooth; /* 1/width, 0 = pure sign */
    bool smooth;      /* inv_smooth > 0 (the step tests an integer) */
    /* state */
    float e_prev; /* NaN until the first step after ctl_reset (no derivative kick) */
    float d_state;
    float u_unsat; /* last output before saturation: the drive faults when it is not finite */
    /* the friction feed-forward's signed gains [V] and the level table (ctl_ff_level) */
    float kfa, kps, kpc;
    /* per entry k: [0] K_fc + K_ps sin(2 pi k / N) + K_pc cos(2 pi k / N), [1] its change
     * per entry (K_ps cos - K_pc sin) 2 pi / N; interleaved: one address for both loads */
    float ff_table[CTL_FF_N][2];
} ctl_t;

/* fs_hz must be finite and > 0. Gains start at 0, u_max at 0: set them. */
ctl_status_t ctl_init(ctl_t *ctl, float fs_hz);
void ctl_reset(ctl_t *ctl); /* forget the derivative state (bumpless re-enable) */

/* ---- per-sample hot path, inline (controller step budget) ---- */

/* sgn as used by the feed-forward. */
static inline float ctl_ff_sign(const ctl_t *ctl, float v_ref)
{
    if (ctl->inv_smooth > 0.0f) {
        float s = v_ref * ctl->inv_smooth;
        if (s > 1.0f) {
            s = 1.0f;
        } else if (s < -1.0f) {
            s = -1.0f;
        }
        return s;
    }
    if (v_ref > 0.0f) {
        return 1.0f;
    }
    if (v_ref < 0.0f) {
        return -1.0f;
    }
    return 0.0f;
}

/* The Coulomb level at the reference angle theta_r [rad] (|theta_r| < 1e6: the target
 * INTEGER32 urad plus the excitation): entry k = trunc(x) mod N of x = theta_r N / (2 pi),
 * moved along its slope by x - trunc(x) in (-1, 1). Branch-free. */
static inline float ctl_ff_level(const ctl_t *ctl, float theta_r)
{
    float x = theta_r * (float)(CTL_FF_N / 6.283185307179586);
    int32_t i = (int32_t)x;
    uint32_t k = (uint32_t)i & (CTL_FF_N - 1u);
    return ctl->ff_table[k][0] + (x - (float)i) * ctl->ff_table[k][1];
}

/* The friction feed-forward FF (above) at reference velocity v_ref [rad/s] and angle
 * theta_r [rad]. */
static inline float ctl_ff(const ctl_t *ctl, float v_ref, float theta_r)
{
    float level = ctl_ff_level(ctl, theta_r);
    float coulomb;
    if (ctl->smooth) {
        float sg = ctl_ff_sign(ctl, v_ref);
        float mag = (sg < 0.0f) ? -sg : sg; /* |sgn| without a libm call */
        coulomb = sg * level + ctl->kfa * mag;
    } else if (v_ref > 0.0f) {
        coulomb = level + ctl->kfa; /* pure sign: the branches that find sgn = +-1 apply it */
    } else if (v_ref < 0.0f) {
        coulomb = ctl->kfa - level;
    } else {
        coulomb = 0.0f;
    }
    return coulomb + ctl->kv * v_ref;
}

/* One step: error e [rad], reference velocity [rad/s], reference angle theta_r [rad] (the
 * position feed-forward's), u_add [V] added before saturation
 * (disturbance injection). Returns the saturated plant input [V]. A NaN passes the
 * saturation (comparisons with NaN are false) and an overflow is clamped to +-u_max, so the
 * caller checks u_unsat (drv_step: not finite -> fault, output 0). */
static inline float ctl_step(ctl_t *ctl, float e, float v_ref, float theta_r, float u_add)
{
    float de = e - ctl->e_prev;
    if (de != de) {
        de = 0.0f; /* the first step after ctl_reset (e_prev NaN): no derivative kick */
    }
    ctl->e_prev = e;
    ctl->d_state = ctl->d_pole * ctl->d_state + ctl->d_gain * de;
    float u = ctl->kp * e + ctl->d_state + ctl_ff(ctl, v_ref, theta_r) + u_add;
    ctl->u_unsat = u;
    if (u > ctl->u_max) {
        u = ctl->u_max;
    } else if (u < -ctl->u_max) {
        u = -ctl->u_max;
    }
    return u;
}

ctl_status_t ctl_set_kp(ctl_t *ctl, float kp_v_per_rad);
ctl_status_t ctl_set_kd(ctl_t *ctl, float kd_vs_per_rad);
ctl_status_t ctl_set_tau_d(ctl_t *ctl, float tau_s);
ctl_status_t ctl_set_kfc(ctl_t *ctl, float kfc_v);
ctl_status_t ctl_set_kv(ctl_t *ctl, float kv_vs_per_rad);
ctl_status_t ctl_set_fc_smooth(ctl_t *ctl, float width_rad_s);
ctl_status_t ctl_set_u_max(ctl_t *ctl, float u_max_v);
/* Signed gains (any finite value; drv checks the od.yaml limits): asymmetry K_fa [V],
 * position sine / cosine K_ps, K_pc [V]. */
ctl_status_t ctl_set_kfa(ctl_t *ctl, float kfa_v);
ctl_status_t ctl_set_kps(ctl_t *ctl, float kps_v);
ctl_status_t ctl_set_kpc(ctl_t *ctl, float kpc_v);

#endif /* CTL_H */
