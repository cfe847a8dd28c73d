/* ctl.c - PD + Coulomb/viscous feed-forward, see ctl.h. */
#include "ctl.h"

#include <math.h>

static ctl_status_t ctl_check_nonneg(float v)
{
    if (!isfinite(v)) {
        return CTL_E_NOT_FINITE;
    }
    if (v < 0.0f) {
        return CTL_E_RANGE_LOW;
    }
    return CTL_OK;
}

static void ctl_update_derived(ctl_t *ctl)
{
    float den = ctl->tau_d + ctl->ts;
    ctl->d_pole = ctl->tau_d / den;
    ctl->d_gain = ctl->kd / den;
    ctl->inv_smooth = (ctl->fc_smooth > 0.0f) ? 1.0f / ctl->fc_smooth : 0.0f;
    if (!isfinite(ctl->inv_smooth)) {
        ctl->inv_smooth = 0.0f; /* a denormal width: 1/w overflows (0 * inf = NaN); pure sign */
    }
}

ctl_status_t ctl_init(ctl_t *ctl, float fs_hz)
{
    if (!isfinite(fs_hz)) {
        return CTL_E_NOT_FINITE;
    }
    if (!(fs_hz > 0.0f)) {
        return CTL_E_RANGE_LOW;
    }
    ctl->kp = 0.0f;
    ctl->kd = 0.0f;
    ctl->tau_d = 0.0f;
    ctl->kfc = 0.0f;
    ctl->kv = 0.0f;
    ctl->fc_smooth = 0.0f;
    ctl->u_max = 0.0f;
    ctl->ts = 1.0f / fs_hz;
    ctl_update_derived(ctl);
    ctl_reset(ctl);
    return CTL_OK;
}

void ctl_reset(ctl_t *ctl)
{
    ctl->e_prev = 0.0f;
    ctl->d_state = 0.0f;
    ctl->u_unsat = 0.0f;
    ctl->primed = false;
}

/* One setter per parameter, all of the same shape: check, then store and re-derive. */
#define CTL_SETTER(fn, field)                      \
    ctl_status_t fn(ctl_t *ctl, float v)           \
    {                                              \
        ctl_status_t st = ctl_check_nonneg(v);     \
        if (st != CTL_OK) {                        \
            return st;                             \
        }                                          \
        ctl->field = v;                            \
        ctl_update_derived(ctl);                   \
        return CTL_OK;                             \
    }

CTL_SETTER(ctl_set_kp, kp)
CTL_SETTER(ctl_set_kd, kd)
CTL_SETTER(ctl_set_tau_d, tau_d)
CTL_SETTER(ctl_set_kfc, kfc)
CTL_SETTER(ctl_set_kv, kv)
CTL_SETTER(ctl_set_fc_smooth, fc_smooth)
CTL_SETTER(ctl_set_u_max, u_max)

