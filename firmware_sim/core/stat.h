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
 * Split between the control interrupt and the background (so drv_step stays in its budget):
 * per recorded sample, stat_push (inline, in drv_step) only copies the signals and the
 * fundamental's sin/cos (7 stores, no selection: cheaper than indexing) into a fixed
 * ping-pong pair of blocks of STAT_BLOCK samples;
 * stat_process (called by the port's main loop between steps, through drv_background)
 * consumes full blocks in order and does the DFT sums and the per-period Welford update:
 * the same float32 operations in the same order as a per-sample update in the interrupt,
 * so the results are bit for bit the same. The run's end (DONE, abort, fault) hands the last,
 * partial block over (stat_flush); stat_finish (the readers: drv_stat_size_bytes /
 * drv_stat_read, i.e. the SDO upload of 0x2041) consumes what is pending once no run is
 * active, so the statistics read after a run are always its final ones. If the interrupt
 * finds both blocks full (the background fell behind), the run's statistics are invalid:
 * no more samples are taken, the data reports P = 0 and status bit STAT_FLAG_OVERRUN, and
 * the overrun counter (0x2040:6) counts it. Interrupt / background hand-over: a block
 * belongs to the interrupt while its `ready` count is 0 and to the background while it is
 * not (single core: compiler fences only, atomic_signal_fence).
 *
 * Statistics data (the byte stream of object 0x2041, little-endian):
 *   u32 periods P (0 when invalid); u8 K; u8 harmonic signal mask; u8 power signal mask;
 *   u8 status (bit 0 STAT_FLAG_OVERRUN: the background fell behind, the numbers are not
 *   the run's);
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
#define STAT_NUM_SIGNALS 5u /* = REC_NUM_SIGNALS, signal numbers in DRV_SIG_* bit order (stat_push
                               copies exactly 5) */
#define STAT_SIGNAL_MASK 0x1Fu
#define STAT_HEADER_BYTES 8u
#define STAT_MAX_BYTES (STAT_HEADER_BYTES + 12u * STAT_K_MAX * STAT_SIG_MAX + 8u * STAT_NUM_SIGNALS)
/* Samples per hand-over block: the background must take a block within STAT_BLOCK control
 * periods (16 at 2560 Hz: 6.25 ms). Values per sample (STAT_SLOT): the STAT_NUM_SIGNALS
 * signals in bit order, then sin and cos of the fundamental (STAT_SLOT_SIN / _COS). */
#define STAT_BLOCK 16u
#define STAT_SLOT_SIN STAT_NUM_SIGNALS
#define STAT_SLOT_COS (STAT_NUM_SIGNALS + 1u)
#define STAT_SLOT (STAT_NUM_SIGNALS + 2u)
#define STAT_FLAG_OVERRUN 0x01u

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
    /* latched at run start (the data's header reports these masks, not the configured
     * ones: a write of 0x2040:2 / :3 after the run never relabels its numbers) */
    uint32_t k_run, nh, np;
    uint32_t hmask_run, pmask_run;
    uint8_t hsel[STAT_SIG_MAX], psel[STAT_NUM_SIGNALS];
    uint32_t n;            /* period [samples] */
    float inv_n;
    /* ---- interrupt side (stat_push) ---- */
    bool active;           /* taking samples this run (false after an overrun) */
    uint32_t wblk;         /* block being filled */
    uint32_t wcount;       /* samples in it */
    float *wptr;           /* next sample's values */
    /* ---- hand-over ---- */
    volatile uint32_t ready[2]; /* samples handed over in each block, 0 = the interrupt's */
    volatile bool overrun; /* this run's statistics are invalid */
    volatile uint32_t overruns; /* runs whose statistics were invalidated, since init */
    float block[2][STAT_BLOCK * STAT_SLOT];
    /* ---- background side (stat_process) ---- */
    uint32_t rblk;         /* next block to consume */
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
/* Start of a run (after stat_check, no run active): clears the statistics and the blocks. */
void stat_begin(stat_t *st, uint32_t n);

/* Interrupt side: a full block goes to the background (called by stat_push). */
void stat_block_full(stat_t *st);
/* Interrupt side (or with the interrupt masked): the run has ended; the partial block goes
 * to the background. Idempotent. */
void stat_flush(stat_t *st);

/* Background: consume the blocks handed over, in order (bounded: at most 2 blocks). */
void stat_process(stat_t *st);
/* Is a block handed over and not yet taken? */
static inline bool stat_pending(const stat_t *st)
{
    return st->ready[st->rblk] != 0u;
}
/* Background, no run active: stat_process, so the statistics are the run's final ones. */
void stat_finish(stat_t *st);
/* End of the period: the period's sums into the running statistics (stat_process). */
void stat_period_end(stat_t *st);

/* ---- per-sample hot path, inline (controller step budget) ---- */

/* One recorded sample: sig[] all STAT_NUM_SIGNALS signals in bit order, (s, c) the sine and
 * cosine of the fundamental's phase at this sample (the generator's). */
static inline void stat_push(stat_t *st, const float sig[STAT_NUM_SIGNALS], float s, float c)
{
    if (!st->active) {
        return;
    }
    float *dst = st->wptr;
    /* written out: gcc keeps a 5-trip copy loop on the M4 (twice the instructions) */
    dst[0] = sig[0];
    dst[1] = sig[1];
    dst[2] = sig[2];
    dst[3] = sig[3];
    dst[4] = sig[4];
    dst[STAT_SLOT_SIN] = s;
    dst[STAT_SLOT_COS] = c;
    st->wptr = dst + STAT_SLOT;
    if (++st->wcount == STAT_BLOCK) {
        stat_block_full(st);
    }
}

uint32_t stat_size_bytes(const stat_t *st);
/* -1 if [offset, offset+len) is not inside the statistics bytes. */
int stat_read(const stat_t *st, uint32_t offset, uint8_t *dst, uint32_t len);

#endif /* STAT_H */
