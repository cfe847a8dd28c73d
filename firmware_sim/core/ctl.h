/*
 * ctl.h - the position controller of the drive (deployable, float32, no OS call).
 *
 *   u = Kp e + D + K_fc sgn(v_r) + K_v v_r + u_add,  saturated to +-u_max
 *
 * e = theta_r - theta_1 [rad], v_r the reference velocity [rad/s] (from the generator),
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
    /* state */
    float e_prev;
    float d_state;
    float u_unsat; /* last output before saturation: the drive faults when it is not finite */
    bool primed; /* e_prev valid (no derivative kick on the first step) */
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

/* One step: error e [rad], reference velocity [rad/s], u_add [V] added before saturation
 * (disturbance injection). Returns the saturated plant input [V]. A NaN passes the
 * saturation (comparisons with NaN are false) and an overflow is clamped to +-u_max, so the
 * caller checks u_unsat (drv_step: not finite -> fault, output 0). */
static inline float ctl_step(ctl_t *ctl, float e, float v_ref, float u_add)
{
    float de = ctl->primed ? (e - ctl->e_prev) : 0.0f;
    ctl->e_prev = e;
    ctl->primed = true;
    ctl->d_state = ctl->d_pole * ctl->d_state + ctl->d_gain * de;
    float u = ctl->kp * e + ctl->d_state + ctl->kfc * ctl_ff_sign(ctl, v_ref) + ctl->kv * v_ref + u_add;
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

#endif /* CTL_H */
