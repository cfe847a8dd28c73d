/*
 * co_node.c - the node: initialisation, receive dispatch by COB-ID, periodic processing.
 */
#include <string.h>

#include "co_node.h"

bool co_node_send(co_node_t *n, uint16_t id, const uint8_t *data, uint8_t len)
{
    co_frame_t f;
    f.id = id;
    f.len = len > 8u ? 8u : len;
    memset(f.data, 0, sizeof f.data);
    if (f.len != 0u) {
        memcpy(f.data, data, f.len);
    }
    if (n->cfg.tx == NULL || !n->cfg.tx(n->cfg.tx_ctx, &f)) {
        n->tx_dropped++;
        return false;
    }
    n->tx_frames++;
    return true;
}

bool co_node_run_active(const co_node_t *n)
{
    uint32_t rs = 0u;
    if (drv_get_u32(n->drv, DRV_P_RUN_STATE, &rs) != DRV_OK) {
        return false;
    }
    return rs == DRV_RUN_SETTLING || rs == DRV_RUN_RECORDING;
}

int co_node_init(co_node_t *n, const co_cfg_t *cfg, drv_t *drv, uint32_t now_us)
{
    memset(n, 0, sizeof *n);
    if (cfg->node_id == 0u || cfg->node_id > 127u) {
        /* refused, not repaired: a node that answered as node 1 would take another node's
         * SDO requests and hide the configuration error; n stays INITIALISING and silent */
        return CO_NODE_EINVAL;
    }
    n->cfg = *cfg;
    n->drv = drv;
    n->now_us = now_us;
    co_od_reset_ram(n, 0x0000u, 0xFFFFu);
    co_402_init(n);
    co_nmt_boot(n);
    return 0;
}

void co_node_rx(co_node_t *n, const co_frame_t *f)
{
    uint16_t id = f->id;
    uint8_t node = n->cfg.node_id;
    if (n->drv == NULL || id > 0x7FFu || f->len > 8u) { /* (drv NULL: co_node_init refused it) */
        return;
    }
    n->rx_frames++;
    if (id == 0x000u) {
        co_nmt_rx(n, f);
        return;
    }
    if (id >= 0x701u && id <= 0x77Fu) {
        co_hb_rx(n, f);
        return;
    }
    if (n->nmt == CO_NMT_STOPPED || n->nmt == CO_NMT_INITIALISING) {
        return;
    }
    if (id == 0x600u + node) {
        co_sdo_rx(n, f);
        return;
    }
    co_pdo_rx(n, f);
}

void co_node_process(co_node_t *n, uint32_t now_us)
{
    if (n->drv == NULL) {
        return; /* co_node_init refused its configuration: the node does nothing */
    }
    n->now_us = now_us;
    co_hb_process(n);
    co_sdo_process(n);
    co_402_process(n);
    co_pdo_process(n);
}
