/*
 * drv_state.h - drv_t, the drive aggregate's state (core's business; included by drv.h).
 * Callers treat drv_t as opaque and only allocate it (static in the port).
 */
#ifndef DRV_STATE_H
#define DRV_STATE_H

#include <stdbool.h>
#include <stdint.h>

#include "ctl.h"
#include "gen.h"
#include "lstat.h"
#include "rec.h"
#include "run.h"
#include "stat.h"
#include "task.h"

typedef struct {
    gen_t gen;
    run_t run;
    rec_t rec;

    float fs_hz;
    float *table_buf;        /* the table in use (committed) */
    float *table_stage;      /* the next one, being downloaded; swapped at commit */
    uint32_t table_capacity; /* samples */
    uint32_t table_length;   /* committed samples (TABLE_LENGTH) */
    uint32_t table_generation;

    /* excitation configuration (EXC_*, MS_*) */
    uint32_t exc_kind, exc_inject, exc_period, exc_sine_cycles;
    uint32_t exc_settle_periods, exc_record_periods;
    float exc_amplitude, exc_offset;
    uint32_t ms_k_min, ms_k_max, ms_group, ms_seed, ms_realization;
    uint32_t run_inject;     /* injection point latched at run start */

    /* live values */
    bool enabled;
    bool fault;
    float target, reference, error, u;
    float motor, load;
    float motor_prev;        /* previous measurement (velocity by backward difference) */

    /* last: its ~1.5 kB (hand-over blocks) would push the fields above beyond the
     * Cortex-M4's short load/store offsets (vldr: 1020 bytes), costing drv_step an address
     * computation per access */
    stat_t stat;
    lstat_t lstat;           /* line statistics of periodic runs (lstat.h) */
    /* with the line statistics: recorded samples of u at the output limit, counted in
     * the background from the recorder (STAT_LINE_SATURATED) */
    uint32_t sat_scanned;    /* recorded samples looked at */
    uint32_t sat_samples;    /* of them with |u| >= sat_u_max */
    float sat_u_max;         /* u_max latched at run start (the count's threshold) */
    task_t task;             /* the repeated task and its statistics (task.h, issue 26) */
    /* the controller last as well: its feed-forward level table (1 kB, ctl.h) would push
     * the fields above beyond the short offsets; the step addresses ctl from one base */
    ctl_t ctl;
} drv_t;

#endif /* DRV_STATE_H */
