/*
 * gen.h - the excitation generator (deployable, float32, O(1) per sample).
 *
 * Produces per controller sample the excitation w[n] = offset + amplitude * shape[n] and
 * its time derivative (used as the reference velocity by the feed-forward, so that the
 * Coulomb sign switches at the right sample and not half a sample late):
 *  - GEN_SINE: shape[n] = sin(2 pi p / N) with the integer phase index
 *    p = (cycles * n) mod N (phase accumulation in integers: the sequence repeats
 *    exactly, bit for bit, every N samples; gen_sincos_index, no libm call). Derivative analytic:
 *    amplitude * 2 pi cycles fs / N * cos(2 pi p / N).
 *  - GEN_TABLE: shape[n] = table[n mod N], played cyclically, bit-exact (multiplying by
 *    amplitude 1 and adding offset 0 leaves a float unchanged, except -0 -> +0).
 *    Derivative: periodic central difference amplitude * (t[n+1] - t[n-1]) * fs / 2,
 *    which for a sampled sinusoid is exactly proportional to its cosine (right sign).
 * The on-drive multisine is built into the table (ms.h) and played as GEN_TABLE.
 */
#ifndef GEN_H
#define GEN_H

#include <stdint.h>

typedef enum { GEN_OFF = 0, GEN_SINE = 1, GEN_TABLE = 2 } gen_kind_t;

#define GEN_N_MAX (1u << 28) /* sine period limit: 4 p must fit 32 bits */

typedef struct {
    gen_kind_t kind;
    uint32_t n;        /* period [samples] */
    uint32_t idx;      /* table index / sample in period, [0, n) */
    uint32_t phase;    /* sine phase index, [0, n) */
    uint32_t cycles;   /* sine cycles per period */
    float amp, offset;
    float quarter_step;/* (pi/2) / n: angle per unit of 4 p mod n */
    float sin_last, cos_last; /* sine: sin, cos of 2 pi p / n of the last sample (stat.h) */
    float vel_gain;    /* sine: amp 2 pi cycles fs / n; table: amp fs / 2 */
    const float *table;
} gen_t;

void gen_init(gen_t *gen);
/* Sine, cycles in [1, n/2) and 4 <= n <= GEN_N_MAX; returns 0 on success, -1 on a bad argument
 * (generator left off). */
int gen_start_sine(gen_t *gen, uint32_t n, uint32_t cycles, float amp, float offset, float fs_hz);
/* Table of n >= 2 samples (caller keeps it alive and unchanged while playing). */
int gen_start_table(gen_t *gen, const float *table, uint32_t n, float amp, float offset, float fs_hz);
void gen_stop(gen_t *gen);

/* ---- per-sample hot path, inline (controller step budget) ---- */

/* sin and cos of 2 pi p / n for an integer phase index p in [0, n): the quadrant and the
 * remainder are found in integers (exact), the remaining angle a = (pi/2) r / n in
 * [0, pi/2) goes through Taylor polynomials to a^11 / a^12 (truncation error < 6e-8, below
 * float32 rounding). Depends on p only: exactly periodic, and the same numbers on the MCU
 * and the host (no libm in the loop). quarter_step = (pi/2) * 4 / n. */
static inline void gen_sincos_index(uint32_t p, uint32_t n, float quarter_step, float *s_out, float *c_out)
{
    uint32_t p4 = 4u * p;
    uint32_t q = p4 / n;
    float a = (float)(p4 - q * n) * quarter_step;
    float a2 = a * a;
    float s = a * (1.0f + a2 * (-1.0f / 6.0f + a2 * (1.0f / 120.0f + a2 * (-1.0f / 5040.0f +
                  a2 * (1.0f / 362880.0f + a2 * (-1.0f / 39916800.0f))))));
    float c = 1.0f + a2 * (-0.5f + a2 * (1.0f / 24.0f + a2 * (-1.0f / 720.0f + a2 * (1.0f / 40320.0f +
                  a2 * (-1.0f / 3628800.0f + a2 * (1.0f / 479001600.0f))))));
    switch (q) {
    case 0u: *s_out = s; *c_out = c; break;
    case 1u: *s_out = c; *c_out = -s; break;
    case 2u: *s_out = -s; *c_out = -c; break;
    default: *s_out = -c; *c_out = s; break;
    }
}

/* Value and derivative of the present sample, then advance one sample.
 * Off: both 0. */
static inline void gen_next(gen_t *gen, float *w, float *w_dot)
{
    switch (gen->kind) {
    case GEN_SINE: {
        float s, c;
        gen_sincos_index(gen->phase, gen->n, gen->quarter_step, &s, &c);
        gen->sin_last = s;
        gen->cos_last = c;
        *w = gen->offset + gen->amp * s;
        *w_dot = gen->vel_gain * c;
        gen->phase += gen->cycles;
        if (gen->phase >= gen->n) {
            gen->phase -= gen->n;
        }
        break;
    }
    case GEN_TABLE: {
        uint32_t i = gen->idx;
        uint32_t prev = (i == 0u) ? gen->n - 1u : i - 1u;
        uint32_t next = (i + 1u == gen->n) ? 0u : i + 1u;
        *w = gen->offset + gen->amp * gen->table[i];
        *w_dot = gen->vel_gain * (gen->table[next] - gen->table[prev]);
        gen->idx = next;
        break;
    }
    default:
        *w = 0.0f;
        *w_dot = 0.0f;
        break;
    }
}

#endif /* GEN_H */
