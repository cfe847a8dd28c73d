/*
 * drv.h - the drive aggregate: the one API the CANopen layer and the host port call.
 *
 * Deployable: no OS call, no heap, no plant. One state struct (drv_t) passed explicitly.
 * Parameters are addressed by id (drv_param_id_t, generated from configs/od.yaml into
 * od_params.h) so that the object dictionary, the EDS and the drive agree by construction.
 *
 * CONTRACT between firmware_sim/core (implements) and firmware_sim/canopen + port (call).
 * Change it only together with both sides.
 */
#ifndef DRV_H
#define DRV_H

#include <stdbool.h>
#include <stdint.h>
#include <stddef.h>

#include "od_params.h" /* generated: drv_param_id_t, DRV_PARAM_COUNT, type/limits table */

/* Result of a parameter access or a command; the CANopen layer maps each to an SDO abort. */
typedef enum {
    DRV_OK = 0,
    DRV_E_NO_PARAM,      /* unknown id                          -> 0x06020000 */
    DRV_E_READ_ONLY,     /* write to a read-only parameter      -> 0x06010002 */
    DRV_E_NOT_FINITE,    /* NaN or inf                          -> 0x06090030 */
    DRV_E_RANGE_HIGH,    /* above the limit                     -> 0x06090031 */
    DRV_E_RANGE_LOW,     /* below the limit                     -> 0x06090032 */
    DRV_E_STATE,         /* not allowed in the present state    -> 0x08000022 */
    DRV_E_NO_FIT,        /* run would not fit the recorder      -> 0x08000022 (last error tells) */
    DRV_E_LENGTH,        /* bad data length / offset            -> 0x06070010 */
    DRV_E_GENERAL,       /*                                     -> 0x08000000 */
    DRV_E_INCOMPATIBLE,  /* parameters inconsistent with each other (run start: sine at or
                            above Nyquist, bad multisine band, table x amplitude overflows)
                                                                -> 0x06040043 */
    DRV_E_VALUE,         /* a value outside its range in downloaded data (line list bin)
                                                                -> 0x06090030 */
    DRV_E_TOO_LONG       /* downloaded data longer than the drive holds -> 0x06070012 */
} drv_status_t;

/* Run states (RUN_STATE parameter). */
typedef enum {
    DRV_RUN_IDLE = 0,
    DRV_RUN_SETTLING = 1,
    DRV_RUN_RECORDING = 2,
    DRV_RUN_DONE = 3,
    DRV_RUN_ABORTED = 4,
    DRV_RUN_FAULT = 5
} drv_run_state_t;

/* Why a run ended other than DONE (RUN_LAST_ERROR parameter). */
typedef enum {
    DRV_STOP_NONE = 0,
    DRV_STOP_ABORT_CMD = 1,      /* host asked */
    DRV_STOP_HEARTBEAT = 2,      /* host heartbeat lost (CANopen layer calls drv_safe_stop) */
    DRV_STOP_DISABLED = 3,       /* CiA 402 left OPERATION ENABLED */
    DRV_STOP_NO_FIT = 4,         /* refused: recorder too small */
    DRV_STOP_BAD_CONFIG = 5,     /* refused: excitation parameters inconsistent */
    DRV_STOP_NMT = 6,            /* NMT left OPERATIONAL */
    DRV_STOP_MEAS_FAULT = 7,     /* (added by core) non-finite measurement: FAULT, output 0 */
    DRV_STOP_OUTPUT_FAULT = 8,   /* controller output not finite (overflow / NaN): FAULT, output 0 */
    DRV_STOP_STAT_NYQUIST = 9,   /* refused: statistics harmonic K x sine cycles >= N / 2 */
    DRV_STOP_STAT_NOT_SINE = 10, /* refused: harmonic statistics asked for a run without a sine */
    DRV_STOP_STAT_LINES = 11     /* refused: line statistics need a power-of-two period within the
                                    table capacity and the recorder holding r, u, y */
} drv_stop_reason_t;

/* Excitation kinds (EXC_KIND) and injection points (EXC_INJECT). */
enum { DRV_EXC_NONE = 0, DRV_EXC_SINE = 1, DRV_EXC_TABLE = 2, DRV_EXC_MULTISINE = 3 };
enum { DRV_INJECT_REFERENCE = 0, DRV_INJECT_PLANT_INPUT = 1 };

/* Recorder signal bits (REC_SIGNALS); recorded per sample in this bit order. */
enum {
    DRV_SIG_REFERENCE = 1u << 0,   /* theta_r [rad] */
    DRV_SIG_PLANT_INPUT = 1u << 1, /* u [V], after saturation */
    DRV_SIG_MOTOR_ANGLE = 1u << 2, /* theta_1 [rad] measured */
    DRV_SIG_LOAD_ANGLE = 1u << 3,  /* theta_2 [rad] measured */
    DRV_SIG_ERROR = 1u << 4        /* theta_r - theta_1 [rad] */
};

/* Measurements handed to one control step. */
typedef struct {
    float motor_angle_rad;
    float load_angle_rad;
} drv_meas_t;

#define DRV_TABLE_MAX 8192u /* table samples at most */

/* Storage the integrator provides (fixed, static in the port; no heap). */
typedef struct {
    float *rec_buf;            /* recorder RAM */
    uint32_t rec_capacity;     /* in float values */
    float *table_buf;          /* waveform table / on-drive multisine period */
    uint32_t table_capacity;   /* in samples, <= DRV_TABLE_MAX */
    float fs_hz;               /* controller rate */
    float *table_stage_buf;    /* table_capacity samples more: a download is written here and
                                  becomes the table only at its commit (a failed download
                                  leaves the previous table); required when table_capacity > 0 */
} drv_storage_t;

#include "drv_state.h" /* drv_t: the module states (core's business) */

drv_status_t drv_init(drv_t *drv, const drv_storage_t *storage);

/* One controller step at fs: returns the plant input [V] (saturated). */
float drv_step(drv_t *drv, const drv_meas_t *meas);

/* Parameters: typed by od_params.h (f32 or u32). Range-checked; old value kept on error. */
drv_status_t drv_get_f32(const drv_t *drv, drv_param_id_t id, float *value);
drv_status_t drv_set_f32(drv_t *drv, drv_param_id_t id, float value);
drv_status_t drv_get_u32(const drv_t *drv, drv_param_id_t id, uint32_t *value);
drv_status_t drv_set_u32(drv_t *drv, drv_param_id_t id, uint32_t value);

/* Run control. start: DRV_E_STATE unless enabled and idle/done/aborted; DRV_E_NO_FIT etc. */
drv_status_t drv_run_start(drv_t *drv);
void drv_run_abort(drv_t *drv, drv_stop_reason_t reason);
/* Safe stop (heartbeat loss, disable): excitation off, controller holds the present position. */
void drv_safe_stop(drv_t *drv, drv_stop_reason_t reason);
/* Power stage enable from CiA 402 (OPERATION ENABLED <-> not). Disabling aborts a run. */
void drv_enable(drv_t *drv, bool enabled);

/* Recorder data as a byte stream: float32 little-endian, per sample the selected signals
 * in bit order. Size is valid after DONE (or partial after abort). */
uint32_t drv_rec_size_bytes(const drv_t *drv);
drv_status_t drv_rec_read(const drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len);

/* Waveform table download: bytes of float32 LE samples written into the staging buffer;
 * commit checks samples [0, total/4) of it (finite, and finite central differences, which the
 * generator's derivative forms) and only then swaps it in as the table (sets TABLE_LENGTH).
 * Until a commit succeeds, the previous table stays in use and readable.
 * Refused (DRV_E_STATE) while a run is active. */
drv_status_t drv_table_write(drv_t *drv, uint32_t offset, const uint8_t *src, uint32_t len);
drv_status_t drv_table_commit(drv_t *drv, uint32_t total_len_bytes);
uint32_t drv_table_size_bytes(const drv_t *drv);
drv_status_t drv_table_read(const drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len);
/* Counts changes of the table's content (commit, multisine run start rebuilding it): a
 * reader streaming the table (SDO upload of 0x2002) aborts when it changes under it. */
uint32_t drv_table_generation(const drv_t *drv);

/* ---- Additions by core (backward compatible; nothing above changed meaning) ---- */

/* Position set-point of the hold / cyclic synchronous position mode (0x607A) [rad]; the
 * excitation (at the reference) is added to it during a run. Enabling the drive sets it to
 * the present motor angle (no jump). DRV_E_NOT_FINITE for NaN/inf. */
drv_status_t drv_set_target(drv_t *drv, float target_rad);

/* Live values for CiA 402 objects and status PDOs (0x6062, 0x6064, 0x606C, 0x60F4). */
typedef struct {
    float target_rad;            /* set-point */
    float reference_rad;         /* theta_r of the last step (set-point + excitation) */
    float motor_angle_rad;       /* last measured theta_1 */
    float load_angle_rad;        /* last measured theta_2 */
    float motor_velocity_rad_s;  /* backward difference of the last two theta_1 samples */
    float following_error_rad;   /* theta_r - theta_1 */
    float plant_input_v;         /* last output (saturated) */
    bool enabled;
    bool fault;                  /* latched until drv_enable(drv, true) */
} drv_monitor_t;
void drv_get_monitor(const drv_t *drv, drv_monitor_t *mon);

/* Latched fault: a non-finite measurement (reason DRV_STOP_MEAS_FAULT) or a non-finite
 * controller output before saturation (DRV_STOP_OUTPUT_FAULT, e.g. an overflow in the
 * derivative): output 0 from that step on, run FAULT, the controller state reset. Cleared by
 * drv_enable(drv, true) (CiA 402 fault reset + enable). */
bool drv_fault(const drv_t *drv);

/* Background work (the statistics' sums, stat.h): the port calls it from its main loop, never
 * from the control interrupt, often enough that it takes each block of STAT_BLOCK samples
 * within STAT_BLOCK control periods (else that run's statistics are marked invalid and the
 * overrun counter 0x2040:6 counts it). Bounded: at most 2 blocks per call. Safe against the
 * control interrupt on a single core without masking it. */
void drv_background(drv_t *drv);
/* The harmonic statistics' share of drv_background alone (bounded: at most 2 blocks), if a
 * block waits: for a port whose main loop can be starved by back-to-back control
 * interrupts (an emulator under host load: port/mcu), called at the end of the control
 * interrupt while its main loop is NOT inside drv_background (the port's flag). */
bool drv_background_catch_up(drv_t *drv); /* true if it took a block */
/* On-drive run statistics (stat.h): the byte stream of object 0x2041, valid after DONE.
 * Not const: with no run active, both first consume what the background has not (the
 * run's last samples), so a read right after the run sees the final values. Call from the
 * background context (the CANopen layer's), not from the control interrupt. */
uint32_t drv_stat_size_bytes(drv_t *drv);
drv_status_t drv_stat_read(drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len);

/* Line statistics of periodic runs (lstat.h). The line list (object 0x2042): u16 LE bins
 * written into a staging list, checked at the commit against EXC_PERIOD (DRV_E_VALUE: bin
 * 0, at or above N/2, not ascending; DRV_E_LENGTH: odd bytes; DRV_E_TOO_LONG: more than
 * STAT_LINES_CAP lines) and only then the list; DRV_E_STATE while a run is active. The
 * data (0x2043) as the statistics above: not const, the rest is computed at the read. */
drv_status_t drv_lines_write(drv_t *drv, uint32_t offset, const uint8_t *src, uint32_t len);
drv_status_t drv_lines_commit(drv_t *drv, uint32_t total_len_bytes);
uint32_t drv_lines_size_bytes(const drv_t *drv);
drv_status_t drv_lines_read(const drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len);
uint32_t drv_line_stats_size_bytes(drv_t *drv);
drv_status_t drv_line_stats_read(drv_t *drv, uint32_t offset, uint8_t *dst, uint32_t len);

/* ---- The repeated task (core/task.h, issue 26; objects 0x2060-0x2062) ----
 * With TASK_MODE != 0 a run plays the task instead of the excitation (EXC_KIND must be 0):
 * EXC_SETTLE_PERIODS + EXC_RECORD_PERIODS repetitions of TASK_PERIOD samples, the reference
 * at the set-point plus the task's offset, K_a a_r added to the plant input; at the end (or
 * an abort) the set-point moves to the last reference (no jump back). The statistics
 * (DRV_TASK_*): data or design part of the run's recorded repetitions (valid after the run),
 * or of the last completed one alone (latched at its end, valid while the run goes on). */
enum { DRV_TASK_DATA = 0, DRV_TASK_DESIGN = 1, DRV_TASK_LAST_DATA = 2, DRV_TASK_LAST_DESIGN = 3 };
uint32_t drv_task_stats_size_bytes(const drv_t *drv, uint32_t part);
drv_status_t drv_task_stats_read(const drv_t *drv, uint32_t part, uint32_t offset, uint8_t *dst, uint32_t len);

#endif /* DRV_H */
