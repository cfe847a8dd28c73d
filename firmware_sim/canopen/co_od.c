/*
 * co_od.c - object dictionary search and typed read / write: routes each entry to the
 * CANopen layer's RAM, the drive's parameters (drv_get_/drv_set_), the simulation hook or a
 * DOMAIN handler. The side effects of a write are the entry's write hook (declared in
 * configs/od.yaml, defined by the module that owns them); nothing here depends on an index.
 */
#include <string.h>

#include "co_node.h"

uint8_t co_od_type_size(uint8_t type)
{
    switch (type) {
    case CO_T_BOOLEAN:
    case CO_T_INTEGER8:
    case CO_T_UNSIGNED8:
        return 1u;
    case CO_T_INTEGER16:
    case CO_T_UNSIGNED16:
        return 2u;
    case CO_T_INTEGER32:
    case CO_T_UNSIGNED32:
    case CO_T_REAL32:
        return 4u;
    default:
        return 0u;
    }
}

const co_od_entry_t *co_od_find(const co_od_entry_t *table, uint16_t count, uint16_t index,
                                uint8_t sub, bool *index_exists)
{
    uint32_t key = ((uint32_t)index << 8) | sub;
    uint32_t lo = 0u, hi = count;
    *index_exists = false;
    while (lo < hi) {
        uint32_t mid = lo + (hi - lo) / 2u;
        uint32_t k = ((uint32_t)table[mid].index << 8) | table[mid].sub;
        if (k == key) {
            *index_exists = true;
            return &table[mid];
        }
        if (k < key) {
            lo = mid + 1u;
        } else {
            hi = mid;
        }
    }
    /* lo is the insertion point: a neighbour with the same index means "no sub-index" */
    if ((lo < count && table[lo].index == index) || (lo > 0u && table[lo - 1u].index == index)) {
        *index_exists = true;
    }
    return NULL;
}

const co_od_entry_t *co_od_lookup(uint16_t index, uint8_t sub, uint32_t *abort_code)
{
    bool exists;
    const co_od_entry_t *e = co_od_find(CO_OD, CO_OD_COUNT, index, sub, &exists);
    if (e == NULL) {
        *abort_code = exists ? CO_SDO_AB_SUB_UNKNOWN : CO_SDO_AB_NO_OBJECT;
    } else {
        *abort_code = 0u;
    }
    return e;
}

uint32_t co_od_abort_from_drv(drv_status_t st)
{
    switch (st) {
    case DRV_OK:
        return 0u;
    case DRV_E_NO_PARAM:
        return CO_SDO_AB_NO_OBJECT;
    case DRV_E_READ_ONLY:
        return CO_SDO_AB_READONLY;
    case DRV_E_NOT_FINITE:
        return CO_SDO_AB_INVALID_VALUE;
    case DRV_E_RANGE_HIGH:
        return CO_SDO_AB_VALUE_HIGH;
    case DRV_E_RANGE_LOW:
        return CO_SDO_AB_VALUE_LOW;
    case DRV_E_STATE:
    case DRV_E_NO_FIT:
        return CO_SDO_AB_DATA_DEV_STATE;
    case DRV_E_LENGTH:
        return CO_SDO_AB_TYPE_MISMATCH;
    case DRV_E_INCOMPATIBLE:
        return CO_SDO_AB_PARAM_INCOMPAT;
    case DRV_E_VALUE:
        return CO_SDO_AB_INVALID_VALUE;
    case DRV_E_TOO_LONG:
        return CO_SDO_AB_DATA_LONG;
    default:
        return CO_SDO_AB_GENERAL;
    }
}

static uint32_t load_le(const uint8_t *p, uint8_t size)
{
    uint32_t v = 0u;
    for (uint8_t i = 0u; i < size; i++) {
        v |= (uint32_t)p[i] << (8u * i);
    }
    return v;
}

static void store_le(uint8_t *p, uint32_t v, uint8_t size)
{
    for (uint8_t i = 0u; i < size; i++) {
        p[i] = (uint8_t)(v >> (8u * i));
    }
}

static int64_t as_signed(uint32_t raw, uint8_t type)
{
    switch (type) {
    case CO_T_INTEGER8:
        return (int8_t)(uint8_t)raw;
    case CO_T_INTEGER16:
        return (int16_t)(uint16_t)raw;
    case CO_T_INTEGER32:
        return (int32_t)raw;
    default:
        return (int64_t)raw;
    }
}

static uint8_t *ram_ptr(co_node_t *n, const co_od_entry_t *e)
{
    return (uint8_t *)&n->ram + e->ref;
}

void co_od_reset_ram(co_node_t *n, uint16_t index_lo, uint16_t index_hi)
{
    for (uint16_t i = 0u; i < CO_OD_COUNT; i++) {
        const co_od_entry_t *e = &CO_OD[i];
        if (e->src != CO_SRC_RAM || e->index < index_lo || e->index > index_hi) {
            continue;
        }
        uint32_t v = e->def;
        if (e->flags & CO_F_NODEID) {
            v += n->cfg.node_id;
        }
        /* RAM fields are naturally aligned scalars: copy through a typed pointer */
        uint8_t *p = ram_ptr(n, e);
        switch (e->size) {
        case 1u:
            *p = (uint8_t)v;
            break;
        case 2u: {
            uint16_t v16 = (uint16_t)v;
            memcpy(p, &v16, 2u);
            break;
        }
        default:
            memcpy(p, &v, 4u);
            break;
        }
    }
}

static uint32_t ram_get(co_node_t *n, const co_od_entry_t *e)
{
    const uint8_t *p = ram_ptr(n, e);
    if (e->size == 1u) {
        return *p;
    }
    if (e->size == 2u) {
        uint16_t v16;
        memcpy(&v16, p, 2u);
        return v16;
    }
    uint32_t v;
    memcpy(&v, p, 4u);
    return v;
}

static void ram_set(co_node_t *n, const co_od_entry_t *e, uint32_t v)
{
    uint8_t *p = ram_ptr(n, e);
    if (e->size == 1u) {
        *p = (uint8_t)v;
    } else if (e->size == 2u) {
        uint16_t v16 = (uint16_t)v;
        memcpy(p, &v16, 2u);
    } else {
        memcpy(p, &v, 4u);
    }
}

uint32_t co_od_read(co_node_t *n, const co_od_entry_t *e, uint8_t *dst, uint32_t cap, uint32_t *len)
{
    *len = 0u;
    if (!(e->access & CO_ACC_R)) {
        return CO_SDO_AB_WRITEONLY;
    }
    if (e->type == CO_T_VISIBLE_STRING) {
        if (e->str == NULL || e->size > cap) {
            return CO_SDO_AB_GENERAL;
        }
        memcpy(dst, e->str, e->size);
        *len = e->size;
        return 0u;
    }
    if (e->type == CO_T_DOMAIN || e->size == 0u || e->size > cap) {
        return CO_SDO_AB_GENERAL;
    }
    uint32_t raw = 0u;
    switch (e->src) {
    case CO_SRC_CONST:
        raw = e->def + ((e->flags & CO_F_NODEID) ? n->cfg.node_id : 0u);
        break;
    case CO_SRC_RAM:
        if (e->flags & CO_F_REFRESH) {
            co_402_refresh(n);
        }
        raw = ram_get(n, e);
        break;
    case CO_SRC_PARAM: {
        drv_status_t st;
        if (e->type == CO_T_REAL32) {
            float f = 0.0f;
            st = drv_get_f32(n->drv, (drv_param_id_t)e->ref, &f);
            memcpy(&raw, &f, 4u);
        } else {
            st = drv_get_u32(n->drv, (drv_param_id_t)e->ref, &raw);
        }
        if (st != DRV_OK) {
            return co_od_abort_from_drv(st);
        }
        break;
    }
    case CO_SRC_SIM: {
        float f = 0.0f;
        if (n->cfg.sim_get == NULL || !n->cfg.sim_get(n->cfg.sim_ctx, (drv_param_id_t)e->ref, &f)) {
            return CO_SDO_AB_GENERAL;
        }
        memcpy(&raw, &f, 4u);
        break;
    }
    default:
        return CO_SDO_AB_GENERAL;
    }
    store_le(dst, raw, e->size);
    *len = e->size;
    return 0u;
}

uint32_t co_od_write(co_node_t *n, const co_od_entry_t *e, const uint8_t *src, uint32_t len)
{
    if (!(e->access & CO_ACC_W)) {
        return CO_SDO_AB_READONLY;
    }
    if (e->type == CO_T_DOMAIN) {
        uint32_t ab = co_od_domain_begin(n, e, len, true);
        if (ab == 0u) {
            ab = co_od_domain_write(n, e, 0u, src, len);
        }
        return ab != 0u ? ab : co_od_domain_commit(n, e, len);
    }
    if (e->size == 0u) {
        return CO_SDO_AB_UNSUPPORTED;
    }
    if (len > e->size) {
        return CO_SDO_AB_DATA_LONG;
    }
    if (len < e->size) {
        return CO_SDO_AB_DATA_SHORT;
    }
    uint32_t raw = load_le(src, e->size);
    if (e->flags & CO_F_LIMITS) {
        int64_t v = as_signed(raw, e->type);
        if (v > e->high) {
            return CO_SDO_AB_VALUE_HIGH;
        }
        if (v < e->low) {
            return CO_SDO_AB_VALUE_LOW;
        }
    }
    if (e->type == CO_T_BOOLEAN && raw > 1u) {
        return CO_SDO_AB_VALUE_HIGH;
    }
    const co_od_hook_t *hook = e->hook;
    uint32_t ab = 0u;
    if (hook != NULL && hook->check != NULL) {
        ab = hook->check(n, e, raw);
        if (ab != 0u) {
            return ab;
        }
    }
    if (hook != NULL && hook->store != NULL) {
        ab = hook->store(n, e, raw);
    } else if (e->src == CO_SRC_RAM) {
        ram_set(n, e, raw);
    } else if (e->src == CO_SRC_PARAM && e->type == CO_T_REAL32) {
        float f;
        memcpy(&f, &raw, 4u);
        ab = co_od_abort_from_drv(drv_set_f32(n->drv, (drv_param_id_t)e->ref, f));
    } else if (e->src == CO_SRC_PARAM) {
        ab = co_od_abort_from_drv(drv_set_u32(n->drv, (drv_param_id_t)e->ref, raw));
    } else {
        ab = CO_SDO_AB_READONLY;
    }
    if (ab == 0u && hook != NULL && hook->written != NULL) {
        hook->written(n, e, raw);
    }
    return ab;
}

/* the drive's task statistics part (drv.h DRV_TASK_*) of a task DOMAIN */
static uint32_t co_od_task_part(uint32_t ref)
{
    switch (ref) {
    case CO_DOMAIN_TASK_DESIGN: return DRV_TASK_DESIGN;
    case CO_DOMAIN_TASK_LAST_DATA: return DRV_TASK_LAST_DATA;
    case CO_DOMAIN_TASK_LAST_DESIGN: return DRV_TASK_LAST_DESIGN;
    default: return DRV_TASK_DATA;
    }
}

uint32_t co_od_domain_size(co_node_t *n, const co_od_entry_t *e, uint32_t *size)
{
    *size = 0u;
    if (!(e->access & CO_ACC_R)) {
        return CO_SDO_AB_WRITEONLY;
    }
    if (e->ref == CO_DOMAIN_RECORDER) {
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE; /* data is being recorded */
        }
        *size = drv_rec_size_bytes(n->drv);
        return 0u;
    }
    if (e->ref == CO_DOMAIN_TABLE) {
        *size = drv_table_size_bytes(n->drv);
        return 0u;
    }
    if (e->ref == CO_DOMAIN_STATS || e->ref == CO_DOMAIN_LINE_STATS) {
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE; /* being accumulated */
        }
        *size = e->ref == CO_DOMAIN_STATS ? drv_stat_size_bytes(n->drv) : drv_line_stats_size_bytes(n->drv);
        return 0u;
    }
    if (e->ref == CO_DOMAIN_STAT_LINES) {
        *size = drv_lines_size_bytes(n->drv);
        return 0u;
    }
    if (e->ref == CO_DOMAIN_TASK_DATA || e->ref == CO_DOMAIN_TASK_DESIGN) { /* task statistics */
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE; /* being accumulated */
        }
        *size = drv_task_stats_size_bytes(n->drv, co_od_task_part(e->ref));
        return 0u;
    }
    if (e->ref == CO_DOMAIN_TASK_LAST_DATA || e->ref == CO_DOMAIN_TASK_LAST_DESIGN) { /* latched: any time */
        *size = drv_task_stats_size_bytes(n->drv, co_od_task_part(e->ref));
        return 0u;
    }
    return CO_SDO_AB_GENERAL;
}

uint32_t co_od_domain_generation(co_node_t *n, const co_od_entry_t *e)
{
    uint32_t counter = 0u;
    if (e->ref == CO_DOMAIN_RECORDER || e->ref == CO_DOMAIN_STATS || e->ref == CO_DOMAIN_LINE_STATS ||
        e->ref == CO_DOMAIN_TASK_DATA || e->ref == CO_DOMAIN_TASK_DESIGN) {
        (void)drv_get_u32(n->drv, DRV_P_RUN_COUNTER, &counter);
    } else if (e->ref == CO_DOMAIN_TASK_LAST_DATA || e->ref == CO_DOMAIN_TASK_LAST_DESIGN) {
        /* a repetition latched under an upload changes the record: the upload aborts */
        uint32_t run = 0u;
        (void)drv_get_u32(n->drv, DRV_P_RUN_COUNTER, &run);
        (void)drv_get_u32(n->drv, DRV_P_TASK_LATCHED, &counter);
        counter += run << 20;
    } else if (e->ref == CO_DOMAIN_TABLE) {
        counter = drv_table_generation(n->drv); /* a multisine run start rewrites it */
    }
    return counter;
}

uint32_t co_od_domain_read(co_node_t *n, const co_od_entry_t *e, uint32_t off, uint8_t *dst, uint32_t len)
{
    drv_status_t st;
    if (e->ref == CO_DOMAIN_RECORDER) {
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE;
        }
        st = drv_rec_read(n->drv, off, dst, len);
    } else if (e->ref == CO_DOMAIN_STATS) {
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE;
        }
        st = drv_stat_read(n->drv, off, dst, len);
    } else if (e->ref == CO_DOMAIN_LINE_STATS) {
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE;
        }
        st = drv_line_stats_read(n->drv, off, dst, len);
    } else if (e->ref == CO_DOMAIN_TASK_DATA || e->ref == CO_DOMAIN_TASK_DESIGN) {
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE;
        }
        st = drv_task_stats_read(n->drv, co_od_task_part(e->ref), off, dst, len);
    } else if (e->ref == CO_DOMAIN_TASK_LAST_DATA || e->ref == CO_DOMAIN_TASK_LAST_DESIGN) {
        st = drv_task_stats_read(n->drv, co_od_task_part(e->ref), off, dst, len);
    } else if (e->ref == CO_DOMAIN_STAT_LINES) {
        st = drv_lines_read(n->drv, off, dst, len);
    } else if (e->ref == CO_DOMAIN_TABLE) {
        st = drv_table_read(n->drv, off, dst, len);
    } else {
        return CO_SDO_AB_GENERAL;
    }
    /* the size was fixed when the transfer began: a failing read now means the data changed
     * under the transfer (e.g. a new run was started), not a bad request */
    return st == DRV_OK ? 0u : CO_SDO_AB_GENERAL;
}

uint32_t co_od_domain_begin(co_node_t *n, const co_od_entry_t *e, uint32_t size, bool size_known)
{
    if (!(e->access & CO_ACC_W)) {
        return CO_SDO_AB_READONLY;
    }
    if (e->ref == CO_DOMAIN_STAT_LINES) {
        uint32_t cap = 0u;
        (void)drv_get_u32(n->drv, DRV_P_STAT_LINES_CAP, &cap);
        if (co_node_run_active(n)) {
            return CO_SDO_AB_DATA_DEV_STATE;
        }
        if (size_known && size > 2u * cap) {
            return CO_SDO_AB_DATA_LONG; /* more lines than the drive holds */
        }
        if (size_known && size == 0u) {
            return CO_SDO_AB_DATA_SHORT; /* no lines: 0x2040:7 = 0 switches them off */
        }
        return 0u;
    }
    if (e->ref != CO_DOMAIN_TABLE) {
        return CO_SDO_AB_GENERAL;
    }
    if (co_node_run_active(n)) {
        return CO_SDO_AB_DATA_DEV_STATE;
    }
    if (size_known && size > n->cfg.table_capacity_bytes) {
        return CO_SDO_AB_DATA_LONG;
    }
    if (size_known && size == 0u) {
        return CO_SDO_AB_DATA_SHORT; /* an empty DOMAIN: nothing to commit */
    }
    return 0u;
}

uint32_t co_od_domain_write(co_node_t *n, const co_od_entry_t *e, uint32_t off, const uint8_t *src, uint32_t len)
{
    if (e->ref == CO_DOMAIN_STAT_LINES) {
        return co_od_abort_from_drv(drv_lines_write(n->drv, off, src, len));
    }
    if (e->ref != CO_DOMAIN_TABLE) {
        return CO_SDO_AB_GENERAL;
    }
    if ((uint64_t)off + len > n->cfg.table_capacity_bytes) {
        return CO_SDO_AB_DATA_LONG;
    }
    return co_od_abort_from_drv(drv_table_write(n->drv, off, src, len));
}

uint32_t co_od_domain_commit(co_node_t *n, const co_od_entry_t *e, uint32_t total)
{
    if (e->ref == CO_DOMAIN_STAT_LINES) {
        if (total == 0u) {
            return CO_SDO_AB_DATA_SHORT;
        }
        return co_od_abort_from_drv(drv_lines_commit(n->drv, total)); /* odd: 0x06070010 */
    }
    if (e->ref != CO_DOMAIN_TABLE) {
        return CO_SDO_AB_GENERAL;
    }
    if ((total % 4u) != 0u) {
        return CO_SDO_AB_TYPE_MISMATCH; /* whole float32 samples only */
    }
    if (total < 8u) {
        return CO_SDO_AB_DATA_SHORT; /* empty, or one sample: a table has at least two */
    }
    return co_od_abort_from_drv(drv_table_commit(n->drv, total));
}
