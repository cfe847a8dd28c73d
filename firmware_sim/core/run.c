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

bool run_active(const run_t *run)
{
    return run->state == RUN_SETTLING || run->state == RUN_RECORDING;
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

run_tick_t run_tick(run_t *run)
{
    run_tick_t what;
    if (run->state == RUN_SETTLING) {
        what = RUN_TICK_SETTLE;
    } else if (run->state == RUN_RECORDING) {
        what = RUN_TICK_RECORD;
    } else {
        return RUN_TICK_NONE;
    }
    run->progress++;
    if (run->progress == run->total) {
        run->state = RUN_DONE;
    } else if (run->progress == run->settle_total) {
        run->state = RUN_RECORDING;
    }
    return what;
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
