/*
 * drv.c - the drive aggregate (see drv.h): parameter dispatch on the generated DRV_P_* ids,
 * run start/stop, one control step. Generic checks (type, access, finite, od.yaml limits)
 * come from DRV_PARAM_INFO so configs/od.yaml stays the one source of truth; the module
 * setters then apply the physical checks. Deployable: no OS call, no heap.
 */
#include "drv.h"

#include <math.h>

#include "ms.h"

#define DRV_FS_MAX_HZ 1.0e6f

/* ---- the repeated task (issue 26, task.h): implemented at the end of this file ---- */
static drv_status_t drv_task_get_f32(const drv_t *drv, drv_param_id_t id, float *value);
static drv_status_t drv_task_get_u32(const drv_t *drv, drv_param_id_t id, uint32_t *value);
static drv_status_t drv_task_set_f32(drv_t *drv, drv_param_id_t id, float value);
static drv_status_t drv_task_set_u32(drv_t *drv, drv_param_id_t id, uint32_t value);
static drv_status_t drv_task_start(drv_t *drv);
static void drv_task_end(drv_t *drv, float reference);

/* ---- helpers ---- */

static drv_status_t drv_from_ctl(ctl_status_t st)
{
    switch (st) {
    case CTL_OK:
        return DRV_OK;
    case CTL_E_NOT_FINITE:
        return DRV_E_NOT_FINITE;
    case CTL_E_RANGE_LOW:
        return DRV_E_RANGE_LOW;
    default:
        return DRV_E_RANGE_HIGH;
    }
}

/* Generic checks shared by get/set: known drive parameter of the right type. */
static drv_status_t drv_check_id(drv_param_id_t id, drv_param_type_t type)
{
    if ((uint32_t)id >= (uint32_t)DRV_PARAM_COUNT) {
        return DRV_E_NO_PARAM;
    }
    if (DRV_PARAM_INFO[id].sim_only) {
        return DRV_E_NO_PARAM; /* the simulated plant's, see sim_get_f32 */
    }
    if (DRV_PARAM_INFO[id].type != type) {
        return DRV_E_LENGTH; /* type mismatch: CiA 301 0x06070010 */
    }
    return DRV_OK;
}

/* ---- init ---- */

drv_status_t drv_init(drv_t *drv, const drv_storage_t *storage)
{
    if (drv == NULL || storage == NULL) {
        return DRV_E_GENERAL;
    }
    if (!isfinite(storage->fs_hz)) {
        return DRV_E_NOT_FINITE;
    }
    if (!(storage->fs_hz > 0.0f)) {
        return DRV_E_RANGE_LOW;
    }
    if (storage->fs_hz > DRV_FS_MAX_HZ || storage->table_capacity > DRV_TABLE_MAX) {
        return DRV_E_RANGE_HIGH;
    }
    if ((storage->rec_buf == NULL && storage->rec_capacity != 0u) ||
        ((storage->table_buf == NULL || storage->table_stage_buf == NULL ||
          storage->table_stage_buf == storage->table_buf) && storage->table_capacity != 0u)) {
        return DRV_E_GENERAL;
    }
    drv->fs_hz = storage->fs_hz;
    drv->table_buf = storage->table_buf;
    drv->table_stage = storage->table_stage_buf;
    drv->table_capacity = storage->table_capacity;
    drv->table_length = 0u;
    drv->table_generation = 0u;
    (void)ctl_init(&drv->ctl, storage->fs_hz);
    gen_init(&drv->gen);
    run_init(&drv->run);
    (void)rec_init(&drv->rec, storage->rec_buf, storage->rec_capacity);
    stat_init(&drv->stat);
    lstat_init(&drv->lstat);
    task_init(&drv->task, storage->fs_hz);
    drv->exc_kind = DRV_EXC_NONE;
    drv->exc_inject = DRV_INJECT_REFERENCE;
    drv->run_inject = DRV_INJECT_REFERENCE;
    drv->enabled = false;
    drv->fault = false;
    drv->target = 0.0f;
    drv->reference = 0.0f;
    drv->error = 0.0f;
    drv->u = 0.0f;
    drv->motor = 0.0f;
    drv->load = 0.0f;
    drv->motor_prev = 0.0f;
    drv->sat_scanned = 0u;
    drv->sat_samples = 0u;
    drv->sat_u_max = 0.0f;
    /* defaults of every writable drive parameter from od.yaml, through the checked path */
    for (uint32_t i = 0u; i < (uint32_t)DRV_PARAM_COUNT; i++) {
        const drv_param_info_t *info = &DRV_PARAM_INFO[i];
        if (!info->writable || info->sim_only || i == (uint32_t)DRV_P_RUN_COMMAND) {
            continue;
        }
        drv_status_t st = (info->type == DRV_PT_F32)
                              ? drv_set_f32(drv, (drv_param_id_t)i, info->default_f32)
                              : drv_set_u32(drv, (drv_param_id_t)i, info->default_u32);
        /* DRV_E_NO_PARAM: an OD parameter this core does not implement (yet); the drive
         * still starts, and test_drv_defaults_from_od flags it */
        if (st != DRV_OK && st != DRV_E_NO_PARAM) {
            return DRV_E_GENERAL; /* od.yaml default outside its own limits */
        }
    }
    return DRV_OK;
}

/* ---- parameters ---- */

drv_status_t drv_get_f32(const drv_t *drv, drv_param_id_t id, float *value)
{
    drv_status_t st = drv_check_id(id, DRV_PT_F32);
    if (st != DRV_OK) {
        return st;
    }
    if (value == NULL) {
        return DRV_E_GENERAL;
    }
    float v;
    switch (id) {
    case DRV_P_KP: v = drv->ctl.kp; break;
    case DRV_P_KD: v = drv->ctl.kd; break;
    case DRV_P_TAU_D: v = drv->ctl.tau_d; break;
    case DRV_P_KFC: v = drv->ctl.kfc; break;
    case DRV_P_KV: v = drv->ctl.kv; break;
    case DRV_P_FC_SMOOTH: v = drv->ctl.fc_smooth; break;
    case DRV_P_KFA: v = drv->ctl.kfa; break;
    case DRV_P_KPS: v = drv->ctl.kps; break;
    case DRV_P_KPC: v = drv->ctl.kpc; break;
    case DRV_P_U_MAX: v = drv->ctl.u_max; break;
    case DRV_P_FS: v = drv->fs_hz; break;
    case DRV_P_EXC_AMPLITUDE: v = drv->exc_amplitude; break;
    case DRV_P_EXC_OFFSET: v = drv->exc_offset; break;
    case DRV_P_MEAS_MOTOR_ANGLE: v = drv->motor; break;
    case DRV_P_MEAS_LOAD_ANGLE: v = drv->load; break;
    case DRV_P_MEAS_REFERENCE: v = drv->reference; break;
    case DRV_P_MEAS_PLANT_INPUT: v = drv->u; break;
    default: return drv_task_get_f32(drv, id, value); /* the task's, or DRV_E_NO_PARAM */
    }
    *value = v;
    return DRV_OK;
}

/* Parameters fixed for the duration of a run (DRV_E_STATE while one is active): the
 * excitation, the recorder and statistics set-up, and u_max (the run's saturation count
 * compares the recorded u with it: one limit per run, latched at the start for the
 * background, sat_u_max). */
static bool drv_exc_param(drv_param_id_t id)
{
    switch (id) {
    case DRV_P_U_MAX:
    case DRV_P_EXC_KIND: case DRV_P_EXC_INJECT: case DRV_P_EXC_AMPLITUDE: case DRV_P_EXC_OFFSET:
    case DRV_P_EXC_PERIOD: case DRV_P_EXC_SINE_CYCLES: case DRV_P_EXC_SETTLE_PERIODS:
    case DRV_P_EXC_RECORD_PERIODS: case DRV_P_MS_K_MIN: case DRV_P_MS_K_MAX: case DRV_P_MS_GROUP:
    case DRV_P_MS_SEED: case DRV_P_MS_REALIZATION: case DRV_P_REC_SIGNALS:
    case DRV_P_STAT_HARMONICS: case DRV_P_STAT_SIGNALS: case DRV_P_STAT_POWER:
    case DRV_P_STAT_LINE_MODE:
        return true;
    default:
        return false;
    }
}

drv_status_t drv_set_f32(drv_t *drv, drv_param_id_t id, float value)
{
    drv_status_t st = drv_check_id(id, DRV_PT_F32);
    if (st != DRV_OK) {
        return st;
    }
    const drv_param_info_t *info = &DRV_PARAM_INFO[id];
    if (!info->writable) {
        return DRV_E_READ_ONLY;
    }
    if (!isfinite(value)) {
        return DRV_E_NOT_FINITE;
    }
    if (info->has_low && value < info->low_f32) {
        return DRV_E_RANGE_LOW;
    }
    if (info->has_high && value > info->high_f32) {
        return DRV_E_RANGE_HIGH;
    }
    if (drv_exc_param(id) && run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    switch (id) {
    case DRV_P_KP: return drv_from_ctl(ctl_set_kp(&drv->ctl, value));
    case DRV_P_KD: return drv_from_ctl(ctl_set_kd(&drv->ctl, value));
    case DRV_P_TAU_D: return drv_from_ctl(ctl_set_tau_d(&drv->ctl, value));
    case DRV_P_KFC: return drv_from_ctl(ctl_set_kfc(&drv->ctl, value));
    case DRV_P_KV: return drv_from_ctl(ctl_set_kv(&drv->ctl, value));
    case DRV_P_FC_SMOOTH: return drv_from_ctl(ctl_set_fc_smooth(&drv->ctl, value));
    case DRV_P_KFA: return drv_from_ctl(ctl_set_kfa(&drv->ctl, value));
    case DRV_P_KPS: return drv_from_ctl(ctl_set_kps(&drv->ctl, value));
    case DRV_P_KPC: return drv_from_ctl(ctl_set_kpc(&drv->ctl, value));
    case DRV_P_U_MAX: return drv_from_ctl(ctl_set_u_max(&drv->ctl, value));
    case DRV_P_EXC_AMPLITUDE: drv->exc_amplitude = value; return DRV_OK;
    case DRV_P_EXC_OFFSET: drv->exc_offset = value; return DRV_OK;
    default: return drv_task_set_f32(drv, id, value);
    }
}

drv_status_t drv_get_u32(const drv_t *drv, drv_param_id_t id, uint32_t *value)
{
    drv_status_t st = drv_check_id(id, DRV_PT_U32);
    if (st != DRV_OK) {
        return st;
    }
    if (value == NULL) {
        return DRV_E_GENERAL;
    }
    uint32_t v;
    switch (id) {
    case DRV_P_EXC_KIND: v = drv->exc_kind; break;
    case DRV_P_EXC_INJECT: v = drv->exc_inject; break;
    case DRV_P_EXC_PERIOD: v = drv->exc_period; break;
    case DRV_P_EXC_SINE_CYCLES: v = drv->exc_sine_cycles; break;
    case DRV_P_EXC_SETTLE_PERIODS: v = drv->exc_settle_periods; break;
    case DRV_P_EXC_RECORD_PERIODS: v = drv->exc_record_periods; break;
    case DRV_P_MS_K_MIN: v = drv->ms_k_min; break;
    case DRV_P_MS_K_MAX: v = drv->ms_k_max; break;
    case DRV_P_MS_GROUP: v = drv->ms_group; break;
    case DRV_P_MS_SEED: v = drv->ms_seed; break;
    case DRV_P_MS_REALIZATION: v = drv->ms_realization; break;
    case DRV_P_TABLE_LENGTH: v = drv->table_length; break;
    case DRV_P_TABLE_CAP: v = drv->table_capacity; break;
    case DRV_P_RUN_COMMAND: v = 0u; break;
    case DRV_P_RUN_STATE: v = drv->run.state; break;
    case DRV_P_RUN_PROGRESS: v = drv->run.progress; break;
    case DRV_P_RUN_COUNTER: v = drv->run.counter; break;
    case DRV_P_RUN_LAST_ERROR: v = drv->run.last_error; break;
    case DRV_P_RUN_TOTAL: v = drv->run.total; break;
    case DRV_P_REC_SIGNALS: v = drv->rec.signals; break;
    case DRV_P_REC_CAPACITY: v = drv->rec.capacity; break;
    case DRV_P_REC_SAMPLES: v = drv->rec.samples; break;
    case DRV_P_REC_BYTES: v = rec_size_bytes(&drv->rec); break;
    case DRV_P_STAT_HARMONICS: v = drv->stat.k; break;
    case DRV_P_STAT_SIGNALS: v = drv->stat.hmask; break;
    case DRV_P_STAT_POWER: v = drv->stat.pmask; break;
    case DRV_P_STAT_PERIODS: v = drv->stat.overrun ? 0u : drv->stat.periods; break;
    case DRV_P_STAT_OVERRUNS: v = drv->stat.overruns; break;
    case DRV_P_STAT_LINE_MODE: v = drv->lstat.mode; break;
    case DRV_P_STAT_LINES: v = drv->lstat.nlines; break;
    case DRV_P_STAT_LINES_CAP: v = LSTAT_LINES_MAX; break;
    case DRV_P_STAT_LINE_PERIODS: v = drv->lstat.periods; break;
    case DRV_P_STAT_LINE_SATURATED: v = drv->sat_samples; break;
    case DRV_P_STAT_BYTES: v = stat_size_bytes(&drv->stat); break;
    default: return drv_task_get_u32(drv, id, value);
    }
    *value = v;
    return DRV_OK;
}

drv_status_t drv_set_u32(drv_t *drv, drv_param_id_t id, uint32_t value)
{
    drv_status_t st = drv_check_id(id, DRV_PT_U32);
    if (st != DRV_OK) {
        return st;
    }
    const drv_param_info_t *info = &DRV_PARAM_INFO[id];
    if (!info->writable) {
        return DRV_E_READ_ONLY;
    }
    if (info->has_low && value < info->low_u32) {
        return DRV_E_RANGE_LOW;
    }
    if (info->has_high && value > info->high_u32) {
        return DRV_E_RANGE_HIGH;
    }
    if (drv_exc_param(id) && run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    switch (id) {
    case DRV_P_EXC_KIND: drv->exc_kind = value; return DRV_OK;
    case DRV_P_EXC_INJECT: drv->exc_inject = value; return DRV_OK;
    case DRV_P_EXC_PERIOD: drv->exc_period = value; return DRV_OK;
    case DRV_P_EXC_SINE_CYCLES: drv->exc_sine_cycles = value; return DRV_OK;
    case DRV_P_EXC_SETTLE_PERIODS: drv->exc_settle_periods = value; return DRV_OK;
    case DRV_P_EXC_RECORD_PERIODS: drv->exc_record_periods = value; return DRV_OK;
    case DRV_P_MS_K_MIN: drv->ms_k_min = value; return DRV_OK;
    case DRV_P_MS_K_MAX: drv->ms_k_max = value; return DRV_OK;
    case DRV_P_MS_GROUP:
        if (value == 1u) {
            return DRV_E_RANGE_LOW; /* valid: 0 (none) or 2 .. 16 */
        }
        drv->ms_group = value;
        return DRV_OK;
    case DRV_P_MS_SEED: drv->ms_seed = value; return DRV_OK;
    case DRV_P_MS_REALIZATION: drv->ms_realization = value; return DRV_OK;
    case DRV_P_REC_SIGNALS:
        return rec_set_signals(&drv->rec, value) == 0 ? DRV_OK : DRV_E_RANGE_HIGH;
    case DRV_P_STAT_HARMONICS:
        return stat_set_harmonics(&drv->stat, value) == STAT_OK ? DRV_OK : DRV_E_RANGE_HIGH;
    case DRV_P_STAT_SIGNALS: /* more than STAT_SIG_MAX signals: more than the drive holds */
        return stat_set_signals(&drv->stat, value) == STAT_OK ? DRV_OK : DRV_E_RANGE_HIGH;
    case DRV_P_STAT_POWER:
        return stat_set_power(&drv->stat, value) == STAT_OK ? DRV_OK : DRV_E_RANGE_HIGH;
    case DRV_P_STAT_LINE_MODE:
        return lstat_set_mode(&drv->lstat, value) == LSTAT_OK ? DRV_OK : DRV_E_RANGE_HIGH;
    case DRV_P_RUN_COMMAND:
        if (value == 1u) {
            return drv_run_start(drv);
        }
        if (value == 2u) {
            drv_run_abort(drv, DRV_STOP_ABORT_CMD);
        }
        return DRV_OK;
    default:
        return drv_task_set_u32(drv, id, value);
    }
}

/* ---- run control ---- */

/* Largest |t[i]| and |t[i+1] - t[i-1]| (periodic) of a table; false if one is not finite
 * (a central difference of two samples near +-FLT_MAX overflows). */
static bool drv_table_extent(const float *t, uint32_t n, float *peak, float *diff)
{
    float p = 0.0f, d = 0.0f;
    for (uint32_t i = 0u; i < n; i++) {
        float a = fabsf(t[i]);
        float b = fabsf(t[(i + 1u == n) ? 0u : i + 1u] - t[(i == 0u) ? n - 1u : i - 1u]);
        if (!isfinite(a) || !isfinite(b)) {
            return false;
        }
        p = a > p ? a : p;
        d = b > d ? b : d;
    }
    *peak = p;
    *diff = d;
    return true;
}

/* The generator forms offset + amp t[i] and amp fs / 2 (t[i+1] - t[i-1]): both must be
 * finite for this table (amp <= 1000, samples up to FLT_MAX: they can overflow). */
static bool drv_table_fits(const float *t, uint32_t n, float amp, float offset, float fs_hz)
{
    float peak, diff;
    if (!drv_table_extent(t, n, &peak, &diff)) {
        return false;
    }
    return isfinite(fabsf(offset) + amp * peak) && isfinite(amp * fs_hz * 0.5f * diff);
}

static drv_status_t drv_refuse(drv_t *drv, drv_stop_reason_t reason, drv_status_t st)
{
    run_refuse(&drv->run, (uint32_t)reason);
    return st;
}

/* The settle and record lengths of a run of period n: within 32 bits, something
 * recorded, and the record fits the recorder (refused with the stop reason otherwise). */
static drv_status_t drv_check_lengths(drv_t *drv, uint32_t n, uint32_t *settle, uint32_t *record)
{
    uint64_t s = (uint64_t)drv->exc_settle_periods * n;
    uint64_t r = (uint64_t)drv->exc_record_periods * n;
    if (r == 0u || s + r > UINT32_MAX) {
        return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
    }
    if (!rec_fits(&drv->rec, (uint32_t)r)) {
        return drv_refuse(drv, DRV_STOP_NO_FIT, DRV_E_NO_FIT);
    }
    *settle = (uint32_t)s;
    *record = (uint32_t)r;
    return DRV_OK;
}

drv_status_t drv_run_start(drv_t *drv)
{
    if (!drv->enabled || drv->fault || run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    if (drv->task.mode != TASK_MODE_OFF) {
        return drv_task_start(drv); /* a task run (issue 26) */
    }
    uint32_t n = drv->exc_period;
    ms_design_t ms = {n, drv->ms_k_min, drv->ms_k_max, drv->ms_group, drv->ms_seed, drv->ms_realization};
    switch (drv->exc_kind) {
    case DRV_EXC_NONE:
        break;
    case DRV_EXC_SINE:
        if (n < 4u || drv->exc_sine_cycles < 1u || 2u * drv->exc_sine_cycles >= n) {
            return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE); /* at/above Nyquist */
        }
        break;
    case DRV_EXC_TABLE:
        if (drv->table_length < 2u || drv->table_length != n) {
            return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
        }
        if (!drv_table_fits(drv->table_buf, n, drv->exc_amplitude, drv->exc_offset, drv->fs_hz)) {
            return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
        }
        break;
    case DRV_EXC_MULTISINE:
        if (ms_check(&ms) != MS_OK || n > drv->table_capacity) {
            return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
        }
        break;
    default:
        return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
    }
    uint32_t settle = 0u;
    uint32_t record = 0u;
    drv_status_t lst = drv_check_lengths(drv, n, &settle, &record);
    if (lst != DRV_OK) {
        return lst;
    }
    switch (stat_check(&drv->stat, n, drv->exc_kind == DRV_EXC_SINE ? drv->exc_sine_cycles : 0u)) {
    case STAT_OK: break;
    case STAT_E_NYQUIST: return drv_refuse(drv, DRV_STOP_STAT_NYQUIST, DRV_E_INCOMPATIBLE);
    default: return drv_refuse(drv, DRV_STOP_STAT_NOT_SINE, DRV_E_INCOMPATIBLE);
    }
    /* line statistics: the FFT work space is the table's download staging buffer (no
     * download while a run is active) */
    switch (lstat_check(&drv->lstat, n, drv->rec.signals, drv->table_stage != NULL ? drv->table_capacity : 0u)) {
    case LSTAT_OK: break;
    case LSTAT_E_NYQUIST: return drv_refuse(drv, DRV_STOP_STAT_NYQUIST, DRV_E_INCOMPATIBLE);
    default: return drv_refuse(drv, DRV_STOP_STAT_LINES, DRV_E_INCOMPATIBLE);
    }
    int gst = 0;
    switch (drv->exc_kind) {
    case DRV_EXC_SINE:
        gst = gen_start_sine(&drv->gen, n, drv->exc_sine_cycles, drv->exc_amplitude, drv->exc_offset, drv->fs_hz);
        break;
    case DRV_EXC_TABLE:
        gst = gen_start_table(&drv->gen, drv->table_buf, n, drv->exc_amplitude, drv->exc_offset, drv->fs_hz);
        break;
    case DRV_EXC_MULTISINE:
        /* one unit-rms period, scaled by the amplitude (= rms) at play time; it replaces
         * the table (readable back through drv_table_read) */
        drv->table_generation++; /* the table is rewritten in place (an upload aborts) */
        if (ms_build(&ms, 1.0f, drv->table_buf, drv->table_capacity) != MS_OK) {
            drv->table_length = 0u;
            return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
        }
        drv->table_length = n;
        gst = gen_start_table(&drv->gen, drv->table_buf, n, drv->exc_amplitude, drv->exc_offset, drv->fs_hz);
        break;
    default:
        gen_stop(&drv->gen);
        break;
    }
    if (gst != 0) {
        return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
    }
    rec_clear(&drv->rec);
    stat_begin(&drv->stat, n);
    lstat_begin(&drv->lstat, n);
    drv->sat_scanned = 0u;
    drv->sat_samples = 0u;
    drv->sat_u_max = drv->ctl.u_max;
    drv->run_inject = drv->exc_inject;
    (void)run_begin(&drv->run, settle, record);
    return DRV_OK;
}

void drv_run_abort(drv_t *drv, drv_stop_reason_t reason)
{
    if (run_active(&drv->run)) {
        run_stop(&drv->run, RUN_ABORTED, (uint32_t)reason);
        drv_task_end(drv, drv->reference); /* a task stops where its reference is */
        gen_stop(&drv->gen);
        stat_flush(&drv->stat); /* the samples so far go to the background */
    }
}

void drv_safe_stop(drv_t *drv, drv_stop_reason_t reason)
{
    drv_run_abort(drv, reason);
    drv->target = drv->motor;
    ctl_reset(&drv->ctl);
}

void drv_enable(drv_t *drv, bool enabled)
{
    if (enabled) {
        if (!drv->enabled || drv->fault) {
            drv->fault = false;
            drv->enabled = true;
            drv->target = drv->motor;
            ctl_reset(&drv->ctl);
        }
        return;
    }
    drv_run_abort(drv, DRV_STOP_DISABLED);
    drv->enabled = false;
    drv->u = 0.0f;
}

drv_status_t drv_set_target(drv_t *drv, float target_rad)
{
    if (!isfinite(target_rad)) {
        return DRV_E_NOT_FINITE;
    }
    drv->target = target_rad;
    return DRV_OK;
}

void drv_get_monitor(const drv_t *drv, drv_monitor_t *mon)
{
    mon->target_rad = drv->target;
    mon->reference_rad = drv->reference;
    mon->motor_angle_rad = drv->motor;
    mon->load_angle_rad = drv->load;
    mon->motor_velocity_rad_s = (drv->motor - drv->motor_prev) * drv->fs_hz;
    mon->following_error_rad = drv->error;
    mon->plant_input_v = drv->u;
    mon->enabled = drv->enabled;
    mon->fault = drv->fault;
}

bool drv_fault(const drv_t *drv)
{
    return drv->fault;
}

/* ---- the control step ---- */

/* Latch a fault: excitation off, run FAULT with the reason, controller state cleared (a
 * NaN in the derivative state would stay there), output 0. */
static float drv_fault_stop(drv_t *drv, drv_stop_reason_t reason)
{
    run_stop(&drv->run, RUN_FAULT, reason);
    drv->run.state = RUN_FAULT;
    drv->run.last_error = reason;
    drv->task.running = false;
    gen_stop(&drv->gen);
    stat_flush(&drv->stat);
    ctl_reset(&drv->ctl);
    drv->fault = true;
    drv->u = 0.0f;
    return 0.0f;
}

/* 0 for a finite x, NaN for +-inf and NaN (IEEE 754: inf - inf and NaN - NaN are NaN). The
 * step's finiteness tests as `probe != probe`: one subtraction and one compare, no constant
 * to load (isfinite: |x| <= FLT_MAX), and two values tested at once by adding their probes.
 * No build uses -ffinite-math-only / -ffast-math, under which x - x could fold to 0: the C
 * tests feed inf and NaN through drv_step. */
static inline float drv_nan_unless_finite(float x)
{
    return x - x;
}

float drv_step(drv_t *drv, const drv_meas_t *meas)
{
    if (meas == NULL) {
        return drv_fault_stop(drv, DRV_STOP_MEAS_FAULT);
    }
    float motor = meas->motor_angle_rad, load = meas->load_angle_rad;
    float probe = drv_nan_unless_finite(motor) + drv_nan_unless_finite(load); /* both, one test */
    if (probe != probe) {
        return drv_fault_stop(drv, DRV_STOP_MEAS_FAULT);
    }
    drv->motor_prev = drv->motor;
    drv->motor = motor;
    drv->load = load;

    float w = 0.0f, w_dot = 0.0f, u_task = 0.0f;
    bool active = run_active(&drv->run);
    bool task = active && drv->task.running; /* read once: nothing below starts or ends it */
    if (active) {
        if (task) {
            task_next(&drv->task, &w, &w_dot, &u_task); /* issue 26 */
        } else {
            gen_next(&drv->gen, &w, &w_dot);
        }
    }
    float ref = drv->target, v_ref = 0.0f, u_add = u_task;
    if (drv->run_inject == DRV_INJECT_REFERENCE) {
        ref += w;
        v_ref = w_dot;
    } else {
        u_add = w;
    }
    float e = ref - motor;
    float u = 0.0f;
    if (drv->enabled && !drv->fault) {
        u = ctl_step(&drv->ctl, e, v_ref, ref, u_add);
        /* the last line of defence: whatever the inputs, a non-finite sum (NaN passes the
         * saturation, an overflow would be clamped to +-u_max) never reaches the plant */
        float probe_u = drv_nan_unless_finite(drv->ctl.u_unsat);
        if (probe_u != probe_u) {
            drv->reference = ref;
            drv->error = e;
            return drv_fault_stop(drv, DRV_STOP_OUTPUT_FAULT);
        }
    }
    drv->reference = ref;
    drv->error = e;
    drv->u = u;
    if (active) {
        if (run_tick(&drv->run) == RUN_TICK_RECORD) {
            const float sig[REC_NUM_SIGNALS] = {ref, u, motor, drv->load, e};
            rec_push(&drv->rec, sig);
            if (task) {
                task_push(&drv->task, ctl_ff_sign(&drv->ctl, v_ref), u, e);
            }
            /* last, and drv->reference below: fewer of the step's floats are kept alive
             * across its rare call (a full block), 2 instructions per step on the M4 */
            stat_push(&drv->stat, sig, drv->gen.sin_last, drv->gen.cos_last);
        }
        if (!run_active(&drv->run)) {
            drv_task_end(drv, drv->reference);
            gen_stop(&drv->gen);
            stat_flush(&drv->stat); /* the last samples go to the background */
        }
    }
    return u;
}

/* ---- recorder, statistics and table byte streams ---- */

/* The recorded samples of u below `done` not looked at yet: count those at the output
 * limit (the clamp in ctl_step returns exactly +-u_max). In the background, from the
 * recorder, so that drv_step pays nothing for it. Reads only what the run latched at its
 * start (the recording's layout rec.nsel / rec.sel, sat_u_max): a write of 0x2020:1 or
 * u_max after the run, while this is still behind, changes nothing here. */
static void drv_sat_scan(drv_t *drv, uint32_t done)
{
    uint32_t col = REC_NUM_SIGNALS;
    for (uint32_t i = 0u; i < drv->rec.nsel; i++) {
        if (drv->rec.sel[i] == 1u) { /* signal 1: plant input u */
            col = i;
        }
    }
    if (col == REC_NUM_SIGNALS || drv->rec.buf == NULL) {
        drv->sat_scanned = done;
        return;
    }
    const float u_max = drv->sat_u_max; /* the run's limit, whatever was written since */
    for (uint32_t k = drv->sat_scanned; k < done; k++) {
        if (fabsf(drv->rec.buf[(size_t)k * drv->rec.nsel + col]) >= u_max) {
            drv->sat_samples++;
        }
    }
    drv->sat_scanned = done;
}

/* One recorded period's line spectra, if the recorder holds one not yet done (samples
 * is the interrupt's count: read once, everything below it is written). */
static bool drv_lines_step(drv_t *drv)
{
    if (drv->lstat.nl_run == 0u) {
        return false; /* no line statistics this run: no call */
    }
    const uint32_t done = *(const volatile uint32_t *)&drv->rec.samples;
    drv_sat_scan(drv, done);
    return lstat_process(&drv->lstat, drv->rec.buf, drv->rec.nsel, done, drv->table_stage);
}

bool drv_background_catch_up(drv_t *drv)
{
    if (!stat_pending(&drv->stat)) {
        return false;
    }
    stat_process(&drv->stat);
    return true;
}

void drv_background(drv_t *drv)
{
    stat_process(&drv->stat);
    (void)drv_lines_step(drv);
}

/* A reader after the run gets the final statistics: what the background has not consumed
 * yet is consumed now (no run active: the interrupt adds nothing). */
static void drv_stat_settle(drv_t *drv)
{
    if (!run_active(&drv->run)) {
        stat_finish(&drv->stat);
        while (drv_lines_step(drv)) {
        }
    }
}

drv_status_t drv_lines_write(drv_t *drv, uint32_t offset, const uint8_t *src, uint32_t len)
{
    if (run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    switch (lstat_write(&drv->lstat, offset, src, len)) {
    case LSTAT_OK: return DRV_OK;
    case LSTAT_E_LENGTH: return DRV_E_TOO_LONG;
    default: return DRV_E_GENERAL;
    }
}

drv_status_t drv_lines_commit(drv_t *drv, uint32_t total_len_bytes)
{
    if (run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    switch (lstat_commit(&drv->lstat, total_len_bytes, drv->exc_period)) {
    case LSTAT_OK: return DRV_OK;
    case LSTAT_E_LENGTH: return DRV_E_TOO_LONG;
    case LSTAT_E_ODD: return DRV_E_LENGTH;
    default: return DRV_E_VALUE;
    }
}

uint32_t drv_lines_size_bytes(const drv_t *drv)
{
    return lstat_list_size_bytes(&drv->lstat);
}

drv_status_t drv_lines_read(const drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return lstat_list_read(&drv->lstat, offset, dst, len) == 0 ? DRV_OK : DRV_E_LENGTH;
}

uint32_t drv_line_stats_size_bytes(drv_t *drv)
{
    drv_stat_settle(drv);
    return lstat_size_bytes(&drv->lstat);
}

drv_status_t drv_line_stats_read(drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len)
{
    drv_stat_settle(drv);
    return lstat_read(&drv->lstat, offset, dst, len) == 0 ? DRV_OK : DRV_E_LENGTH;
}

uint32_t drv_stat_size_bytes(drv_t *drv)
{
    drv_stat_settle(drv);
    return stat_size_bytes(&drv->stat);
}

drv_status_t drv_stat_read(drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len)
{
    drv_stat_settle(drv);
    return stat_read(&drv->stat, offset, dst, len) == 0 ? DRV_OK : DRV_E_LENGTH;
}

uint32_t drv_rec_size_bytes(const drv_t *drv)
{
    return rec_size_bytes(&drv->rec);
}

drv_status_t drv_rec_read(const drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len)
{
    return rec_read(&drv->rec, offset, dst, len) == 0 ? DRV_OK : DRV_E_LENGTH;
}

drv_status_t drv_table_write(drv_t *drv, uint32_t offset, const uint8_t *src, uint32_t len)
{
    if (run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    drv_stat_settle(drv); /* the staging buffer is the line spectra's work space */
    uint32_t cap = drv->table_capacity * 4u;
    if (offset > cap || len > cap - offset || (src == NULL && len != 0u)) {
        return DRV_E_LENGTH;
    }
    uint8_t *dst = (uint8_t *)drv->table_stage + offset; /* the table in use stays */
    for (uint32_t i = 0u; i < len; i++) {
        dst[i] = src[i];
    }
    return DRV_OK;
}

drv_status_t drv_table_commit(drv_t *drv, uint32_t total_len_bytes)
{
    if (run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    drv_stat_settle(drv); /* the swap changes the line spectra's work space */
    uint32_t n = total_len_bytes / 4u;
    if (total_len_bytes % 4u != 0u || n < 2u || n > drv->table_capacity) {
        return DRV_E_LENGTH;
    }
    float peak, diff;
    if (!drv_table_extent(drv->table_stage, n, &peak, &diff)) {
        return DRV_E_NOT_FINITE; /* the previous table stays */
    }
    float *t = drv->table_buf;
    drv->table_buf = drv->table_stage;
    drv->table_stage = t;
    drv->table_length = n;
    drv->table_generation++;
    return DRV_OK;
}

uint32_t drv_table_generation(const drv_t *drv)
{
    return drv->table_generation;
}

uint32_t drv_table_size_bytes(const drv_t *drv)
{
    return drv->table_length * 4u;
}

drv_status_t drv_table_read(const drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len)
{
    uint32_t size = drv->table_length * 4u;
    if (offset > size || len > size - offset || (dst == NULL && len != 0u)) {
        return DRV_E_LENGTH;
    }
    const uint8_t *src = (const uint8_t *)drv->table_buf + offset;
    for (uint32_t i = 0u; i < len; i++) {
        dst[i] = src[i];
    }
    return DRV_OK;
}

/* ---- the repeated task (issue 26, task.h; objects 0x2060-0x2062) ---- */

static drv_status_t drv_task_from(task_status_t st)
{
    return st == TASK_OK ? DRV_OK : DRV_E_RANGE_HIGH;
}

static drv_status_t drv_task_get_f32(const drv_t *drv, drv_param_id_t id, float *value)
{
    switch (id) {
    case DRV_P_TASK_DISTANCE: *value = task_get_param(&drv->task, TASK_P_DISTANCE); return DRV_OK;
    case DRV_P_TASK_V_MAX: *value = task_get_param(&drv->task, TASK_P_V_MAX); return DRV_OK;
    case DRV_P_TASK_A_MAX: *value = task_get_param(&drv->task, TASK_P_A_MAX); return DRV_OK;
    case DRV_P_TASK_JERK: *value = task_get_param(&drv->task, TASK_P_JERK); return DRV_OK;
    case DRV_P_TASK_DWELL: *value = task_get_param(&drv->task, TASK_P_DWELL); return DRV_OK;
    case DRV_P_TASK_KA: *value = task_get_param(&drv->task, TASK_P_KA); return DRV_OK;
    default: return DRV_E_NO_PARAM; /* an F32 id added to od.yaml but not to the drive */
    }
}

static drv_status_t drv_task_get_u32(const drv_t *drv, drv_param_id_t id, uint32_t *value)
{
    switch (id) {
    case DRV_P_TASK_MODE: *value = drv->task.mode; return DRV_OK;
    case DRV_P_TASK_PERIOD: *value = task_period(&drv->task); return DRV_OK;
    case DRV_P_TASK_BLOCKS: *value = TASK_BLOCKS; return DRV_OK;
    case DRV_P_TASK_LATCHED: *value = drv->task.latched; return DRV_OK;
    default: return DRV_E_NO_PARAM;
    }
}

static drv_status_t drv_task_set_f32(drv_t *drv, drv_param_id_t id, float value)
{
    uint32_t which;
    switch (id) {
    case DRV_P_TASK_DISTANCE: which = TASK_P_DISTANCE; break;
    case DRV_P_TASK_V_MAX: which = TASK_P_V_MAX; break;
    case DRV_P_TASK_A_MAX: which = TASK_P_A_MAX; break;
    case DRV_P_TASK_JERK: which = TASK_P_JERK; break;
    case DRV_P_TASK_DWELL: which = TASK_P_DWELL; break;
    case DRV_P_TASK_KA: /* like K_fc: may change at any time */
        return drv_task_from(task_set_param(&drv->task, TASK_P_KA, value));
    default: return DRV_E_NO_PARAM;
    }
    if (run_active(&drv->run)) {
        return DRV_E_STATE; /* the profile of a running task stays */
    }
    return drv_task_from(task_set_param(&drv->task, which, value));
}

static drv_status_t drv_task_set_u32(drv_t *drv, drv_param_id_t id, uint32_t value)
{
    if (id != DRV_P_TASK_MODE) {
        return DRV_E_NO_PARAM;
    }
    if (run_active(&drv->run)) {
        return DRV_E_STATE;
    }
    return drv_task_from(task_set_mode(&drv->task, value));
}

/* A task run: the task replaces the excitation (which must be off); the harmonic / line
 * statistics are refused by their own checks (no sine, period not a power of two). */
static drv_status_t drv_task_start(drv_t *drv)
{
    uint32_t n = task_period(&drv->task);
    if (drv->exc_kind != DRV_EXC_NONE || n == 0u) {
        return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
    }
    uint32_t settle = 0u;
    uint32_t record = 0u;
    drv_status_t lst = drv_check_lengths(drv, n, &settle, &record);
    if (lst != DRV_OK) {
        return lst;
    }
    if (stat_check(&drv->stat, n, 0u) != STAT_OK) {
        return drv_refuse(drv, DRV_STOP_STAT_NOT_SINE, DRV_E_INCOMPATIBLE);
    }
    if (drv->lstat.mode != 0u) {
        return drv_refuse(drv, DRV_STOP_STAT_LINES, DRV_E_INCOMPATIBLE);
    }
    if (task_begin(&drv->task) != TASK_OK) {
        return drv_refuse(drv, DRV_STOP_BAD_CONFIG, DRV_E_INCOMPATIBLE);
    }
    gen_stop(&drv->gen);
    rec_clear(&drv->rec);
    stat_begin(&drv->stat, n);
    lstat_begin(&drv->lstat, n);
    drv->sat_scanned = 0u;
    drv->sat_samples = 0u;
    drv->sat_u_max = drv->ctl.u_max;
    drv->run_inject = DRV_INJECT_REFERENCE;
    drv->task.running = true;
    (void)run_begin(&drv->run, settle, record);
    return DRV_OK;
}

/* The task run ended (done or aborted): the set-point takes the last reference, so the
 * axis holds where the task left it (a forward-only task ends D per repetition further). */
static void drv_task_end(drv_t *drv, float reference)
{
    if (drv->task.running) {
        drv->task.running = false;
        drv->target = reference;
    }
}

uint32_t drv_task_stats_size_bytes(const drv_t *drv, uint32_t part)
{
    return (part == DRV_TASK_DESIGN || part == DRV_TASK_LAST_DESIGN) ? task_design_size_bytes(&drv->task)
                                                                   : task_data_size_bytes(&drv->task);
}

drv_status_t drv_task_stats_read(const drv_t *drv, uint32_t part, uint32_t offset, uint8_t *dst, uint32_t len)
{
    int r;
    switch (part) {
    case DRV_TASK_DATA: r = task_data_read(&drv->task, offset, dst, len); break;
    case DRV_TASK_DESIGN: r = task_design_read(&drv->task, offset, dst, len); break;
    case DRV_TASK_LAST_DATA: r = task_latch_data_read(&drv->task, offset, dst, len); break;
    case DRV_TASK_LAST_DESIGN: r = task_latch_design_read(&drv->task, offset, dst, len); break;
    default: return DRV_E_NO_PARAM;
    }
    return r == 0 ? DRV_OK : DRV_E_LENGTH;
}
