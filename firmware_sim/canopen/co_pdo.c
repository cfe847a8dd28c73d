/*
 * co_pdo.c - event-driven TPDOs (on change, inhibit time, event timer, once on entering
 * OPERATIONAL) and RPDOs (applied on reception), with dynamic mapping checked on write.
 * Transmission types 254 / 255 only (no SYNC).
 */
#include <string.h>

#include "co_node.h"

#define PDO_NOT_VALID 0x80000000u
#define PDO_EXTENDED 0x20000000u

void co_pdo_init(co_pdo_t *pdo)
{
    memset(pdo, 0, sizeof *pdo);
}

void co_pdo_on_operational(co_node_t *n)
{
    for (uint32_t i = 0u; i < CO_NUM_TPDO; i++) {
        n->pdo.tpdo[i].force = true;
    }
}

static bool cob_id_restricted(uint32_t id)
{
    return id <= 0x07Fu || (id >= 0x101u && id <= 0x180u) || (id >= 0x581u && id <= 0x5FFu) ||
           (id >= 0x601u && id <= 0x67Fu) || (id >= 0x6E0u && id <= 0x6FFu) || id >= 0x701u;
}

/* A mapping value (index << 16 | sub << 8 | bits) refers to a mappable object of that size. */
static const co_od_entry_t *map_target(uint32_t value, bool rpdo)
{
    uint32_t ab;
    const co_od_entry_t *e = co_od_lookup((uint16_t)(value >> 16), (uint8_t)(value >> 8), &ab);
    if (e == NULL || !(e->flags & CO_F_PDO) || (uint32_t)e->size * 8u != (value & 0xFFu)) {
        return NULL;
    }
    if (!(e->access & (rpdo ? CO_ACC_W : CO_ACC_R))) {
        return NULL;
    }
    return e;
}

/* Write hook `pdo` (every PDO communication / mapping entry): CiA 301's rules. */
static uint32_t pdo_check(co_node_t *n, const co_od_entry_t *e, uint32_t value)
{
    uint16_t base = (uint16_t)(e->index & 0xFE00u);
    uint32_t i = e->index & 0x01FFu;
    bool rpdo = (base == 0x1400u || base == 0x1600u);
    uint32_t npdo = rpdo ? CO_NUM_RPDO : CO_NUM_TPDO;
    if (i >= npdo) {
        return CO_SDO_AB_NO_OBJECT;
    }
#if CO_NUM_RPDO > 0 && CO_NUM_TPDO > 0
    co_pdo_comm_t *comm = rpdo ? &n->ram.rpdo_comm[i] : &n->ram.tpdo_comm[i];
    co_pdo_map_t *map = rpdo ? &n->ram.rpdo_map[i] : &n->ram.tpdo_map[i];
#else
#error "the CANopen layer expects at least one RPDO and one TPDO"
#endif
    bool valid = (comm->cob_id & PDO_NOT_VALID) == 0u;
    if (base == 0x1400u || base == 0x1800u) {
        if (e->sub == 3u && !rpdo && valid && value != comm->inhibit_100us) {
            return CO_SDO_AB_INVALID_VALUE; /* CiA 301: inhibit time only while not valid */
        }
        if (e->sub != 1u || value == comm->cob_id) {
            return 0u;
        }
        if (value & PDO_EXTENDED) {
            return CO_SDO_AB_INVALID_VALUE;
        }
        bool valid_new = (value & PDO_NOT_VALID) == 0u;
        if (valid && valid_new && (value & 0x7FFu) != (comm->cob_id & 0x7FFu)) {
            return CO_SDO_AB_INVALID_VALUE; /* change the CAN-ID only while not valid */
        }
        if (valid_new && cob_id_restricted(value & 0x7FFu)) {
            return CO_SDO_AB_INVALID_VALUE;
        }
        return 0u;
    }
    /* mapping parameter */
    if (e->sub == 0u) {
        if (value == map->count) {
            return 0u;
        }
        if (valid) {
            return CO_SDO_AB_UNSUPPORTED;
        }
        uint32_t bits = 0u;
        for (uint32_t k = 0u; k < value && k < CO_PDO_MAX_ENTRIES; k++) {
            if (map_target(map->entry[k], rpdo) == NULL) {
                return CO_SDO_AB_NO_MAP;
            }
            bits += map->entry[k] & 0xFFu;
        }
        return bits > 64u ? CO_SDO_AB_MAP_LEN : 0u;
    }
    if (value == map->entry[e->sub - 1u]) {
        return 0u;
    }
    if (valid || map->count != 0u) {
        return CO_SDO_AB_UNSUPPORTED; /* CiA 301: disable the PDO and set sub 0 to 0 first */
    }
    if (value != 0u && map_target(value, rpdo) == NULL) {
        return CO_SDO_AB_NO_MAP;
    }
    return 0u;
}

/* A TPDO's COB-ID written: a (newly) valid TPDO is sent once at the next processing. */
static void pdo_written(co_node_t *n, const co_od_entry_t *e, uint32_t value)
{
    uint32_t i = e->index & 0x01FFu;
    if ((e->index & 0xFE00u) == 0x1800u && e->sub == 1u && i < CO_NUM_TPDO) {
        n->pdo.tpdo[i].force = (value & PDO_NOT_VALID) == 0u;
        n->pdo.tpdo[i].sent_once = false;
    }
}

const co_od_hook_t co_hook_pdo = {pdo_check, NULL, pdo_written};

void co_pdo_rx(co_node_t *n, const co_frame_t *f)
{
    if (n->nmt != CO_NMT_OPERATIONAL) {
        return;
    }
    for (uint32_t i = 0u; i < CO_NUM_RPDO; i++) {
        const co_pdo_comm_t *comm = &n->ram.rpdo_comm[i];
        if ((comm->cob_id & PDO_NOT_VALID) || (comm->cob_id & 0x7FFu) != f->id) {
            continue;
        }
        const co_pdo_map_t *map = &n->ram.rpdo_map[i];
        uint32_t bytes = 0u;
        for (uint32_t k = 0u; k < map->count && k < CO_PDO_MAX_ENTRIES; k++) {
            bytes += (map->entry[k] & 0xFFu) / 8u;
        }
        if (f->len < bytes) {
            /* EMCY once per error episode (as CANopenNode); reset by the next correct one */
            if (!n->pdo.rpdo_length_error[i]) {
                n->pdo.rpdo_length_error[i] = true;
                uint8_t mfr[5] = {(uint8_t)i, f->len, (uint8_t)bytes, 0, 0};
                co_emcy_send(n, CO_EMCY_PDO_LENGTH, CO_ERR_REG_COMM | CO_ERR_REG_GENERIC, 0u, mfr);
            }
            return;
        }
        if (n->pdo.rpdo_length_error[i]) {
            n->pdo.rpdo_length_error[i] = false;
            co_emcy_reset_comm(n);
        }
        uint32_t off = 0u;
        for (uint32_t k = 0u; k < map->count && k < CO_PDO_MAX_ENTRIES; k++) {
            const co_od_entry_t *e = map_target(map->entry[k], true);
            uint32_t size = (map->entry[k] & 0xFFu) / 8u;
            if (e != NULL) {
                /* a value the object refuses is dropped, as a write by SDO would be */
                (void)co_od_write(n, e, &f->data[off], size);
            }
            off += size;
        }
        return;
    }
}

/* Current TPDO payload from its mapping. */
static uint8_t tpdo_build(co_node_t *n, uint32_t i, uint8_t data[8])
{
    const co_pdo_map_t *map = &n->ram.tpdo_map[i];
    uint32_t off = 0u;
    memset(data, 0, 8u);
    for (uint32_t k = 0u; k < map->count && k < CO_PDO_MAX_ENTRIES; k++) {
        uint32_t size = (map->entry[k] & 0xFFu) / 8u;
        const co_od_entry_t *e = map_target(map->entry[k], false);
        uint8_t tmp[4];
        uint32_t len = 0u;
        if (off + size > 8u) {
            break;
        }
        if (e != NULL && co_od_read(n, e, tmp, sizeof tmp, &len) == 0u && len == size) {
            memcpy(&data[off], tmp, size);
        }
        off += size;
    }
    return (uint8_t)off;
}

void co_pdo_process(co_node_t *n)
{
    if (n->nmt != CO_NMT_OPERATIONAL) {
        return;
    }
    for (uint32_t i = 0u; i < CO_NUM_TPDO; i++) {
        const co_pdo_comm_t *comm = &n->ram.tpdo_comm[i];
        co_tpdo_state_t *st = &n->pdo.tpdo[i];
        if (comm->cob_id & PDO_NOT_VALID) {
            continue;
        }
        uint8_t data[8];
        uint8_t len = tpdo_build(n, i, data);
        uint32_t since = (uint32_t)(n->now_us - st->last_tx_us);
        bool changed = !st->sent_once || len != st->len || memcmp(data, st->data, len) != 0;
        bool timer = comm->event_ms != 0u && since >= (uint32_t)comm->event_ms * 1000u;
        bool inhibit_ok = !st->sent_once || since >= (uint32_t)comm->inhibit_100us * 100u;
        if ((changed || timer || st->force) && inhibit_ok) {
            if (co_node_send(n, (uint16_t)(comm->cob_id & 0x7FFu), data, len)) {
                memcpy(st->data, data, 8u);
                st->len = len;
                st->sent_once = true;
                st->force = false;
                st->last_tx_us = n->now_us;
            }
        }
    }
}
