/* test_core.c - unit tests of the deployable drive core (firmware_sim/core). */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "ctl.h"
#include "drv.h"
#include "fft.h"
#include "gen.h"
#include "lstat.h"
#include "ms.h"
#include "ms_vectors.h"
#include "task.h"
#include "th.h"

#define FS 2560.0f
#define REC_CAP 20000u
#define TAB_CAP 8192u

static float rec_buf[REC_CAP];
static float tab_buf[TAB_CAP];
static float stage_buf[TAB_CAP];

static drv_t make_drv(uint32_t rec_cap)
{
    drv_t d;
    drv_storage_t st = {rec_buf, rec_cap, tab_buf, TAB_CAP, FS, stage_buf};
    drv_status_t s = drv_init(&d, &st);
    TH_EQ(s, DRV_OK);
    return d;
}

static float step0(drv_t *d)
{
    drv_meas_t m = {0.0f, 0.0f};
    return drv_step(d, &m);
}

/* ---------------- controller ---------------- */

static void test_ctl_law_pd_filtered_derivative(void)
{
    ctl_t c;
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    TH_EQ(ctl_set_kp(&c, 3.0f), CTL_OK);
    TH_EQ(ctl_set_kd(&c, 0.2f), CTL_OK);
    TH_EQ(ctl_set_tau_d(&c, 0.001f), CTL_OK);
    TH_EQ(ctl_set_u_max(&c, 1000.0f), CTL_OK);
    /* reference: backward-Euler filtered derivative in double */
    double T = 1.0 / FS, tau = 0.001, D = 0.0, e_prev = 0.0;
    for (int n = 0; n < 200; n++) {
        double e = 0.3 * sin(0.05 * n) + 0.01 * n;
        double de = n == 0 ? 0.0 : e - e_prev;
        D = tau / (tau + T) * D + 0.2 / (tau + T) * de;
        double u_ref = 3.0 * e + D;
        float u = ctl_step(&c, (float)e, 0.0f, 0.0f, 0.0f);
        TH_NEAR(u, u_ref, 1e-4 * (1.0 + fabs(u_ref)));
        e_prev = e;
    }
    /* tau = 0: plain backward difference Kd (e[n] - e[n-1]) / T */
    ctl_reset(&c);
    TH_EQ(ctl_set_tau_d(&c, 0.0f), CTL_OK);
    TH_EQ(ctl_set_kp(&c, 0.0f), CTL_OK);
    (void)ctl_step(&c, 1.0f, 0.0f, 0.0f, 0.0f);
    float u = ctl_step(&c, 1.5f, 0.0f, 0.0f, 0.0f);
    TH_NEAR(u, 0.2 * 0.5 * FS, 1e-3);
}

static void test_ctl_feedforward_and_saturation(void)
{
    ctl_t c;
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    TH_EQ(ctl_set_kfc(&c, 0.5f), CTL_OK);
    TH_EQ(ctl_set_kv(&c, 0.1f), CTL_OK);
    TH_EQ(ctl_set_u_max(&c, 2.0f), CTL_OK);
    TH_NEAR(ctl_step(&c, 0.0f, 3.0f, 0.0f, 0.0f), 0.5 + 0.3, 1e-6);
    TH_NEAR(ctl_step(&c, 0.0f, -3.0f, 0.0f, 0.0f), -0.5 - 0.3, 1e-6);
    TH_NEAR(ctl_step(&c, 0.0f, 0.0f, 0.0f, 0.0f), 0.0, 0.0); /* sign(0) = 0 */
    TH_NEAR(ctl_step(&c, 0.0f, 1e-30f, 0.0f, 0.0f), 0.5, 1e-6); /* pure sign */
    TH_NEAR(ctl_ff_sign(&c, -1e-30f), -1.0, 0.0);
    /* smoothing width 2 rad/s: clamp(v / 2, -1, 1) */
    TH_EQ(ctl_set_fc_smooth(&c, 2.0f), CTL_OK);
    TH_NEAR(ctl_ff_sign(&c, 1.0f), 0.5, 1e-7);
    TH_NEAR(ctl_ff_sign(&c, -5.0f), -1.0, 0.0);
    /* saturation both ways, u_add added before it */
    TH_EQ(ctl_set_kp(&c, 100.0f), CTL_OK);
    TH_NEAR(ctl_step(&c, 1.0f, 0.0f, 0.0f, 0.0f), 2.0, 0.0);
    TH_NEAR(ctl_step(&c, -1.0f, 0.0f, 0.0f, 0.0f), -2.0, 0.0);
    TH_EQ(ctl_set_kp(&c, 0.0f), CTL_OK);
    TH_EQ(ctl_set_kfc(&c, 0.0f), CTL_OK);
    TH_EQ(ctl_set_kv(&c, 0.0f), CTL_OK);
    TH_NEAR(ctl_step(&c, 0.0f, 0.0f, 0.0f, 1.25f), 1.25, 0.0);
    TH_NEAR(ctl_step(&c, 0.0f, 0.0f, 0.0f, -7.0f), -2.0, 0.0);
}

static void test_ctl_setters_reject_and_keep(void)
{
    ctl_t c;
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    ctl_status_t (*setters[])(ctl_t *, float) = {ctl_set_kp, ctl_set_kd, ctl_set_tau_d, ctl_set_kfc,
                                                 ctl_set_kv, ctl_set_fc_smooth, ctl_set_u_max};
    for (size_t i = 0; i < sizeof setters / sizeof setters[0]; i++) {
        TH_EQ(setters[i](&c, 1.5f), CTL_OK);
        ctl_t before = c;
        TH_EQ(setters[i](&c, NAN), CTL_E_NOT_FINITE);
        TH_EQ(setters[i](&c, INFINITY), CTL_E_NOT_FINITE);
        TH_EQ(setters[i](&c, -INFINITY), CTL_E_NOT_FINITE);
        TH_EQ(setters[i](&c, -0.001f), CTL_E_RANGE_LOW);
        TH_ASSERT(memcmp(&before, &c, sizeof c) == 0);
    }
    TH_EQ(ctl_init(&c, 0.0f), CTL_E_RANGE_LOW);
    TH_EQ(ctl_init(&c, NAN), CTL_E_NOT_FINITE);
}

/* The friction feed-forward of several terms (issue 35): Coulomb, asymmetry, position
 * (sine and cosine of the reference angle), viscous, against the formula in double over
 * angles of both signs and several revolutions, both directions and a smoothed sign. */
static void test_ctl_friction_ff_terms(void)
{
    ctl_t c;
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    TH_EQ(ctl_set_u_max(&c, 100.0f), CTL_OK);
    const double kfc = 0.53, kfa = -0.11, kps = 0.21, kpc = -0.073, kv = 0.31;
    TH_EQ(ctl_set_kfc(&c, (float)kfc), CTL_OK);
    TH_EQ(ctl_set_kfa(&c, (float)kfa), CTL_OK);
    TH_EQ(ctl_set_kps(&c, (float)kps), CTL_OK);
    TH_EQ(ctl_set_kpc(&c, (float)kpc), CTL_OK);
    TH_EQ(ctl_set_kv(&c, (float)kv), CTL_OK);
    const double amp = sqrt(kps * kps + kpc * kpc);
    const double tol = 0.5 * pow(2.0 * M_PI / CTL_FF_N, 2) * amp + 2e-6; /* the header's bound */
    double worst = 0.0;
    for (int n = 0; n < 2000; n++) {
        double th = -21.0 + 0.02113 * n; /* -21 .. +21 rad, not on the table's grid */
        for (int dir = -1; dir <= 1; dir += 2) {
            double v = dir * (0.7 + 0.001 * n);
            double expect = dir * (kfc + kps * sin(th) + kpc * cos(th)) + kfa + kv * v;
            double got = ctl_ff(&c, (float)v, (float)th);
            TH_NEAR(got, expect, tol);
            worst = fmax(worst, fabs(got - expect));
        }
    }
    TH_ASSERT(worst > 1e-7); /* the interpolation is not exact: the bound is the one tested */
    /* moving forward the level is Fc+ = K_fc + K_fa, back -Fc- = -(K_fc - K_fa) (at theta 0:
     * sin 0, cos 1) */
    TH_NEAR(ctl_ff(&c, 1e-3f, 0.0f), kfc + kpc + kfa + kv * 1e-3, 1e-6);
    TH_NEAR(ctl_ff(&c, -1e-3f, 0.0f), -(kfc + kpc - kfa) - kv * 1e-3, 1e-6);
    /* at rest (v_r = 0, sgn 0) no Coulomb, asymmetry or position term */
    TH_NEAR(ctl_ff(&c, 0.0f, 1.3f), 0.0, 0.0);
    /* smoothed sign: width 2 rad/s, v = -0.5: sgn = -0.25, |sgn| = 0.25 */
    TH_EQ(ctl_set_fc_smooth(&c, 2.0f), CTL_OK);
    double th = 2.4;
    double expect = -0.25 * (kfc + kps * sin(th) + kpc * cos(th)) + 0.25 * kfa - 0.5 * kv;
    TH_NEAR(ctl_ff(&c, -0.5f, (float)th), expect, tol);
    /* through ctl_step: FF added to the PD part (kp 0, kd 0 here) */
    TH_NEAR(ctl_step(&c, 0.0f, -0.5f, (float)th, 0.0f), expect, tol);
    /* the table follows K_fc alone as well */
    TH_EQ(ctl_set_fc_smooth(&c, 0.0f), CTL_OK);
    TH_EQ(ctl_set_kfc(&c, 0.2f), CTL_OK);
    TH_NEAR(ctl_ff(&c, 1.0f, -1.1f), 0.2 + kps * sin(-1.1) + kpc * cos(-1.1) + kfa + kv, tol);
}

/* ctl_ff applies sgn inside its branches (the M4 step budget, issue 35); it must give the
 * same float32 numbers as the plain formula sg * level + K_fa |sg| + K_v v_r evaluated here
 * from ctl_ff_sign and ctl_ff_level: over velocities of both signs, zero, subnormal and large,
 * angles of both signs, gains of both signs, pure and smoothed sign (up to the sign of a
 * zero result). */
static void test_ctl_ff_branches_equal_the_formula(void)
{
    static const float vs[] = {0.0f, -0.0f, 1e-40f, -1e-40f, 1e-30f, -3e-7f, 0.013f, -0.41f, 0.5f, -2.0f,
                               7.25f, -130.0f, 3e5f};
    static const float gains[][5] = {/* kfc, kfa, kps, kpc, kv */
                                     {0.53f, -0.11f, 0.21f, -0.073f, 0.31f},
                                     {0.0f, 0.37f, -0.05f, 0.19f, 0.0f},
                                     {1.7f, 0.0f, 0.0f, 0.0f, 0.004f}};
    static const float widths[] = {0.0f, 0.8f, 1e-45f};
    uint32_t n_checked = 0u, n_coulomb = 0u;
    for (size_t g = 0; g < sizeof gains / sizeof gains[0]; g++) {
        for (size_t w = 0; w < sizeof widths / sizeof widths[0]; w++) {
            ctl_t c;
            TH_EQ(ctl_init(&c, FS), CTL_OK);
            TH_EQ(ctl_set_kfc(&c, gains[g][0]), CTL_OK);
            TH_EQ(ctl_set_kfa(&c, gains[g][1]), CTL_OK);
            TH_EQ(ctl_set_kps(&c, gains[g][2]), CTL_OK);
            TH_EQ(ctl_set_kpc(&c, gains[g][3]), CTL_OK);
            TH_EQ(ctl_set_kv(&c, gains[g][4]), CTL_OK);
            TH_EQ(ctl_set_fc_smooth(&c, widths[w]), CTL_OK);
            for (size_t i = 0; i < sizeof vs / sizeof vs[0]; i++) {
                for (int k = 0; k < 37; k++) {
                    float th = -31.4f + 1.737f * (float)k;
                    float sg = ctl_ff_sign(&c, vs[i]);
                    float mag = sg < 0.0f ? -sg : sg;
                    float lvl = ctl_ff_level(&c, th);
                    float expect = sg * lvl + c.kfa * mag + c.kv * vs[i];
                    float got = ctl_ff(&c, vs[i], th);
                    TH_ASSERT(got == expect);
                    n_checked++;
                    n_coulomb += (sg != 0.0f && lvl != 0.0f) ? 1u : 0u;
                }
            }
        }
    }
    TH_ASSERT(n_checked == 3u * 3u * 13u * 37u);
    TH_ASSERT(n_coulomb > n_checked / 2u); /* the level term took part in most of them */
}

/* The signed gains accept negative values, refuse NaN / inf and keep everything (the level
 * table included) on a refusal. */
static void test_ctl_signed_setters(void)
{
    ctl_t c;
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    ctl_status_t (*setters[])(ctl_t *, float) = {ctl_set_kfa, ctl_set_kps, ctl_set_kpc};
    for (size_t i = 0; i < sizeof setters / sizeof setters[0]; i++) {
        TH_EQ(setters[i](&c, -2.5f), CTL_OK);
        TH_EQ(setters[i](&c, 1.5f), CTL_OK);
        ctl_t before = c;
        TH_EQ(setters[i](&c, NAN), CTL_E_NOT_FINITE);
        TH_EQ(setters[i](&c, INFINITY), CTL_E_NOT_FINITE);
        TH_EQ(setters[i](&c, -INFINITY), CTL_E_NOT_FINITE);
        TH_ASSERT(memcmp(&before, &c, sizeof c) == 0);
    }
    TH_NEAR(c.kfa, 1.5, 0.0);
    TH_NEAR(c.kps, 1.5, 0.0);
    TH_NEAR(c.kpc, 1.5, 0.0);
}

/* ctl.h's promises after ctl_init (all gains 0, u_max 0, tau_d 0) and at its edges: a
 * small fs, a smoothing width below 1 rad/s, a denormal width (pure sign) and the reset
 * that forgets the last error (found missing by mutation testing: docs/testing.md). */
static void test_ctl_init_defaults_reset_and_edges(void)
{
    ctl_t c;
    TH_EQ(ctl_init(&c, 0.5f), CTL_OK); /* any fs > 0 */
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    TH_NEAR(ctl_step(&c, 0.3f, 0.7f, 0.0f, 1.0f), 0.0, 0.0); /* u_max 0: no output at all */
    TH_EQ(ctl_set_u_max(&c, 100.0f), CTL_OK);
    TH_NEAR(ctl_step(&c, 0.3f, 0.7f, 0.0f, 0.0f), 0.0, 0.0); /* kp, kd, kfc, kv all 0 */
    TH_NEAR(ctl_step(&c, -0.4f, -0.2f, 0.0f, 0.0f), 0.0, 0.0);
    /* kd alone: tau_d starts at 0, the plain backward difference kd (e[n] - e[n-1]) / T */
    TH_EQ(ctl_init(&c, FS), CTL_OK);
    TH_EQ(ctl_set_u_max(&c, 1000.0f), CTL_OK);
    TH_EQ(ctl_set_kd(&c, 0.01f), CTL_OK);
    (void)ctl_step(&c, 0.0f, 0.0f, 0.0f, 0.0f);
    TH_NEAR(ctl_step(&c, 0.1f, 0.0f, 0.0f, 0.0f), 0.01 * 0.1 * FS, 1e-4);
    /* reset: the next step has no derivative kick from the error before the reset */
    TH_EQ(ctl_set_kp(&c, 2.0f), CTL_OK);
    (void)ctl_step(&c, 0.5f, 0.0f, 0.0f, 0.0f);
    TH_NEAR(c.u_unsat, 2.0 * 0.5 + 0.01 * (0.5 - 0.1) * FS, 1e-3); /* last output, unsaturated */
    ctl_reset(&c);
    TH_NEAR(c.u_unsat, 0.0, 0.0); /* no last output after a reset */
    TH_NEAR(ctl_step(&c, 0.5f, 0.0f, 0.0f, 0.0f), 1.0, 1e-6);
    TH_NEAR(ctl_step(&c, 0.5f, 0.0f, 0.0f, 0.0f), 1.0, 1e-6);
    /* smoothing width 0.5 rad/s (below 1): clamp(v / 0.5, -1, 1) */
    TH_EQ(ctl_set_fc_smooth(&c, 0.5f), CTL_OK);
    TH_NEAR(ctl_ff_sign(&c, 0.25f), 0.5, 1e-7);
    /* a denormal width: 1/w overflows, the pure sign is used */
    TH_EQ(ctl_set_fc_smooth(&c, 1e-45f), CTL_OK);
    TH_NEAR(ctl_ff_sign(&c, 0.5f), 1.0, 0.0);
    TH_NEAR(ctl_ff_sign(&c, 0.0f), 0.0, 0.0);
}

/* ---------------- drive parameters ---------------- */

static void test_drv_defaults_from_od(void)
{
    drv_t d = make_drv(REC_CAP);
    for (uint32_t i = 0; i < DRV_PARAM_COUNT; i++) {
        const drv_param_info_t *p = &DRV_PARAM_INFO[i];
        if (!p->writable || p->sim_only || i == DRV_P_RUN_COMMAND) {
            continue;
        }
        if (p->type == DRV_PT_F32) {
            float v = -1.0f;
            TH_EQ(drv_get_f32(&d, (drv_param_id_t)i, &v), DRV_OK);
            TH_NEAR(v, p->default_f32, 0.0);
        } else {
            uint32_t v = 12345u;
            TH_EQ(drv_get_u32(&d, (drv_param_id_t)i, &v), DRV_OK);
            TH_EQ(v, p->default_u32);
        }
    }
    float fs = 0.0f;
    TH_EQ(drv_get_f32(&d, DRV_P_FS, &fs), DRV_OK);
    TH_NEAR(fs, FS, 0.0);
    uint32_t cap = 0u;
    TH_EQ(drv_get_u32(&d, DRV_P_REC_CAPACITY, &cap), DRV_OK);
    TH_EQ(cap, REC_CAP);
}

static void test_drv_param_validation_keeps_old_value(void)
{
    drv_t d = make_drv(REC_CAP);
    int checked = 0;
    for (uint32_t i = 0; i < DRV_PARAM_COUNT; i++) {
        const drv_param_info_t *p = &DRV_PARAM_INFO[i];
        drv_param_id_t id = (drv_param_id_t)i;
        if (p->sim_only) {
            float v;
            TH_EQ(drv_get_f32(&d, id, &v), DRV_E_NO_PARAM);
            TH_EQ(drv_set_f32(&d, id, 1.0f), DRV_E_NO_PARAM);
            continue;
        }
        if (p->type == DRV_PT_F32) {
            float before, after;
            uint32_t dummy;
            TH_EQ(drv_get_f32(&d, id, &before), DRV_OK);
            TH_EQ(drv_get_u32(&d, id, &dummy), DRV_E_LENGTH); /* type mismatch */
            if (!p->writable) {
                TH_EQ(drv_set_f32(&d, id, 1.0f), DRV_E_READ_ONLY);
                continue;
            }
            TH_EQ(drv_set_f32(&d, id, NAN), DRV_E_NOT_FINITE);
            TH_EQ(drv_set_f32(&d, id, INFINITY), DRV_E_NOT_FINITE);
            TH_EQ(drv_set_f32(&d, id, -INFINITY), DRV_E_NOT_FINITE);
            if (p->has_low) {
                TH_EQ(drv_set_f32(&d, id, p->low_f32 - 1.0f), DRV_E_RANGE_LOW);
            }
            if (p->has_high) {
                TH_EQ(drv_set_f32(&d, id, p->high_f32 * 2.0f + 1.0f), DRV_E_RANGE_HIGH);
            }
            TH_EQ(drv_get_f32(&d, id, &after), DRV_OK);
            TH_ASSERT(memcmp(&before, &after, sizeof before) == 0);
            checked++;
        } else {
            uint32_t before, after;
            float dummy;
            TH_EQ(drv_get_u32(&d, id, &before), DRV_OK);
            TH_EQ(drv_get_f32(&d, id, &dummy), DRV_E_LENGTH);
            if (!p->writable) {
                TH_EQ(drv_set_u32(&d, id, 1u), DRV_E_READ_ONLY);
                continue;
            }
            if (p->has_low && p->low_u32 > 0u) {
                TH_EQ(drv_set_u32(&d, id, p->low_u32 - 1u), DRV_E_RANGE_LOW);
            }
            if (p->has_high && p->high_u32 < UINT32_MAX) {
                TH_EQ(drv_set_u32(&d, id, p->high_u32 + 1u), DRV_E_RANGE_HIGH);
            }
            TH_EQ(drv_get_u32(&d, id, &after), DRV_OK);
            TH_EQ(after, before);
            checked++;
        }
    }
    TH_ASSERT(checked >= 20);
    /* physical checks beyond od.yaml limits */
    uint32_t g;
    TH_EQ(drv_set_u32(&d, DRV_P_MS_GROUP, 1u), DRV_E_RANGE_LOW);
    TH_EQ(drv_get_u32(&d, DRV_P_MS_GROUP, &g), DRV_OK);
    TH_EQ(g, 5u);
    float v;
    TH_EQ(drv_get_f32(&d, DRV_PARAM_COUNT, &v), DRV_E_NO_PARAM);
    TH_EQ(drv_set_u32(&d, (drv_param_id_t)1000, 0u), DRV_E_NO_PARAM);
    TH_EQ(drv_set_target(&d, NAN), DRV_E_NOT_FINITE);
    /* bad storage */
    drv_t d2;
    drv_storage_t bad = {rec_buf, REC_CAP, tab_buf, 9000u, FS, stage_buf};
    TH_EQ(drv_init(&d2, &bad), DRV_E_RANGE_HIGH);
    bad.table_capacity = TAB_CAP;
    bad.fs_hz = NAN;
    TH_EQ(drv_init(&d2, &bad), DRV_E_NOT_FINITE);
    bad.fs_hz = -1.0f;
    TH_EQ(drv_init(&d2, &bad), DRV_E_RANGE_LOW);
    bad.fs_hz = FS;
    bad.table_stage_buf = NULL; /* a table needs its staging buffer */
    TH_EQ(drv_init(&d2, &bad), DRV_E_GENERAL);
    bad.table_stage_buf = tab_buf;
    TH_EQ(drv_init(&d2, &bad), DRV_E_GENERAL);
    /* a port with a smaller table (the PIL build: 4096) reports its capacity (0x2004) and
     * refuses a longer table download */
    drv_storage_t small = {rec_buf, REC_CAP, tab_buf, 3000u, FS, stage_buf};
    TH_EQ(drv_init(&d2, &small), DRV_OK);
    uint32_t cap = 0u;
    TH_EQ(drv_get_u32(&d2, DRV_P_TABLE_CAP, &cap), DRV_OK);
    TH_EQ(cap, 3000u);
    TH_EQ(drv_get_u32(&d, DRV_P_TABLE_CAP, &cap), DRV_OK);
    TH_EQ(cap, TAB_CAP);
    TH_ASSERT(drv_table_write(&d2, 0u, (const uint8_t *)tab_buf, 3001u * 4u) != DRV_OK);
}

/* ---------------- generator ---------------- */

static void test_sine_exactly_periodic(void)
{
    const uint32_t n = 1000u, cycles = 7u; /* N not a power of two on purpose */
    gen_t g;
    TH_EQ(gen_start_sine(&g, n, cycles, 0.8f, 0.1f, FS), 0);
    static float w[3000], wd[3000];
    for (uint32_t i = 0; i < 3u * n; i++) {
        gen_next(&g, &w[i], &wd[i]);
    }
    TH_ASSERT(memcmp(w, w + n, n * sizeof(float)) == 0);
    TH_ASSERT(memcmp(w, w + 2u * n, n * sizeof(float)) == 0);
    TH_ASSERT(memcmp(wd, wd + n, n * sizeof(float)) == 0);
    double wmax = 0.0, dmax = 0.0;
    double om = 2.0 * M_PI * cycles / n;
    for (uint32_t i = 0; i < n; i++) {
        wmax = fmax(wmax, fabs(w[i] - (0.1 + 0.8 * sin(om * i))));
        dmax = fmax(dmax, fabs(wd[i] - 0.8 * om * FS * cos(om * i)));
    }
    TH_NEAR(wmax, 0.0, 2e-6);
    TH_NEAR(dmax, 0.0, 2e-6 * 0.8 * om * FS);
    TH_EQ(gen_start_sine(&g, 8u, 4u, 1.0f, 0.0f, FS), -1); /* at Nyquist */
}

/* Issue 33's hand-written bug audit: the table's velocity feed-forward is the central
 * difference (t[i+1] - t[i-1]) fs / 2 times the amplitude, wrapping at both ends of the
 * period (an uneven table: a factor, a sign or a one-sided difference fails). */
static void test_table_velocity_is_the_central_difference(void)
{
    const uint32_t n = 5u;
    static const float t[5] = {0.0f, 0.25f, 1.0f, -0.5f, 0.125f};
    const float fs = 1000.0f, amp = 0.8f, off = 0.05f;
    gen_t g;
    TH_EQ(gen_start_table(&g, t, n, amp, off, fs), 0);
    for (uint32_t k = 0u; k < 2u * n; k++) {
        uint32_t i = k % n, nx = (i + 1u) % n, pv = (i + n - 1u) % n;
        float w, wd;
        gen_next(&g, &w, &wd);
        TH_NEAR(w, 0.05 + 0.8 * (double)t[i], 1e-6);
        TH_NEAR(wd, 0.8 * ((double)t[nx] - (double)t[pv]) * 1000.0 / 2.0, 1e-3);
    }
}

/* Issue 33's hand-written bug audit: the recorder takes samples until the last one that
 * fits (rec_fits: samples x signals <= capacity, equal included), then none: capacity 6,
 * signals 0 and 2: three samples kept in order, the fourth dropped, nothing beyond. */
static void test_recorder_fills_to_its_last_sample(void)
{
    static float buf[8];
    rec_t r;
    TH_EQ(rec_init(&r, buf, 6u), 0);
    TH_EQ(rec_set_signals(&r, 0x05u), 0);
    rec_clear(&r);
    TH_ASSERT(rec_fits(&r, 3u) && !rec_fits(&r, 4u));
    float sig[REC_NUM_SIGNALS];
    for (uint32_t k = 0u; k < 4u; k++) {
        for (uint32_t s = 0u; s < REC_NUM_SIGNALS; s++) {
            sig[s] = (float)(10u * k + s + 1u);
        }
        rec_push(&r, sig);
    }
    TH_EQ(r.samples, 3u);
    TH_EQ(rec_size_bytes(&r), 24u);
    float back[6];
    TH_EQ(rec_read(&r, 0u, (uint8_t *)back, 24u), 0);
    static const float want[6] = {1.0f, 3.0f, 11.0f, 13.0f, 21.0f, 23.0f};
    TH_ASSERT(memcmp(back, want, sizeof want) == 0);
    TH_ASSERT(buf[6] == 0.0f && buf[7] == 0.0f);
    TH_EQ(rec_read(&r, 0u, (uint8_t *)back, 25u), -1);
}

static void test_table_playback_bit_exact(void)
{
    drv_t d = make_drv(REC_CAP);
    const uint32_t n = 37u;
    float t[37];
    for (uint32_t i = 0; i < n; i++) {
        t[i] = (float)(0.3 + sin(1.7 * i) * 1e-3 * (i + 1)); /* arbitrary, no -0 */
    }
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t, 20u), DRV_OK); /* two segments, odd split */
    TH_EQ(drv_table_write(&d, 20u, (const uint8_t *)t + 20, n * 4u - 20u), DRV_OK);
    TH_EQ(drv_table_commit(&d, n * 4u), DRV_OK);
    TH_EQ(drv_table_size_bytes(&d), n * 4u);
    uint8_t back[37 * 4];
    TH_EQ(drv_table_read(&d, 0u, back, n * 4u), DRV_OK);
    TH_ASSERT(memcmp(back, t, sizeof back) == 0);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_TABLE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, n), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 1.0f), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, 1u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_RECORD_PERIODS, 3u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, DRV_SIG_REFERENCE), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_OK);
    for (uint32_t i = 0; i < 4u * n; i++) {
        (void)step0(&d);
    }
    uint32_t state;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &state), DRV_OK);
    TH_EQ(state, DRV_RUN_DONE);
    TH_EQ(drv_rec_size_bytes(&d), 3u * n * 4u);
    static uint8_t rec[3 * 37 * 4];
    TH_EQ(drv_rec_read(&d, 0u, rec, sizeof rec), DRV_OK);
    for (uint32_t p = 0; p < 3u; p++) {
        TH_ASSERT(memcmp(rec + p * n * 4u, t, n * 4u) == 0);
    }
    TH_EQ(drv_rec_read(&d, 1u, rec, sizeof rec), DRV_E_LENGTH);
}

static void test_table_write_checks(void)
{
    drv_t d = make_drv(REC_CAP);
    float t[8] = {0, 1, 2, 3, 4, 5, 6, 7};
    TH_EQ(drv_table_write(&d, TAB_CAP * 4u - 4u, (const uint8_t *)t, 8u), DRV_E_LENGTH);
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t, sizeof t), DRV_OK);
    TH_EQ(drv_table_commit(&d, 30u), DRV_E_LENGTH);        /* not a multiple of 4 */
    TH_EQ(drv_table_commit(&d, 4u), DRV_E_LENGTH);         /* one sample */
    TH_EQ(drv_table_commit(&d, TAB_CAP * 4u + 4u), DRV_E_LENGTH);
    t[3] = NAN;
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t, sizeof t), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof t), DRV_E_NOT_FINITE);
    TH_EQ(drv_table_size_bytes(&d), 0u);
    t[3] = 3.0f;
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t, sizeof t), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof t), DRV_OK);
    /* table length must equal the period */
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_TABLE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 16u), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE);
    uint32_t why;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &why), DRV_OK);
    TH_EQ(why, DRV_STOP_BAD_CONFIG);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 8u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t, 4u), DRV_E_STATE); /* while running */
    TH_EQ(drv_table_commit(&d, sizeof t), DRV_E_STATE);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 16u), DRV_E_STATE);
    TH_EQ(drv_set_f32(&d, DRV_P_KFC, 0.25f), DRV_OK); /* controller tunable while running */
}

/* A failed download keeps the previous table (issue 10, finding 14); the generation counts
 * changes of the content (finding 4). */
static void test_table_kept_until_commit(void)
{
    drv_t d = make_drv(REC_CAP);
    float a[4] = {0.1f, 0.2f, 0.3f, 0.4f}, b[8] = {1, 2, 3, 4, 5, 6, 7, NAN}, back[4];
    TH_EQ(drv_table_generation(&d), 0u);
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)a, sizeof a), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof a), DRV_OK);
    TH_EQ(drv_table_generation(&d), 1u);
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)b, 12u), DRV_OK); /* a download under way */
    TH_EQ(drv_table_size_bytes(&d), sizeof a);
    TH_EQ(drv_table_read(&d, 0u, (uint8_t *)back, sizeof back), DRV_OK);
    TH_ASSERT(memcmp(back, a, sizeof a) == 0);
    TH_EQ(drv_table_write(&d, 12u, (const uint8_t *)&b[3], sizeof b - 12u), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof b), DRV_E_NOT_FINITE); /* the download fails */
    TH_EQ(drv_table_size_bytes(&d), sizeof a);
    TH_EQ(drv_table_read(&d, 0u, (uint8_t *)back, sizeof back), DRV_OK);
    TH_ASSERT(memcmp(back, a, sizeof a) == 0);
    TH_EQ(drv_table_generation(&d), 1u);
    uint32_t len;
    TH_EQ(drv_get_u32(&d, DRV_P_TABLE_LENGTH, &len), DRV_OK);
    TH_EQ(len, 4u);
    /* and the kept table still plays */
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_TABLE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 4u), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 1.0f), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_OK);
    step0(&d);
    float ref;
    TH_EQ(drv_get_f32(&d, DRV_P_MEAS_REFERENCE, &ref), DRV_OK);
    TH_NEAR(ref, 0.1f, 0.0);
    drv_run_abort(&d, DRV_STOP_ABORT_CMD);
    /* a multisine run start rewrites the table: a new generation */
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_MULTISINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 128u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_K_MAX, 40u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    TH_EQ(drv_table_generation(&d), 2u);
}

/* Issue 10, finding 1: tables whose samples or central differences overflow float32 are
 * refused at commit; table x amplitude overflowing is refused at the run start; and
 * whatever gets through, a non-finite controller sum is a fault with output 0. */
static void test_overflowing_inputs_refused_and_output_fault(void)
{
    drv_t d = make_drv(REC_CAP);
    float t1[4] = {3e38f, 0.0f, -3e38f, 0.0f}; /* t[2] - t[0] = -6e38: -inf */
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t1, sizeof t1), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof t1), DRV_E_NOT_FINITE);
    TH_EQ(drv_table_size_bytes(&d), 0u);
    float t2[4] = {3e38f, 3e38f, 3e38f, 3e38f}; /* finite, but amplitude 2 overflows */
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t2, sizeof t2), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof t2), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_TABLE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 4u), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 2.0f), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE);
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_BAD_CONFIG);
    float t3[4] = {1e36f, 1e36f, -1e36f, 1e36f}; /* difference x velocity gain overflows */
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t3, sizeof t3), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof t3), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 1.0f), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE); /* 2560 / 2 * 2e36 > FLT_MAX */
    /* accepted inputs whose controller sum overflows (Kp 1e5 x 3e38 rad): fault, output 0 */
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 1.0f), DRV_OK);
    TH_EQ(drv_table_write(&d, 0u, (const uint8_t *)t2, sizeof t2), DRV_OK);
    TH_EQ(drv_table_commit(&d, sizeof t2), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KP, 1.0e5f), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KV, 0.0f), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    for (int k = 0; k < 16; k++) {
        float u = step0(&d);
        TH_ASSERT(isfinite(u));
        TH_NEAR(u, 0.0, 0.0);
    }
    TH_ASSERT(drv_fault(&d));
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_FAULT);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_OUTPUT_FAULT);
    float u_meas;
    TH_EQ(drv_get_f32(&d, DRV_P_MEAS_PLANT_INPUT, &u_meas), DRV_OK);
    TH_NEAR(u_meas, 0.0, 0.0);
    /* cleared by enable, the controller state starts from zero (no NaN left in it) */
    drv_enable(&d, true);
    TH_ASSERT(!drv_fault(&d));
    TH_ASSERT(isfinite(step0(&d)));
}

/* ---------------- run control ---------------- */

static void test_run_exact_sample_counts(void)
{
    drv_t d = make_drv(REC_CAP);
    const uint32_t n = 16u, settle = 2u, record = 3u;
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, n), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SINE_CYCLES, 3u), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 0.5f), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, settle), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_RECORD_PERIODS, record), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, 0x1Fu), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_E_STATE); /* not enabled */
    drv_enable(&d, true);
    TH_EQ(drv_set_u32(&d, DRV_P_RUN_COMMAND, 1u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_E_STATE); /* already running */
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_TOTAL, &v), DRV_OK);
    TH_EQ(v, (settle + record) * n);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_COUNTER, &v), DRV_OK);
    TH_EQ(v, 1u);
    uint32_t counts[6] = {0};
    for (uint32_t i = 0; i < 200u; i++) {
        uint32_t s;
        TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &s), DRV_OK);
        counts[s]++;
        (void)step0(&d);
    }
    TH_EQ(counts[DRV_RUN_SETTLING], settle * n);
    TH_EQ(counts[DRV_RUN_RECORDING], record * n);
    TH_EQ(counts[DRV_RUN_DONE], 200u - (settle + record) * n);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_PROGRESS, &v), DRV_OK);
    TH_EQ(v, (settle + record) * n);
    TH_EQ(drv_get_u32(&d, DRV_P_REC_SAMPLES, &v), DRV_OK);
    TH_EQ(v, record * n);
    TH_EQ(drv_get_u32(&d, DRV_P_REC_BYTES, &v), DRV_OK);
    TH_EQ(v, record * n * 5u * 4u);
    /* the recorded reference starts at phase 0 of the period, error = ref - motor */
    float first[5];
    TH_EQ(drv_rec_read(&d, 0u, (uint8_t *)first, sizeof first), DRV_OK);
    TH_NEAR(first[0], 0.0, 0.0);
    TH_NEAR(first[4], first[0] - first[2], 0.0);
    /* after the run the excitation is off: reference back at the set-point */
    float ref;
    TH_EQ(drv_get_f32(&d, DRV_P_MEAS_REFERENCE, &ref), DRV_OK);
    TH_NEAR(ref, 0.0, 0.0);
    /* second run: counter 2, abort mid-way keeps the partial record */
    TH_EQ(drv_run_start(&d), DRV_OK);
    for (uint32_t i = 0; i < settle * n + 5u; i++) {
        (void)step0(&d);
    }
    TH_EQ(drv_set_u32(&d, DRV_P_RUN_COMMAND, 2u), DRV_OK);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_ABORTED);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_ABORT_CMD);
    TH_EQ(drv_get_u32(&d, DRV_P_REC_SAMPLES, &v), DRV_OK);
    TH_EQ(v, 5u);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_COUNTER, &v), DRV_OK);
    TH_EQ(v, 2u);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_COMMAND, &v), DRV_OK);
    TH_EQ(v, 0u);
    /* zero settle periods: recording from the first step */
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, 0u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_RECORDING);
}

static void test_run_refusals(void)
{
    /* recorder capacity: 3 signals x 64 samples = 192 floats; 191 refuse, 192 fit */
    drv_t d = make_drv(191u);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 64u), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_E_NO_FIT);
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_NO_FIT);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_IDLE);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_COUNTER, &v), DRV_OK);
    TH_EQ(v, 0u);
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, 0x03u), DRV_OK); /* 2 signals: 128 fit */
    TH_EQ(drv_run_start(&d), DRV_OK);
    drv_t d2 = make_drv(192u);
    TH_EQ(drv_set_u32(&d2, DRV_P_EXC_PERIOD, 64u), DRV_OK);
    drv_enable(&d2, true);
    TH_EQ(drv_run_start(&d2), DRV_OK); /* exact fit, kind none */
    /* inconsistent excitation configs */
    drv_t d3 = make_drv(REC_CAP);
    drv_enable(&d3, true);
    TH_EQ(drv_set_u32(&d3, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(&d3, DRV_P_EXC_PERIOD, 64u), DRV_OK);
    TH_EQ(drv_set_u32(&d3, DRV_P_EXC_SINE_CYCLES, 32u), DRV_OK);
    TH_EQ(drv_run_start(&d3), DRV_E_INCOMPATIBLE); /* at Nyquist */
    TH_EQ(drv_get_u32(&d3, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_BAD_CONFIG);
    TH_EQ(drv_set_u32(&d3, DRV_P_EXC_KIND, DRV_EXC_MULTISINE), DRV_OK);
    TH_EQ(drv_set_u32(&d3, DRV_P_EXC_PERIOD, 100u), DRV_OK); /* not a power of two */
    TH_EQ(drv_run_start(&d3), DRV_E_INCOMPATIBLE);
    TH_EQ(drv_set_u32(&d3, DRV_P_EXC_PERIOD, 128u), DRV_OK);
    TH_EQ(drv_set_u32(&d3, DRV_P_MS_K_MAX, 64u), DRV_OK); /* k_max >= N/2 */
    TH_EQ(drv_run_start(&d3), DRV_E_INCOMPATIBLE);
    TH_EQ(drv_set_u32(&d3, DRV_P_MS_K_MAX, 63u), DRV_OK);
    TH_EQ(drv_run_start(&d3), DRV_OK);
    TH_EQ(drv_get_u32(&d3, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_NONE);
}

static void test_enable_safe_stop_fault(void)
{
    drv_t d = make_drv(REC_CAP);
    drv_meas_t m = {0.7f, 0.6f};
    TH_NEAR(drv_step(&d, &m), 0.0, 0.0); /* disabled: no output */
    drv_enable(&d, true);
    drv_monitor_t mon;
    drv_get_monitor(&d, &mon);
    TH_NEAR(mon.target_rad, 0.7, 1e-7); /* holds where it is: no jump */
    TH_NEAR(drv_step(&d, &m), 0.0, 1e-6);
    TH_EQ(drv_set_target(&d, 0.8f), DRV_OK);
    /* Kp 20 V/rad on 0.1 rad plus the derivative kick Kd/(tau+T) * 0.1, saturated at 10 V */
    TH_NEAR(drv_step(&d, &m), 10.0, 1e-6);
    TH_EQ(drv_set_f32(&d, DRV_P_KD, 0.0f), DRV_OK);
    TH_EQ(drv_set_target(&d, 0.7f), DRV_OK);
    for (int i = 0; i < 100; i++) {
        (void)drv_step(&d, &m); /* the old derivative state decays */
    }
    TH_EQ(drv_set_target(&d, 0.8f), DRV_OK);
    TH_NEAR(drv_step(&d, &m), 20.0 * 0.1, 1e-4);
    /* start a run, then lose the host: aborted, hold present position */
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 0.1f), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    for (int i = 0; i < 10; i++) {
        (void)drv_step(&d, &m);
    }
    m.motor_angle_rad = 0.75f;
    (void)drv_step(&d, &m);
    drv_safe_stop(&d, DRV_STOP_HEARTBEAT);
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_ABORTED);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_HEARTBEAT);
    TH_NEAR(drv_step(&d, &m), 0.0, 1e-6); /* target = 0.75 = measured */
    /* disabling aborts a run */
    TH_EQ(drv_run_start(&d), DRV_OK);
    drv_enable(&d, false);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_DISABLED);
    /* non-finite measurement: fault, output 0, latched until re-enable */
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_OK);
    drv_meas_t bad = {NAN, 0.0f};
    TH_NEAR(drv_step(&d, &bad), 0.0, 0.0);
    TH_ASSERT(drv_fault(&d));
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_FAULT);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_MEAS_FAULT);
    m.motor_angle_rad = 0.0f;
    TH_NEAR(drv_step(&d, &m), 0.0, 0.0);
    TH_EQ(drv_run_start(&d), DRV_E_STATE);
    drv_enable(&d, true);
    TH_ASSERT(!drv_fault(&d));
    TH_EQ(drv_run_start(&d), DRV_OK);
}

/* drv_step tests both measurements for finiteness at once (drv_nan_unless_finite): each of
 * NaN, +inf and -inf in either one faults (reason MEAS_FAULT, output 0); the largest finite,
 * the smallest subnormal and a negative zero pass (no fault, the controller's output). */
static void test_meas_not_finite_in_either_faults(void)
{
    const float bad[] = {NAN, INFINITY, -INFINITY};
    for (int which = 0; which < 2; which++) {
        for (size_t i = 0; i < sizeof bad / sizeof bad[0]; i++) {
            drv_t d = make_drv(REC_CAP);
            drv_enable(&d, true);
            drv_meas_t m = {0.25f, -0.5f};
            TH_ASSERT(isfinite(drv_step(&d, &m)));
            if (which == 0) {
                m.motor_angle_rad = bad[i];
            } else {
                m.load_angle_rad = bad[i];
            }
            TH_NEAR(drv_step(&d, &m), 0.0, 0.0);
            TH_ASSERT(drv_fault(&d));
            uint32_t v;
            TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
            TH_EQ(v, DRV_STOP_MEAS_FAULT);
        }
    }
    const float good[][2] = {{3.4028235e38f, -3.4028235e38f}, {1e-45f, -1e-45f}, {-0.0f, 0.0f}};
    for (size_t i = 0; i < sizeof good / sizeof good[0]; i++) {
        drv_t d = make_drv(REC_CAP);
        TH_EQ(drv_set_f32(&d, DRV_P_KP, 1e-3f), DRV_OK); /* kp e stays finite at FLT_MAX */
        TH_EQ(drv_set_f32(&d, DRV_P_U_MAX, 10.0f), DRV_OK);
        drv_enable(&d, true); /* target = the last measurement (0) */
        drv_meas_t m = {good[i][0], good[i][1]};
        float u = drv_step(&d, &m);
        TH_ASSERT(!drv_fault(&d));
        /* kp (0 - motor), saturated to +-10 V */
        double expect = fmax(-10.0, fmin(10.0, -1e-3 * (double)good[i][0]));
        TH_NEAR(u, expect, 1e-6 * fabs(expect) + 1e-44); /* the subnormal product underflows */
    }
}

static void test_plant_input_injection(void)
{
    drv_t d = make_drv(REC_CAP);
    TH_EQ(drv_set_f32(&d, DRV_P_KP, 0.0f), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KD, 0.0f), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_INJECT, DRV_INJECT_PLANT_INPUT), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 64u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, 0u), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 2.0f), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_OFFSET, 0.5f), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KFC, 1.0f), DRV_OK); /* no reference velocity: no FF */
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, DRV_SIG_REFERENCE | DRV_SIG_PLANT_INPUT), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_OK);
    for (uint32_t i = 0; i < 64u; i++) {
        float u = step0(&d);
        TH_NEAR(u, 0.5 + 2.0 * sin(2.0 * M_PI * i / 64.0), 2e-6);
    }
    float r[2];
    TH_EQ(drv_rec_read(&d, 8u * 16u, (uint8_t *)r, 8u), DRV_OK); /* sample 16 */
    TH_NEAR(r[0], 0.0, 0.0);       /* reference untouched */
    TH_NEAR(r[1], 2.5, 2e-6);      /* u = offset + amp at a quarter period */
}

/* ---------------- multisine ---------------- */

static void test_ms_prng_vectors(void)
{
    for (size_t i = 0; i < MSV_N_FMIX; i++) {
        TH_EQ(ms_fmix32(MSV_FMIX[i].in), MSV_FMIX[i].out);
    }
    for (size_t i = 0; i < MSV_N_PRNG; i++) {
        const msv_prng_t *p = &MSV_PRNG[i];
        uint32_t x = ms_stream_init(p->seed, p->stream);
        TH_EQ(x, p->init);
        for (int k = 0; k < 8; k++) {
            TH_EQ(ms_next(&x), p->outputs[k]);
        }
    }
    TH_NEAR(ms_uniform01(0xFFFFFFFFu), 1.0 - 1.0 / 16777216.0, 0.0);
    TH_EQ(ms_index(0xFFFFFFFFu, 5u), 4u);
}

static void test_ms_lines_and_period_vectors(void)
{
    static float buf[8192];
    for (size_t i = 0; i < MSV_N_DESIGNS; i++) {
        const msv_design_t *v = &MSV_DESIGNS[i];
        ms_design_t d = {v->n, v->k_min, v->k_max, v->g, v->seed, v->m};
        TH_EQ(ms_check(&d), MS_OK);
        TH_EQ(ms_excited_count(&d), v->n_excited);
        ms_lines_t it;
        ms_lines_begin(&it, &d);
        uint32_t bin, ne = 0, nr = 0;
        bool exc;
        while (ms_lines_next(&it, &bin, &exc)) {
            if (exc) {
                TH_ASSERT(ne < v->n_excited && v->excited[ne] == bin);
                ne++;
            } else {
                TH_ASSERT(nr < v->n_removed && v->removed[nr] == bin);
                nr++;
            }
        }
        TH_EQ(ne, v->n_excited);
        TH_EQ(nr, v->n_removed);
        TH_EQ(ms_build(&d, (float)v->rms, buf, 8192u), MS_OK);
        double peak = 0.0, err = 0.0;
        for (uint32_t k = 0; k < v->n; k++) {
            peak = fmax(peak, fabs(v->period[k]));
            err = fmax(err, fabs(buf[k] - v->period[k]));
        }
        TH_ASSERT(err <= 1e-5 * peak);
        if (!(err <= 1e-5 * peak)) {
            fprintf(stderr, "  design %zu: max err %.3g, peak %.3g\n", i, err, peak);
        }
    }
}

/* The documented ranges of ms.h at their edges (each limit on both sides), the line
 * counts of one-line bands, and ms_build's argument checks (found missing by mutation
 * testing: docs/testing.md). */
static void test_ms_check_and_build_edges(void)
{
    ms_design_t d = {64u, 1u, 25u, 0u, 1u, 0u};
    TH_EQ(ms_check(&d), MS_OK);
    d.n = MS_N_MIN;
    d.k_max = 7u;
    TH_EQ(ms_check(&d), MS_OK);
    d.n = MS_N_MIN / 2u;
    d.k_max = 3u;
    TH_EQ(ms_check(&d), MS_E_N);
    d.n = MS_N_MAX;
    TH_EQ(ms_check(&d), MS_OK);
    d.n = 2u * MS_N_MAX;
    TH_EQ(ms_check(&d), MS_E_N);
    d.n = 48u;
    TH_EQ(ms_check(&d), MS_E_N); /* not a power of two */
    d.n = 64u;
    d.k_min = 0u;
    TH_EQ(ms_check(&d), MS_E_BAND);
    d.k_min = 31u;
    d.k_max = 31u; /* N/2 - 1: the highest line allowed */
    TH_EQ(ms_check(&d), MS_OK);
    d.k_max = 32u;
    TH_EQ(ms_check(&d), MS_E_BAND);
    d.k_min = 6u;
    d.k_max = 5u;
    TH_EQ(ms_check(&d), MS_E_BAND);
    TH_EQ(ms_candidate_count(&d), 0u); /* called on its own with an empty band */
    /* one-line bands: k_min = k_max odd gives one line; even gives none */
    d.k_min = 5u;
    d.k_max = 5u;
    TH_EQ(ms_candidate_count(&d), 1u);
    TH_EQ(ms_excited_count(&d), 1u);
    TH_EQ(ms_check(&d), MS_OK);
    d.k_min = 4u;
    d.k_max = 4u;
    TH_EQ(ms_candidate_count(&d), 0u);
    TH_EQ(ms_check(&d), MS_E_NO_LINES);
    /* group: 0 or 2 .. MS_G_MAX */
    d.k_min = 1u;
    d.k_max = 25u;
    d.group = 1u;
    TH_EQ(ms_check(&d), MS_E_GROUP);
    d.group = MS_G_MAX;
    TH_EQ(ms_check(&d), MS_OK);
    d.group = MS_G_MAX + 1u;
    TH_EQ(ms_check(&d), MS_E_GROUP);
    /* ms_build: rms finite and >= 0 (0 allowed: a zero period), buffer of >= N floats,
     * and every sample written (also the DC bin of the packed spectrum) */
    static float buf[65];
    d.group = 0u;
    TH_EQ(ms_build(&d, NAN, buf, 64u), MS_E_RMS);
    TH_EQ(ms_build(&d, INFINITY, buf, 64u), MS_E_RMS);
    TH_EQ(ms_build(&d, -1.0f, buf, 64u), MS_E_RMS);
    TH_EQ(ms_build(&d, 1.0f, buf, 63u), MS_E_CAPACITY);
    TH_EQ(ms_build(&d, 1.0f, NULL, 64u), MS_E_CAPACITY);
    for (int i = 0; i < 65; i++) {
        buf[i] = 1000.0f;
    }
    TH_EQ(ms_build(&d, 0.0f, buf, 64u), MS_OK);
    double worst = 0.0;
    for (int i = 0; i < 64; i++) {
        worst = fmax(worst, fabs(buf[i]));
    }
    TH_NEAR(worst, 0.0, 0.0);
    TH_NEAR(buf[64], 1000.0, 0.0); /* nothing written past N */
    for (int i = 0; i < 65; i++) {
        buf[i] = 1000.0f;
    }
    TH_EQ(ms_build(&d, 1.0f, buf, 65u), MS_OK);
    double mean = 0.0, power = 0.0;
    for (int i = 0; i < 64; i++) {
        mean += buf[i] / 64.0;
        power += (double)buf[i] * buf[i] / 64.0;
    }
    TH_NEAR(mean, 0.0, 1e-6);      /* no line at DC */
    TH_NEAR(power, 1.0, 1e-5);     /* rms 1 */
    TH_NEAR(buf[64], 1000.0, 0.0);
}

static void test_ms_through_drive(void)
{
    /* the drive builds the period at run start; recorded reference = rms * unit period */
    const msv_design_t *v = &MSV_DESIGNS[2];
    drv_t d = make_drv(REC_CAP);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_MULTISINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, v->n), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_K_MIN, v->k_min), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_K_MAX, v->k_max), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_GROUP, v->g), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_SEED, v->seed), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_REALIZATION, v->m), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, (float)v->rms), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, 1u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_RECORD_PERIODS, 2u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, DRV_SIG_REFERENCE), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_run_start(&d), DRV_OK);
    uint32_t len;
    TH_EQ(drv_get_u32(&d, DRV_P_TABLE_LENGTH, &len), DRV_OK);
    TH_EQ(len, v->n);
    for (uint32_t i = 0; i < 3u * v->n; i++) {
        (void)step0(&d);
    }
    static float r[512];
    TH_EQ(drv_rec_read(&d, 0u, (uint8_t *)r, 2u * v->n * 4u), DRV_OK);
    double peak = 0.0, err = 0.0;
    for (uint32_t k = 0; k < 2u * v->n; k++) {
        double ref = v->period[k % v->n];
        peak = fmax(peak, fabs(ref));
        err = fmax(err, fabs(r[k] - ref));
    }
    TH_ASSERT(err <= 1e-5 * peak);
}

static void test_fft_inverse_complex_small(void)
{
    /* a single bin k=3 of M=8: a[m] = exp(+j 2 pi 3 m / 8) */
    float a[16] = {0};
    a[6] = 1.0f;
    TH_ASSERT(fft_inverse_complex(a, 8u));
    for (int m = 0; m < 8; m++) {
        TH_NEAR(a[2 * m], cos(2 * M_PI * 3 * m / 8.0), 1e-6);
        TH_NEAR(a[2 * m + 1], sin(2 * M_PI * 3 * m / 8.0), 1e-6);
    }
    TH_ASSERT(!fft_inverse_complex(a, 6u));
    TH_ASSERT(!fft_inverse_real(a, 12u));
}

/* xorshift for the randomized sequence (deterministic) */
static uint32_t rnd_state = 0x12345678u;
static uint32_t rnd(void)
{
    rnd_state ^= rnd_state << 13;
    rnd_state ^= rnd_state >> 17;
    rnd_state ^= rnd_state << 5;
    return rnd_state;
}

static float rnd_float(void)
{
    switch (rnd() % 8u) {
    case 0: return NAN;
    case 1: return (rnd() & 1u) ? INFINITY : -INFINITY;
    case 2: return -(float)(rnd() % 1000u) * 0.01f;
    case 3: return (float)(rnd() % 100000u) * 10.0f;
    default: return (float)(rnd() % 1000u) * 0.001f;
    }
}

static void test_random_api_sequences_keep_invariants(void)
{
    /* 200 000 random calls (parameters incl. NaN/inf/out of range, run start/abort/safe
     * stop, enable, table writes, non-finite measurements, steps). After every call: a
     * rejected set leaves the value unchanged; the output is finite and within +-u_max; the
     * recorder never exceeds its capacity; progress never exceeds the run length. */
    drv_t d = make_drv(4096u);
    /* a one-line list, so that the line statistics switched on at random refuse a start
     * for their set-up only (with no list at all every later start would be refused) */
    const uint16_t one_line[1] = {1u};
    TH_EQ(drv_lines_write(&d, 0u, (const uint8_t *)one_line, 2u), DRV_OK);
    TH_EQ(drv_lines_commit(&d, 2u), DRV_OK);
    float motor = 0.0f;
    int fails = 0;
    for (int i = 0; i < 200000 && fails < 5; i++) {
        uint32_t op = rnd() % 10u;
        drv_param_id_t id = (drv_param_id_t)(rnd() % (DRV_PARAM_COUNT + 2u));
        if (op <= 2u) {
            float before = 0.0f, after = 0.0f, v = rnd_float();
            drv_status_t g = drv_get_f32(&d, id, &before);
            drv_status_t s = drv_set_f32(&d, id, v);
            if (g == DRV_OK && s != DRV_OK) {
                (void)drv_get_f32(&d, id, &after);
                if (memcmp(&before, &after, sizeof before) != 0) {
                    TH_ASSERT(!"rejected f32 set changed the value");
                    fails++;
                }
            }
        } else if (op <= 4u) {
            uint32_t before = 0u, after = 0u, v = (rnd() & 1u) ? rnd() % 40u : rnd() % 9000u;
            if (id == DRV_P_EXC_PERIOD && (rnd() & 1u)) {
                v = 16u << (rnd() % 5u);
            }
            drv_status_t g = drv_get_u32(&d, id, &before);
            drv_status_t s = drv_set_u32(&d, id, v);
            if (g == DRV_OK && s != DRV_OK && id != DRV_P_RUN_COMMAND) {
                (void)drv_get_u32(&d, id, &after);
                if (after != before) {
                    TH_ASSERT(!"rejected u32 set changed the value");
                    fails++;
                }
            }
        } else if (op == 5u) {
            switch (rnd() % 6u) {
            case 0:
                if (rnd() % 4u == 0u) {
                    /* now and then a consistent set-up first (a short sine run), so that
                     * runs keep starting whatever the random writes left configured */
                    (void)drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE);
                    (void)drv_set_u32(&d, DRV_P_EXC_PERIOD, 64u);
                    (void)drv_set_u32(&d, DRV_P_EXC_SINE_CYCLES, 1u);
                    (void)drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, rnd() % 2u);
                    (void)drv_set_u32(&d, DRV_P_EXC_RECORD_PERIODS, 1u + rnd() % 3u);
                    (void)drv_set_u32(&d, DRV_P_REC_SIGNALS, 0x07u);
                }
                (void)drv_run_start(&d);
                break;
            case 1: drv_run_abort(&d, DRV_STOP_ABORT_CMD); break;
            case 2: drv_safe_stop(&d, DRV_STOP_HEARTBEAT); break;
            case 3: drv_enable(&d, (rnd() & 1u) != 0u); break;
            case 4: (void)drv_set_target(&d, rnd_float()); break;
            default: {
                float t[16];
                for (int k = 0; k < 16; k++) {
                    t[k] = (float)(rnd() % 200u) * 0.01f - 1.0f;
                }
                uint32_t off = (rnd() % 8u) * 64u;
                (void)drv_table_write(&d, off, (const uint8_t *)t, sizeof t);
                (void)drv_table_commit(&d, off + (uint32_t)sizeof t);
                break;
            }
            }
        } else {
            drv_meas_t m = {motor, 0.5f * motor};
            if (rnd() % 5000u == 0u) {
                m.motor_angle_rad = NAN;
            }
            float u = drv_step(&d, &m);
            float umax;
            (void)drv_get_f32(&d, DRV_P_U_MAX, &umax);
            if (!isfinite(u) || fabsf(u) > umax) {
                TH_ASSERT(!"output not finite or beyond u_max");
                fails++;
            }
            motor += 1e-3f * u;
        }
        uint32_t cap, bytes, prog, total;
        (void)drv_get_u32(&d, DRV_P_REC_CAPACITY, &cap);
        (void)drv_get_u32(&d, DRV_P_REC_BYTES, &bytes);
        (void)drv_get_u32(&d, DRV_P_RUN_PROGRESS, &prog);
        (void)drv_get_u32(&d, DRV_P_RUN_TOTAL, &total);
        if (bytes > cap * 4u || prog > total) {
            TH_ASSERT(!"recorder beyond capacity or progress beyond the run");
            fails++;
        }
    }
    uint32_t runs;
    (void)drv_get_u32(&d, DRV_P_RUN_COUNTER, &runs);
    TH_ASSERT(runs > 10u); /* the sequence did exercise runs */
    printf("random API sequences: %u runs started\n", (unsigned)runs);
}


/* ---------------- on-drive statistics (stat.h): deferred to the background ---------------- */

/* The per-sample update as the control step did it before the background split (the
 * reference): the same float32 operations in the same order, fed with the recorded
 * samples (all 5 signals) and the generator's sin/cos of the phase index. Writes the
 * 0x2041 byte stream; returns its length. */
static uint32_t ref_stats(const float *rec, uint32_t samples, uint32_t n, uint32_t cycles, uint32_t k_run,
                          uint32_t hmask, uint32_t pmask, float quarter_step, uint8_t *out)
{
    uint32_t hsel[3], psel[5], nh = 0u, np = 0u;
    for (uint32_t b = 0u; b < 5u; b++) {
        if (hmask & (1u << b)) {
            hsel[nh++] = b;
        }
        if (pmask & (1u << b)) {
            psel[np++] = b;
        }
    }
    float x0[3] = {0}, ar[3][8] = {{0}}, ai[3][8] = {{0}}, mr[3][8] = {{0}}, mi[3][8] = {{0}}, m2[3][8] = {{0}};
    float psum[5] = {0}, psq[5] = {0}, pmean[5] = {0}, pmsq[5] = {0};
    const float inv_n = 1.0f / (float)n;
    uint32_t idx = 0u, periods = 0u;
    for (uint32_t i = 0u; i < samples; i++) {
        const float *sig = rec + 5u * i;
        float s, c;
        gen_sincos_index((uint32_t)(((uint64_t)cycles * i) % n), n, quarter_step, &s, &c);
        if (i == 0u) {
            for (uint32_t j = 0u; j < nh; j++) {
                x0[j] = sig[hsel[j]];
            }
        }
        float zr[8], zi[8];
        zr[0] = c;
        zi[0] = -s;
        zr[1] = c * c - s * s;
        zi[1] = -2.0f * c * s;
        zr[2] = zr[1] * c + zi[1] * s;
        zi[2] = zi[1] * c - zr[1] * s;
        zr[3] = zr[1] * zr[1] - zi[1] * zi[1];
        zi[3] = 2.0f * zr[1] * zi[1];
        for (uint32_t k = 0u; k < 4u; k++) {
            zr[4u + k] = zr[3] * zr[k] - zi[3] * zi[k];
            zi[4u + k] = zr[3] * zi[k] + zi[3] * zr[k];
        }
        for (uint32_t j = 0u; j < nh && k_run > 0u; j++) {
            const float x = sig[hsel[j]] - x0[j];
            for (uint32_t k = 0u; k < 8u; k++) {
                ar[j][k] += x * zr[k];
                ai[j][k] += x * zi[k];
            }
        }
        for (uint32_t j = 0u; j < np; j++) {
            psum[j] += sig[psel[j]];
            psq[j] += sig[psel[j]] * sig[psel[j]];
        }
        if (++idx == n) {
            idx = 0u;
            periods++;
            const float w = 1.0f / (float)periods;
            for (uint32_t j = 0u; j < nh; j++) {
                for (uint32_t k = 0u; k < k_run; k++) {
                    const float xr = ar[j][k], xi = ai[j][k];
                    const float dr = xr - mr[j][k], di = xi - mi[j][k];
                    mr[j][k] += dr * w;
                    mi[j][k] += di * w;
                    m2[j][k] += dr * (xr - mr[j][k]) + di * (xi - mi[j][k]);
                    ar[j][k] = 0.0f;
                    ai[j][k] = 0.0f;
                }
            }
            for (uint32_t j = 0u; j < np; j++) {
                pmean[j] += (psum[j] * inv_n - pmean[j]) * w;
                pmsq[j] += (psq[j] * inv_n - pmsq[j]) * w;
                psum[j] = 0.0f;
                psq[j] = 0.0f;
            }
        }
    }
    float f[8u + 3u * 8u * 3u + 2u * 5u];
    uint32_t nf = 0u;
    for (uint32_t j = 0u; j < nh && k_run > 0u; j++) {
        for (uint32_t k = 0u; k < k_run; k++) {
            f[nf++] = mr[j][k];
            f[nf++] = mi[j][k];
            f[nf++] = periods > 1u ? m2[j][k] / (float)(periods - 1u) : 0.0f;
        }
    }
    for (uint32_t j = 0u; j < np; j++) {
        f[nf++] = pmean[j];
        f[nf++] = pmsq[j];
    }
    uint32_t hdr[2] = {periods, k_run | ((k_run ? hmask : 0u) << 8) | (pmask << 16)};
    memcpy(out, hdr, 8u);
    memcpy(out + 8u, f, 4u * nf);
    return 8u + 4u * nf;
}

/* A sine run with statistics (K = 8 of reference, plant input, motor angle; power of
 * motor angle and error), all 5 signals recorded. */
static void stat_setup(drv_t *d, uint32_t n, uint32_t cycles, uint32_t periods)
{
    drv_enable(d, true);
    TH_EQ(drv_set_f32(d, DRV_P_KFC, 0.1f), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_REC_SIGNALS, 0x1Fu), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_PERIOD, n), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_SINE_CYCLES, cycles), DRV_OK);
    TH_EQ(drv_set_f32(d, DRV_P_EXC_AMPLITUDE, 0.4f), DRV_OK);
    TH_EQ(drv_set_f32(d, DRV_P_EXC_OFFSET, 2.5f), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_SETTLE_PERIODS, 1u), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_RECORD_PERIODS, periods), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_STAT_HARMONICS, 8u), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_STAT_SIGNALS, 0x07u), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_STAT_POWER, 0x14u), DRV_OK);
    TH_EQ(drv_run_start(d), DRV_OK);
}

/* A crude plant so the signals are not trivial: motor follows u through an integrator. */
static float stat_step(drv_t *d, float motor)
{
    drv_meas_t m = {motor, 0.5f * motor};
    float u = drv_step(d, &m);
    return motor + 2e-3f * u + 1e-4f * sinf(37.0f * motor);
}

static void test_stat_deferred_equals_per_sample_reference_bit_for_bit(void)
{
    static uint8_t got[STAT_MAX_BYTES], want[STAT_MAX_BYTES];
    /* background every step, every 11th step (blocks pile up to 2), and a period that is
     * not a multiple of the block (periods end inside blocks) */
    const uint32_t every[] = {1u, 11u, 16u, 0u}; /* 0: drv_background_catch_up after each step
                                                     (the PIL port's interrupt-side catch-up) */
    for (uint32_t t = 0u; t < sizeof every / sizeof every[0]; t++) {
        drv_t d = make_drv(REC_CAP);
        const uint32_t n = 500u, cycles = 3u, periods = 5u;
        stat_setup(&d, n, cycles, periods);
        const float quarter_step = d.gen.quarter_step;
        float motor = 2.5f;
        for (uint32_t i = 0u; i < (periods + 1u) * n; i++) {
            motor = stat_step(&d, motor);
            if (every[t] == 0u) {
                (void)drv_background_catch_up(&d);
            } else if ((i + 1u) % every[t] == 0u) {
                drv_background(&d);
            }
        }
        uint32_t state, samples, ovr;
        TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &state), DRV_OK);
        TH_EQ(state, DRV_RUN_DONE);
        TH_EQ(drv_get_u32(&d, DRV_P_REC_SAMPLES, &samples), DRV_OK);
        TH_EQ(samples, periods * n);
        uint32_t size = drv_stat_size_bytes(&d);
        TH_EQ(size, 8u + 12u * 8u * 3u + 8u * 2u);
        TH_EQ(drv_stat_read(&d, 0u, got, size), DRV_OK);
        uint32_t wsize = ref_stats(rec_buf, samples, n, cycles, 8u, 0x07u, 0x14u, quarter_step, want);
        TH_EQ(wsize, size);
        TH_ASSERT(memcmp(got, want, size) == 0);
        uint32_t p;
        memcpy(&p, got, 4u);
        TH_EQ(p, periods);
        TH_EQ(drv_get_u32(&d, DRV_P_STAT_OVERRUNS, &ovr), DRV_OK);
        TH_EQ(ovr, 0u);
        /* not a trivial match: the fundamental of the reference is about amp N / 2 */
        float mre, mim;
        memcpy(&mre, got + 8u, 4u);
        memcpy(&mim, got + 12u, 4u);
        TH_NEAR(sqrtf(mre * mre + mim * mim), 0.4f * (float)n / 2.0f, 1e-2f);
    }
}

static void test_stat_overrun_is_reported_not_delivered(void)
{
    static uint8_t got[STAT_MAX_BYTES];
    drv_t d = make_drv(REC_CAP);
    stat_setup(&d, 200u, 1u, 3u);
    float motor = 2.5f;
    /* settle, then the background keeps up for a while ... */
    for (uint32_t i = 0u; i < 300u; i++) {
        motor = stat_step(&d, motor);
        drv_background(&d);
    }
    /* ... then misses 2 blocks and a bit: the interrupt finds both blocks full */
    for (uint32_t i = 0u; i < 2u * STAT_BLOCK + 1u; i++) {
        motor = stat_step(&d, motor);
    }
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_OVERRUNS, &v), DRV_OK);
    TH_EQ(v, 1u);
    while (drv_get_u32(&d, DRV_P_RUN_STATE, &v) == DRV_OK && v == DRV_RUN_RECORDING) {
        motor = stat_step(&d, motor);
        drv_background(&d);
    }
    TH_EQ(v, DRV_RUN_DONE);
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_PERIODS, &v), DRV_OK);
    TH_EQ(v, 0u); /* the host's check (periods == recorded periods) rejects it */
    uint32_t size = drv_stat_size_bytes(&d);
    TH_EQ(drv_stat_read(&d, 0u, got, size), DRV_OK);
    uint32_t w0, w1;
    memcpy(&w0, got, 4u);
    memcpy(&w1, got + 4u, 4u);
    TH_EQ(w0, 0u);
    TH_EQ(w1 >> 24, STAT_FLAG_OVERRUN);
    TH_EQ(w1 & 0xFFu, 8u); /* the layout stays readable */
    uint32_t nonzero = 0u;
    for (uint32_t i = 8u; i < size; i++) {
        nonzero += got[i] != 0u;
    }
    TH_EQ(nonzero, 0u); /* no numbers rather than wrong ones */
    /* the next run with a background that keeps up is valid again; the counter stays */
    TH_EQ(drv_run_start(&d), DRV_OK);
    while (drv_get_u32(&d, DRV_P_RUN_STATE, &v) == DRV_OK && v == DRV_RUN_SETTLING) {
        motor = stat_step(&d, motor);
        drv_background(&d);
    }
    while (drv_get_u32(&d, DRV_P_RUN_STATE, &v) == DRV_OK && v == DRV_RUN_RECORDING) {
        motor = stat_step(&d, motor);
        drv_background(&d);
    }
    TH_EQ(drv_stat_read(&d, 0u, got, size), DRV_OK);
    memcpy(&w0, got, 4u);
    memcpy(&w1, got + 4u, 4u);
    TH_EQ(w0, 3u);
    TH_EQ(w1 >> 24, 0u);
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_OVERRUNS, &v), DRV_OK);
    TH_EQ(v, 1u);
}

static void test_stat_read_right_after_the_run_is_final(void)
{
    static uint8_t got[STAT_MAX_BYTES], want[STAT_MAX_BYTES];
    /* 3 x 100 samples: the last block holds 300 % 16 = 12 samples; the background never
     * runs after the last 20 steps, so the last period is still pending at DONE */
    drv_t d = make_drv(REC_CAP);
    const uint32_t n = 100u, periods = 3u;
    stat_setup(&d, n, 2u, periods);
    const float quarter_step = d.gen.quarter_step;
    float motor = 2.5f;
    const uint32_t steps = (periods + 1u) * n;
    for (uint32_t i = 0u; i < steps; i++) {
        motor = stat_step(&d, motor);
        if (i + 20u < steps) {
            drv_background(&d);
        }
    }
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_DONE);
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_PERIODS, &v), DRV_OK);
    TH_EQ(v, periods - 1u); /* the background has not seen the last period yet */
    uint32_t size = drv_stat_size_bytes(&d); /* the reader (SDO upload of 0x2041) drains */
    TH_EQ(drv_stat_read(&d, 0u, got, size), DRV_OK);
    TH_EQ(ref_stats(rec_buf, periods * n, n, 2u, 8u, 0x07u, 0x14u, quarter_step, want), size);
    TH_ASSERT(memcmp(got, want, size) == 0);
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_PERIODS, &v), DRV_OK);
    TH_EQ(v, periods);

    /* an abort mid-period: the read has the completed periods and the samples so far */
    drv_t a = make_drv(REC_CAP);
    stat_setup(&a, n, 2u, periods);
    for (uint32_t i = 0u; i < n + 2u * n + 37u; i++) {
        motor = stat_step(&a, motor);
        if (i % 5u == 0u) {
            drv_background(&a);
        }
    }
    drv_run_abort(&a, DRV_STOP_ABORT_CMD);
    size = drv_stat_size_bytes(&a);
    TH_EQ(drv_stat_read(&a, 0u, got, size), DRV_OK);
    uint32_t rs;
    TH_EQ(drv_get_u32(&a, DRV_P_REC_SAMPLES, &rs), DRV_OK);
    TH_EQ(rs, 2u * n + 37u);
    TH_EQ(ref_stats(rec_buf, rs, n, 2u, 8u, 0x07u, 0x14u, quarter_step, want), size);
    TH_ASSERT(memcmp(got, want, size) == 0);
    TH_EQ(drv_get_u32(&a, DRV_P_STAT_PERIODS, &v), DRV_OK);
    TH_EQ(v, 2u);
}

/* ---------------- line statistics of multisine runs (lstat.h) ---------------- */

static void lines_setup(drv_t *d, uint32_t n, uint32_t periods, const uint16_t *bins, uint32_t nb)
{
    drv_enable(d, true);
    TH_EQ(drv_set_f32(d, DRV_P_KFC, 0.1f), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_REC_SIGNALS, 0x07u), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_KIND, DRV_EXC_MULTISINE), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_PERIOD, n), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_MS_K_MIN, 2u), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_MS_K_MAX, 40u), DRV_OK);
    TH_EQ(drv_set_f32(d, DRV_P_EXC_AMPLITUDE, 0.2f), DRV_OK);
    TH_EQ(drv_set_f32(d, DRV_P_EXC_OFFSET, 0.0f), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_SETTLE_PERIODS, 1u), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_EXC_RECORD_PERIODS, periods), DRV_OK);
    TH_EQ(drv_lines_write(d, 0u, (const uint8_t *)bins, 2u * nb), DRV_OK);
    TH_EQ(drv_lines_commit(d, 2u * nb), DRV_OK);
    TH_EQ(drv_set_u32(d, DRV_P_STAT_LINE_MODE, 1u), DRV_OK);
}

/* The reference line statistics in double of per-period spectra spec[p][l][signal][re, im]
 * (signals r, u, y): the means over the periods, and with 1 / (P - 1) the variances of U
 * and Y and the covariance (Y - mean) conj(U - mean). */
#define REF_LINES_MAX 60u
typedef struct {
    double mr[3], mi[3];
    double vu, vy, cr, ci;
} ref_line_t;

static ref_line_t ref_line(const double spec[][REF_LINES_MAX][3][2], uint32_t periods, uint32_t l)
{
    ref_line_t r = {{0}, {0}, 0.0, 0.0, 0.0, 0.0};
    for (uint32_t s = 0u; s < 3u; s++) {
        for (uint32_t p = 0u; p < periods; p++) {
            r.mr[s] += spec[p][l][s][0] / periods;
            r.mi[s] += spec[p][l][s][1] / periods;
        }
    }
    for (uint32_t p = 0u; p < periods; p++) {
        double dur = spec[p][l][1][0] - r.mr[1], dui = spec[p][l][1][1] - r.mi[1];
        double dyr = spec[p][l][2][0] - r.mr[2], dyi = spec[p][l][2][1] - r.mi[2];
        r.vu += (dur * dur + dui * dui) / (periods - 1u);
        r.vy += (dyr * dyr + dyi * dyi) / (periods - 1u);
        r.cr += (dyr * dur + dyi * dui) / (periods - 1u);
        r.ci += (dyi * dur - dyr * dui) / (periods - 1u);
    }
    return r;
}

static void test_line_stats_equal_a_double_dft_of_the_recorded_periods(void)
{
    static uint16_t bins[LSTAT_LINES_MAX];
    static uint8_t got[LSTAT_HEADER_BYTES + LSTAT_LINE_BYTES * LSTAT_LINES_MAX];
    const uint32_t n = 1024u, periods = 4u, nb = 60u;
    for (uint32_t i = 0u; i < nb; i++) {
        bins[i] = (uint16_t)(1u + i); /* excited 2..40 and detection lines around them */
    }
    drv_t d = make_drv(REC_CAP);
    lines_setup(&d, n, periods, bins, nb);
    TH_EQ(drv_run_start(&d), DRV_OK);
    float motor = 1.5f;
    for (uint32_t i = 0u; i < (periods + 1u) * n; i++) {
        motor = stat_step(&d, motor);
        if (i % 3u == 0u) {
            drv_background(&d); /* periods pile up; the read finishes them */
        }
    }
    uint32_t size = drv_line_stats_size_bytes(&d);
    TH_EQ(size, LSTAT_HEADER_BYTES + LSTAT_LINE_BYTES * nb);
    TH_EQ(drv_line_stats_read(&d, 0u, got, size), DRV_OK);
    uint32_t p, hdr;
    memcpy(&p, got, 4u);
    memcpy(&hdr, got + 4u, 4u);
    TH_EQ(p, periods);
    TH_EQ(hdr, nb);
    /* reference: the DFT in double of the recorded r, u, y (columns 0, 1, 2) */
    double ymax = 0.0, umax = 0.0, worst_mean = 0.0, worst_sd = 0.0;
    static double spec[4][REF_LINES_MAX][3][2];
    for (uint32_t pp = 0u; pp < periods; pp++) {
        for (uint32_t l = 0u; l < nb; l++) {
            for (uint32_t s = 0u; s < 3u; s++) {
                double re = 0.0, im = 0.0;
                for (uint32_t k = 0u; k < n; k++) {
                    double x = (double)rec_buf[3u * (pp * n + k) + s];
                    double a = 2.0 * M_PI * (double)bins[l] * (double)k / (double)n;
                    re += x * cos(a);
                    im -= x * sin(a);
                }
                spec[pp][l][s][0] = re;
                spec[pp][l][s][1] = im;
            }
        }
    }
    for (uint32_t l = 0u; l < nb; l++) {
        const ref_line_t ref = ref_line(spec, periods, l);
        const double *mr = ref.mr, *mi = ref.mi;
        const double vu = ref.vu, vy = ref.vy, cr = ref.cr, ci = ref.ci;
        float f[10];
        uint32_t b;
        memcpy(&b, got + 8u + LSTAT_LINE_BYTES * l, 4u);
        memcpy(f, got + 12u + LSTAT_LINE_BYTES * l, 40u);
        TH_EQ(b, bins[l]);
        /* order in the data: U, Y, R; reference order here: r 0, u 1, y 2 */
        const uint32_t col[3] = {1u, 2u, 0u};
        for (uint32_t s = 0u; s < 3u; s++) {
            worst_mean = fmax(worst_mean, hypot((double)f[2u * s] - mr[col[s]], (double)f[2u * s + 1u] - mi[col[s]]));
        }
        umax = fmax(umax, hypot(mr[1], mi[1]));
        ymax = fmax(ymax, hypot(mr[2], mi[2]));
        worst_sd = fmax(worst_sd, fabs(sqrt(fmax((double)f[6], 0.0)) - sqrt(vu)));
        worst_sd = fmax(worst_sd, fabs(sqrt(fmax((double)f[7], 0.0)) - sqrt(vy)));
        worst_sd = fmax(worst_sd, fabs(sqrt(hypot((double)f[8], (double)f[9])) - sqrt(hypot(cr, ci))));
    }
    /* float32 FFT: within 1e-5 of the largest line; spreads (sd) within 1e-5 of it too */
    const double scale = fmax(umax, ymax);
    TH_ASSERT(scale > 1.0);
    TH_ASSERT(worst_mean <= 1e-5 * scale);
    TH_ASSERT(worst_sd <= 1e-5 * scale);
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_LINE_PERIODS, &v), DRV_OK);
    TH_EQ(v, periods);
}

/* Shifted data (lstat.h): periods that differ by a spread far below the float32 resolution
 * of the lines (a quiet plant: sd / |X| about 1e-6) give variances and covariance within
 * 1e-5 relative of the float64 statistics of the same float32 samples, and identical
 * periods give exactly 0 with the means equal to one period's. lstat_* directly, on a
 * synthetic recorder of r, u, y. */
#define LQ_N 1024u
#define LQ_P 5u
#define LQ_L 60u
_Static_assert(LQ_L <= REF_LINES_MAX, "the reference spectra hold REF_LINES_MAX lines");
static float lq_rec[3u * LQ_P * LQ_N];
static float lq_work[LQ_N];
static lstat_t lq_ls;
static uint8_t lq_got[LSTAT_HEADER_BYTES + LSTAT_LINE_BYTES * LQ_L];

static uint32_t lq_lcg(uint32_t *s)
{
    *s = *s * 1664525u + 1013904223u;
    return *s >> 8;
}

/* column c of period p: offset + lines 2, 4 .. 40 (amplitude 1, phases k^2) + noise */
static void lq_fill(double noise)
{
    const double off[3] = {0.25, -3.0, 100.0};
    uint32_t seed = 12345u;
    for (uint32_t p = 0u; p < LQ_P; p++) {
        for (uint32_t i = 0u; i < LQ_N; i++) {
            double x = 0.0;
            for (uint32_t k = 2u; k <= 40u; k += 2u) {
                x += cos(2.0 * M_PI * (double)k * (double)i / LQ_N + 0.1 * (double)(k * k));
            }
            double eu = noise * ((double)lq_lcg(&seed) / 16777216.0 - 0.5);
            double ey = noise * ((double)lq_lcg(&seed) / 16777216.0 - 0.5);
            double v[3] = {off[0] + x, off[1] + 0.8 * x + eu, off[2] + 1.7 * x - 0.6 * eu + ey};
            for (uint32_t c = 0u; c < 3u; c++) {
                lq_rec[3u * (p * LQ_N + i) + c] = (float)v[c];
            }
        }
    }
}

static void lq_run(uint32_t periods)
{
    uint16_t bins[LQ_L];
    for (uint32_t i = 0u; i < LQ_L; i++) {
        bins[i] = (uint16_t)(1u + i);
    }
    lstat_init(&lq_ls);
    TH_EQ(lstat_write(&lq_ls, 0u, (const uint8_t *)bins, sizeof bins), LSTAT_OK);
    TH_EQ(lstat_commit(&lq_ls, sizeof bins, LQ_N), LSTAT_OK);
    TH_EQ(lstat_set_mode(&lq_ls, 1u), LSTAT_OK);
    TH_EQ(lstat_check(&lq_ls, LQ_N, 0x07u, LQ_N), LSTAT_OK);
    lstat_begin(&lq_ls, LQ_N);
    uint32_t done = 0u;
    while (lstat_process(&lq_ls, lq_rec, 3u, periods * LQ_N, lq_work)) {
        done++;
    }
    TH_EQ(done, periods);
    TH_EQ(lstat_size_bytes(&lq_ls), sizeof lq_got);
    TH_EQ(lstat_read(&lq_ls, 0u, lq_got, sizeof lq_got), 0);
}

static void test_line_stats_shifted_data_quiet_and_identical_periods(void)
{
    /* quiet: noise 1e-4 on samples of about 20 -> line spreads ~1e-6 of the excited lines */
    lq_fill(1e-4);
    lq_run(LQ_P);
    static double spec[LQ_P][REF_LINES_MAX][3][2];   /* LQ_L = REF_LINES_MAX lines */
    for (uint32_t p = 0u; p < LQ_P; p++) {
        for (uint32_t l = 0u; l < LQ_L; l++) {
            for (uint32_t c = 0u; c < 3u; c++) {
                double re = 0.0, im = 0.0;
                for (uint32_t i = 0u; i < LQ_N; i++) {
                    double x = (double)lq_rec[3u * (p * LQ_N + i) + c];
                    double a = 2.0 * M_PI * (double)(l + 1u) * (double)i / LQ_N;
                    re += x * cos(a);
                    im -= x * sin(a);
                }
                spec[p][l][c][0] = re;
                spec[p][l][c][1] = im;
            }
        }
    }
    double worst_var = 0.0, worst_cov = 0.0, worst_mean = 0.0, worst_mean_own = 0.0, xmax = 0.0, sd_rel = 0.0;
    for (uint32_t l = 0u; l < LQ_L; l++) {
        const ref_line_t ref = ref_line(spec, LQ_P, l);
        const double *mr = ref.mr, *mi = ref.mi;
        const double vu = ref.vu, vy = ref.vy, cr = ref.cr, ci = ref.ci;
        for (uint32_t c = 0u; c < 3u; c++) {
            xmax = fmax(xmax, hypot(mr[c], mi[c]));
        }
        float f[10];
        memcpy(f, lq_got + 12u + LSTAT_LINE_BYTES * l, 40u);
        const uint32_t col[3] = {1u, 2u, 0u}; /* data order U, Y, R */
        for (uint32_t s = 0u; s < 3u; s++) {
            double e = hypot((double)f[2u * s] - mr[col[s]], (double)f[2u * s + 1u] - mi[col[s]]);
            double mag = hypot(mr[col[s]], mi[col[s]]);
            worst_mean = fmax(worst_mean, e);
            if ((l + 1u) % 2u == 0u && l + 1u <= 40u) { /* excited line: its own magnitude */
                worst_mean_own = fmax(worst_mean_own, e / mag);
                sd_rel = fmax(sd_rel, sqrt(s == 0u ? vu : vy) / mag);
            }
        }
        worst_var = fmax(worst_var, fabs((double)f[6] - vu) / vu);
        worst_var = fmax(worst_var, fabs((double)f[7] - vy) / vy);
        worst_cov = fmax(worst_cov, hypot((double)f[8] - cr, (double)f[9] - ci) / hypot(cr, ci));
    }
    printf("lstat quiet: spread/|X| <= %.2g; rel. error var %.2g, cov %.2g; means %.2g of the largest line, "
           "%.2g of their own (excited lines)\n", sd_rel, worst_var, worst_cov, worst_mean / xmax, worst_mean_own);
    TH_ASSERT(sd_rel < 1e-5);          /* far below float32 resolution of the lines */
    TH_ASSERT(worst_var <= 1e-5);
    TH_ASSERT(worst_cov <= 1e-5);
    TH_ASSERT(worst_mean <= 1e-5 * xmax);
    TH_ASSERT(worst_mean_own <= 1e-5);

    /* identical periods: variances and covariance exactly 0, means those of one period */
    lq_fill(0.0);
    lq_run(1u);
    static uint8_t one[sizeof lq_got];
    memcpy(one, lq_got, sizeof one);
    lq_run(LQ_P);
    uint32_t p;
    memcpy(&p, lq_got, 4u);
    TH_EQ(p, LQ_P);
    for (uint32_t l = 0u; l < LQ_L; l++) {
        const uint8_t *a = lq_got + 8u + LSTAT_LINE_BYTES * l, *b = one + 8u + LSTAT_LINE_BYTES * l;
        TH_ASSERT(memcmp(a, b, 4u + 24u) == 0); /* bin and the means: bit for bit */
        float f[4];
        memcpy(f, a + 28u, 16u);
        for (uint32_t j = 0u; j < 4u; j++) {
            TH_ASSERT(f[j] == 0.0f);
        }
    }
}

static void test_line_list_checks_and_run_refusals(void)
{
    drv_t d = make_drv(REC_CAP);
    static uint16_t bins[LSTAT_LINES_MAX + 1u];
    for (uint32_t i = 0u; i <= LSTAT_LINES_MAX; i++) {
        bins[i] = (uint16_t)(1u + i);
    }
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 512u), DRV_OK);
    uint16_t good[3] = {3u, 5u, 7u};
    TH_EQ(drv_lines_write(&d, 0u, (const uint8_t *)good, 6u), DRV_OK);
    TH_EQ(drv_lines_commit(&d, 6u), DRV_OK);
    uint16_t nyq[2] = {3u, 256u}; /* N/2 */
    TH_EQ(drv_lines_write(&d, 0u, (const uint8_t *)nyq, 4u), DRV_OK);
    TH_EQ(drv_lines_commit(&d, 4u), DRV_E_VALUE);
    uint16_t zero[1] = {0u};
    TH_EQ(drv_lines_write(&d, 0u, (const uint8_t *)zero, 2u), DRV_OK);
    TH_EQ(drv_lines_commit(&d, 2u), DRV_E_VALUE);
    uint16_t desc[2] = {9u, 4u};
    TH_EQ(drv_lines_write(&d, 0u, (const uint8_t *)desc, 4u), DRV_OK);
    TH_EQ(drv_lines_commit(&d, 4u), DRV_E_VALUE);
    TH_EQ(drv_lines_commit(&d, 3u), DRV_E_LENGTH); /* half a bin */
    TH_EQ(drv_lines_write(&d, 0u, (const uint8_t *)bins, 2u * (LSTAT_LINES_MAX + 1u)), DRV_E_TOO_LONG);
    TH_EQ(drv_lines_commit(&d, 2u * (LSTAT_LINES_MAX + 1u)), DRV_E_TOO_LONG);
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_LINES, &v), DRV_OK);
    TH_EQ(v, 3u); /* the good list stayed */
    uint8_t back[6];
    TH_EQ(drv_lines_read(&d, 0u, back, 6u), DRV_OK);
    TH_ASSERT(memcmp(back, good, 6u) == 0);
    TH_EQ(drv_set_u32(&d, DRV_P_STAT_LINE_MODE, 2u), DRV_E_RANGE_HIGH);
    /* run start (a sine run here: the checks apply to any periodic run): the period changed
     * below a line; N not a power of two; r, u, y not recorded */
    lines_setup(&d, 512u, 2u, good, 3u);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SINE_CYCLES, 1u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 12u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_STAT_NYQUIST);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 24u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_STAT_LINES);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 32u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, 0x06u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_STAT_LINES);
    TH_EQ(drv_set_u32(&d, DRV_P_REC_SIGNALS, 0x07u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    TH_EQ(drv_lines_commit(&d, 6u), DRV_E_STATE);
    TH_EQ(drv_set_u32(&d, DRV_P_STAT_LINE_MODE, 0u), DRV_E_STATE);
}


/* Issue 21: what a run's background work reads is fixed at its start. A multisine run with
 * line statistics whose background is behind when the run ends (as on the MCU port: not
 * one drv_background call during the run), then, before the background catches up: a new
 * period and a new list committed (bin 100 is valid for N = 256 but beyond the run's
 * N/2 = 32: the old code indexed the FFT work space with it), another recorder selection
 * (5 signals instead of 3: the old code walked the recording with the new stride), a new
 * u_max (the saturation count's threshold), the line statistics off. The run's 0x2043 and
 * saturation count must be exactly those of the same run read with nothing written. */
static void lines_run_behind(drv_t *d, uint32_t n, uint32_t periods, const uint16_t *bins, uint32_t nb)
{
    lines_setup(d, n, periods, bins, nb);
    TH_EQ(drv_set_u32(d, DRV_P_MS_K_MAX, 20u), DRV_OK); /* below N/2 */
    TH_EQ(drv_set_f32(d, DRV_P_U_MAX, 1.0f), DRV_OK); /* some samples at the limit, not all */
    TH_EQ(drv_run_start(d), DRV_OK);
    float motor = 1.5f;
    for (uint32_t i = 0u; i < (periods + 1u) * n; i++) {
        motor = stat_step(d, motor); /* no drv_background: every period still pending */
    }
    uint32_t v;
    TH_EQ(drv_get_u32(d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_DONE);
    TH_EQ(drv_get_u32(d, DRV_P_STAT_LINE_PERIODS, &v), DRV_OK);
    TH_EQ(v, 0u);
}

static void test_line_stats_fixed_at_run_start(void)
{
    const uint32_t n = 64u, periods = 3u, nb = 4u;
    const uint16_t bins[4] = {3u, 5u, 9u, 31u};
    static uint8_t want[LSTAT_HEADER_BYTES + LSTAT_LINE_BYTES * 4u];
    static uint8_t got[LSTAT_HEADER_BYTES + LSTAT_LINE_BYTES * 4u];
    uint32_t sat_want, sat_got, v;

    drv_t a = make_drv(REC_CAP); /* the reference: read with nothing written after the run */
    lines_run_behind(&a, n, periods, bins, nb);
    uint32_t size = drv_line_stats_size_bytes(&a);
    TH_EQ(size, (uint32_t)sizeof want);
    TH_EQ(drv_line_stats_read(&a, 0u, want, size), DRV_OK);
    TH_EQ(drv_get_u32(&a, DRV_P_STAT_LINE_SATURATED, &sat_want), DRV_OK);
    TH_ASSERT(sat_want > 0u && sat_want < periods * n);
    uint32_t p0;
    memcpy(&p0, want, 4u);
    TH_EQ(p0, periods);

    drv_t b = make_drv(REC_CAP); /* the same run, then the writes while the background is behind */
    lines_run_behind(&b, n, periods, bins, nb);
    drv_background(&b); /* the main loop gets one turn: one period done, two pending */
    TH_EQ(drv_get_u32(&b, DRV_P_STAT_LINE_PERIODS, &v), DRV_OK);
    TH_EQ(v, 1u);
    TH_EQ(drv_set_u32(&b, DRV_P_EXC_PERIOD, 256u), DRV_OK);
    const uint16_t next[2] = {2u, 100u};
    TH_EQ(drv_lines_write(&b, 0u, (const uint8_t *)next, 4u), DRV_OK);
    TH_EQ(drv_lines_commit(&b, 4u), DRV_OK); /* the next run's list: accepted */
    TH_EQ(drv_set_u32(&b, DRV_P_REC_SIGNALS, 0x1Fu), DRV_OK);
    TH_EQ(drv_set_f32(&b, DRV_P_U_MAX, 1000.0f), DRV_OK);
    TH_EQ(drv_set_u32(&b, DRV_P_STAT_LINE_MODE, 0u), DRV_OK);
    drv_background(&b);
    TH_EQ(drv_line_stats_size_bytes(&b), size);
    TH_EQ(drv_line_stats_read(&b, 0u, got, size), DRV_OK);
    TH_ASSERT(memcmp(got, want, size) == 0); /* the run's own bins and numbers */
    uint32_t bin0;
    memcpy(&bin0, got + LSTAT_HEADER_BYTES, 4u);
    TH_EQ(bin0, 3u);
    TH_EQ(drv_get_u32(&b, DRV_P_STAT_LINE_SATURATED, &sat_got), DRV_OK);
    TH_EQ(sat_got, sat_want);
    /* the recording keeps its layout (3 signals a sample) */
    TH_EQ(drv_get_u32(&b, DRV_P_REC_BYTES, &v), DRV_OK);
    TH_EQ(v, 4u * 3u * periods * n);
    /* 0x2042 reads back the committed list, the next run's */
    uint8_t back[4];
    TH_EQ(drv_lines_read(&b, 0u, back, 4u), DRV_OK);
    TH_ASSERT(memcmp(back, next, 4u) == 0);
    TH_EQ(drv_get_u32(&b, DRV_P_REC_SIGNALS, &v), DRV_OK);
    TH_EQ(v, 0x1Fu);
}

/* Line statistics switched on with no list (e.g. 0x2040:7 = 1 after reset node): refused at
 * the start with stop reason 11, not a run that reports P = 0, L = 0. */
static void test_line_stats_on_without_a_list_refused(void)
{
    drv_t d = make_drv(REC_CAP);
    drv_enable(&d, true);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_MULTISINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 64u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_K_MIN, 2u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_MS_K_MAX, 20u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_STAT_LINE_MODE, 1u), DRV_OK);
    uint32_t v;
    TH_EQ(drv_get_u32(&d, DRV_P_STAT_LINES, &v), DRV_OK);
    TH_EQ(v, 0u);
    TH_EQ(drv_run_start(&d), DRV_E_INCOMPATIBLE);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_LAST_ERROR, &v), DRV_OK);
    TH_EQ(v, DRV_STOP_STAT_LINES);
    TH_EQ(drv_get_u32(&d, DRV_P_RUN_STATE, &v), DRV_OK);
    TH_EQ(v, DRV_RUN_IDLE);
    /* off again: the same run starts */
    TH_EQ(drv_set_u32(&d, DRV_P_STAT_LINE_MODE, 0u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    /* u_max is fixed while a run is active (the saturation count's threshold) */
    TH_EQ(drv_set_f32(&d, DRV_P_U_MAX, 5.0f), DRV_E_STATE);
    float um;
    TH_EQ(drv_get_f32(&d, DRV_P_U_MAX, &um), DRV_OK);
    TH_NEAR(um, 10.0f, 0.0f);
}

/* The harmonic statistics' header (0x2041) names the run's masks: a write of 0x2040:2 / :3
 * after the run does not relabel its numbers (the old header showed the new masks beside
 * numbers of the old ones). */
static void test_stat_header_names_the_runs_masks(void)
{
    static uint8_t want[STAT_MAX_BYTES], got[STAT_MAX_BYTES];
    const uint32_t n = 64u, periods = 2u;
    drv_t a = make_drv(REC_CAP);
    stat_setup(&a, n, 2u, periods);
    float motor = 0.3f;
    for (uint32_t i = 0u; i < (periods + 1u) * n; i++) {
        motor = stat_step(&a, motor);
    }
    uint32_t size = drv_stat_size_bytes(&a);
    TH_EQ(drv_stat_read(&a, 0u, want, size), DRV_OK);
    uint32_t hdr;
    memcpy(&hdr, want + 4u, 4u);
    TH_EQ(hdr & 0xFFu, 8u);
    TH_EQ((hdr >> 8) & 0xFFu, 0x07u);
    TH_EQ((hdr >> 16) & 0xFFu, 0x14u);
    TH_EQ(drv_set_u32(&a, DRV_P_STAT_SIGNALS, 0x18u), DRV_OK);
    TH_EQ(drv_set_u32(&a, DRV_P_STAT_POWER, 0x03u), DRV_OK);
    TH_EQ(drv_set_u32(&a, DRV_P_STAT_HARMONICS, 2u), DRV_OK);
    TH_EQ(drv_stat_size_bytes(&a), size);
    TH_EQ(drv_stat_read(&a, 0u, got, size), DRV_OK);
    TH_ASSERT(memcmp(got, want, size) == 0);
}

/* The feed-forward gains as drive parameters (od.yaml 0x2000:9-11): od.yaml's limits
 * (+-100 V), NaN / inf refused with the old value kept, settable during a run like K_fc, and
 * in the output of a sine run: u at a step equals the formula at that step's reference. */
static void test_drv_friction_ff_params(void)
{
    drv_t d = make_drv(REC_CAP);
    const drv_param_id_t ids[] = {DRV_P_KFA, DRV_P_KPS, DRV_P_KPC};
    for (size_t i = 0; i < sizeof ids / sizeof ids[0]; i++) {
        float v = 1.0f;
        TH_EQ(drv_get_f32(&d, ids[i], &v), DRV_OK);
        TH_NEAR(v, 0.0, 0.0); /* od.yaml default */
        TH_EQ(drv_set_f32(&d, ids[i], -0.37f), DRV_OK);
        TH_EQ(drv_set_f32(&d, ids[i], 100.5f), DRV_E_RANGE_HIGH);
        TH_EQ(drv_set_f32(&d, ids[i], -100.5f), DRV_E_RANGE_LOW);
        TH_EQ(drv_set_f32(&d, ids[i], NAN), DRV_E_NOT_FINITE);
        TH_EQ(drv_set_f32(&d, ids[i], INFINITY), DRV_E_NOT_FINITE);
        TH_EQ(drv_get_f32(&d, ids[i], &v), DRV_OK);
        TH_NEAR(v, -0.37, 1e-7);
        TH_EQ(drv_set_u32(&d, ids[i], 1u), DRV_E_LENGTH); /* REAL32 */
    }
    /* a sine run with every term: u = Kp e + FF(v_r, theta_r) (kd 0) at each step */
    const float kp = 0.8f, kfc = 0.3f, kfa = 0.05f, kps = -0.12f, kpc = 0.04f, kv = 0.02f;
    TH_EQ(drv_set_f32(&d, DRV_P_KD, 0.0f), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KP, kp), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KFC, kfc), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KFA, kfa), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KPS, kps), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KPC, kpc), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_KV, kv), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_U_MAX, 50.0f), DRV_OK);
    drv_enable(&d, true);
    TH_EQ(drv_set_target(&d, 0.7f), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_KIND, DRV_EXC_SINE), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_PERIOD, 256u), DRV_OK);
    TH_EQ(drv_set_f32(&d, DRV_P_EXC_AMPLITUDE, 3.0f), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_SETTLE_PERIODS, 0u), DRV_OK);
    TH_EQ(drv_set_u32(&d, DRV_P_EXC_RECORD_PERIODS, 1u), DRV_OK);
    TH_EQ(drv_run_start(&d), DRV_OK);
    const double w = 2.0 * M_PI * FS / 256.0, tol = 0.5 * pow(2.0 * M_PI / CTL_FF_N, 2) * 0.13 + 2e-5;
    int moving = 0;
    for (int n = 0; n < 256; n++) {
        drv_meas_t m = {0.7f + 0.01f * (float)(n % 7), 0.0f};
        float u = drv_step(&d, &m);
        double ref = 0.7 + 3.0 * sin(w * n / FS), v = 3.0 * w * cos(w * n / FS);
        double sg = v > 0.0 ? 1.0 : (v < 0.0 ? -1.0 : 0.0);
        double ff = sg * (kfc + kps * sin(ref) + kpc * cos(ref)) + kfa * fabs(sg) + kv * v;
        if (fabs(v) > 1.0) { /* at a reversal the float generator's sign may differ */
            TH_NEAR(u, kp * (ref - m.motor_angle_rad) + ff, tol + 1e-5 * fabs(v));
            moving++;
        }
        if (n == 100) {
            TH_EQ(drv_set_f32(&d, DRV_P_KPS, kps), DRV_OK); /* settable while running */
        }
        if (n == 150) { /* refusals while running: the run goes on with the old gains */
            const drv_param_id_t signed_ids[] = {DRV_P_KFA, DRV_P_KPS, DRV_P_KPC};
            for (size_t i = 0; i < 3u; i++) {
                TH_EQ(drv_set_f32(&d, signed_ids[i], NAN), DRV_E_NOT_FINITE);
                TH_EQ(drv_set_f32(&d, signed_ids[i], -INFINITY), DRV_E_NOT_FINITE);
                TH_EQ(drv_set_f32(&d, signed_ids[i], 3e38f), DRV_E_RANGE_HIGH);
                TH_EQ(drv_set_f32(&d, signed_ids[i], -1e30f), DRV_E_RANGE_LOW);
                TH_EQ(drv_set_u32(&d, signed_ids[i], 0x7FC00000u), DRV_E_LENGTH);
            }
            TH_ASSERT(!drv_fault(&d));
        }
    }
    TH_ASSERT(moving > 200);
}

/* ---- issue 33: task.c's statistics read-out (objects 0x2061/0x2062 through drv) --------
 * A task_t filled by task_push alone (no generator: v_last, a_last set by hand per sample),
 * n_rep = 20 samples in TASK_BLOCKS = 8 blocks, block b from sample floor(20 b / 8) (2 or 3
 * samples: unequal), two repetitions of different inputs. Every word of the four streams
 * (run sums and the last repetition alone, data and design) is compared with sums computed
 * here per sample, block 0 and block 7 included; then the byte ranges at and beyond the
 * ends. */
#define TT_NREP 20u

static float tt_u(uint32_t rep, uint32_t k) { return 0.5f + (float)k * 0.25f + (float)rep * 3.0f; }
static float tt_e(uint32_t rep, uint32_t k) { return 0.01f * (float)(k + 1u) - 0.002f * (float)rep; }
static float tt_s(uint32_t k) { return (k % 3u == 1u) ? -1.0f : 1.0f; }
static float tt_v(uint32_t rep, uint32_t k) { return 0.125f * (float)k - 1.0f + 0.0625f * (float)rep; }
static float tt_a(uint32_t rep, uint32_t k) { return 2.0f - 0.375f * (float)k + (float)rep; }

/* the sums of block b of repetition rep, in the stream's order */
static void tt_ref(uint32_t rep, uint32_t b, double des[TASK_DESIGN_SUMS], double dat[TASK_DATA_SUMS])
{
    for (uint32_t i = 0; i < TASK_DESIGN_SUMS; i++) {
        des[i] = 0.0;
    }
    for (uint32_t i = 0; i < TASK_DATA_SUMS; i++) {
        dat[i] = 0.0;
    }
    for (uint32_t k = 0; k < TT_NREP; k++) {
        /* block b holds samples floor(20 b / 8) <= k < floor(20 (b + 1) / 8) */
        if (k < b * TT_NREP / TASK_BLOCKS || k >= (b + 1u) * TT_NREP / TASK_BLOCKS) {
            continue;
        }
        double s = tt_s(k), v = tt_v(rep, k), a = tt_a(rep, k), u = tt_u(rep, k), e = tt_e(rep, k);
        double p = s > 0 ? s : 0, n = s < 0 ? s : 0;
        double d[TASK_DESIGN_SUMS] = {p * p, n * n, p * v, p * a, n * v, n * a, v * v, v * a, a * a};
        double x[TASK_DATA_SUMS] = {p * u, n * u, v * u, a * u, e * e, u * u};
        for (uint32_t i = 0; i < TASK_DESIGN_SUMS; i++) {
            des[i] += d[i];
        }
        for (uint32_t i = 0; i < TASK_DATA_SUMS; i++) {
            dat[i] += x[i];
        }
    }
}

static uint32_t tt_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}

static float tt_f32(const uint8_t *p)
{
    uint32_t w = tt_u32(p);
    float f;
    memcpy(&f, &w, 4);
    return f;
}

/* one stream read whole and compared: header (count, 20), then block by block the sums of
 * repetitions [rep_lo, rep_hi] */
static void tt_check_stream(int (*rd)(const task_t *, uint32_t, uint8_t *, uint32_t), const task_t *t,
                            uint32_t m, uint32_t count, uint32_t rep_lo, uint32_t rep_hi)
{
    uint8_t buf[TASK_DESIGN_BYTES];
    uint32_t size = TASK_HEADER_BYTES + 4u * TASK_BLOCKS * m;
    TH_EQ(rd(t, 0u, buf, size), 0);
    TH_EQ(tt_u32(buf), count);
    TH_EQ(tt_u32(buf + 4), TT_NREP);
    for (uint32_t b = 0; b < TASK_BLOCKS; b++) {
        double des[TASK_DESIGN_SUMS], dat[TASK_DATA_SUMS], sd[TASK_DESIGN_SUMS] = {0}, sx[TASK_DATA_SUMS] = {0};
        for (uint32_t r = rep_lo; r <= rep_hi; r++) {
            tt_ref(r, b, des, dat);
            for (uint32_t i = 0; i < TASK_DESIGN_SUMS; i++) {
                sd[i] += des[i];
            }
            for (uint32_t i = 0; i < TASK_DATA_SUMS; i++) {
                sx[i] += dat[i];
            }
        }
        for (uint32_t i = 0; i < m; i++) {
            double want = m == TASK_DESIGN_SUMS ? sd[i] : sx[i];
            TH_NEAR(tt_f32(buf + TASK_HEADER_BYTES + 4u * (b * m + i)), want, 1e-5 * (1.0 + fabs(want)));
        }
    }
}

static void tt_push_rep(task_t *t, uint32_t rep)
{
    for (uint32_t k = 0; k < TT_NREP; k++) {
        t->v_last = tt_v(rep, k);
        t->a_last = tt_a(rep, k);
        task_push(t, tt_s(k), tt_u(rep, k), tt_e(rep, k));
    }
}

static void test_task_statistics_read_out(void)
{
    static task_t t;
    memset(&t, 0, sizeof t);
    t.n_rep = TT_NREP;
    t.blk_end = TT_NREP / TASK_BLOCKS;
    tt_push_rep(&t, 0);
    TH_EQ(t.reps, 1);
    TH_EQ(t.latched, 1);
    tt_check_stream(task_latch_data_read, &t, TASK_DATA_SUMS, 1u, 0u, 0u);
    tt_check_stream(task_latch_design_read, &t, TASK_DESIGN_SUMS, 1u, 0u, 0u);
    tt_push_rep(&t, 1);
    TH_EQ(t.reps, 2);
    TH_EQ(t.latched, 2);
    /* the run: both repetitions; the latched record: the second alone */
    tt_check_stream(task_data_read, &t, TASK_DATA_SUMS, 2u, 0u, 1u);
    tt_check_stream(task_design_read, &t, TASK_DESIGN_SUMS, 2u, 0u, 1u);
    tt_check_stream(task_latch_data_read, &t, TASK_DATA_SUMS, 2u, 1u, 1u);
    tt_check_stream(task_latch_design_read, &t, TASK_DESIGN_SUMS, 2u, 1u, 1u);
    /* block 0 of the latched data (0x2061's first block) is the second repetition's */
    double des[TASK_DESIGN_SUMS], dat[TASK_DATA_SUMS];
    tt_ref(1u, 0u, des, dat);
    uint8_t w[4];
    TH_EQ(task_latch_data_read(&t, TASK_HEADER_BYTES, w, 4u), 0);
    TH_NEAR(tt_f32(w), dat[0], 1e-5 * (1.0 + fabs(dat[0])));

    /* byte ranges: up to the end accepted, one byte beyond refused, at every entry */
    int (*rds[4])(const task_t *, uint32_t, uint8_t *, uint32_t) = {task_data_read, task_design_read,
                                                                    task_latch_data_read, task_latch_design_read};
    uint32_t sizes[4] = {TASK_DATA_BYTES, TASK_DESIGN_BYTES, TASK_DATA_BYTES, TASK_DESIGN_BYTES};
    TH_EQ(task_data_size_bytes(&t), TASK_DATA_BYTES);
    TH_EQ(task_design_size_bytes(&t), TASK_DESIGN_BYTES);
    for (int j = 0; j < 4; j++) {
        uint8_t buf[TASK_DESIGN_BYTES + 8];
        uint32_t size = sizes[j];
        uint8_t whole[TASK_DESIGN_BYTES];
        TH_EQ(rds[j](&t, 0u, whole, size), 0);
        TH_EQ(rds[j](&t, 0u, buf, size + 1u), -1);
        TH_EQ(rds[j](&t, size - 4u, buf, 4u), 0); /* the last sum of the last block */
        TH_ASSERT(memcmp(buf, whole + size - 4u, 4u) == 0);
        TH_EQ(rds[j](&t, size - 4u, buf, 5u), -1);
        TH_EQ(rds[j](&t, size, buf, 0u), 0);  /* empty read at the end */
        TH_EQ(rds[j](&t, size + 1u, buf, 0u), -1);
        TH_EQ(rds[j](&t, 0xFFFFFFFFu, buf, 2u), -1); /* no wrap-around of offset + len */
        TH_EQ(rds[j](&t, 8u, buf, 0xFFFFFFFCu), -1);
        TH_EQ(rds[j](&t, 3u, NULL, 0u), 0);
        TH_EQ(rds[j](&t, 3u, NULL, 1u), -1);
        TH_EQ(rds[j](&t, 7u, buf, 6u), 0); /* unaligned: bytes 7 .. 12 */
        TH_ASSERT(memcmp(buf, whole + 7u, 6u) == 0);
    }
}

/* task_init's state (every byte zero but fs, ts = 1/fs or 0, dir = +1 and a one-sample
 * dwell), and whole-sample durations: a count within 1e-4 (relative above one sample) of
 * an integer is that integer (float noise), else rounded up; n_move is one move and its
 * dwell (the sum of the 8 segments), n_rep two of them back and forth, one forward. */
static void test_task_init_and_whole_samples(void)
{
    static task_t t, ref;
    memset(&t, 0xA5, sizeof t);
    task_init(&t, 2500.0f);
    memset(&ref, 0, sizeof ref);
    ref.fs = 2500.0f;
    ref.ts = 1.0f / 2500.0f;
    ref.dir = 1.0f;
    ref.n_seg[7] = 1u;
    TH_ASSERT(memcmp(&t, &ref, sizeof t) == 0);
    TH_ASSERT(t.ts == 1.0f / 2500.0f && t.dir == 1.0f && t.n_seg[7] == 1u && t.n_rep == 0u);
    task_init(&t, 0.0f);
    TH_ASSERT(t.fs == 0.0f && t.ts == 0.0f);
    task_init(&t, -5.0f);
    TH_ASSERT(t.ts == 0.0f);
    TH_EQ(task_set_param(&t, TASK_P_DISTANCE, 0.2f), TASK_OK); /* fs <= 0: no design */
    TH_EQ(task_set_param(&t, TASK_P_V_MAX, 1.0f), TASK_OK);
    TH_EQ(task_set_param(&t, TASK_P_A_MAX, 10.0f), TASK_OK);
    TH_EQ(task_set_param(&t, TASK_P_JERK, 1000.0f), TASK_OK);
    TH_EQ(task_set_mode(&t, TASK_MODE_BACK_AND_FORTH), TASK_OK);
    TH_EQ(t.n_rep, 0);

    /* fs 1000: t_j 10 ms, t_a 90 ms, t_v 90 ms: a move of 4 10 + 2 90 + 90 = 310 samples */
    task_init(&t, 1000.0f);
    TH_EQ(task_set_param(&t, TASK_P_DISTANCE, 0.2f), TASK_OK);
    TH_EQ(task_set_param(&t, TASK_P_V_MAX, 1.0f), TASK_OK);
    TH_EQ(task_set_param(&t, TASK_P_A_MAX, 10.0f), TASK_OK);
    TH_EQ(task_set_param(&t, TASK_P_JERK, 1000.0f), TASK_OK);
    /* dwell [s] -> samples at 1 kHz: x = dwell 1000 */
    const struct {
        float dwell_s;
        uint32_t n;
    } cases[] = {
        {0.25002f, 250u},   /* 250.02: within 1e-4 250 = 0.025 of 250 */
        {0.25003f, 251u},   /* 250.03: beyond it, rounded up */
        {0.0009f, 1u},      /* 0.9 */
        {1.5e-7f, 1u},      /* 1.5e-4: beyond the absolute 1e-4 below one sample */
        {5e-8f, 0u},        /* 5e-5: within it */
        {0.0f, 0u},
    };
    for (uint32_t m = TASK_MODE_BACK_AND_FORTH; m <= TASK_MODE_FORWARD; m++) {
        TH_EQ(task_set_mode(&t, m), TASK_OK);
        for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
            TH_EQ(task_set_param(&t, TASK_P_DWELL, cases[c].dwell_s), TASK_OK);
            TH_EQ(t.n_seg[7], cases[c].n);
            uint32_t sum = 0u;
            for (int s = 0; s < 8; s++) {
                sum += t.n_seg[s];
            }
            TH_EQ(t.n_move, 310u + cases[c].n);
            TH_EQ(t.n_move, sum);
            TH_EQ(t.n_rep, (m == TASK_MODE_FORWARD ? 1u : 2u) * (310u + cases[c].n));
        }
    }
}

/* task.c's API edges: parameters refused (unknown, negative, NaN) keep the old value and
 * read 0 when unknown; period 0 and displacement 0 when off; task_begin's state (every
 * generator and statistics field from a scrambled run); the design's bounds (a
 * repetition of exactly TASK_REP_MIN = 64 samples kept, 63 and 62 refused; a jerk phase
 * below one sample made one sample; fs = 1 Hz valid); task_init writes no byte beyond
 * the struct. */
static void tt_design(task_t *t, float fs, float d, float vm, float am, float jm, float dwell, uint32_t mode)
{
    task_init(t, fs);
    TH_EQ(task_set_param(t, TASK_P_DISTANCE, d), TASK_OK);
    TH_EQ(task_set_param(t, TASK_P_V_MAX, vm), TASK_OK);
    TH_EQ(task_set_param(t, TASK_P_A_MAX, am), TASK_OK);
    TH_EQ(task_set_param(t, TASK_P_JERK, jm), TASK_OK);
    TH_EQ(task_set_param(t, TASK_P_DWELL, dwell), TASK_OK);
    TH_EQ(task_set_mode(t, mode), TASK_OK);
}

static void test_task_api_begin_and_design_bounds(void)
{
    static struct {
        task_t t;
        uint8_t canary[16];
    } s;
    memset(s.canary, 0x5A, sizeof s.canary);
    task_init(&s.t, 1000.0f);
    for (size_t i = 0; i < sizeof s.canary; i++) {
        TH_EQ(s.canary[i], 0x5A);
    }
    task_t *t = &s.t;

    /* parameters */
    TH_EQ(task_set_param(t, TASK_P_KA, 0.75f), TASK_OK);
    TH_EQ(task_set_param(t, 6u, 2.0f), TASK_E_RANGE);
    TH_EQ(task_set_param(t, 99u, 2.0f), TASK_E_RANGE);
    TH_ASSERT(task_get_param(t, 6u) == 0.0f && task_get_param(t, 99u) == 0.0f);
    TH_EQ(task_set_param(t, TASK_P_KA, -0.5f), TASK_E_RANGE);
    TH_EQ(task_set_param(t, TASK_P_KA, NAN), TASK_E_RANGE);
    TH_ASSERT(task_get_param(t, TASK_P_KA) == 0.75f);
    TH_EQ(task_set_mode(t, TASK_MODE_MAX + 1u), TASK_E_RANGE);

    /* fs 100: t_j 10 ms, t_a 90 ms, t_v 90 ms: a move of 4 1 + 2 9 + 9 = 31 samples */
    tt_design(t, 100.0f, 0.2f, 1.0f, 10.0f, 1000.0f, 0.33f, TASK_MODE_FORWARD);
    TH_EQ(t->n_seg[0], 1);
    TH_EQ(t->n_seg[1], 9);
    TH_EQ(t->n_seg[3], 9);
    TH_EQ(task_period(t), 64); /* 31 + 33: exactly the minimum, kept */
    TH_ASSERT(task_displacement(t) == 0.2f);
    TH_EQ(task_set_param(t, TASK_P_DWELL, 0.32f), TASK_OK);
    TH_EQ(task_period(t), 0); /* 63 */
    TH_EQ(t->n_rep, 0);
    TH_EQ(t->n_move, 0);
    tt_design(t, 100.0f, 0.2f, 1.0f, 10.0f, 1000.0f, 0.01f, TASK_MODE_BACK_AND_FORTH);
    TH_EQ(task_period(t), 64); /* 2 (31 + 1) */
    TH_ASSERT(task_displacement(t) == 0.0f);
    TH_EQ(task_set_param(t, TASK_P_DWELL, 0.0f), TASK_OK);
    TH_EQ(task_period(t), 0); /* 62 */
    TH_EQ(task_begin(t), TASK_E_DESIGN);

    /* off: no period even with a valid design; no displacement even when forward-designed */
    tt_design(t, 1000.0f, 0.2f, 1.0f, 10.0f, 1000.0f, 0.0f, TASK_MODE_FORWARD);
    TH_EQ(t->n_rep, 310);
    TH_EQ(task_set_mode(t, TASK_MODE_OFF), TASK_OK);
    TH_EQ(t->n_rep, 620); /* (designed as back and forth) */
    TH_EQ(task_period(t), 0);
    TH_ASSERT(task_displacement(t) == 0.0f);
    TH_EQ(task_begin(t), TASK_E_DESIGN);

    /* a jerk phase far below one sample (t_j = 10 ns): one sample each */
    tt_design(t, 1000.0f, 0.2f, 1.0f, 10.0f, 1e9f, 0.0f, TASK_MODE_BACK_AND_FORTH);
    TH_EQ(t->n_seg[0], 1);
    TH_EQ(t->n_seg[2], 1);
    TH_EQ(t->n_seg[4], 1);
    TH_EQ(t->n_seg[6], 1);
    TH_ASSERT(t->n_rep > 0u);

    /* the longest repetition, in binary-exact numbers: fs 1024, j 256, a 8, v 0.5, D 0.109375:
     * t_j = t_a = 1/32 s (32 samples), t_v = 1/8 s (128): a move of 320 samples; a dwell of
     * 2^24 - 320 samples makes exactly TASK_N_MAX (kept), one sample more is refused */
    tt_design(t, 1024.0f, 0.109375f, 0.5f, 8.0f, 256.0f, (float)(TASK_N_MAX - 320u) / 1024.0f,
              TASK_MODE_FORWARD);
    TH_EQ(t->n_seg[0], 32);
    TH_EQ(t->n_seg[1], 32);
    TH_EQ(t->n_seg[3], 128);
    TH_EQ(task_period(t), TASK_N_MAX);
    TH_EQ(task_set_param(t, TASK_P_DWELL, (float)(TASK_N_MAX - 319u) / 1024.0f), TASK_OK);
    TH_EQ(task_period(t), 0);

    /* fs = 1 Hz: D 40, v 1, a 1, j 1: t_j 1 s, t_a 0, t_v 38 s: 2 (4 + 38) = 84 samples */
    tt_design(t, 1.0f, 40.0f, 1.0f, 1.0f, 1.0f, 0.0f, TASK_MODE_BACK_AND_FORTH);
    TH_ASSERT(t->ts == 1.0f);
    TH_EQ(task_period(t), 84);

    /* task_begin from a scrambled run: segment 0 (one sample long: not skipped), sample 0,
     * forward from 0 at rest, every sum cleared */
    tt_design(t, 100.0f, 0.2f, 1.0f, 10.0f, 1000.0f, 0.33f, TASK_MODE_FORWARD);
    TH_EQ(t->n_seg[0], 1);
    t->seg = 5u;
    t->k = 3u;
    t->dir = -1.0f;
    t->base = 7.0f;
    t->v_last = 2.5f;
    t->a_last = -4.0f;
    t->blk = 6u;
    t->rk = 17u;
    t->reps = 9u;
    t->latched = 4u;
    t->blk_end = 3u;
    for (uint32_t b = 0; b < TASK_BLOCKS; b++) {
        for (uint32_t i = 0; i < TASK_DESIGN_SUMS; i++) {
            t->design[b][i] = t->rep_design[b][i] = t->latch_design[b][i] = 1.5f + (float)i;
        }
        for (uint32_t i = 0; i < TASK_DATA_SUMS; i++) {
            t->data[b][i] = t->rep_data[b][i] = t->latch_data[b][i] = -2.5f - (float)i;
        }
    }
    TH_EQ(task_begin(t), TASK_OK);
    TH_EQ(t->seg, 0);
    TH_EQ(t->k, 0);
    TH_ASSERT(t->dir == 1.0f && t->base == 0.0f && t->v_last == 0.0f && t->a_last == 0.0f);
    TH_EQ(t->blk, 0);
    TH_EQ(t->rk, 0);
    TH_EQ(t->reps, 0);
    TH_EQ(t->latched, 0);
    TH_EQ(t->blk_end, 64u / TASK_BLOCKS);
    int nonzero = 0;
    for (uint32_t b = 0; b < TASK_BLOCKS; b++) {
        for (uint32_t i = 0; i < TASK_DESIGN_SUMS; i++) {
            nonzero += t->design[b][i] != 0.0f || t->rep_design[b][i] != 0.0f || t->latch_design[b][i] != 0.0f;
        }
        for (uint32_t i = 0; i < TASK_DATA_SUMS; i++) {
            nonzero += t->data[b][i] != 0.0f || t->rep_data[b][i] != 0.0f || t->latch_data[b][i] != 0.0f;
        }
    }
    TH_EQ(nonzero, 0);
    /* the first sample: segment 0 at its start (position, velocity 0, acceleration 0) */
    float w = 1.0f, wd = 1.0f, ua = 1.0f;
    task_next(t, &w, &wd, &ua);
    TH_ASSERT(w == 0.0f && wd == 0.0f);
    TH_EQ(t->seg, 1); /* its one sample done */
}

int main(void)
{
    TH_RUN(test_ctl_law_pd_filtered_derivative);
    TH_RUN(test_task_statistics_read_out);
    TH_RUN(test_task_init_and_whole_samples);
    TH_RUN(test_task_api_begin_and_design_bounds);
    TH_RUN(test_ctl_feedforward_and_saturation);
    TH_RUN(test_ctl_setters_reject_and_keep);
    TH_RUN(test_ctl_init_defaults_reset_and_edges);
    TH_RUN(test_ctl_friction_ff_terms);
    TH_RUN(test_ctl_signed_setters);
    TH_RUN(test_ctl_ff_branches_equal_the_formula);
    TH_RUN(test_drv_friction_ff_params);
    TH_RUN(test_drv_defaults_from_od);
    TH_RUN(test_drv_param_validation_keeps_old_value);
    TH_RUN(test_sine_exactly_periodic);
    TH_RUN(test_table_playback_bit_exact);
    TH_RUN(test_table_velocity_is_the_central_difference);
    TH_RUN(test_recorder_fills_to_its_last_sample);
    TH_RUN(test_table_write_checks);
    TH_RUN(test_table_kept_until_commit);
    TH_RUN(test_overflowing_inputs_refused_and_output_fault);
    TH_RUN(test_run_exact_sample_counts);
    TH_RUN(test_run_refusals);
    TH_RUN(test_enable_safe_stop_fault);
    TH_RUN(test_meas_not_finite_in_either_faults);
    TH_RUN(test_plant_input_injection);
    TH_RUN(test_ms_prng_vectors);
    TH_RUN(test_ms_lines_and_period_vectors);
    TH_RUN(test_ms_check_and_build_edges);
    TH_RUN(test_ms_through_drive);
    TH_RUN(test_fft_inverse_complex_small);
    TH_RUN(test_random_api_sequences_keep_invariants);
    TH_RUN(test_stat_deferred_equals_per_sample_reference_bit_for_bit);
    TH_RUN(test_stat_overrun_is_reported_not_delivered);
    TH_RUN(test_stat_read_right_after_the_run_is_final);
    TH_RUN(test_line_stats_equal_a_double_dft_of_the_recorded_periods);
    TH_RUN(test_line_stats_shifted_data_quiet_and_identical_periods);
    TH_RUN(test_line_list_checks_and_run_refusals);
    TH_RUN(test_line_stats_fixed_at_run_start);
    TH_RUN(test_line_stats_on_without_a_list_refused);
    TH_RUN(test_stat_header_names_the_runs_masks);
    return th_finish();
}
