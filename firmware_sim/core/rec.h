/*
 * rec.h - the run recorder (deployable): selected signals per sample into a fixed RAM
 * buffer, read back as a byte stream (float32 little-endian, per sample the selected
 * signals in bit order). Little-endian targets only (checked at compile time).
 */
#ifndef REC_H
#define REC_H

#include <stdbool.h>
#include <stdint.h>

#define REC_NUM_SIGNALS 5u
#define REC_SIGNAL_MASK 0x1Fu

typedef struct {
    float *buf;
    uint32_t capacity;  /* float values */
    uint32_t signals;   /* configured selection (0x2020:1), 0 .. 0x1F: the next recording's */
    /* layout of the recording in the buffer: the selection latched by rec_clear (run start),
     * so that a later write of the selection never changes how the background (line
     * statistics, saturation count) or a reader indexes the samples already recorded */
    uint32_t nsel;      /* popcount of the latched selection */
    uint8_t sel[REC_NUM_SIGNALS]; /* latched signal numbers in bit order */
    uint32_t wpos;      /* floats written */
    uint32_t samples;   /* samples recorded */
} rec_t;

/* buf may be NULL only with capacity 0. Selection starts at 0x07 (latched). */
int rec_init(rec_t *rec, float *buf, uint32_t capacity);
/* 0 .. 0x1F (0: nothing recorded, statistics only); returns -1 (unchanged) otherwise.
 * Configures the next recording: the layout of the present one stays until rec_clear. */
int rec_set_signals(rec_t *rec, uint32_t mask);
/* Would `samples` samples of the configured selection fit? (no overflow) */
bool rec_fits(const rec_t *rec, uint32_t samples);
/* Empty the recorder and latch the configured selection as its layout (run start). */
void rec_clear(rec_t *rec);

/* ---- per-sample hot path, inline (controller step budget) ---- */

/* Append one sample; sig[] holds all REC_NUM_SIGNALS signals in bit order.
 * Silently drops when full (run control makes sure that never happens). */
static inline void rec_push(rec_t *rec, const float sig[REC_NUM_SIGNALS])
{
    if (rec->wpos + rec->nsel > rec->capacity) {
        return;
    }
    float *dst = rec->buf + rec->wpos;
    for (uint32_t i = 0u; i < rec->nsel; i++) {
        dst[i] = sig[rec->sel[i]];
    }
    rec->wpos += rec->nsel;
    rec->samples++;
}

uint32_t rec_size_bytes(const rec_t *rec);
/* -1 if [offset, offset+len) is not inside the recorded bytes. */
int rec_read(const rec_t *rec, uint32_t offset, uint8_t *dst, uint32_t len);

#endif /* REC_H */
