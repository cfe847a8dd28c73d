/* lstat.c - see lstat.h. */
#include "lstat.h"
#include "words.h"

#include <math.h>
#include <stddef.h>

#include "fft.h"

#if defined(__BYTE_ORDER__) && (__BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__)
#error "lstat.c streams words as little-endian bytes: little-endian targets only"
#endif

#define LSTAT_TWO_PI 6.28318530717958647692f

static void lstat_clear(lstat_t *ls)
{
    ls->next_period = 0u;
    ls->periods = 0u;
    for (uint32_t s = 0u; s < 3u; s++) {
        ls->x0[s] = 0.0f;
    }
    for (uint32_t i = 0u; i < LSTAT_LINES_MAX; i++) {
        lstat_line_t *a = &ls->acc[i];
        for (uint32_t j = 0u; j < 4u; j++) {
            a->base[j] = 0.0f;
        }
        for (uint32_t j = 0u; j < 6u; j++) {
            a->mean[j] = 0.0f;
        }
        for (uint32_t j = 0u; j < 4u; j++) {
            a->m2[j] = 0.0f;
        }
        a->du[0] = 0.0f;
        a->du[1] = 0.0f;
    }
}

void lstat_init(lstat_t *ls)
{
    ls->nlines = 0u;
    ls->mode = 0u;
    ls->nl_run = 0u;
    ls->n = 1u;
    for (uint32_t i = 0u; i < LSTAT_LINES_MAX; i++) {
        ls->stage[i] = 0u;
        ls->lines[i] = 0u;
        ls->run_lines[i] = 0u;
    }
    lstat_clear(ls);
}

lstat_status_t lstat_write(lstat_t *ls, uint32_t offset, const uint8_t *src, uint32_t len)
{
    const uint32_t cap = 2u * LSTAT_LINES_MAX;
    if (offset > cap || len > cap - offset) {
        return LSTAT_E_LENGTH;
    }
    if (src == NULL && len != 0u) {
        return LSTAT_E_VALUE;
    }
    for (uint32_t b = 0u; b < len; b++) {
        uint32_t pos = offset + b;
        uint16_t v = ls->stage[pos / 2u];
        v = (pos % 2u == 0u) ? (uint16_t)((v & 0xFF00u) | src[b]) : (uint16_t)((v & 0x00FFu) | ((uint32_t)src[b] << 8));
        ls->stage[pos / 2u] = v;
    }
    return LSTAT_OK;
}

/* every bin in 1 .. n/2 - 1, strictly ascending */
static bool lstat_list_ok(const uint16_t *bins, uint32_t count, uint32_t n)
{
    for (uint32_t i = 0u; i < count; i++) {
        if (bins[i] == 0u || 2u * (uint32_t)bins[i] >= n || (i > 0u && bins[i] <= bins[i - 1u])) {
            return false;
        }
    }
    return true;
}

lstat_status_t lstat_commit(lstat_t *ls, uint32_t total_bytes, uint32_t n)
{
    if (total_bytes > 2u * LSTAT_LINES_MAX) {
        return LSTAT_E_LENGTH;
    }
    if (total_bytes % 2u != 0u) {
        return LSTAT_E_ODD;
    }
    uint32_t count = total_bytes / 2u;
    if (!lstat_list_ok(ls->stage, count, n)) {
        return LSTAT_E_VALUE; /* the list in use stays */
    }
    for (uint32_t i = 0u; i < count; i++) {
        ls->lines[i] = ls->stage[i];
    }
    ls->nlines = count;
    return LSTAT_OK;
}

uint32_t lstat_list_size_bytes(const lstat_t *ls)
{
    return 2u * ls->nlines;
}

int lstat_list_read(const lstat_t *ls, uint32_t offset, uint8_t *dst, uint32_t len)
{
    uint32_t size = 2u * ls->nlines;
    if (offset > size || len > size - offset || (dst == NULL && len != 0u)) {
        return -1;
    }
    for (uint32_t b = 0u; b < len; b++) {
        uint32_t pos = offset + b;
        dst[b] = (uint8_t)(ls->lines[pos / 2u] >> (8u * (pos % 2u)));
    }
    return 0;
}

lstat_status_t lstat_set_mode(lstat_t *ls, uint32_t mode)
{
    if (mode > 1u) {
        return LSTAT_E_VALUE;
    }
    ls->mode = mode;
    return LSTAT_OK;
}

lstat_status_t lstat_check(const lstat_t *ls, uint32_t n, uint32_t rec_signals, uint32_t work_floats)
{
    if (ls->mode == 0u) {
        return LSTAT_OK;
    }
    if (ls->nlines == 0u) {
        return LSTAT_E_SETUP; /* on, but no list (e.g. after reset node): nothing to report */
    }
    if (!lstat_list_ok(ls->lines, ls->nlines, n)) {
        return LSTAT_E_NYQUIST;
    }
    if (n < LSTAT_N_MIN || !fft_is_pow2(n) || n > work_floats || (rec_signals & 0x07u) != 0x07u) {
        return LSTAT_E_SETUP;
    }
    return LSTAT_OK;
}

void lstat_begin(lstat_t *ls, uint32_t n)
{
    ls->nl_run = (ls->mode != 0u) ? ls->nlines : 0u;
    ls->n = n;
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        ls->run_lines[i] = ls->lines[i];
    }
    lstat_clear(ls);
}

/* X[k] of the real period whose packed, conjugated inverse transform is w (lstat.h):
 * Z[k] = conj W[k] is the forward DFT of z[m] = x[2m] + j x[2m+1]; its even / odd halves
 * E = (Z[k] + conj Z[M-k]) / 2, O = (Z[k] - conj Z[M-k]) / 2j, X[k] = E + exp(-j 2 pi k / N) O. */
static void lstat_bin(const float *w, uint32_t n, uint32_t k, float *xr, float *xi)
{
    const uint32_t m = n / 2u;
    const float ar = w[2u * k], ai = -w[2u * k + 1u];                /* Z[k] */
    const float br = w[2u * (m - k)], bi = w[2u * (m - k) + 1u];     /* conj Z[M-k] */
    const float er = 0.5f * (ar + br), ei = 0.5f * (ai + bi);
    const float orr = 0.5f * (ai - bi), oi = -0.5f * (ar - br);     /* (a - b) / 2j */
    const float ang = LSTAT_TWO_PI * (float)k / (float)n;
    const float c = cosf(ang), s = sinf(ang);                        /* t = c - j s */
    *xr = er + c * orr + s * oi;
    *xi = ei + c * oi - s * orr;
}

/* Into work (n/2 complex values, packed and conjugated), then inverse-transformed: period p
 * of recorder column col minus its first recorded sample (shift = false), or minus period 0
 * sample by sample (shift = true, p >= 1: d_p = x_p - x_0, lstat.h). */
static void lstat_transform(const lstat_t *ls, const float *rec, uint32_t nsel, uint32_t p, uint32_t col,
                            bool shift, float *work)
{
    const uint32_t n = ls->n;
    const float *src = rec + ((size_t)p * n) * nsel + col;
    if (!shift) {
        const float x0 = ls->x0[col];
        for (uint32_t i = 0u; i < n; i += 2u) {
            work[i] = src[(size_t)i * nsel] - x0;
            work[i + 1u] = -(src[(size_t)(i + 1u) * nsel] - x0);
        }
    } else {
        const float *src0 = rec + col;
        for (uint32_t i = 0u; i < n; i += 2u) {
            work[i] = src[(size_t)i * nsel] - src0[(size_t)i * nsel];
            work[i + 1u] = src0[(size_t)(i + 1u) * nsel] - src[(size_t)(i + 1u) * nsel];
        }
    }
    (void)fft_inverse_complex(work, n / 2u); /* n a power of two: checked at the start */
}

/* Period 0: the base spectra X_0 of u and y (D_0 = 0 is the first period of their means and
 * sums, which stay 0) and the first of r's means. */
static void lstat_base(lstat_t *ls, const float *rec, uint32_t nsel, float *work)
{
    const uint32_t n = ls->n;
    /* recorder columns (bit order): 0 reference r, 1 plant input u, 2 motor angle y */
    lstat_transform(ls, rec, nsel, 0u, 1u, false, work);
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        lstat_bin(work, n, ls->run_lines[i], &ls->acc[i].base[0], &ls->acc[i].base[1]);
    }
    lstat_transform(ls, rec, nsel, 0u, 2u, false, work);
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        lstat_bin(work, n, ls->run_lines[i], &ls->acc[i].base[2], &ls->acc[i].base[3]);
    }
    lstat_transform(ls, rec, nsel, 0u, 0u, false, work);
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        lstat_bin(work, n, ls->run_lines[i], &ls->acc[i].mean[4], &ls->acc[i].mean[5]);
    }
}

bool lstat_process(lstat_t *ls, const float *rec, uint32_t nsel, uint32_t samples_done, float *work)
{
    if (ls->nl_run == 0u || ls->nl_run > LSTAT_LINES_MAX || rec == NULL || work == NULL || nsel < 3u) {
        return false;
    }
    /* every bin against the run's own period before one is used as an index (lstat_bin
     * reads w[2k] and w[2(n/2 - k)]): the list was checked at the start, this keeps any
     * later change from turning into an out-of-bounds read */
    if (ls->n < LSTAT_N_MIN || !lstat_list_ok(ls->run_lines, ls->nl_run, ls->n)) {
        return false;
    }
    const uint32_t n = ls->n;
    const uint32_t p = ls->next_period;
    if ((uint64_t)(p + 1u) * n > samples_done) {
        return false; /* not recorded yet */
    }
    if (p == 0u) {
        for (uint32_t s = 0u; s < 3u; s++) {
            ls->x0[s] = rec[s];
        }
        lstat_base(ls, rec, nsel, work);
        ls->periods = 1u;
        ls->next_period = 1u;
        return true;
    }
    ls->periods++;
    const float w = 1.0f / (float)ls->periods;
    lstat_transform(ls, rec, nsel, p, 1u, true, work); /* D of U */
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        lstat_line_t *a = &ls->acc[i];
        float xr, xi;
        lstat_bin(work, n, ls->run_lines[i], &xr, &xi);
        const float dr = xr - a->mean[0], di = xi - a->mean[1];
        a->mean[0] += dr * w;
        a->mean[1] += di * w;
        a->du[0] = xr - a->mean[0];
        a->du[1] = xi - a->mean[1];
        a->m2[0] += dr * a->du[0] + di * a->du[1];
    }
    lstat_transform(ls, rec, nsel, p, 2u, true, work); /* D of Y */
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        lstat_line_t *a = &ls->acc[i];
        float xr, xi;
        lstat_bin(work, n, ls->run_lines[i], &xr, &xi);
        const float dr = xr - a->mean[2], di = xi - a->mean[3];
        a->mean[2] += dr * w;
        a->mean[3] += di * w;
        a->m2[1] += dr * (xr - a->mean[2]) + di * (xi - a->mean[3]);
        /* co-moment: (D_Y,p - old mean) conj(D_U,p - new mean) */
        a->m2[2] += dr * a->du[0] + di * a->du[1];
        a->m2[3] += di * a->du[0] - dr * a->du[1];
    }
    lstat_transform(ls, rec, nsel, p, 0u, false, work); /* X of R */
    for (uint32_t i = 0u; i < ls->nl_run; i++) {
        lstat_line_t *a = &ls->acc[i];
        float xr, xi;
        lstat_bin(work, n, ls->run_lines[i], &xr, &xi);
        a->mean[4] += (xr - a->mean[4]) * w;
        a->mean[5] += (xi - a->mean[5]) * w;
    }
    ls->next_period = p + 1u;
    return true;
}

uint32_t lstat_size_bytes(const lstat_t *ls)
{
    return LSTAT_HEADER_BYTES + LSTAT_LINE_BYTES * ls->nl_run;
}

static uint32_t lstat_word(const lstat_t *ls, uint32_t i)
{
    union { float f; uint32_t u; } w;
    if (i == 0u) {
        return ls->periods;
    }
    if (i == 1u) {
        return ls->nl_run & 0xFFFFu;
    }
    i -= 2u;
    const uint32_t line = i / (1u + LSTAT_LINE_FLOATS), r = i % (1u + LSTAT_LINE_FLOATS);
    if (r == 0u) {
        return ls->run_lines[line];
    }
    const lstat_line_t *a = &ls->acc[line];
    const float inv = ls->periods > 1u ? 1.0f / (float)(ls->periods - 1u) : 0.0f;
    w.f = (r <= 4u) ? a->base[r - 1u] + a->mean[r - 1u] : (r <= 6u) ? a->mean[r - 1u] : a->m2[r - 7u] * inv;
    return w.u;
}

static uint32_t lstat_word_of(const void *ctx, uint32_t i)
{
    return lstat_word((const lstat_t *)ctx, i);
}

int lstat_read(const lstat_t *ls, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return words_read(lstat_size_bytes(ls), lstat_word_of, ls, offset, dst, len);
}
