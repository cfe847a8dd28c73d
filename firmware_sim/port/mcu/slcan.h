/*
 * slcan.h - SLCAN (Lawicel ASCII) adapter side: the drive MCU itself answers as a CAN
 * adapter on a serial line, so that python-can's `slcan` interface talks to its CANopen
 * node directly. Pure C, no hardware: fed one received byte at a time, it returns frames
 * for the node and reply text for the line; slcan_encode formats the node's frames.
 *
 * Commands (each ends with CR; the reply is CR for OK, BEL (0x07) for an error):
 *   O  open     L  open listen-only     C  close
 *   Sn bitrate 0..8 (closed only)       sXXYY BTR (closed only; accepted, not used)
 *   V  version -> "V1013\r"             N  serial -> "NPIL1\r"
 *   F  status flags -> "F00\r"          Z0 timestamps off (Z1 refused)
 *   Mxxxxxxxx / mxxxxxxxx acceptance code / mask (accepted, all frames pass)
 *   tiiildd..   Tiiiiiiiildd..   riiil   Riiiiiiiil   frames (open, not listen-only):
 *               reply "z\r" (standard) / "Z\r" (extended); BEL when closed or malformed
 * An empty line gets no reply (python-can sends one for an empty data-bitrate code); an LF
 * at the start of a line is skipped (CR LF senders). A line longer than SLCAN_LINE_MAX is
 * discarded up to its CR and answered with BEL; anything malformed is answered with BEL and
 * counted, never passed on. python-can 4.6 opens with "C", "S8", "", "O", "O".
 */
#ifndef SLCAN_H
#define SLCAN_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

/* longest valid line without its CR: 'T' + 8 id + 1 dlc + 16 data digits */
#define SLCAN_LINE_MAX 26u
/* longest reply and longest encoded frame, with CR */
#define SLCAN_REPLY_MAX 8u
#define SLCAN_FRAME_TEXT_MAX 27u

typedef struct {
    uint32_t id;  /* 11 or 29 bits */
    bool ext;
    bool rtr;
    uint8_t len;  /* 0..8 */
    uint8_t data[8];
} slcan_frame_t;

typedef struct {
    char line[SLCAN_LINE_MAX];
    uint8_t len;
    bool overlong;    /* discarding up to the next CR */
    bool open;
    bool listen_only;
    uint8_t bitrate_code; /* last Sn */
    /* statistics */
    uint32_t frames_in;
    uint32_t commands;
    uint32_t bad_lines;      /* malformed or refused */
    uint32_t overlong_lines;
    uint32_t partial_dropped; /* lines cut off by slcan_drop_partial */
} slcan_t;

typedef enum {
    SLCAN_NONE = 0,  /* nothing complete yet */
    SLCAN_REPLY,     /* a command line: send reply (maybe empty) */
    SLCAN_FRAME      /* a frame for the bus in *frame, and its reply */
} slcan_event_t;

void slcan_init(slcan_t *s);
/* One received byte. On SLCAN_REPLY / SLCAN_FRAME, reply[0..*reply_len) is the text to send
 * back (reply has room for SLCAN_REPLY_MAX bytes). */
slcan_event_t slcan_feed(slcan_t *s, uint8_t byte, slcan_frame_t *frame, char *reply, size_t *reply_len);
/* Forget a partial line (the port calls this after a silence: a sender that went away
 * mid-line must not corrupt the next session's first command). */
void slcan_drop_partial(slcan_t *s);
/* The frame as SLCAN text with CR ("t1238DEADBEEF00112233\r"); 0 if it does not fit cap or
 * the frame is invalid. */
size_t slcan_encode(const slcan_frame_t *f, char *out, size_t cap);

#endif /* SLCAN_H */
