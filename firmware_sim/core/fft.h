/*
 * fft.h - radix-2 inverse FFTs in float32, in place, no tables, no heap (deployable).
 *
 * fft_inverse_complex: a[m] <- sum_k a[k] exp(+j 2 pi k m / M), M a power of two,
 *   a interleaved (re, im) pairs, 2*M floats. Unnormalised.
 * fft_inverse_real: the real sequence x[n] = sum_{k=0}^{N-1} X[k] exp(+j 2 pi k n / N) of a
 *   Hermitian spectrum X (X[N-k] = conj X[k]) whose X[0] and X[N/2] are zero. On entry
 *   buf holds X[k] for k = 0 .. N/2-1 as interleaved pairs (buf[2k], buf[2k+1]; the pair
 *   k = 0 must be zero); on return buf[n] = x[n], n = 0 .. N-1. One N/2-point complex
 *   FFT plus an O(N) split (the standard "two real halves in one complex FFT" packing).
 * Twiddles come from sinf/cosf per use (N calls in all), which keeps the error at
 * float32 level without a twiddle table in RAM.
 */
#ifndef FFT_H
#define FFT_H

#include <stdbool.h>
#include <stdint.h>

bool fft_is_pow2(uint32_t n);
/* m >= 1 power of two; returns false (buffer untouched) otherwise. */
bool fft_inverse_complex(float *a, uint32_t m);
/* n >= 4 power of two; returns false (buffer untouched) otherwise. */
bool fft_inverse_real(float *buf, uint32_t n);

#endif /* FFT_H */
