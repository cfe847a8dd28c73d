/* ms.c - see ms.h and docs/multisine.md. */
#include "ms.h"

#include <math.h>

#include "fft.h"

#define MS_PI 3.14159265358979323846f

/* newlib's sqrtf wrapper sets errno (a C-library object the deployable part must not
 * touch); the builtin with -fno-math-errno is the FPU's vsqrt.f32 instead. */
#if defined(__GNUC__)
#define MS_SQRTF(x) __builtin_sqrtf(x)
#else
#define MS_SQRTF(x) sqrtf(x)
#endif

uint32_t ms_fmix32(uint32_t z)
{
    z ^= z >> 16;
    z *= 0x85EBCA6Bu;
    z ^= z >> 13;
    z *= 0xC2B2AE35u;
    z ^= z >> 16;
    return z;
}

uint32_t ms_stream_init(uint32_t seed, uint32_t stream)
{
    uint32_t x = ms_fmix32(seed + stream * 0x9E3779B9u);
    return x != 0u ? x : 0x6D2B79F5u;
}

uint32_t ms_next(uint32_t *x)
{
    uint32_t v = *x;
    v ^= v << 13;
    v ^= v >> 17;
    v ^= v << 5;
    *x = v;
    return v;
}

float ms_uniform01(uint32_t x)
{
    return (float)(x >> 8) * (1.0f / 16777216.0f);
}

uint32_t ms_index(uint32_t x, uint32_t g)
{
    return (uint32_t)(((uint64_t)x * (uint64_t)g) >> 32);
}

ms_status_t ms_check(const ms_design_t *d)
{
    if (d->n < MS_N_MIN || d->n > MS_N_MAX || !fft_is_pow2(d->n)) {
        return MS_E_N;
    }
    if (d->k_min < 1u || d->k_min > d->k_max || d->k_max >= d->n / 2u) {
        return MS_E_BAND;
    }
    if (d->group == 1u || d->group > MS_G_MAX) {
        return MS_E_GROUP;
    }
    if (ms_excited_count(d) == 0u) {
        return MS_E_NO_LINES;
    }
    return MS_OK;
}

uint32_t ms_candidate_count(const ms_design_t *d)
{
    if (d->k_max < d->k_min) {
        return 0u;
    }
    uint32_t first = d->k_min | 1u; /* smallest odd >= k_min */
    if (first > d->k_max) {
        return 0u;
    }
    return (d->k_max - first) / 2u + 1u;
}

uint32_t ms_excited_count(const ms_design_t *d)
{
    uint32_t l = ms_candidate_count(d);
    if (d->group >= 2u) {
        return l - l / d->group;
    }
    return l;
}

void ms_lines_begin(ms_lines_t *it, const ms_design_t *d)
{
    uint32_t l = ms_candidate_count(d);
    it->k = d->k_min | 1u;
    it->k_max = d->k_max;
    it->group = d->group >= 2u ? d->group : 0u;
    it->full_groups = it->group ? l / it->group : 0u;
    it->pos = 0u;
    it->removed = 0u;
    it->x = ms_stream_init(d->seed, 0u);
}

bool ms_lines_next(ms_lines_t *it, uint32_t *bin, bool *excited)
{
    if (it->k > it->k_max || it->k < 1u) {
        return false;
    }
    bool removed = false;
    if (it->group) {
        uint32_t g = it->pos / it->group;
        uint32_t in_group = it->pos % it->group;
        if (g < it->full_groups) {
            if (in_group == 0u) {
                it->removed = ms_index(ms_next(&it->x), it->group);
            }
            removed = (in_group == it->removed);
        }
    }
    *bin = it->k;
    *excited = !removed;
    it->k += 2u;
    it->pos++;
    return true;
}

ms_status_t ms_build(const ms_design_t *d, float rms, float *buf, uint32_t capacity)
{
    ms_status_t st = ms_check(d);
    if (st != MS_OK) {
        return st;
    }
    if (!isfinite(rms) || rms < 0.0f) {
        return MS_E_RMS;
    }
    if (buf == 0 || capacity < d->n) {
        return MS_E_CAPACITY;
    }
    for (uint32_t i = 0u; i < d->n; i++) {
        buf[i] = 0.0f;
    }
    /* X[k] = C/2 with C = a (sin phi - j cos phi), so that
     * sum_k X[k] e^{j 2 pi k n/N} + conj = a sin(2 pi k n / N + phi). */
    float half_a = 0.5f * rms * MS_SQRTF(2.0f / (float)ms_excited_count(d));
    uint32_t xp = ms_stream_init(d->seed, d->realization + 1u);
    ms_lines_t it;
    ms_lines_begin(&it, d);
    uint32_t bin;
    bool excited;
    while (ms_lines_next(&it, &bin, &excited)) {
        if (!excited) {
            continue;
        }
        float phi = MS_PI * (2.0f * ms_uniform01(ms_next(&xp)) - 1.0f);
        buf[2u * bin] = half_a * sinf(phi);
        buf[2u * bin + 1u] = -half_a * cosf(phi);
    }
    (void)fft_inverse_real(buf, d->n); /* N checked above */
    return MS_OK;
}
