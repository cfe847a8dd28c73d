/* fft.c - see fft.h. */
#include "fft.h"

#include <math.h>

#define FFT_TWO_PI 6.28318530717958647692f

bool fft_is_pow2(uint32_t n)
{
    return n != 0u && (n & (n - 1u)) == 0u;
}

bool fft_inverse_complex(float *a, uint32_t m)
{
    if (!fft_is_pow2(m)) {
        return false;
    }
    /* bit-reversal permutation */
    for (uint32_t i = 1u, j = 0u; i < m; i++) {
        uint32_t bit = m >> 1;
        while (j & bit) {
            j ^= bit;
            bit >>= 1;
        }
        j |= bit;
        if (i < j) {
            float tr = a[2u * i], ti = a[2u * i + 1u];
            a[2u * i] = a[2u * j];
            a[2u * i + 1u] = a[2u * j + 1u];
            a[2u * j] = tr;
            a[2u * j + 1u] = ti;
        }
    }
    /* butterflies; twiddle loop outside so each twiddle is computed once per stage */
    for (uint32_t len = 2u; len <= m; len <<= 1) {
        uint32_t half = len >> 1;
        for (uint32_t k = 0u; k < half; k++) {
            float ang = FFT_TWO_PI * (float)k / (float)len;
            float wr = cosf(ang), wi = sinf(ang);
            for (uint32_t i = k; i < m; i += len) {
                uint32_t p = 2u * i, q = 2u * (i + half);
                float tr = wr * a[q] - wi * a[q + 1u];
                float ti = wr * a[q + 1u] + wi * a[q];
                a[q] = a[p] - tr;
                a[q + 1u] = a[p + 1u] - ti;
                a[p] += tr;
                a[p + 1u] += ti;
            }
        }
    }
    return true;
}

/* Z[k] = (X[k] + X[k+M]) + j (X[k] - X[k+M]) W^k, W = exp(+j 2 pi / N), X[k+M] = conj X[M-k]. */
static void fft_split_pair(const float *xk, const float *xmk, uint32_t k, uint32_t n, float *zr, float *zi)
{
    float ar = xk[0], ai = xk[1];       /* X[k] */
    float br = xmk[0], bi = -xmk[1];    /* X[k+M] = conj X[M-k] */
    float sr = ar + br, si = ai + bi;   /* X[k] + X[k+M] */
    float dr = ar - br, di = ai - bi;   /* X[k] - X[k+M] */
    float ang = FFT_TWO_PI * (float)k / (float)n;
    float wr = cosf(ang), wi = sinf(ang);
    float tr = dr * wr - di * wi, ti = dr * wi + di * wr; /* (X[k]-X[k+M]) W^k */
    *zr = sr - ti;                      /* + j * t */
    *zi = si + tr;
}

bool fft_inverse_real(float *buf, uint32_t n)
{
    if (n < 4u || !fft_is_pow2(n)) {
        return false;
    }
    uint32_t m = n / 2u;
    /* k = 0 pairs with M (both zero by contract): Z[0] = X[0] + X[M] + j(X[0] - X[M]) = 0 */
    buf[0] = 0.0f;
    buf[1] = 0.0f;
    for (uint32_t k = 1u; k <= m / 2u; k++) {
        uint32_t mk = m - k;
        float zr_k, zi_k, zr_mk, zi_mk;
        fft_split_pair(&buf[2u * k], &buf[2u * mk], k, n, &zr_k, &zi_k);
        fft_split_pair(&buf[2u * mk], &buf[2u * k], mk, n, &zr_mk, &zi_mk);
        buf[2u * k] = zr_k;
        buf[2u * k + 1u] = zi_k;
        if (mk != k) {
            buf[2u * mk] = zr_mk;
            buf[2u * mk + 1u] = zi_mk;
        }
    }
    /* z[m] = x[2m] + j x[2m+1]: the interleaved complex result is x in order */
    return fft_inverse_complex(buf, m);
}
