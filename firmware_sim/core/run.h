/*
 * run.h - run control (deployable): idle -> settling -> recording -> done, or aborted /
 * fault. Exact sample counts: a run of S settle and R record samples spends exactly S
 * controller steps settling and R recording, then is DONE. States and stop reasons use
 * the numbering of drv.h (DRV_RUN_*, DRV_STOP_*).
 */
#ifndef RUN_H
#define RUN_H

#include <stdbool.h>
#include <stdint.h>

enum { RUN_IDLE = 0, RUN_SETTLING = 1, RUN_RECORDING = 2, RUN_DONE = 3, RUN_ABORTED = 4, RUN_FAULT = 5 };
/* what the present sample is, as returned by run_tick */
typedef enum { RUN_TICK_NONE = 0, RUN_TICK_SETTLE = 1, RUN_TICK_RECORD = 2 } run_tick_t;

typedef struct {
    uint32_t state;
    uint32_t progress;     /* samples elapsed in this run */
    uint32_t settle_total; /* settle samples */
    uint32_t total;        /* settle + record samples */
    uint32_t counter;      /* runs started */
    uint32_t last_error;   /* DRV_STOP_* of the last refusal / stop */
} run_t;

void run_init(run_t *run);

/* ---- per-sample hot path, inline (controller step budget) ---- */

static inline bool run_active(const run_t *run)
{
    return run->state == RUN_SETTLING || run->state == RUN_RECORDING;
}

/* Classifies the present sample and advances; call once per controller step. */
static inline run_tick_t run_tick(run_t *run)
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

/* Start (caller has checked the state and the configuration). record_samples >= 1;
 * returns -1 if settle + record overflows 32 bits. */
int run_begin(run_t *run, uint32_t settle_samples, uint32_t record_samples);
/* End an active run in `state` (RUN_ABORTED or RUN_FAULT) with reason; no-op if idle. */
void run_stop(run_t *run, uint32_t state, uint32_t reason);
void run_refuse(run_t *run, uint32_t reason);

#endif /* RUN_H */
