/*
 * gen.h - the excitation generator (deployable, float32, O(1) per sample).
 *
 * Produces per controller sample the excitation w[n] = offset + amplitude * shape[n] and
 * its time derivative (used as the reference velocity by the feed-forward, so that the
 * Coulomb sign switches at the right sample and not half a sample late):
 *  - GEN_SINE: shape[n] = sin(2 pi p / N) with the integer phase index
 *    p = (cycles * n) mod N (phase accumulation in integers: the sequence repeats
 *    exactly, bit for bit, every N samples). Derivative analytic:
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

typedef struct {
    gen_kind_t kind;
    uint32_t n;        /* period [samples] */
    uint32_t idx;      /* table index / sample in period, [0, n) */
    uint32_t phase;    /* sine phase index, [0, n) */
    uint32_t cycles;   /* sine cycles per period */
    float amp, offset;
    float sine_step;   /* 2 pi / n */
    float vel_gain;    /* sine: amp 2 pi cycles fs / n; table: amp fs / 2 */
    const float *table;
} gen_t;

void gen_init(gen_t *gen);
/* Sine, cycles in [1, n/2) and n >= 4; returns 0 on success, -1 on a bad argument
 * (generator left off). */
int gen_start_sine(gen_t *gen, uint32_t n, uint32_t cycles, float amp, float offset, float fs_hz);
/* Table of n >= 2 samples (caller keeps it alive and unchanged while playing). */
int gen_start_table(gen_t *gen, const float *table, uint32_t n, float amp, float offset, float fs_hz);
void gen_stop(gen_t *gen);

/* Value and derivative of the present sample, then advance one sample.
 * Off: both 0. */
void gen_next(gen_t *gen, float *w, float *w_dot);

#endif /* GEN_H */
