/*
 * cbus.c - classic CAN bus model (see cbus.h).
 */
#include "cbus.h"

#include <string.h>

#define CBUS_BITS_MAX 160u /* SOF..CRC of an extended 8-byte frame: 118 bits */

/* The frame's bits from SOF through the data field (before the CRC), MSB first. */
static uint32_t frame_bits_before_crc(const scd_frame_t *f, uint8_t *bit)
{
    uint32_t n = 0;
    uint8_t len = f->len > 8u ? 8u : f->len;
    bit[n++] = 0u; /* SOF */
    if (!f->ext) {
        for (int i = 10; i >= 0; i--) {
            bit[n++] = (uint8_t)((f->id >> i) & 1u);
        }
        bit[n++] = 0u; /* RTR: data frame */
        bit[n++] = 0u; /* IDE: base format */
        bit[n++] = 0u; /* r0 */
    } else {
        for (int i = 28; i >= 18; i--) { /* identifier A (11 bits) */
            bit[n++] = (uint8_t)((f->id >> i) & 1u);
        }
        bit[n++] = 1u; /* SRR */
        bit[n++] = 1u; /* IDE: extended format */
        for (int i = 17; i >= 0; i--) { /* identifier B (18 bits) */
            bit[n++] = (uint8_t)((f->id >> i) & 1u);
        }
        bit[n++] = 0u; /* RTR */
        bit[n++] = 0u; /* r1 */
        bit[n++] = 0u; /* r0 */
    }
    for (int i = 3; i >= 0; i--) {
        bit[n++] = (uint8_t)((len >> i) & 1u); /* DLC */
    }
    for (uint8_t k = 0; k < len; k++) {
        for (int i = 7; i >= 0; i--) {
            bit[n++] = (uint8_t)((f->data[k] >> i) & 1u);
        }
    }
    return n;
}

static uint16_t crc15(const uint8_t *bit, uint32_t n)
{
    uint16_t crc = 0u;
    for (uint32_t i = 0; i < n; i++) {
        uint16_t next = (uint16_t)(bit[i] ^ ((crc >> 14) & 1u));
        crc = (uint16_t)((crc << 1) & 0x7FFFu);
        if (next) {
            crc ^= 0x4599u;
        }
    }
    return crc;
}

uint16_t cbus_crc15(const scd_frame_t *f)
{
    uint8_t bit[CBUS_BITS_MAX];
    uint32_t n = frame_bits_before_crc(f, bit);
    return crc15(bit, n);
}

uint32_t cbus_stuff_bits(const scd_frame_t *f)
{
    uint8_t bit[CBUS_BITS_MAX];
    uint32_t n = frame_bits_before_crc(f, bit);
    uint16_t crc = crc15(bit, n);
    for (int i = 14; i >= 0; i--) {
        bit[n++] = (uint8_t)((crc >> i) & 1u);
    }
    /* after 5 equal bits the transmitter inserts their complement, which itself counts
     * toward the next run */
    uint32_t stuffed = 0u, run = 0u;
    uint8_t last = 2u;
    for (uint32_t i = 0; i < n; i++) {
        if (bit[i] == last) {
            run++;
        } else {
            last = bit[i];
            run = 1u;
        }
        if (run == 5u) {
            stuffed++;
            last = (uint8_t)(1u - last);
            run = 1u;
        }
    }
    return stuffed;
}

uint32_t cbus_frame_bits(const scd_frame_t *f)
{
    uint32_t len = f->len > 8u ? 8u : f->len;
    uint32_t head = f->ext ? 54u : 34u; /* SOF..CRC without data */
    /* + CRC delimiter, ACK slot, ACK delimiter, EOF 7, interframe space 3 */
    return head + 8u * len + cbus_stuff_bits(f) + 1u + 1u + 1u + 7u + 3u;
}

int cbus_init(cbus_t *b, uint32_t bitrate)
{
    memset(b, 0, sizeof *b);
    if (bitrate < CBUS_BITRATE_MIN || bitrate > CBUS_BITRATE_MAX) {
        return -1;
    }
    b->bitrate = bitrate;
    b->wire_src = -1;
    return 0;
}

bool cbus_submit(cbus_t *b, int src, const scd_frame_t *f, uint64_t now_ns)
{
    if (src < 0 || src >= CBUS_SOURCES) {
        return false;
    }
    cbus_fifo_t *q = &b->q[src];
    if (q->len >= CBUS_QUEUE) {
        b->dropped++;
        return false;
    }
    q->frame[(q->head + q->len) % CBUS_QUEUE] = *f;
    q->len++;
    if (!b->busy && b->free_ns < now_ns) {
        b->free_ns = now_ns; /* an idle bus: the frame starts now */
    }
    return true;
}

uint32_t cbus_queued(const cbus_t *b, int src)
{
    return (src >= 0 && src < CBUS_SOURCES) ? b->q[src].len : 0u;
}

void cbus_flush_source(cbus_t *b, int src)
{
    if (src >= 0 && src < CBUS_SOURCES) {
        b->q[src].len = 0u;
        b->q[src].head = 0u;
    }
}

/* Arbitration key: the bits from the identifier to RTR as sent (a dominant 0 wins). */
static uint64_t arbitration_key(const scd_frame_t *f)
{
    if (!f->ext) {
        return (uint64_t)(f->id & 0x7FFu) << 21; /* RTR 0, IDE 0 */
    }
    return ((uint64_t)((f->id >> 18) & 0x7FFu) << 21) | (1u << 20) | (1u << 19) |
           ((uint64_t)(f->id & 0x3FFFFu) << 1);
}

/* Put the winner of arbitration among the queue heads on the wire at b->free_ns. */
static bool start_next(cbus_t *b)
{
    int best = -1;
    uint64_t best_key = 0;
    for (int s = 0; s < CBUS_SOURCES; s++) {
        const cbus_fifo_t *q = &b->q[s];
        if (q->len == 0u) {
            continue;
        }
        uint64_t key = arbitration_key(&q->frame[q->head]);
        if (best < 0 || key < best_key) {
            best = s;
            best_key = key;
        }
    }
    if (best < 0) {
        return false;
    }
    cbus_fifo_t *q = &b->q[best];
    b->wire = q->frame[q->head];
    q->head = (q->head + 1u) % CBUS_QUEUE;
    q->len--;
    uint32_t bits = cbus_frame_bits(&b->wire);
    b->busy = true;
    b->wire_src = best;
    b->wire_end_ns = b->free_ns + ((uint64_t)bits * 1000000000u + b->bitrate / 2u) / b->bitrate;
    b->bits += bits;
    return true;
}

void cbus_advance(cbus_t *b, uint64_t now_ns, cbus_deliver_fn deliver, void *ctx)
{
    for (;;) {
        if (!b->busy) {
            if (b->free_ns > now_ns || !start_next(b)) {
                return;
            }
        }
        if (b->wire_end_ns > now_ns) {
            return;
        }
        scd_frame_t f = b->wire;
        int src = b->wire_src;
        uint64_t end = b->wire_end_ns;
        b->busy = false;
        b->wire_src = -1;
        b->free_ns = end;
        b->frames++;
        deliver(ctx, src, &f, end);
    }
}

uint64_t cbus_next_event_ns(const cbus_t *b)
{
    if (b->busy) {
        return b->wire_end_ns;
    }
    for (int s = 0; s < CBUS_SOURCES; s++) {
        if (b->q[s].len > 0u) {
            return b->free_ns;
        }
    }
    return UINT64_MAX;
}
