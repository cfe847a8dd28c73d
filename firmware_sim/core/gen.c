/* gen.c - see gen.h. */
#include "gen.h"

#include <math.h>
#include <stddef.h>

#define GEN_TWO_PI 6.28318530717958647692f

void gen_init(gen_t *gen)
{
    gen->kind = GEN_OFF;
    gen->n = 1u;
    gen->idx = 0u;
    gen->phase = 0u;
    gen->cycles = 0u;
    gen->amp = 0.0f;
    gen->offset = 0.0f;
    gen->quarter_step = 0.0f;
    gen->vel_gain = 0.0f;
    gen->sin_last = 0.0f;
    gen->cos_last = 1.0f;
    gen->table = NULL;
}

static int gen_check_common(float amp, float offset, float fs_hz)
{
    if (!isfinite(amp) || !isfinite(offset) || !isfinite(fs_hz) || !(fs_hz > 0.0f)) {
        return -1;
    }
    return 0;
}

int gen_start_sine(gen_t *gen, uint32_t n, uint32_t cycles, float amp, float offset, float fs_hz)
{
    if (gen_check_common(amp, offset, fs_hz) != 0 || n < 4u || n > GEN_N_MAX || cycles < 1u || 2u * cycles >= n) {
        gen_init(gen);
        return -1;
    }
    gen_init(gen);
    gen->kind = GEN_SINE;
    gen->n = n;
    gen->cycles = cycles;
    gen->amp = amp;
    gen->offset = offset;
    gen->quarter_step = 0.25f * GEN_TWO_PI / (float)n;
    gen->vel_gain = amp * GEN_TWO_PI * (float)cycles * fs_hz / (float)n;
    return 0;
}

int gen_start_table(gen_t *gen, const float *table, uint32_t n, float amp, float offset, float fs_hz)
{
    if (gen_check_common(amp, offset, fs_hz) != 0 || table == NULL || n < 2u) {
        gen_init(gen);
        return -1;
    }
    gen_init(gen);
    gen->kind = GEN_TABLE;
    gen->n = n;
    gen->table = table;
    gen->amp = amp;
    gen->offset = offset;
    gen->vel_gain = amp * fs_hz * 0.5f;
    return 0;
}

void gen_stop(gen_t *gen)
{
    gen_init(gen);
}

