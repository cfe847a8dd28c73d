/*
 * drv_state.h - TEST DOUBLE of the drive state for the CANopen unit tests (found before
 * core/drv_state.h on the test include path). Never linked into drive_sim.
 */
#ifndef DRV_STATE_H
#define DRV_STATE_H

#include <stdbool.h>
#include <stdint.h>

#include "od_params.h"

typedef struct {
    float f[DRV_PARAM_COUNT];
    uint32_t u[DRV_PARAM_COUNT];
    bool enabled, fault;
    uint32_t run_state, last_error, run_counter;
    uint32_t rec_bytes;       /* size of the (synthetic) recorder data */
    uint8_t table[32768];
    uint32_t table_bytes;     /* committed */
    uint32_t table_generation;
    uint16_t line_stage[1024], lines[1024]; /* line list (0x2042), capacity STAT_LINES_CAP */
    uint32_t nlines;
    float target_rad;
    float motor_rad, reference_rad, velocity_rad_s;
    int safe_stops, enables, disables;
} drv_t;

#endif
