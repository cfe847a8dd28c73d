/*
 * stat.h - on-drive run statistics (deployable, float32, no table, no heap).
 *
 * Harmonic statistics of a sine run: while the run records, for up to STAT_SIG_MAX
 * selected signals x and the harmonics k = 1 .. K (K <= STAT_K_MAX) of the sine at bin c
 * (EXC_SINE_CYCLES) of the period of N samples, the per-period DFT
 *
 *     X_p[k] = sum_{n=0}^{N-1} (x_p[n] - x0) exp(-j 2 pi k c n / N)
 *
 * (numpy's rfft convention at bin k c; x0 = the signal's first recorded sample, which does
 * not change X for k >= 1 but keeps a large position offset out of the float32 partial
 * sums), accumulated with a rotating phasor: per sample one complex multiply-add per
 * signal and harmonic, constant cost, no table. The fundamental phasor exp(-j 2 pi c n / N)
 * is the generator's own sin/cos of the integer phase index (gen.h), so it is exact to
 * float32 rounding at every sample and does not drift; harmonic k is its k-th power (error
 * about k float32 roundings). At the end of each period X_p goes into Welford's running
 * mean and sum of squared deviations over periods (complex values; variance
 * sum_p |X_p - mean|^2 / (P - 1)).
 * Power statistics: for the signals of a second mask, the mean and the mean square over the
 * recorded samples (per period, then over periods), e.g. the rms tracking error.
 *
 * Statistics data (the byte stream of object 0x2041, little-endian):
 *   u32 periods P; u8 K; u8 harmonic signal mask; u8 power signal mask; u8 0;
 *   per harmonic signal (bit order), per k = 1 .. K: f32 mean re, f32 mean im, f32 variance
 *     (0 when P < 2);
 *   per power signal (bit order): f32 mean, f32 mean square.
 */
#ifndef STAT_H
#define STAT_H

#include <stdbool.h>
#include <stdint.h>

#define STAT_K_MAX 8u       /* harmonics the drive holds */
#define STAT_SIG_MAX 3u     /* signals with harmonic statistics */
#define STAT_NUM_SIGNALS 5u /* = REC_NUM_SIGNALS, signal numbers in DRV_SIG_* bit order */
#define STAT_SIGNAL_MASK 0x1Fu
#define STAT_HEADER_BYTES 8u
#define STAT_MAX_BYTES (STAT_HEADER_BYTES + 12u * STAT_K_MAX * STAT_SIG_MAX + 8u * STAT_NUM_SIGNALS)

typedef enum {
    STAT_OK = 0,
    STAT_E_RANGE = 1,    /* more harmonics / signals than the drive holds */
    STAT_E_NYQUIST = 2,  /* harmonic K of the sine at or above fs/2 */
    STAT_E_NOT_SINE = 3  /* harmonic statistics need a sine run */
} stat_status_t;

typedef struct {
    /* configuration (STAT_HARMONICS, STAT_SIGNALS, STAT_POWER) */
    uint32_t k;            /* harmonics K, 0 = harmonic statistics off */
    uint32_t hmask, pmask; /* signal masks */
    /* latched at run start */
    uint32_t k_run, nh, np;
    uint8_t hsel[STAT_SIG_MAX], psel[STAT_NUM_SIGNALS];
    uint32_t n;            /* period [samples] */
    float inv_n;
    bool active;           /* any statistics this run */
    bool first;            /* next sample is the run's first recorded one */
    /* per period */
    uint32_t idx;          /* sample in the period */
    float x0[STAT_SIG_MAX];
    float acc_re[STAT_SIG_MAX][STAT_K_MAX], acc_im[STAT_SIG_MAX][STAT_K_MAX];
    float psum[STAT_NUM_SIGNALS], psq[STAT_NUM_SIGNALS];
    /* over periods (Welford) */
    uint32_t periods;
    float mean_re[STAT_SIG_MAX][STAT_K_MAX], mean_im[STAT_SIG_MAX][STAT_K_MAX];
    float m2[STAT_SIG_MAX][STAT_K_MAX];
    float pmean[STAT_NUM_SIGNALS], pmsq[STAT_NUM_SIGNALS];
} stat_t;

void stat_init(stat_t *st);
/* Configuration; STAT_E_RANGE (unchanged) for k > STAT_K_MAX, a mask outside 0x1F or more
 * than STAT_SIG_MAX harmonic signals. */
stat_status_t stat_set_harmonics(stat_t *st, uint32_t k);
stat_status_t stat_set_signals(stat_t *st, uint32_t mask);
stat_status_t stat_set_power(stat_t *st, uint32_t mask);
/* Would a run with period n, sine cycles c (0 for a run without a sine) be accepted? */
stat_status_t stat_check(const stat_t *st, uint32_t n, uint32_t cycles);
/* Start of a run (after stat_check): clears the statistics. */
void stat_begin(stat_t *st, uint32_t n);
/* End of the period: the period's sums into the running statistics (called by stat_push). */
void stat_period_end(stat_t *st);

/* ---- per-sample hot path, inline (controller step budget) ---- */

/* One recorded sample: sig[] all STAT_NUM_SIGNALS signals in bit order, (s, c) the sine and
 * cosine of the fundamental's phase at this sample (the generator's). */
static inline void stat_push(stat_t *st, const float sig[STAT_NUM_SIGNALS], float s, float c)
{
    if (!st->active) {
        return;
    }
    if (st->first) {
        for (uint32_t j = 0u; j < st->nh; j++) {
            st->x0[j] = sig[st->hsel[j]];
        }
        st->first = false;
    }
    if (st->k_run > 0u) {
        /* z_k = exp(-j 2 pi k c n / N) = (c - j s)^k for all STAT_K_MAX harmonics (constant
         * cost, fixed trip counts the compiler unrolls / vectorises; unused ones are never
         * read): z2 = z1^2, z3 = z2 z1, z4 = z2^2, z5..z8 = z4 z1..z4 (at most 3 roundings
         * deep, no drift) */
        float zr[STAT_K_MAX], zi[STAT_K_MAX];
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
        for (uint32_t j = 0u; j < st->nh; j++) {
            const float x = sig[st->hsel[j]] - st->x0[j];
            float *ar = st->acc_re[j], *ai = st->acc_im[j];
            for (uint32_t k = 0u; k < STAT_K_MAX; k++) {
                ar[k] += x * zr[k];
                ai[k] += x * zi[k];
            }
        }
    }
    for (uint32_t j = 0u; j < st->np; j++) {
        const float x = sig[st->psel[j]];
        st->psum[j] += x;
        st->psq[j] += x * x;
    }
    if (++st->idx == st->n) {
        stat_period_end(st);
    }
}

uint32_t stat_size_bytes(const stat_t *st);
/* -1 if [offset, offset+len) is not inside the statistics bytes. */
int stat_read(const stat_t *st, uint32_t offset, uint8_t *dst, uint32_t len);

#endif /* STAT_H */
