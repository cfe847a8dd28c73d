/*
 * lstat.h - on-drive line statistics of periodic (multisine / table) runs (deployable,
 * float32, no heap).
 *
 * For a line list configured by the host (DFT bins 1 <= k < N/2, strictly ascending, at most
 * LSTAT_LINES_MAX) and each recorded period p of N samples, the per-period spectra
 *
 *     X_p[k] = sum_{n=0}^{N-1} x_p[n] exp(-j 2 pi k n / N)               (numpy rfft at bin k)
 *
 * of the reference r, the plant input u and the motor angle y, and over periods their means
 * and the period-to-period variances of U and Y and covariance of Y and U: the sufficient
 * statistics of the robust BLA with known reference (docs/analysis.md) of one realization.
 *
 * Shifted data (the numerically sound way to a variance that is small beside the mean):
 * period 0's spectrum X_0 is the base (computed from x_0[n] - x_0[0]: the same for k >= 1,
 * a position offset stays out of the float32 FFT); every later period transforms the
 * sample-wise difference d_p[n] = x_p[n] - x_0[n] (period 0's samples are still in the
 * recorder; a float32 difference of close values is exact, any other is rounded relative to
 * itself), so D_p = X_p - X_0 carries float32 FFT rounding relative to |D_p|, not |X_p|.
 * Welford over p = 0 .. P-1 of D_p (D_0 = 0 counts as a period): the mean of D and the sums
 * of squared deviations |D_p - mean D|^2 of U and Y and the co-moment
 * (D_Y,p - mean D_Y) conj(D_U,p - mean D_U), the same as those of X (a shift by a constant
 * changes no deviation). Reported: mean X = X_0 + mean D, the variances and covariance from
 * the sums of D. The reference r has no spread in the data: its mean is Welford's of X_p
 * itself (x_p[n] - x_0[0] transformed; no base: 8 bytes a line less), as accurate as
 * X_0 + mean D would be (both carry X_0's rounding relative to the largest line).
 *
 * Computed in the background (lstat_process, from drv_background), one period per call,
 * from the samples already in the recorder (which must hold r, u and y); the FFT work
 * space is N floats the integrator provides (the drive passes the table's download staging
 * buffer, unused while a run is active). Per signal and period: one N/2-point complex FFT
 * (fft.h) of the real samples (or differences) packed two per complex value, then per line
 * the split of the even / odd halves (one sinf/cosf pair per line).
 *
 * Line statistics data (object 0x2043, little-endian): the run's own list (latched at its
 * start), whatever was committed to 0x2042 since:
 *   u32 periods P; u16 lines L; u8 status (0); u8 0;
 *   per line: u32 bin; f32 mean U re, im; mean Y re, im; mean R re, im;
 *             var U, var Y (sum |X_p - mean|^2 / (P - 1), 0 when P < 2);
 *             cov YU re, im (sum (Y_p - mean Y) conj(U_p - mean U) / (P - 1)).
 */
#ifndef LSTAT_H
#define LSTAT_H

#include <stdbool.h>
#include <stdint.h>

#ifndef LSTAT_LINES_MAX
#define LSTAT_LINES_MAX 1024u /* lines the drive holds (a port may build with fewer: -DLSTAT_LINES_MAX) */
#endif
#define LSTAT_HEADER_BYTES 8u
#define LSTAT_LINE_FLOATS 10u
#define LSTAT_LINE_BYTES (4u + 4u * LSTAT_LINE_FLOATS)
#define LSTAT_N_MIN 8u

typedef enum {
    LSTAT_OK = 0,
    LSTAT_E_LENGTH = 1,  /* list longer than LSTAT_LINES_MAX, or bytes beyond it */
    LSTAT_E_ODD = 2,     /* not a whole number of u16 bins */
    LSTAT_E_VALUE = 3,   /* bin 0, at or above N/2, or not strictly ascending */
    LSTAT_E_NYQUIST = 4, /* run start: a line at or above N/2 of this run's period */
    LSTAT_E_SETUP = 5    /* run start: N not a power of two >= 8 within the work space,
                            the recorder does not hold r, u and y, or no line list (mode on
                            with 0x2042 empty) */
} lstat_status_t;

/* One line's accumulators (signal order U, Y, R; re, im). */
typedef struct {
    float base[4];  /* X_0: period 0's spectra of U, Y */
    float mean[6];  /* Welford means of D_p = X_p - X_0 of U, Y over p = 0 ..; of X_p of R */
    float m2[4];    /* sum |dD_U|^2, sum |dD_Y|^2, sum dD_Y conj dD_U re, im */
    float du[2];    /* this period's D_U - new mean D_U (for the cross term) */
} lstat_line_t;

typedef struct {
    /* configuration */
    uint16_t stage[LSTAT_LINES_MAX];  /* the list being downloaded */
    uint16_t lines[LSTAT_LINES_MAX];  /* the committed list (0x2042: the next run's) */
    uint32_t nlines;
    uint32_t mode;                    /* 0 off, 1 on */
    /* latched at run start: what the background and the data (0x2043) use, so a later
     * commit of 0x2042 or write of the period never changes the run's own bins */
    uint16_t run_lines[LSTAT_LINES_MAX]; /* the run's list, each 1 <= bin < n/2 */
    uint32_t nl_run;                  /* lines this run, 0 = off */
    uint32_t n;                       /* period */
    /* background */
    uint32_t next_period;             /* next recorded period to transform */
    uint32_t periods;                 /* periods accumulated */
    float x0[3];                      /* r, u, y first recorded samples */
    lstat_line_t acc[LSTAT_LINES_MAX]; /* per line: base, mean D, sums */
} lstat_t;

void lstat_init(lstat_t *ls);
/* Line list download: bytes of u16 LE bins into the staging list; commit checks the
 * staged list against the period n (EXC_PERIOD now) and only then makes it the list. */
lstat_status_t lstat_write(lstat_t *ls, uint32_t offset, const uint8_t *src, uint32_t len);
lstat_status_t lstat_commit(lstat_t *ls, uint32_t total_bytes, uint32_t n);
uint32_t lstat_list_size_bytes(const lstat_t *ls);
int lstat_list_read(const lstat_t *ls, uint32_t offset, uint8_t *dst, uint32_t len);
lstat_status_t lstat_set_mode(lstat_t *ls, uint32_t mode);

/* Run start: would a run of period n with recorder signal mask rec_signals and a work
 * space of work_floats be accepted? (LSTAT_OK when off.) */
lstat_status_t lstat_check(const lstat_t *ls, uint32_t n, uint32_t rec_signals, uint32_t work_floats);
/* Start of a run (after lstat_check): clears the statistics, copies the committed list
 * as the run's (run_lines). */
void lstat_begin(lstat_t *ls, uint32_t n);
/* Background: transform the next recorded period if the recorder holds it (samples_done
 * samples of nsel values each, r, u, y the first three: the recording's latched layout);
 * work: n floats. At most one period per call; returns true if it did one. Only the run's
 * own list (run_lines) is read, each bin checked against the run's n (a bin outside
 * 1 .. n/2 - 1 cannot come from lstat_begin; it would stop the statistics, not index). */
bool lstat_process(lstat_t *ls, const float *rec, uint32_t nsel, uint32_t samples_done, float *work);

uint32_t lstat_size_bytes(const lstat_t *ls);
/* -1 if [offset, offset+len) is not inside the data. */
int lstat_read(const lstat_t *ls, uint32_t offset, uint8_t *dst, uint32_t len);

#endif /* LSTAT_H */
