/*
 * cbus.h - a classic CAN bus model for drive_sim (--bitrate): every frame occupies the bus
 * for the bit time a CAN controller needs for it (its bits from SOF to EOF with the stuff
 * bits of its actual content, CRC-15 included, plus the 3-bit interframe space); the nodes
 * (each drive node and each socketcand client) share the bus: a frame waits while another is on
 * the wire, and among waiting frames the lowest identifier wins arbitration (CiA / ISO
 * 11898-1; REFERENCE.md section 3). Each source transmits its own frames in order (one
 * FIFO per source, as a SocketCAN or CANopen driver queue).
 *
 * Time is the caller's clock in nanoseconds (drive_sim: CLOCK_MONOTONIC). The model is an
 * event schedule: cbus_advance(now) completes every frame whose last bit is at or before
 * now and hands it, with its completion time, to the delivery callback; back-to-back
 * frames follow each other exactly on the bus timeline, however late the caller comes.
 * Fixed-size buffers, no allocation. Host only.
 */
#ifndef CBUS_H
#define CBUS_H

#include <stdbool.h>
#include <stdint.h>

#include "scd.h"

#define CBUS_NODES 8                               /* drive_sim's nodes: sources 0 .. 7 */
#define CBUS_SOURCES (CBUS_NODES + SCD_MAX_CLIENTS) /* CBUS_NODES + i: socketcand client i */
#define CBUS_QUEUE 512u                    /* frames per source (an SDO block is 127) */
#define CBUS_BITRATE_MIN 10000u
#define CBUS_BITRATE_MAX 1000000u

typedef struct {
    scd_frame_t frame[CBUS_QUEUE];
    uint32_t head, len;
} cbus_fifo_t;

typedef struct {
    uint32_t bitrate;           /* bit/s */
    cbus_fifo_t q[CBUS_SOURCES];
    bool busy;                  /* a frame is on the wire */
    scd_frame_t wire;           /* that frame (out of its queue already) */
    int wire_src;               /* its source */
    uint64_t wire_end_ns;       /* its last bit (+ interframe space) */
    uint64_t free_ns;           /* the bus is idle from here */
    uint64_t frames, bits;      /* carried so far */
    uint64_t dropped;           /* submitted to a full queue */
} cbus_t;

typedef void (*cbus_deliver_fn)(void *ctx, int src, const scd_frame_t *f, uint64_t end_ns);

/* 0 ok, -1 bitrate outside CBUS_BITRATE_MIN..CBUS_BITRATE_MAX. */
int cbus_init(cbus_t *b, uint32_t bitrate);
/* Bits a data frame occupies on the bus: SOF..EOF with stuff bits, plus 3 interframe bits. */
uint32_t cbus_frame_bits(const scd_frame_t *f);
/* Stuff bits of the frame's SOF..CRC sequence (the part bit stuffing applies to). */
uint32_t cbus_stuff_bits(const scd_frame_t *f);
/* CRC-15 (x^15+x^14+x^10+x^8+x^7+x^4+x^3+1) of the frame's SOF..data bits. */
uint16_t cbus_crc15(const scd_frame_t *f);
/* Queue a frame of source src (0..CBUS_SOURCES-1) at time now_ns; false if its queue is full. */
bool cbus_submit(cbus_t *b, int src, const scd_frame_t *f, uint64_t now_ns);
/* Frames queued for source src (the caller holds a client's input back when high). */
uint32_t cbus_queued(const cbus_t *b, int src);
/* Drop a source's queued frames (its client went away). */
void cbus_flush_source(cbus_t *b, int src);
/* Complete every frame that has left the wire by now_ns (deliver called for each, in bus
 * order), starting the next ones as the bus frees. */
void cbus_advance(cbus_t *b, uint64_t now_ns, cbus_deliver_fn deliver, void *ctx);
/* When the frame on the wire ends (UINT64_MAX: bus idle and nothing queued). */
uint64_t cbus_next_event_ns(const cbus_t *b);

#endif
