/*
 * co_402.c - CiA 402 basics: power state machine (controlword 0x6040 -> statusword 0x6041),
 * modes of operation 0x6060 / 0x6061, position / velocity / following-error objects.
 * The power stage is the drive's enable (drv_enable): on in OPERATION ENABLED and
 * QUICK STOP ACTIVE (the controller holds position), off otherwise.
 */
#include "co_node.h"

#define CO402_MODE_CSP 8
#define CO402_MODE_EXCITATION (-1)

static uint16_t statusword_of(co402_state_t s)
{
    switch (s) {
    case CO402_SWITCH_ON_DISABLED:
        return 0x0040u;
    case CO402_READY_TO_SWITCH_ON:
        return 0x0031u; /* ready, quick stop off (bit 5 = 1), voltage enabled */
    case CO402_SWITCHED_ON:
        return 0x0033u;
    case CO402_OPERATION_ENABLED:
        return 0x0037u;
    case CO402_QUICK_STOP_ACTIVE:
        return 0x0017u;
    case CO402_FAULT_REACTION_ACTIVE:
        return 0x000Fu;
    case CO402_FAULT:
        return 0x0008u;
    default:
        return 0x0000u;
    }
}

static void update_statusword(co_node_t *n)
{
    uint16_t sw = statusword_of(n->cia402.state);
    sw |= 0x0200u; /* remote: controlled over CANopen */
    if (n->ram.error_register != 0u) {
        sw |= 0x0080u; /* warning */
    }
    n->ram.statusword = sw;
}

static bool enabled_in(co402_state_t s)
{
    return s == CO402_OPERATION_ENABLED || s == CO402_QUICK_STOP_ACTIVE;
}

static void set_state(co_node_t *n, co402_state_t s)
{
    co402_state_t old = n->cia402.state;
    if (s == old) {
        return;
    }
    n->cia402.state = s;
    if (s == CO402_QUICK_STOP_ACTIVE && co_node_run_active(n)) {
        drv_safe_stop(n->drv, DRV_STOP_DISABLED); /* stop the excitation, hold position */
    }
    if (enabled_in(old) != enabled_in(s)) {
        drv_enable(n->drv, enabled_in(s)); /* disabling aborts a run in the drive */
    }
    update_statusword(n);
}

void co_402_init(co_node_t *n)
{
    if (enabled_in(n->cia402.state)) {
        drv_enable(n->drv, false);
    }
    n->cia402.state = CO402_SWITCH_ON_DISABLED; /* NOT READY is passed through at once */
    n->cia402.cw_fault_reset_prev = false;
    n->cia402.fault_prev = drv_fault(n->drv);
    update_statusword(n);
}

static void co_402_controlword(co_node_t *n, uint16_t cw)
{
    bool fault_reset = (cw & 0x0080u) != 0u;
    bool edge = fault_reset && !n->cia402.cw_fault_reset_prev;
    n->cia402.cw_fault_reset_prev = fault_reset;
    co402_state_t s = n->cia402.state;
    if (s == CO402_FAULT) {
        if (edge) {
            set_state(n, CO402_SWITCH_ON_DISABLED);
        }
        return;
    }
    if (s == CO402_FAULT_REACTION_ACTIVE || s == CO402_NOT_READY) {
        return;
    }
    /* decode the command (CiA 402 controlword bits 0..3) */
    if (!(cw & 0x0002u)) { /* disable voltage */
        set_state(n, CO402_SWITCH_ON_DISABLED);
        return;
    }
    if (!(cw & 0x0004u)) { /* quick stop */
        set_state(n, s == CO402_OPERATION_ENABLED || s == CO402_QUICK_STOP_ACTIVE
                         ? CO402_QUICK_STOP_ACTIVE : CO402_SWITCH_ON_DISABLED);
        return;
    }
    if (!(cw & 0x0001u)) { /* shutdown */
        if (s != CO402_QUICK_STOP_ACTIVE) {
            set_state(n, CO402_READY_TO_SWITCH_ON);
        }
        return;
    }
    bool enable_op = (cw & 0x0008u) != 0u;
    switch (s) {
    case CO402_READY_TO_SWITCH_ON: /* switch on (3), with enable operation also (4) */
        set_state(n, enable_op ? CO402_OPERATION_ENABLED : CO402_SWITCHED_ON);
        break;
    case CO402_SWITCHED_ON:
        if (enable_op) {
            set_state(n, CO402_OPERATION_ENABLED);
        }
        break;
    case CO402_OPERATION_ENABLED:
        if (!enable_op) {
            set_state(n, CO402_SWITCHED_ON); /* disable operation (5) */
        }
        break;
    case CO402_QUICK_STOP_ACTIVE:
        if (enable_op) {
            set_state(n, CO402_OPERATION_ENABLED); /* (16) */
        }
        break;
    default:
        break;
    }
}

/* The connection to the master was lost (host heartbeat missing) or ended by NMT (stop,
 * pre-operational from operational, reset communication): while the power stage is on,
 * act as 0x6007 (abort connection option code) says. The caller has stopped an active run
 * first (with its own stop reason). 0x6007 outside 0 .. 3 cannot be stored (od.yaml
 * limits); anything else is treated as the default, disable voltage. */
void co_402_abort_connection(co_node_t *n)
{
    co402_state_t s = n->cia402.state;
    if (!enabled_in(s)) {
        return; /* power stage already off: nothing to do */
    }
    switch (n->ram.abort_connection) {
    case CO402_ABORT_NONE:
        break;
    case CO402_ABORT_FAULT:
        set_state(n, CO402_FAULT); /* power off; a fault reset (controlword bit 7) leaves it */
        break;
    case CO402_ABORT_QUICK_STOP:
        set_state(n, CO402_QUICK_STOP_ACTIVE); /* excitation off, holds position */
        break;
    default: /* CO402_ABORT_DISABLE_VOLTAGE */
        set_state(n, CO402_SWITCH_ON_DISABLED);
        break;
    }
}

void co_402_fault(co_node_t *n)
{
    if (n->cia402.state == CO402_FAULT) {
        return;
    }
    set_state(n, CO402_FAULT);
    /* manufacturer byte 0: the drive's stop reason (7 measurement, 8 controller output) */
    uint32_t reason = 0u;
    (void)drv_get_u32(n->drv, DRV_P_RUN_LAST_ERROR, &reason);
    uint8_t mfr[5] = {(uint8_t)reason, 0u, 0u, 0u, 0u};
    co_emcy_send(n, CO_EMCY_RUN_FAULT, CO_ERR_REG_MANUFACTURER | CO_ERR_REG_GENERIC, 0u, mfr);
    update_statusword(n);
}

void co_402_process(co_node_t *n)
{
    /* a drive fault (latched in the drive, e.g. a non-finite measurement) -> FAULT */
    bool fault = drv_fault(n->drv);
    if (fault && !n->cia402.fault_prev) {
        co_402_fault(n);
    }
    n->cia402.fault_prev = fault;
    if (n->cia402.state != CO402_FAULT && (n->ram.error_register & CO_ERR_REG_MANUFACTURER) && !fault) {
        co_emcy_send(n, CO_EMCY_NO_ERROR, 0u, CO_ERR_REG_MANUFACTURER, NULL); /* reset */
    }
    update_statusword(n);
}

/* ---- write hooks (configs/od.yaml `hook:`) ---- */

static void controlword_written(co_node_t *n, const co_od_entry_t *e, uint32_t raw)
{
    (void)e;
    co_402_controlword(n, (uint16_t)raw);
}

static uint32_t mode_check(co_node_t *n, const co_od_entry_t *e, uint32_t raw)
{
    (void)e;
    int8_t mode = (int8_t)(uint8_t)raw;
    if (mode != CO402_MODE_CSP && mode != CO402_MODE_EXCITATION) {
        return CO_SDO_AB_INVALID_VALUE;
    }
    if (mode != n->ram.mode && co_node_run_active(n)) {
        return CO_SDO_AB_DATA_DEV_STATE; /* a run ends before the mode changes */
    }
    return 0u;
}

static void mode_written(co_node_t *n, const co_od_entry_t *e, uint32_t raw)
{
    (void)e;
    (void)raw;
    n->ram.mode_display = n->ram.mode;
}

static void target_written(co_node_t *n, const co_od_entry_t *e, uint32_t raw)
{
    (void)e;
    /* 1 urad per unit; the drive checks the value */
    (void)drv_set_target(n->drv, (float)(int32_t)raw * 1.0e-6f);
}

/* 0x2010:1: 1 starts a run (only in NMT OPERATIONAL, OPERATION ENABLED and the
 * excitation-run mode -1; in mode 8 the drive only follows 0x607A), 2 aborts it. */
static uint32_t run_command_store(co_node_t *n, const co_od_entry_t *e, uint32_t cmd)
{
    (void)e;
    if (cmd == 1u) {
        if (n->nmt != CO_NMT_OPERATIONAL || n->cia402.state != CO402_OPERATION_ENABLED ||
            n->ram.mode != CO402_MODE_EXCITATION) {
            return CO_SDO_AB_DATA_DEV_STATE;
        }
        return co_od_abort_from_drv(drv_run_start(n->drv));
    }
    if (cmd == 2u) {
        drv_run_abort(n->drv, DRV_STOP_ABORT_CMD);
    }
    return 0u;
}

const co_od_hook_t co_hook_controlword = {NULL, NULL, controlword_written};
const co_od_hook_t co_hook_mode_of_operation = {mode_check, NULL, mode_written};
const co_od_hook_t co_hook_target_position = {NULL, NULL, target_written};
const co_od_hook_t co_hook_run_command = {NULL, run_command_store, NULL};

static int32_t to_micro(float v)
{
    float u = v * 1.0e6f;
    if (!(u == u)) {
        return 0;
    }
    if (u >= 2147483520.0f) {
        return INT32_MAX;
    }
    if (u <= -2147483520.0f) {
        return INT32_MIN;
    }
    return (int32_t)(u >= 0.0f ? u + 0.5f : u - 0.5f);
}

void co_402_refresh(co_node_t *n)
{
    drv_monitor_t mon;
    drv_get_monitor(n->drv, &mon);
    n->ram.position_actual = to_micro(mon.motor_angle_rad);
    n->ram.position_demand = to_micro(mon.reference_rad);
    n->ram.following_error = to_micro(mon.following_error_rad);
    n->ram.velocity_actual = to_micro(mon.motor_velocity_rad_s);
}
