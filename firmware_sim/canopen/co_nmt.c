/*
 * co_nmt.c - NMT slave (boot-up, state machine, reset node / communication) and the
 * heartbeat producer (0x1017) and consumer (0x1016).
 */
#include <string.h>

#include "co_node.h"

void co_nmt_boot(co_node_t *n)
{
    /* INITIALISING -> boot-up message -> PRE-OPERATIONAL (CiA 301 reset communication) */
    n->nmt = CO_NMT_INITIALISING;
    co_od_reset_ram(n, 0x1000u, 0x1FFFu);
    co_sdo_init(&n->sdo);
    co_pdo_init(&n->pdo);
    co_hb_init(&n->hb, n->now_us);
    n->ram.error_register = 0u;
    uint8_t zero = 0u;
    (void)co_node_send(n, (uint16_t)(0x700u + n->cfg.node_id), &zero, 1u);
    n->nmt = CO_NMT_PRE_OPERATIONAL;
}

void co_nmt_set_state(co_node_t *n, co_nmt_state_t s)
{
    co_nmt_state_t old = n->nmt;
    if (old == s) {
        return;
    }
    if (old == CO_NMT_OPERATIONAL && co_node_run_active(n)) {
        drv_safe_stop(n->drv, DRV_STOP_NMT);
    }
    /* the master ended the connection (left OPERATIONAL, or stopped the node): 0x6007 */
    if (old == CO_NMT_OPERATIONAL || s == CO_NMT_STOPPED) {
        co_402_abort_connection(n);
    }
    if (s != CO_NMT_PRE_OPERATIONAL && s != CO_NMT_OPERATIONAL) {
        co_sdo_init(&n->sdo); /* no SDO in STOPPED: drop a transfer in progress */
    }
    n->nmt = s;
    if (s == CO_NMT_OPERATIONAL) {
        co_pdo_on_operational(n);
    }
}

void co_nmt_rx(co_node_t *n, const co_frame_t *f)
{
    if (f->len != 2u || (f->data[1] != 0u && f->data[1] != n->cfg.node_id)) {
        return;
    }
    switch (f->data[0]) {
    case 0x01u:
        co_nmt_set_state(n, CO_NMT_OPERATIONAL);
        break;
    case 0x02u:
        co_nmt_set_state(n, CO_NMT_STOPPED);
        break;
    case 0x80u:
        co_nmt_set_state(n, CO_NMT_PRE_OPERATIONAL);
        break;
    case 0x81u: /* reset node: application and communication */
        if (co_node_run_active(n)) {
            drv_safe_stop(n->drv, DRV_STOP_NMT);
        }
        if (n->cfg.reset_app != NULL) {
            n->cfg.reset_app(n->cfg.app_ctx);
        }
        co_od_reset_ram(n, 0x2000u, 0xFFFFu);
        co_402_init(n);
        co_nmt_boot(n);
        break;
    case 0x82u: /* reset communication */
        if (co_node_run_active(n)) {
            drv_safe_stop(n->drv, DRV_STOP_NMT);
        }
        co_402_abort_connection(n); /* 0x6007 (an application object: kept by the reset) */
        co_nmt_boot(n);
        break;
    default:
        break;
    }
}

void co_hb_init(co_hb_t *hb, uint32_t now_us)
{
    memset(hb, 0, sizeof *hb);
    hb->producer_last_us = now_us;
}

/* ---- write hooks (configs/od.yaml `hook:`) ---- */

static uint32_t hb_consumer_check(co_node_t *n, const co_od_entry_t *e, uint32_t value)
{
    (void)n;
    (void)e;
    if ((value >> 24) != 0u) {
        return CO_SDO_AB_INVALID_VALUE; /* reserved bits */
    }
    uint32_t node = (value >> 16) & 0xFFu;
    if ((value & 0xFFFFu) != 0u && (node == 0u || node > 127u)) {
        return CO_SDO_AB_INVALID_VALUE;
    }
    return 0u;
}

/* 0x1016:sub written: that consumer starts over (monitoring resumes with the next
 * heartbeat of the configured node); the others keep running. */
static void hb_consumer_written(co_node_t *n, const co_od_entry_t *e, uint32_t value)
{
    (void)value;
    if (e->sub >= 1u && e->sub <= CO_NUM_HB_CONSUMERS) {
        co_hb_consumer_t *c = &n->hb.consumer[e->sub - 1u];
        bool was_timed_out = c->timed_out;
        c->active = false;
        c->timed_out = false;
        if (was_timed_out) {
            /* the lost heartbeat's error ends here as when the heartbeat returns: error
             * reset EMCY, 0x1001's communication bit cleared unless another remains */
            co_emcy_reset_comm(n);
        }
    }
}

/* 0x1017 written: the producer restarts its period (as CANopenNode). The consumers are
 * not touched: a producer write must never disarm the host watchdog. */
static void hb_producer_written(co_node_t *n, const co_od_entry_t *e, uint32_t value)
{
    (void)e;
    (void)value;
    n->hb.producer_last_us = n->now_us;
}

const co_od_hook_t co_hook_hb_consumer = {hb_consumer_check, NULL, hb_consumer_written};
const co_od_hook_t co_hook_hb_producer = {NULL, NULL, hb_producer_written};

void co_hb_rx(co_node_t *n, const co_frame_t *f)
{
    if (f->len != 1u) {
        return;
    }
    uint8_t node = (uint8_t)(f->id - 0x700u);
    for (uint32_t i = 0u; i < CO_NUM_HB_CONSUMERS; i++) {
        uint32_t cfg = n->ram.hb_consumer[i];
        if ((cfg & 0xFFFFu) == 0u || ((cfg >> 16) & 0xFFu) != node) {
            continue;
        }
        co_hb_consumer_t *c = &n->hb.consumer[i];
        c->last_us = n->now_us;
        c->active = true;
        if (c->timed_out) {
            c->timed_out = false;
            co_emcy_reset_comm(n);
        }
    }
}

void co_hb_process(co_node_t *n)
{
    uint16_t period_ms = n->ram.hb_producer_ms;
    if (period_ms != 0u && (uint32_t)(n->now_us - n->hb.producer_last_us) >= (uint32_t)period_ms * 1000u) {
        uint8_t st = (uint8_t)n->nmt;
        (void)co_node_send(n, (uint16_t)(0x700u + n->cfg.node_id), &st, 1u);
        n->hb.producer_last_us = n->now_us;
    }
    for (uint32_t i = 0u; i < CO_NUM_HB_CONSUMERS; i++) {
        uint32_t cfg = n->ram.hb_consumer[i];
        co_hb_consumer_t *c = &n->hb.consumer[i];
        uint32_t time_ms = cfg & 0xFFFFu;
        if (time_ms == 0u || !c->active) {
            continue;
        }
        if ((uint32_t)(n->now_us - c->last_us) > time_ms * 1000u) {
            /* host lost: stop a run safely, act per 0x6007, report it; monitoring resumes
             * with the next heartbeat of that node */
            c->active = false;
            c->timed_out = true;
            if (co_node_run_active(n)) {
                drv_safe_stop(n->drv, DRV_STOP_HEARTBEAT);
            }
            co_402_abort_connection(n); /* 0x6007: by default the power stage goes off */
            uint8_t mfr[5] = {(uint8_t)(cfg >> 16), 0, 0, 0, 0};
            co_emcy_send(n, CO_EMCY_HEARTBEAT, CO_ERR_REG_COMM | CO_ERR_REG_GENERIC, 0u, mfr);
        }
    }
}
