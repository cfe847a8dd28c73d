/* stat.c - see stat.h. */
#include "stat.h"

#include <stddef.h>

#if defined(__BYTE_ORDER__) && (__BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__)
#error "stat.c streams float32 words as little-endian bytes: little-endian targets only"
#endif

static uint32_t stat_popcount(uint32_t m)
{
    uint32_t c = 0u;
    for (; m != 0u; m &= m - 1u) {
        c++;
    }
    return c;
}

static void stat_clear(stat_t *st)
{
    st->idx = 0u;
    st->periods = 0u;
    st->first = true;
    for (uint32_t j = 0u; j < STAT_SIG_MAX; j++) {
        st->x0[j] = 0.0f;
        for (uint32_t k = 0u; k < STAT_K_MAX; k++) {
            st->acc_re[j][k] = 0.0f;
            st->acc_im[j][k] = 0.0f;
            st->mean_re[j][k] = 0.0f;
            st->mean_im[j][k] = 0.0f;
            st->m2[j][k] = 0.0f;
        }
    }
    for (uint32_t j = 0u; j < STAT_NUM_SIGNALS; j++) {
        st->psum[j] = 0.0f;
        st->psq[j] = 0.0f;
        st->pmean[j] = 0.0f;
        st->pmsq[j] = 0.0f;
    }
}

void stat_init(stat_t *st)
{
    st->k = 0u;
    st->hmask = 0u;
    st->pmask = 0u;
    st->k_run = 0u;
    st->nh = 0u;
    st->np = 0u;
    st->n = 1u;
    st->inv_n = 1.0f;
    st->active = false;
    stat_clear(st);
}

stat_status_t stat_set_harmonics(stat_t *st, uint32_t k)
{
    if (k > STAT_K_MAX) {
        return STAT_E_RANGE;
    }
    st->k = k;
    return STAT_OK;
}

stat_status_t stat_set_signals(stat_t *st, uint32_t mask)
{
    if ((mask & ~STAT_SIGNAL_MASK) != 0u || stat_popcount(mask) > STAT_SIG_MAX) {
        return STAT_E_RANGE;
    }
    st->hmask = mask;
    return STAT_OK;
}

stat_status_t stat_set_power(stat_t *st, uint32_t mask)
{
    if ((mask & ~STAT_SIGNAL_MASK) != 0u) {
        return STAT_E_RANGE;
    }
    st->pmask = mask;
    return STAT_OK;
}

stat_status_t stat_check(const stat_t *st, uint32_t n, uint32_t cycles)
{
    if (st->k == 0u || st->hmask == 0u) {
        return STAT_OK; /* no harmonic statistics: nothing to check */
    }
    if (cycles == 0u) {
        return STAT_E_NOT_SINE;
    }
    /* highest line K c must stay below N / 2 (fs / 2); 64-bit so no product overflows */
    if (2u * (uint64_t)st->k * (uint64_t)cycles >= (uint64_t)n) {
        return STAT_E_NYQUIST;
    }
    return STAT_OK;
}

void stat_begin(stat_t *st, uint32_t n)
{
    st->k_run = st->hmask != 0u ? st->k : 0u;
    st->nh = 0u;
    st->np = 0u;
    if (st->k_run > 0u) {
        for (uint32_t b = 0u; b < STAT_NUM_SIGNALS; b++) {
            if (st->hmask & (1u << b)) {
                st->hsel[st->nh++] = (uint8_t)b;
            }
        }
    }
    for (uint32_t b = 0u; b < STAT_NUM_SIGNALS; b++) {
        if (st->pmask & (1u << b)) {
            st->psel[st->np++] = (uint8_t)b;
        }
    }
    st->n = n > 0u ? n : 1u;
    st->inv_n = 1.0f / (float)st->n;
    st->active = st->k_run > 0u || st->np > 0u;
    stat_clear(st);
}

void stat_period_end(stat_t *st)
{
    st->idx = 0u;
    st->periods++;
    const float w = 1.0f / (float)st->periods;
    for (uint32_t j = 0u; j < st->nh; j++) {
        for (uint32_t k = 0u; k < st->k_run; k++) {
            /* Welford for a complex value: mean += d / p; m2 += Re(d conj(x - mean_new)) */
            const float xr = st->acc_re[j][k], xi = st->acc_im[j][k];
            const float dr = xr - st->mean_re[j][k], di = xi - st->mean_im[j][k];
            st->mean_re[j][k] += dr * w;
            st->mean_im[j][k] += di * w;
            st->m2[j][k] += dr * (xr - st->mean_re[j][k]) + di * (xi - st->mean_im[j][k]);
            st->acc_re[j][k] = 0.0f;
            st->acc_im[j][k] = 0.0f;
        }
    }
    for (uint32_t j = 0u; j < st->np; j++) {
        st->pmean[j] += (st->psum[j] * st->inv_n - st->pmean[j]) * w;
        st->pmsq[j] += (st->psq[j] * st->inv_n - st->pmsq[j]) * w;
        st->psum[j] = 0.0f;
        st->psq[j] = 0.0f;
    }
}

uint32_t stat_size_bytes(const stat_t *st)
{
    return STAT_HEADER_BYTES + 12u * st->k_run * st->nh + 8u * st->np;
}

/* The i-th 32-bit word of the statistics data. */
static uint32_t stat_word(const stat_t *st, uint32_t i)
{
    union { float f; uint32_t u; } w; /* float32 bit pattern, no libc memcpy */
    float f = 0.0f;
    if (i == 0u) {
        return st->periods;
    }
    if (i == 1u) {
        return (st->k_run & 0xFFu) | ((st->k_run ? st->hmask : 0u) << 8) | (st->pmask << 16);
    }
    i -= 2u;
    uint32_t nharm = 3u * st->k_run * st->nh;
    if (i < nharm) {
        uint32_t j = i / (3u * st->k_run), r = i % (3u * st->k_run), k = r / 3u;
        switch (r % 3u) {
        case 0u: f = st->mean_re[j][k]; break;
        case 1u: f = st->mean_im[j][k]; break;
        default: f = st->periods > 1u ? st->m2[j][k] / (float)(st->periods - 1u) : 0.0f; break;
        }
    } else {
        i -= nharm;
        uint32_t j = i / 2u;
        f = (i % 2u == 0u) ? st->pmean[j] : st->pmsq[j];
    }
    w.f = f;
    return w.u;
}

int stat_read(const stat_t *st, uint32_t offset, uint8_t *dst, uint32_t len)
{
    uint32_t size = stat_size_bytes(st);
    if (offset > size || len > size - offset || (dst == NULL && len != 0u)) {
        return -1;
    }
    for (uint32_t b = 0u; b < len; b++) {
        uint32_t pos = offset + b;
        dst[b] = (uint8_t)(stat_word(st, pos / 4u) >> (8u * (pos % 4u)));
    }
    return 0;
}
