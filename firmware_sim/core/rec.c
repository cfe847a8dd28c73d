/* rec.c - see rec.h. */
#include "rec.h"

#include <stddef.h>

#if defined(__BYTE_ORDER__) && (__BYTE_ORDER__ != __ORDER_LITTLE_ENDIAN__)
#error "rec.c streams the float buffer as little-endian bytes: little-endian targets only"
#endif

int rec_init(rec_t *rec, float *buf, uint32_t capacity)
{
    if (buf == NULL && capacity != 0u) {
        return -1;
    }
    rec->buf = buf;
    rec->capacity = capacity;
    rec->wpos = 0u;
    rec->samples = 0u;
    rec->signals = 0u;
    rec->nsel = 0u;
    (void)rec_set_signals(rec, 0x07u);
    rec_clear(rec);
    return 0;
}

static uint32_t rec_count(uint32_t mask)
{
    uint32_t c = 0u;
    for (uint32_t b = 0u; b < REC_NUM_SIGNALS; b++) {
        c += (mask >> b) & 1u;
    }
    return c;
}

int rec_set_signals(rec_t *rec, uint32_t mask)
{
    if ((mask & ~REC_SIGNAL_MASK) != 0u) { /* 0: record nothing (statistics only) */
        return -1;
    }
    rec->signals = mask;
    return 0;
}

bool rec_fits(const rec_t *rec, uint32_t samples)
{
    uint64_t need = (uint64_t)samples * (uint64_t)rec_count(rec->signals);
    return need <= (uint64_t)rec->capacity;
}

void rec_clear(rec_t *rec)
{
    rec->wpos = 0u;
    rec->samples = 0u;
    rec->nsel = 0u;
    for (uint32_t b = 0u; b < REC_NUM_SIGNALS; b++) {
        if (rec->signals & (1u << b)) {
            rec->sel[rec->nsel++] = (uint8_t)b;
        }
    }
}

uint32_t rec_size_bytes(const rec_t *rec)
{
    return rec->wpos * 4u;
}

int rec_read(const rec_t *rec, uint32_t offset, uint8_t *dst, uint32_t len)
{
    uint32_t size = rec_size_bytes(rec);
    if (offset > size || len > size - offset || (dst == NULL && len != 0u)) {
        return -1;
    }
    const uint8_t *src = (const uint8_t *)rec->buf + offset;
    for (uint32_t i = 0u; i < len; i++) {
        dst[i] = src[i];
    }
    return 0;
}
