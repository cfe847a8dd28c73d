/*
 * drv_double.c - TEST DOUBLE of the drive API (core/drv.h) for the CANopen unit tests:
 * parameters with the generated limits, a run state machine the tests advance by hand,
 * synthetic recorder data (byte i = rec_byte(i)). Never linked into drive_sim.
 */
#include <math.h>
#include <string.h>

#include "drv.h"
#include "drv_double.h"

uint8_t rec_byte(uint32_t i) { return (uint8_t)((i * 7u) ^ (i >> 8) ^ (i >> 16)); }

drv_status_t drv_init(drv_t *d, const drv_storage_t *storage)
{
    (void)storage;
    memset(d, 0, sizeof *d);
    for (int i = 0; i < DRV_PARAM_COUNT; i++) {
        d->f[i] = DRV_PARAM_INFO[i].default_f32;
        d->u[i] = DRV_PARAM_INFO[i].default_u32;
    }
    return DRV_OK;
}

float drv_step(drv_t *d, const drv_meas_t *m)
{
    d->motor_rad = m->motor_angle_rad;
    return 0.0f;
}

static bool active(const drv_t *d)
{
    return d->run_state == DRV_RUN_SETTLING || d->run_state == DRV_RUN_RECORDING;
}

drv_status_t drv_get_f32(const drv_t *d, drv_param_id_t id, float *v)
{
    if ((int)id < 0 || id >= DRV_PARAM_COUNT || DRV_PARAM_INFO[id].type != DRV_PT_F32) {
        return DRV_E_NO_PARAM;
    }
    *v = d->f[id];
    return DRV_OK;
}

drv_status_t drv_set_f32(drv_t *d, drv_param_id_t id, float v)
{
    if ((int)id < 0 || id >= DRV_PARAM_COUNT || DRV_PARAM_INFO[id].type != DRV_PT_F32) {
        return DRV_E_NO_PARAM;
    }
    const drv_param_info_t *p = &DRV_PARAM_INFO[id];
    if (!p->writable) {
        return DRV_E_READ_ONLY;
    }
    if (!isfinite(v)) {
        return DRV_E_NOT_FINITE;
    }
    if (p->has_high && v > p->high_f32) {
        return DRV_E_RANGE_HIGH;
    }
    if (p->has_low && v < p->low_f32) {
        return DRV_E_RANGE_LOW;
    }
    d->f[id] = v;
    return DRV_OK;
}

drv_status_t drv_get_u32(const drv_t *d, drv_param_id_t id, uint32_t *v)
{
    if ((int)id < 0 || id >= DRV_PARAM_COUNT || DRV_PARAM_INFO[id].type != DRV_PT_U32) {
        return DRV_E_NO_PARAM;
    }
    switch (id) {
    case DRV_P_RUN_STATE: *v = d->run_state; break;
    case DRV_P_RUN_LAST_ERROR: *v = d->last_error; break;
    case DRV_P_RUN_COUNTER: *v = d->run_counter; break;
    case DRV_P_REC_BYTES: *v = d->rec_bytes; break;
    case DRV_P_RUN_COMMAND: *v = 0u; break;
    default: *v = d->u[id]; break;
    }
    return DRV_OK;
}

drv_status_t drv_set_u32(drv_t *d, drv_param_id_t id, uint32_t v)
{
    if ((int)id < 0 || id >= DRV_PARAM_COUNT || DRV_PARAM_INFO[id].type != DRV_PT_U32) {
        return DRV_E_NO_PARAM;
    }
    const drv_param_info_t *p = &DRV_PARAM_INFO[id];
    if (!p->writable) {
        return DRV_E_READ_ONLY;
    }
    if (p->has_high && v > p->high_u32) {
        return DRV_E_RANGE_HIGH;
    }
    if (p->has_low && v < p->low_u32) {
        return DRV_E_RANGE_LOW;
    }
    d->u[id] = v;
    return DRV_OK;
}

drv_status_t drv_run_start(drv_t *d)
{
    if (!d->enabled || d->fault || active(d)) {
        return DRV_E_STATE;
    }
    d->run_state = DRV_RUN_SETTLING;
    d->last_error = DRV_STOP_NONE;
    d->run_counter++;
    return DRV_OK;
}

void drv_run_abort(drv_t *d, drv_stop_reason_t r)
{
    if (active(d)) {
        d->run_state = DRV_RUN_ABORTED;
        d->last_error = r;
    }
}

void drv_safe_stop(drv_t *d, drv_stop_reason_t r)
{
    d->safe_stops++;
    drv_run_abort(d, r);
}

void drv_enable(drv_t *d, bool en)
{
    if (en) {
        d->enables++;
        d->fault = false;
    } else {
        d->disables++;
        drv_run_abort(d, DRV_STOP_DISABLED);
    }
    d->enabled = en;
}

uint32_t drv_rec_size_bytes(const drv_t *d) { return d->rec_bytes; }

drv_status_t drv_rec_read(const drv_t *d, uint32_t off, uint8_t *dst, uint32_t len)
{
    if ((uint64_t)off + len > d->rec_bytes) {
        return DRV_E_LENGTH;
    }
    for (uint32_t i = 0; i < len; i++) {
        dst[i] = rec_byte(off + i);
    }
    return DRV_OK;
}

/* statistics: 8 synthetic bytes (the header of an empty statistics stream) */
uint32_t drv_stat_size_bytes(drv_t *d) { (void)d; return 8u; }

drv_status_t drv_stat_read(drv_t *d, uint32_t off, uint8_t *dst, uint32_t len)
{
    (void)d;
    if ((uint64_t)off + len > 8u) {
        return DRV_E_LENGTH;
    }
    for (uint32_t i = 0; i < len; i++) {
        dst[i] = (uint8_t)(off + i);
    }
    return DRV_OK;
}

/* line list: u16 bins, checked at the commit like core/lstat.c (against EXC_PERIOD) */
drv_status_t drv_lines_write(drv_t *d, uint32_t off, const uint8_t *src, uint32_t len)
{
    uint32_t cap = 2u * d->u[DRV_P_STAT_LINES_CAP];
    if (active(d)) {
        return DRV_E_STATE;
    }
    if (cap > sizeof d->line_stage || (uint64_t)off + len > cap) {
        return DRV_E_TOO_LONG;
    }
    memcpy((uint8_t *)d->line_stage + off, src, len);
    return DRV_OK;
}

drv_status_t drv_lines_commit(drv_t *d, uint32_t total)
{
    if (active(d)) {
        return DRV_E_STATE;
    }
    if (total > 2u * d->u[DRV_P_STAT_LINES_CAP]) {
        return DRV_E_TOO_LONG;
    }
    if (total % 2u != 0u) {
        return DRV_E_LENGTH;
    }
    for (uint32_t i = 0; i < total / 2u; i++) {
        uint32_t b = d->line_stage[i];
        if (b == 0u || 2u * b >= d->u[DRV_P_EXC_PERIOD] || (i > 0u && b <= d->line_stage[i - 1u])) {
            return DRV_E_VALUE;
        }
    }
    memcpy(d->lines, d->line_stage, total);
    d->nlines = total / 2u;
    d->u[DRV_P_STAT_LINES] = d->nlines;
    return DRV_OK;
}

uint32_t drv_lines_size_bytes(const drv_t *d) { return 2u * d->nlines; }

drv_status_t drv_lines_read(const drv_t *d, uint32_t off, uint8_t *dst, uint32_t len)
{
    if ((uint64_t)off + len > 2u * d->nlines) {
        return DRV_E_LENGTH;
    }
    memcpy(dst, (const uint8_t *)d->lines + off, len);
    return DRV_OK;
}

/* line statistics data: the 8-byte header + 44 synthetic bytes per line */
uint32_t drv_line_stats_size_bytes(drv_t *d) { return 8u + 44u * d->nlines; }

drv_status_t drv_line_stats_read(drv_t *d, uint32_t off, uint8_t *dst, uint32_t len)
{
    if ((uint64_t)off + len > 8u + 44u * d->nlines) {
        return DRV_E_LENGTH;
    }
    for (uint32_t i = 0; i < len; i++) {
        dst[i] = rec_byte(off + i);
    }
    return DRV_OK;
}

drv_status_t drv_table_write(drv_t *d, uint32_t off, const uint8_t *src, uint32_t len)
{
    if (active(d)) {
        return DRV_E_STATE;
    }
    if ((uint64_t)off + len > sizeof d->table) {
        return DRV_E_LENGTH;
    }
    memcpy(&d->table[off], src, len);
    return DRV_OK;
}

drv_status_t drv_table_commit(drv_t *d, uint32_t total)
{
    if (total > sizeof d->table || total % 4u) {
        return DRV_E_LENGTH;
    }
    d->table_bytes = total;
    d->u[DRV_P_TABLE_LENGTH] = total / 4u;
    d->table_generation++;
    return DRV_OK;
}

uint32_t drv_table_generation(const drv_t *d) { return d->table_generation; }

uint32_t drv_table_size_bytes(const drv_t *d) { return d->table_bytes; }

drv_status_t drv_table_read(const drv_t *d, uint32_t off, uint8_t *dst, uint32_t len)
{
    if ((uint64_t)off + len > d->table_bytes) {
        return DRV_E_LENGTH;
    }
    memcpy(dst, &d->table[off], len);
    return DRV_OK;
}

drv_status_t drv_set_target(drv_t *d, float t)
{
    if (!isfinite(t)) {
        return DRV_E_NOT_FINITE;
    }
    d->target_rad = t;
    return DRV_OK;
}

void drv_get_monitor(const drv_t *d, drv_monitor_t *m)
{
    memset(m, 0, sizeof *m);
    m->target_rad = d->target_rad;
    m->reference_rad = d->reference_rad;
    m->motor_angle_rad = d->motor_rad;
    m->motor_velocity_rad_s = d->velocity_rad_s;
    m->following_error_rad = d->reference_rad - d->motor_rad;
    m->enabled = d->enabled;
    m->fault = d->fault;
}

bool drv_fault(const drv_t *d) { return d->fault; }

/* task statistics (issue 26): header + synthetic bytes, design 296 / data 200 bytes */
uint32_t drv_task_stats_size_bytes(const drv_t *d, uint32_t part)
{
    (void)d;
    return (part & 1u) ? 296u : 200u;
}

drv_status_t drv_task_stats_read(const drv_t *d, uint32_t part, uint32_t off, uint8_t *dst, uint32_t len)
{
    if ((uint64_t)off + len > drv_task_stats_size_bytes(d, part)) {
        return DRV_E_LENGTH;
    }
    for (uint32_t i = 0; i < len; i++) {
        dst[i] = rec_byte(off + i);
    }
    return DRV_OK;
}
