/*
 * co_emcy.c - EMCY producer (COB-ID 0x80 + node id) and the error register 0x1001.
 */
#include <string.h>

#include "co_node.h"

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
