/*
 * fuzz_scd.c - libFuzzer target: the socketcand server of drive_sim (port/scd.c): its line
 * parser (scd_feed: bytes a client sent; scd_parse_send) and the paths behind it
 * (handshake replies, "send" -> node + broadcast to the other clients, output buffering,
 * scd_flush), with SCD_MAX_CLIENTS clients whose bytes arrive in chunks cut at arbitrary
 * places and interleaved. Each client slot holds one end of a socketpair (kept across
 * inputs, so that replies and flushed frames are real socket writes); the harness drains
 * the other end. The accept / refuse path and the socket errors are exercised by
 * tests/test_reliability_tcp.py against the running drive_sim.
 *
 * Checked besides the sanitizers (a violation calls __builtin_trap):
 *   - every frame handed to the node has len <= 8 and an 11-bit (29-bit if extended) id;
 *   - a client's line buffer never holds SCD_LINE_MAX bytes or more, its output buffer
 *     never more than SCD_OUT_BUF;
 *   - everything the server writes to a client is a sequence of "< ... >" messages of at
 *     most 80 bytes (what python-can's parser expects).
 *
 * Input format: records [client, chunk length, chunk bytes...] (client mod
 * SCD_MAX_CLIENTS; a record cut short sends what is there). Time advances 50 ms per record.
 */
#include <errno.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "scd.h"

static scd_server_t g_srv;
static int g_peer[SCD_MAX_CLIENTS];
/* what a client has received: its "< ... >" framing state */
static bool g_in_msg[SCD_MAX_CLIENTS];
static size_t g_msg_len[SCD_MAX_CLIENTS];
/* the server may have written to this client's socket since the last drain */
static bool g_touched[SCD_MAX_CLIENTS];

static void fz_check(bool ok, const char *what)
{
    if (!ok) {
        fprintf(stderr, "fuzz_scd: property violated: %s\n", what);
        __builtin_trap();
    }
}

static void on_frame(void *ctx, int client, const scd_frame_t *f)
{
    (void)ctx;
    fz_check(f->len <= 8u, "frame longer than 8 bytes");
    fz_check(f->ext ? f->id <= 0x1FFFFFFFu : f->id <= 0x7FFu, "identifier range");
    fz_check(client >= 0 && client < SCD_MAX_CLIENTS, "client index range");
    scd_broadcast(&g_srv, f, client, 0u); /* as drive_sim does without a bus model */
}

/* Read what the server sent to client i and check its framing. */
static void drain(int i)
{
    char buf[4096];
    ssize_t r;
    if (!g_touched[i]) {
        return; /* saves a system call per idle client and input */
    }
    g_touched[i] = false;
    while (g_peer[i] >= 0 && (r = recv(g_peer[i], buf, sizeof buf, MSG_DONTWAIT)) > 0) {
        for (ssize_t k = 0; k < r; k++) {
            char ch = buf[k];
            if (!g_in_msg[i]) {
                fz_check(ch == '<', "server output outside < >");
                g_in_msg[i] = true;
                g_msg_len[i] = 1;
                continue;
            }
            g_msg_len[i]++;
            fz_check(ch != '<', "server output: < inside a message");
            fz_check(g_msg_len[i] <= 80, "server output: message longer than 80 bytes");
            if (ch == '>') {
                g_in_msg[i] = false;
            }
        }
    }
}

/* Client slot i: a connected socket (re-created when the server dropped it), fresh state. */
static void connect_client(int i)
{
    scd_client_t *c = &g_srv.client[i];
    if (c->fd < 0 || g_peer[i] < 0) {
        if (c->fd >= 0) {
            close(c->fd);
        }
        if (g_peer[i] >= 0) {
            close(g_peer[i]);
        }
        int sv[2];
        if (socketpair(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0, sv) != 0) {
            fprintf(stderr, "fuzz_scd: socketpair: %s\n", strerror(errno));
            abort();
        }
        c->fd = sv[0];
        g_peer[i] = sv[1];
        g_touched[i] = false;
    }
    int fd = c->fd;
    memset(c, 0, offsetof(scd_client_t, out));
    c->fd = fd;
    drain(i);
    g_in_msg[i] = false;
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    (void)argc;
    (void)argv;
    char err[256];
    int port = 0;
    if (scd_open(&g_srv, "127.0.0.1", 0, &port, err, sizeof err) != 0) {
        fprintf(stderr, "fuzz_scd: %s\n", err);
        exit(1);
    }
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        g_peer[i] = -1;
    }
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    /* the pure "send" parser on the raw input */
    scd_frame_t f;
    if (scd_parse_send((const char *)data, size, &f) == 0) {
        fz_check(f.len <= 8u && (f.ext ? f.id <= 0x1FFFFFFFu : f.id <= 0x7FFu), "scd_parse_send result range");
    }
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        connect_client(i);
    }
    size_t p = 0;
    uint64_t now_us = 1000000u;
    while (p < size) {
        int ci = data[p++] % SCD_MAX_CLIENTS;
        size_t len = p < size ? data[p++] : 0;
        if (len > size - p) {
            len = size - p;
        }
        scd_feed(&g_srv, ci, (const char *)&data[p], len, now_us, on_frame, NULL);
        g_touched[ci] = true; /* a handshake reply */
        for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
            g_touched[i] = g_touched[i] || g_srv.client[i].out_len > 0; /* a broadcast frame */
        }
        p += len;
        now_us += 50000u; /* past the handshake grace after a few records */
        for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
            const scd_client_t *c = &g_srv.client[i];
            fz_check(c->line_len < SCD_LINE_MAX, "line buffer bound");
            fz_check(c->out_len <= SCD_OUT_BUF, "output buffer bound");
        }
        if ((p & 0x3F) == 0) {
            scd_flush(&g_srv, now_us);
        }
    }
    scd_flush(&g_srv, now_us + SCD_GRACE_US);
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        drain(i);
    }
    return 0;
}
