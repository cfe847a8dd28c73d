/* task.c - see task.h. Deployable: float32, no OS call, no heap. */
#include "task.h"

#include <math.h>

#define TASK_REP_MIN (8u * TASK_BLOCKS) /* a repetition has at least 8 samples per block */

/* cube root of y > 0 by Newton's method from above (no libm call) */
static float task_cbrt(float y)
{
    float x = y > 1.0f ? y : 1.0f;
    for (int i = 0; i < 200; i++) {
        float nx = (2.0f * x + y / (x * x)) * (1.0f / 3.0f);
        if (!(nx < x)) {
            break;
        }
        x = nx;
    }
    return x;
}

/* whole samples of a duration (rounded up); false if not finite or too long */
static bool task_samples(float dur_s, float fs, uint32_t *n)
{
    float x = dur_s * fs;
    if (!isfinite(x) || x < 0.0f || x > (float)TASK_N_MAX) {
        return false;
    }
    uint32_t k = (uint32_t)x;
    if ((float)k < x - 1e-4f * (x > 1.0f ? x : 1.0f)) { /* (float noise of an exact count) */
        k++;
    }
    *n = k;
    return true;
}

/* The 7-segment design for the present parameters (n_rep = 0 if none). */
static void task_design(task_t *t)
{
    t->n_rep = 0u;
    t->n_move = 0u;
    const float d = t->distance, vm = t->v_max, am = t->a_max, jm = t->jerk;
    if (!(d > 0.0f && vm > 0.0f && am > 0.0f && jm > 0.0f) || !(t->fs > 0.0f)) {
        return;
    }
    /* continuous durations within the limits */
    float tj = am / jm, ta;
    if (vm * jm < am * am) { /* a_max not reached before v_max */
        tj = __builtin_sqrtf(vm / jm);
        ta = 0.0f;
    } else {
        ta = vm / am - tj;
    }
    float tv;
    float d_acc = vm * (2.0f * tj + ta); /* accelerating to v_max and back to 0 */
    if (d >= d_acc) {
        tv = (d - d_acc) / vm;
    } else {
        tv = 0.0f;
        float a = jm * tj; /* keep this acceleration, shorten its constant phase */
        ta = 0.5f * (-3.0f * tj + __builtin_sqrtf(tj * tj + 4.0f * d / a));
        if (!(ta > 0.0f)) {
            ta = 0.0f;
            tj = task_cbrt(d / (2.0f * jm));
        }
    }
    uint32_t nj, na, nv, nd;
    if (!task_samples(tj, t->fs, &nj) || !task_samples(ta, t->fs, &na) || !task_samples(tv, t->fs, &nv) ||
        !task_samples(t->dwell, t->fs, &nd)) {
        return;
    }
    if (nj == 0u) {
        nj = 1u;
    }
    uint64_t move = 4u * (uint64_t)nj + 2u * (uint64_t)na + nv;
    uint64_t rep = (move + nd) * (t->mode == TASK_MODE_FORWARD ? 1u : 2u);
    if (rep < TASK_REP_MIN || rep > TASK_N_MAX) {
        return;
    }
    /* lower v, a, j so that the whole-sample durations cover exactly d */
    const float Tj = (float)nj * t->ts, Ta = (float)na * t->ts, Tv = (float)nv * t->ts;
    const float v = d / (2.0f * Tj + Ta + Tv);
    const float a = v / (Tj + Ta);
    const float j = a / Tj;
    const uint32_t n[7] = {nj, na, nj, nv, nj, na, nj};
    const float jj[7] = {j, 0.0f, -j, 0.0f, -j, 0.0f, j};
    float p0 = 0.0f, v0 = 0.0f, a0 = 0.0f;
    for (int s = 0; s < 7; s++) {
        t->n_seg[s] = n[s];
        t->seg_p[s] = p0;
        t->seg_v[s] = v0;
        t->seg_a[s] = a0;
        t->seg_j[s] = jj[s];
        float T = (float)n[s] * t->ts;
        p0 = p0 + T * (v0 + T * (0.5f * a0 + (1.0f / 6.0f) * jj[s] * T));
        v0 = v0 + T * (a0 + 0.5f * jj[s] * T);
        a0 = a0 + jj[s] * T;
    }
    t->n_seg[7] = nd;
    t->n_move = (uint32_t)(move + nd);
    t->n_rep = (uint32_t)rep;
}

void task_init(task_t *t, float fs_hz)
{
    uint8_t *b = (uint8_t *)t;
    for (uint32_t i = 0u; i < (uint32_t)sizeof *t; i++) {
        b[i] = 0u;
    }
    t->fs = fs_hz;
    t->ts = fs_hz > 0.0f ? 1.0f / fs_hz : 0.0f;
    t->dir = 1.0f;
    t->n_seg[7] = 1u;
}

task_status_t task_set_mode(task_t *t, uint32_t mode)
{
    if (mode > TASK_MODE_MAX) {
        return TASK_E_RANGE;
    }
    t->mode = mode;
    task_design(t);
    return TASK_OK;
}

static float *task_param_ptr(task_t *t, uint32_t which)
{
    switch (which) {
    case TASK_P_DISTANCE: return &t->distance;
    case TASK_P_V_MAX: return &t->v_max;
    case TASK_P_A_MAX: return &t->a_max;
    case TASK_P_JERK: return &t->jerk;
    case TASK_P_DWELL: return &t->dwell;
    case TASK_P_KA: return &t->ka;
    default: return (float *)0;
    }
}

task_status_t task_set_param(task_t *t, uint32_t which, float value)
{
    float *p = task_param_ptr(t, which);
    if (p == (float *)0 || !isfinite(value) || value < 0.0f) {
        return TASK_E_RANGE;
    }
    *p = value;
    if (which != TASK_P_KA) {
        task_design(t);
    }
    return TASK_OK;
}

float task_get_param(const task_t *t, uint32_t which)
{
    float *p = task_param_ptr((task_t *)t, which);
    return p != (float *)0 ? *p : 0.0f;
}

uint32_t task_period(const task_t *t)
{
    return t->mode == TASK_MODE_OFF ? 0u : t->n_rep;
}

float task_displacement(const task_t *t)
{
    return t->mode == TASK_MODE_FORWARD ? t->distance : 0.0f;
}

task_status_t task_begin(task_t *t)
{
    if (task_period(t) == 0u) {
        return TASK_E_DESIGN;
    }
    t->seg = 0u;
    t->k = 0u;
    while (t->n_seg[t->seg] == 0u) {
        t->seg++; /* (segment 0 has nj >= 1 samples: not reached) */
    }
    t->dir = 1.0f;
    t->base = 0.0f;
    t->v_last = 0.0f;
    t->a_last = 0.0f;
    t->blk = 0u;
    t->rk = 0u;
    t->reps = 0u;
    t->blk_end = t->n_rep / TASK_BLOCKS;
    t->latched = 0u;
    for (uint32_t b = 0u; b < TASK_BLOCKS; b++) {
        for (uint32_t i = 0u; i < TASK_DESIGN_SUMS; i++) {
            t->design[b][i] = 0.0f;
            t->rep_design[b][i] = 0.0f;
            t->latch_design[b][i] = 0.0f;
        }
        for (uint32_t i = 0u; i < TASK_DATA_SUMS; i++) {
            t->data[b][i] = 0.0f;
            t->rep_data[b][i] = 0.0f;
            t->latch_data[b][i] = 0.0f;
        }
    }
    return TASK_OK;
}

void task_latch(task_t *t)
{
    for (uint32_t b = 0u; b < TASK_BLOCKS; b++) {
        for (uint32_t i = 0u; i < TASK_DESIGN_SUMS; i++) {
            t->design[b][i] += t->rep_design[b][i];
            t->latch_design[b][i] = t->rep_design[b][i];
            t->rep_design[b][i] = 0.0f;
        }
        for (uint32_t i = 0u; i < TASK_DATA_SUMS; i++) {
            t->data[b][i] += t->rep_data[b][i];
            t->latch_data[b][i] = t->rep_data[b][i];
            t->rep_data[b][i] = 0.0f;
        }
    }
    t->latched++;
}

static void task_put_u32(uint8_t *dst, uint32_t v)
{
    dst[0] = (uint8_t)v;
    dst[1] = (uint8_t)(v >> 8);
    dst[2] = (uint8_t)(v >> 16);
    dst[3] = (uint8_t)(v >> 24);
}

static void task_put_f32(uint8_t *dst, float f)
{
    union {
        float f;
        uint32_t u;
    } c;
    c.f = f;
    task_put_u32(dst, c.u);
}

/* byte i of a stream of header (count, samples) + blocks x m sums of `sums` */
static int task_read(const task_t *t, uint32_t count, const float *sums, uint32_t m, uint32_t offset, uint8_t *dst,
                     uint32_t len)
{
    uint32_t size = TASK_HEADER_BYTES + 4u * TASK_BLOCKS * m;
    if (offset > size || len > size - offset || (dst == (uint8_t *)0 && len != 0u)) {
        return -1;
    }
    for (uint32_t i = 0u; i < len; i++) {
        uint32_t pos = offset + i;
        uint8_t w[4];
        uint32_t word = pos / 4u;
        if (word == 0u) {
            task_put_u32(w, count);
        } else if (word == 1u) {
            task_put_u32(w, t->n_rep);
        } else {
            task_put_f32(w, sums[word - 2u]);
        }
        dst[i] = w[pos % 4u];
    }
    return 0;
}

uint32_t task_design_size_bytes(const task_t *t)
{
    (void)t;
    return TASK_DESIGN_BYTES;
}

int task_design_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return task_read(t, t->reps, &t->design[0][0], TASK_DESIGN_SUMS, offset, dst, len);
}

int task_latch_design_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return task_read(t, t->latched, &t->latch_design[0][0], TASK_DESIGN_SUMS, offset, dst, len);
}

int task_latch_data_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return task_read(t, t->latched, &t->latch_data[0][0], TASK_DATA_SUMS, offset, dst, len);
}

uint32_t task_data_size_bytes(const task_t *t)
{
    (void)t;
    return TASK_DATA_BYTES;
}

int task_data_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return task_read(t, t->reps, &t->data[0][0], TASK_DATA_SUMS, offset, dst, len);
}
