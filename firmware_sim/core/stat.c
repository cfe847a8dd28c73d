/* stat.c - see stat.h. */
#include "stat.h"
#include "words.h"

#include <stdatomic.h> /* atomic_signal_fence only: a compiler barrier, no library call */
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
    st->wblk = 0u;
    st->wcount = 0u;
    st->wptr = st->block[0];
    st->ready[0] = 0u;
    st->ready[1] = 0u;
    st->overrun = false;
    st->rblk = 0u;
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
    st->hmask_run = 0u;
    st->pmask_run = 0u;
    st->n = 1u;
    st->inv_n = 1.0f;
    st->active = false;
    st->overruns = 0u;
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
    st->hmask_run = st->k_run > 0u ? st->hmask : 0u;
    st->pmask_run = st->pmask;
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
    stat_clear(st);
    st->active = st->k_run > 0u || st->np > 0u;
}

/* ---- interrupt side ---- */

void stat_block_full(stat_t *st)
{
    uint32_t b = st->wblk;
    atomic_signal_fence(memory_order_release); /* the samples before the hand-over */
    st->ready[b] = st->wcount;
    b ^= 1u;
    if (st->ready[b] != 0u) {
        /* the background still holds the other block: nowhere to write the next sample */
        st->overrun = true;
        st->overruns++;
        st->active = false;
        return;
    }
    st->wblk = b;
    st->wcount = 0u;
    st->wptr = st->block[b];
}

void stat_flush(stat_t *st)
{
    if (!st->active) {
        return;
    }
    st->active = false;
    if (st->wcount > 0u) {
        atomic_signal_fence(memory_order_release);
        st->ready[st->wblk] = st->wcount;
    }
}

/* ---- background side ---- */

/* One recorded sample's update (v: its STAT_SLOT values). The float32
 * operations and their order are those of the per-sample update this replaces. */
static void stat_sample(stat_t *st, const float *v)
{
    if (st->first) {
        for (uint32_t j = 0u; j < st->nh; j++) {
            st->x0[j] = v[st->hsel[j]];
        }
        st->first = false;
    }
    if (st->k_run > 0u) {
        const float s = v[STAT_SLOT_SIN], c = v[STAT_SLOT_COS];
        /* z_k = exp(-j 2 pi k c n / N) = (c - j s)^k for all STAT_K_MAX harmonics (fixed
         * trip counts; unused ones are never read): z2 = z1^2, z3 = z2 z1, z4 = z2^2,
         * z5..z8 = z4 z1..z4 (at most 3 roundings deep, no drift) */
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
            const float x = v[st->hsel[j]] - st->x0[j];
            float *ar = st->acc_re[j], *ai = st->acc_im[j];
            for (uint32_t k = 0u; k < STAT_K_MAX; k++) {
                ar[k] += x * zr[k];
                ai[k] += x * zi[k];
            }
        }
    }
    for (uint32_t j = 0u; j < st->np; j++) {
        const float x = v[st->psel[j]];
        st->psum[j] += x;
        st->psq[j] += x * x;
    }
    if (++st->idx == st->n) {
        stat_period_end(st);
    }
}

void stat_process(stat_t *st)
{
    for (uint32_t i = 0u; i < 2u; i++) {
        uint32_t b = st->rblk;
        uint32_t count = st->ready[b];
        if (count == 0u) {
            return;
        }
        atomic_signal_fence(memory_order_acquire); /* the samples after the hand-over */
        if (!st->overrun) {
            const float *v = st->block[b];
            for (uint32_t i_s = 0u; i_s < count; i_s++, v += STAT_SLOT) {
                stat_sample(st, v);
            }
        }
        atomic_signal_fence(memory_order_release); /* done reading before giving it back */
        st->ready[b] = 0u;
        st->rblk = b ^ 1u;
    }
}

void stat_finish(stat_t *st)
{
    stat_process(st);
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
        return st->overrun ? 0u : st->periods;
    }
    if (i == 1u) {
        return (st->k_run & 0xFFu) | (st->hmask_run << 8) | (st->pmask_run << 16) |
               ((st->overrun ? STAT_FLAG_OVERRUN : 0u) << 24);
    }
    if (st->overrun) {
        return 0u; /* invalid: no number rather than a wrong one */
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

static uint32_t stat_word_of(const void *ctx, uint32_t i)
{
    return stat_word((const stat_t *)ctx, i);
}

int stat_read(const stat_t *st, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return words_read(stat_size_bytes(st), stat_word_of, st, offset, dst, len);
}
