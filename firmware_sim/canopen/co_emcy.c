/*
 * co_emcy.c - EMCY producer (COB-ID 0x80 + node id) and the error register 0x1001.
 */
#include <string.h>

#include "co_node.h"

/* True while a communication error is present: a heartbeat consumer timed out or an RPDO
 * had the wrong length. The error register's communication bit follows it. */
static bool comm_error_present(const co_node_t *n)
{
    for (uint32_t i = 0u; i < CO_NUM_HB_CONSUMERS; i++) {
        if (n->hb.consumer[i].timed_out) {
            return true;
        }
    }
    for (uint32_t i = 0u; i < CO_NUM_RPDO; i++) {
        if (n->pdo.rpdo_length_error[i]) {
            return true;
        }
    }
    return false;
}

void co_emcy_reset_comm(co_node_t *n)
{
    /* EMCY 0x0000 (error reset); the communication bit is cleared only when no other
     * communication error remains */
    co_emcy_send(n, CO_EMCY_NO_ERROR, 0u, comm_error_present(n) ? 0u : CO_ERR_REG_COMM, NULL);
}

void co_emcy_send(co_node_t *n, uint16_t code, uint8_t set_reg, uint8_t clear_reg,
                  const uint8_t mfr[5])
{
    uint8_t reg = (uint8_t)((n->ram.error_register | set_reg) & (uint8_t)~clear_reg);
    if ((reg & (uint8_t)~CO_ERR_REG_GENERIC) == 0u) {
        reg = 0u; /* the generic bit stays set only while another error is present */
    }
    n->ram.error_register = reg;
    n->last_emcy_code = code;
    n->emcy_count++;
    if (n->nmt != CO_NMT_PRE_OPERATIONAL && n->nmt != CO_NMT_OPERATIONAL) {
        return; /* EMCY is not sent in STOPPED */
    }
    uint8_t d[8] = {(uint8_t)code, (uint8_t)(code >> 8), reg, 0, 0, 0, 0, 0};
    if (mfr != NULL) {
        memcpy(&d[3], mfr, 5u);
    }
    (void)co_node_send(n, (uint16_t)(0x80u + n->cfg.node_id), d, 8u);
}
