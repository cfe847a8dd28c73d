/* run.c - see run.h. */
#include "run.h"

void run_init(run_t *run)
{
    run->state = RUN_IDLE;
    run->progress = 0u;
    run->settle_total = 0u;
    run->total = 0u;
    run->counter = 0u;
    run->last_error = 0u;
}

int run_begin(run_t *run, uint32_t settle_samples, uint32_t record_samples)
{
    if (record_samples == 0u || settle_samples > UINT32_MAX - record_samples) {
        return -1;
    }
    run->settle_total = settle_samples;
    run->total = settle_samples + record_samples;
    run->progress = 0u;
    run->counter++;
    run->last_error = 0u;
    run->state = settle_samples > 0u ? RUN_SETTLING : RUN_RECORDING;
    return 0;
}

void run_stop(run_t *run, uint32_t state, uint32_t reason)
{
    if (!run_active(run)) {
        return;
    }
    run->state = state;
    run->last_error = reason;
}

void run_refuse(run_t *run, uint32_t reason)
{
    run->last_error = reason;
}
