/* ctl.c - PD + friction feed-forward (Coulomb, asymmetry, position, viscous), see ctl.h. */
#include "ctl.h"

#include <math.h>

#include "gen.h" /* gen_sincos_index: the level table's sin / cos without libm */

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

/* The level table of ctl_ff_level from K_fc, K_ps, K_pc (off the control path). */
static void ctl_update_ff(ctl_t *ctl)
{
    const float quarter = (float)(1.5707963267948966 / CTL_FF_N);
    const float step = (float)(6.283185307179586 / CTL_FF_N);
    for (uint32_t k = 0u; k < CTL_FF_N; k++) {
        float s, c;
        gen_sincos_index(k, CTL_FF_N, quarter, &s, &c);
        ctl->ff_table[k][0] = ctl->kfc + ctl->kps * s + ctl->kpc * c;
        ctl->ff_table[k][1] = (ctl->kps * c - ctl->kpc * s) * step;
    }
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
    ctl->smooth = ctl->inv_smooth > 0.0f;
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
    ctl->kfa = 0.0f;
    ctl->kps = 0.0f;
    ctl->kpc = 0.0f;
    ctl_update_ff(ctl);
    ctl->ts = 1.0f / fs_hz;
    ctl_update_derived(ctl);
    ctl_reset(ctl);
    return CTL_OK;
}

void ctl_reset(ctl_t *ctl)
{
    ctl->e_prev = NAN; /* e - NaN is NaN: the step's test for its first sample */
    ctl->d_state = 0.0f;
    ctl->u_unsat = 0.0f;
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
CTL_SETTER(ctl_set_kv, kv)
CTL_SETTER(ctl_set_fc_smooth, fc_smooth)
CTL_SETTER(ctl_set_u_max, u_max)


/* K_fc and the position gains: the level table follows. */
ctl_status_t ctl_set_kfc(ctl_t *ctl, float v)
{
    ctl_status_t st = ctl_check_nonneg(v);
    if (st != CTL_OK) {
        return st;
    }
    ctl->kfc = v;
    ctl_update_ff(ctl);
    return CTL_OK;
}

/* The signed gains: any finite value (drv checks the od.yaml limits). */
#define CTL_SETTER_SIGNED(fn, field, table)  \
    ctl_status_t fn(ctl_t *ctl, float v)     \
    {                                        \
        if (!isfinite(v)) {                  \
            return CTL_E_NOT_FINITE;         \
        }                                    \
        ctl->field = v;                      \
        if (table) {                         \
            ctl_update_ff(ctl);              \
        }                                    \
        return CTL_OK;                       \
    }

CTL_SETTER_SIGNED(ctl_set_kfa, kfa, false)
CTL_SETTER_SIGNED(ctl_set_kps, kps, true)
CTL_SETTER_SIGNED(ctl_set_kpc, kpc, true)
