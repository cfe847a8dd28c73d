/*
 * ms.h - the on-drive random odd multisine of docs/multisine.md (deployable, float32).
 *
 * PRNG (fmix32-seeded xorshift32 streams), the line selection with one detection line
 * removed at random per full group of G odd candidates, the phases, and one period built
 * with a radix-2 inverse real FFT (fft.h) directly in the caller's buffer.
 * Stream 0 selects the removed lines; stream m + 1 draws the phases of realization m.
 */
#ifndef MS_H
#define MS_H

#include <stdbool.h>
#include <stdint.h>

#define MS_N_MIN 16u
#define MS_N_MAX 8192u
#define MS_G_MAX 16u

typedef enum {
    MS_OK = 0,
    MS_E_N,        /* N not a power of two in [16, 8192] */
    MS_E_BAND,     /* not 1 <= k_min <= k_max < N/2 */
    MS_E_GROUP,    /* G not 0 or 2..16 */
    MS_E_NO_LINES, /* no excited line in the band */
    MS_E_CAPACITY, /* buffer shorter than N */
    MS_E_RMS       /* rms not finite or negative */
} ms_status_t;

typedef struct {
    uint32_t n;           /* samples per period */
    uint32_t k_min, k_max;/* band in DFT bins, inclusive */
    uint32_t group;       /* G: 0 = no detection lines */
    uint32_t seed;
    uint32_t realization; /* m */
} ms_design_t;

uint32_t ms_fmix32(uint32_t z);
uint32_t ms_stream_init(uint32_t seed, uint32_t stream);
uint32_t ms_next(uint32_t *x);              /* xorshift32 step; returns the new state */
float ms_uniform01(uint32_t x);             /* (x >> 8) * 2^-24 */
uint32_t ms_index(uint32_t x, uint32_t g);  /* (x * g) >> 32 */

ms_status_t ms_check(const ms_design_t *d);
uint32_t ms_candidate_count(const ms_design_t *d); /* L: odd bins in [k_min, k_max] */
uint32_t ms_excited_count(const ms_design_t *d);   /* E */

/* Walks the odd candidates in ascending order, telling which are excited. */
typedef struct {
    uint32_t k;         /* next candidate bin */
    uint32_t k_max;
    uint32_t group;
    uint32_t full_groups;
    uint32_t pos;       /* candidate position c_pos */
    uint32_t removed;   /* position (in group) removed in the present group */
    uint32_t x;         /* stream 0 state */
} ms_lines_t;

void ms_lines_begin(ms_lines_t *it, const ms_design_t *d);
/* false when done; else *bin = candidate bin, *excited = not a removed detection line. */
bool ms_lines_next(ms_lines_t *it, uint32_t *bin, bool *excited);

/* One period u[0..N-1] with the given rms into buf (capacity >= N floats). */
ms_status_t ms_build(const ms_design_t *d, float rms, float *buf, uint32_t capacity);

#endif /* MS_H */
