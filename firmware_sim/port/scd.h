/*
 * scd.h - a socketcand (rawmode) server: one simulated CAN bus shared by the node and up to
 * SCD_MAX_CLIENTS TCP clients (python-can's "socketcand" interface, socketcand's own
 * clients). Host only (POSIX sockets).
 *
 * Protocol (linux-can/socketcand doc/protocol.md), as python-can 4.6 reads it: on connect
 * "< hi >"; "< open CHANNEL >" -> "< ok >"; "< rawmode >" -> "< ok >"; each alone in its TCP
 * write and nothing after it until the client sends again (python-can compares one recv()
 * with the expected text), except that frames start SCD_GRACE_US after the last "< ok >"
 * if the client stays silent. Then "< frame ID SEC.USEC DATA >" to the client and
 * "< send ID DLC B0 .. >" from it. Frames a client sends reach the node and every other
 * client, as on one bus (the caller's rx hook decides: at once, or through a bus model).
 * Bounded: clients, line length, per-client output buffer (frames for a client whose buffer
 * is full are dropped and counted, like a CAN receive overflow), bytes read per client per
 * pass (read_budget), time to finish the handshake (SCD_HANDSHAKE_US: a connection that
 * has not reached rawmode by then is closed; when every slot is taken, a new connection
 * evicts the longest-silent one still in its handshake, if silent for SCD_EVICT_IDLE_US).
 */
#ifndef SCD_H
#define SCD_H

#include <poll.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define SCD_MAX_CLIENTS 8
#define SCD_LINE_MAX 128           /* longest valid command is ~40 characters */
#define SCD_OUT_BUF (256u * 1024u) /* per client */
#define SCD_GRACE_US 200000u
#define SCD_HANDSHAKE_US 3000000u  /* connect .. rawmode; python-can needs a few ms */
#define SCD_EVICT_IDLE_US 100000u  /* an unhandshaken client silent this long may be evicted */
#define SCD_READ_BUDGET 4096u      /* default bytes read per client per scd_handle */

typedef struct {
    uint32_t id;  /* 11 or 29 bit */
    bool ext;
    uint8_t len;
    uint8_t data[8];
} scd_frame_t;

typedef struct {
    int fd;
    int stage; /* 0 sent hi, 1 opened, 2 rawmode */
    char line[SCD_LINE_MAX];
    size_t line_len;
    bool in_cmd;
    bool discard; /* over-long command: skip to its '>' */
    size_t out_head, out_len;
    uint64_t frames_after_us; /* grace after the last "< ok >" */
    uint64_t accepted_us;     /* connection time (handshake timeout) */
    uint64_t last_rx_us;      /* last bytes received (eviction of silent handshakes) */
    bool rx_paused;           /* the caller holds its input back (bus queue full) */
    uint64_t dropped;
    uint8_t out[SCD_OUT_BUF];
} scd_client_t;

typedef struct {
    int listen_fd;
    char channel[32];
    scd_client_t client[SCD_MAX_CLIENTS];
    uint64_t garbage;  /* commands that were not understood */
    uint64_t refused;  /* connections beyond SCD_MAX_CLIENTS */
    uint64_t dropped;  /* frames not queued to a client (buffer full) */
    uint64_t evicted;  /* unhandshaken clients evicted for a new connection */
    uint64_t handshake_timeouts; /* clients closed for not reaching rawmode in time */
    size_t read_budget; /* bytes read per client per scd_handle (SCD_READ_BUDGET by default) */
    size_t write_budget; /* bytes written per client per flush (0: as much as the socket takes) */
} scd_server_t;

/* A frame client `client` sent: the caller hands it to the node and to the other clients
 * (scd_broadcast with except = client), at once or when a bus model says it has arrived. */
typedef void (*scd_rx_fn)(void *ctx, int client, const scd_frame_t *frame);

/* Listen on host:port (port 0: any free port, reported in *bound_port). 0 ok, -1 error. */
int scd_open(scd_server_t *s, const char *host, int port, int *bound_port, char *err, size_t errlen);
void scd_close(scd_server_t *s);
/* Fill pollfds (at most 1 + SCD_MAX_CLIENTS); returns the count. POLLOUT only for output
 * that can be written now (not during a client's handshake grace: no busy loop), POLLIN
 * not for clients whose input is paused. */
int scd_pollfds(const scd_server_t *s, struct pollfd *pfd, uint64_t now_us);
/* Earliest time (us) at which held-back output becomes writable (end of a grace), or
 * UINT64_MAX: the caller's poll timeout. */
uint64_t scd_next_wakeup_us(const scd_server_t *s);
/* Close clients that have not finished the handshake within SCD_HANDSHAKE_US. */
void scd_expire(scd_server_t *s, uint64_t now_us);
/* Handle readiness; frames from clients go to rx (and to the other clients). */
void scd_handle(scd_server_t *s, const struct pollfd *pfd, int npfd, uint64_t now_us,
                scd_rx_fn rx, void *ctx);
/* A frame on the bus: queued to every client in rawmode except `except` (-1: none), with
 * the receive time stamp_us (microseconds since the epoch; 0: now). */
void scd_broadcast(scd_server_t *s, const scd_frame_t *f, int except, uint64_t stamp_us);
/* Write queued output (call once per main-loop pass). */
void scd_flush(scd_server_t *s, uint64_t now_us);
/* Parse one command body (between '<' and '>', exclusive) of a "send". 0 ok, -1 bad. */
int scd_parse_send(const char *cmd, size_t len, scd_frame_t *f);
/* Bytes received from client ci (what scd_handle does after recv; split out so that the
 * line parser can be fuzzed without sockets: firmware_sim/fuzz/fuzz_scd.c). */
void scd_feed(scd_server_t *s, int ci, const char *buf, size_t len, uint64_t now_us, scd_rx_fn rx, void *ctx);

#endif
