/*
 * task.h - the machine's own repeated task and its statistics (deployable, float32, no
 * OS call, no heap, fixed buffers; docs/track.md).
 *
 * Task generator: point-to-point moves with a third-order (jerk-limited, 7-segment)
 * set-point profile and a dwell, from five parameters: distance D [rad], v_max [rad/s],
 * a_max [rad/s^2], jerk j_max [rad/s^3], dwell [s]. One repetition is
 *   mode 1 (back and forth): +D move, dwell, -D move, dwell (ends where it started);
 *   mode 2 (forward only, an indexing axis): +D move, dwell (never reverses).
 * The segment lengths are whole samples (the continuous design rounded UP, then v, a and
 * j lowered so that the move covers exactly D): the task is exactly periodic, its samples
 * depend on the sample index only, and no limit is exceeded. Position, velocity and
 * acceleration are evaluated in closed form per sample (no integration drift).
 *
 * Statistics (per run, over the recorded repetitions): the repetition is cut into
 * TASK_BLOCKS blocks of equal sample counts; per block the drive sums the products of the
 * regressors phi = [p, n, v_r, a_r] (p = max(s, 0), n = min(s, 0), s the feed-forward's
 * sign of v_r) with themselves (the design part: 9 sums, p n = 0) and with the plant input
 * u, plus sum e^2 and sum u^2 (the data part: 6 sums). The host solves for the friction
 * (fftune.analysis.track). Byte streams: task_design_read / task_data_read (the run's
 * recorded repetitions), task_latch_*_read (the last one alone, while the run goes on).
 */
#ifndef TASK_H
#define TASK_H

#include <stdbool.h>
#include <stdint.h>

#define TASK_BLOCKS 8u           /* blocks per repetition */
#define TASK_N_MAX (1u << 24)    /* samples per repetition at most (float time exact) */
#define TASK_DESIGN_SUMS 9u      /* pp nn pv pa nv na vv va aa */
#define TASK_DATA_SUMS 6u        /* pu nu vu au ee uu */
#define TASK_HEADER_BYTES 8u     /* u32 repetitions, u32 samples per repetition */
#define TASK_DESIGN_BYTES (TASK_HEADER_BYTES + 4u * TASK_BLOCKS * TASK_DESIGN_SUMS)
#define TASK_DATA_BYTES (TASK_HEADER_BYTES + 4u * TASK_BLOCKS * TASK_DATA_SUMS)

enum { TASK_MODE_OFF = 0, TASK_MODE_BACK_AND_FORTH = 1, TASK_MODE_FORWARD = 2, TASK_MODE_MAX = 2 };

typedef enum { TASK_OK = 0, TASK_E_RANGE = 1, TASK_E_DESIGN = 2, TASK_E_LENGTH = 3 } task_status_t;

typedef struct {
    /* parameters (SI) */
    uint32_t mode;
    float distance, v_max, a_max, jerk, dwell, ka;
    float fs, ts;
    /* design (task_design): segment lengths and the start state of the 7 move segments */
    uint32_t n_seg[8];       /* 7 move segments + dwell, samples */
    float seg_p[7], seg_v[7], seg_a[7], seg_j[7];
    uint32_t n_move, n_rep;  /* samples of one move (+ its dwell), of one repetition; 0 = invalid */
    /* generator state */
    uint32_t seg, k;         /* segment, sample within it */
    float dir;               /* +1 forward, -1 backward (mode 1, second half) */
    float base;              /* position the present move starts from [rad] */
    float v_last, a_last;    /* of the last sample */
    bool running;            /* a task run is active (drv) */
    /* statistics */
    uint32_t blk, blk_end, rk; /* block, its end sample, sample within the repetition */
    uint32_t reps;           /* recorded repetitions accumulated */
    float design[TASK_BLOCKS][TASK_DESIGN_SUMS];
    float data[TASK_BLOCKS][TASK_DATA_SUMS];
    /* the last completed recorded repetition alone (latched at its end, readable while the
     * run goes on: continuous tracking); its sums are those accumulated since the previous
     * latch, kept in rep_* */
    uint32_t latched;        /* repetitions latched in this run */
    float rep_design[TASK_BLOCKS][TASK_DESIGN_SUMS];
    float rep_data[TASK_BLOCKS][TASK_DATA_SUMS];
    float latch_design[TASK_BLOCKS][TASK_DESIGN_SUMS];
    float latch_data[TASK_BLOCKS][TASK_DATA_SUMS];
} task_t;

void task_init(task_t *t, float fs_hz);
/* Parameter setters: finite and >= 0 (mode <= TASK_MODE_MAX), else TASK_E_RANGE and the
 * old value kept; each recomputes the design (n_rep 0 when the set is not a valid task). */
task_status_t task_set_mode(task_t *t, uint32_t mode);
task_status_t task_set_param(task_t *t, uint32_t which, float value); /* TASK_P_* */
enum { TASK_P_DISTANCE = 0, TASK_P_V_MAX, TASK_P_A_MAX, TASK_P_JERK, TASK_P_DWELL, TASK_P_KA };
float task_get_param(const task_t *t, uint32_t which);
/* Samples per repetition of the present parameters, 0 if they make no valid task (a limit
 * 0, a repetition longer than TASK_N_MAX samples). */
uint32_t task_period(const task_t *t);
/* Position [rad] a repetition ends at, relative to where it started (0 or D). */
float task_displacement(const task_t *t);

/* Start a task run (generator at the repetition's start, sums cleared). TASK_E_DESIGN if
 * the parameters make no task. */
task_status_t task_begin(task_t *t);

/* ---- per-sample hot path, inline ---- */

/* Offset w [rad] from the run's start, velocity [rad/s], acceleration feed-forward
 * K_a a_r [V] of the present sample; then advance one sample. */
static inline void task_next(task_t *t, float *w, float *w_dot, float *u_acc)
{
    float p, v, a;
    uint32_t s = t->seg;
    if (s < 7u) {
        float tt = (float)t->k * t->ts;
        float j = t->seg_j[s];
        a = t->seg_a[s] + j * tt;
        v = t->seg_v[s] + tt * (t->seg_a[s] + 0.5f * j * tt);
        p = t->seg_p[s] + tt * (t->seg_v[s] + tt * (0.5f * t->seg_a[s] + (1.0f / 6.0f) * j * tt));
    } else {
        a = 0.0f;
        v = 0.0f;
        p = t->distance;
    }
    v *= t->dir;
    a *= t->dir;
    *w = t->base + t->dir * p;
    *w_dot = v;
    *u_acc = t->ka * a;
    t->v_last = v;
    t->a_last = a;
    if (++t->k >= t->n_seg[s]) {
        t->k = 0u;
        do { /* skip empty segments (no constant-acceleration or cruise phase) */
            s++;
            if (s == 8u) {
                s = 0u;
                t->base += t->dir * t->distance;
                if (t->mode == TASK_MODE_BACK_AND_FORTH) {
                    t->dir = -t->dir;
                }
            }
        } while (t->n_seg[s] == 0u);
        t->seg = s;
    }
}

/* End of a recorded repetition: its own sums become the latched record (task.c). */
void task_latch(task_t *t);

/* One recorded sample: s the feed-forward's sign of the velocity of the sample task_next
 * returned last, u the plant input [V], e the tracking error [rad]. The run's sums are those
 * of the latched repetitions plus the present one (task_latch adds them up). */
static inline void task_push(task_t *t, float s, float u, float e)
{
    const float v = t->v_last, a = t->a_last;
    const float p = s > 0.0f ? s : 0.0f;
    const float n = s < 0.0f ? s : 0.0f;
    float *d = t->rep_design[t->blk];
    float *x = t->rep_data[t->blk];
    d[0] += p * p;
    d[1] += n * n;
    d[2] += p * v;
    d[3] += p * a;
    d[4] += n * v;
    d[5] += n * a;
    d[6] += v * v;
    d[7] += v * a;
    d[8] += a * a;
    x[0] += p * u;
    x[1] += n * u;
    x[2] += v * u;
    x[3] += a * u;
    x[4] += e * e;
    x[5] += u * u;
    if (++t->rk == t->blk_end) {
        if (t->rk == t->n_rep) {
            t->rk = 0u;
            t->blk = 0u;
            t->reps++;
            task_latch(t);
        } else {
            t->blk++;
        }
        t->blk_end = (uint32_t)(((uint64_t)(t->blk + 1u) * t->n_rep) / TASK_BLOCKS);
    }
}

/* Byte streams (little-endian): u32 repetitions accumulated, u32 samples per repetition,
 * then per block the sums (design: pp nn pv pa nv na vv va aa; data: pu nu vu au ee uu) as
 * f32. -1 if [offset, offset + len) is outside. */
uint32_t task_design_size_bytes(const task_t *t);
int task_design_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len);
uint32_t task_data_size_bytes(const task_t *t);
int task_data_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len);
/* The same layout for the last latched repetition (header: u32 latched count, u32 samples). */
int task_latch_design_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len);
int task_latch_data_read(const task_t *t, uint32_t offset, uint8_t *dst, uint32_t len);

#endif /* TASK_H */
