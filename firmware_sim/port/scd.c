/*
 * scd.c - socketcand rawmode server (see scd.h).
 */
#include "scd.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

static void client_reset(scd_client_t *c)
{
    c->fd = -1;
    c->stage = 0;
    c->line_len = 0;
    c->in_cmd = false;
    c->discard = false;
    c->out_head = 0;
    c->out_len = 0;
    c->frames_after_us = 0;
    c->accepted_us = 0;
    c->last_rx_us = 0;
    c->rx_paused = false;
    c->dropped = 0;
}

int scd_open(scd_server_t *s, const char *host, int port, int *bound_port, char *err, size_t errlen)
{
    memset(s, 0, sizeof *s);
    s->listen_fd = -1;
    s->read_budget = SCD_READ_BUDGET;
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        client_reset(&s->client[i]);
    }
    struct sockaddr_in a;
    memset(&a, 0, sizeof a);
    a.sin_family = AF_INET;
    a.sin_port = htons((uint16_t)port);
    if (inet_pton(AF_INET, host, &a.sin_addr) != 1) {
        snprintf(err, errlen, "socketcand: bad IPv4 address '%s'", host);
        return -1;
    }
    int fd = socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (fd < 0) {
        snprintf(err, errlen, "socketcand: socket: %s", strerror(errno));
        return -1;
    }
    int one = 1;
    (void)setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (bind(fd, (struct sockaddr *)&a, sizeof a) != 0 || listen(fd, 8) != 0) {
        snprintf(err, errlen, "socketcand: cannot listen on %s:%d: %s", host, port, strerror(errno));
        close(fd);
        return -1;
    }
    socklen_t al = sizeof a;
    if (getsockname(fd, (struct sockaddr *)&a, &al) == 0) {
        *bound_port = ntohs(a.sin_port);
    }
    s->listen_fd = fd;
    return 0;
}

void scd_close(scd_server_t *s)
{
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        if (s->client[i].fd >= 0) {
            close(s->client[i].fd);
            client_reset(&s->client[i]);
        }
    }
    if (s->listen_fd >= 0) {
        close(s->listen_fd);
        s->listen_fd = -1;
    }
}

static bool output_held(const scd_client_t *c, uint64_t now_us)
{
    return c->stage == 2 && now_us < c->frames_after_us;
}

int scd_pollfds(const scd_server_t *s, struct pollfd *pfd, uint64_t now_us)
{
    int n = 0;
    pfd[n].fd = s->listen_fd;
    pfd[n].events = POLLIN;
    pfd[n].revents = 0;
    n++;
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        const scd_client_t *c = &s->client[i];
        if (c->fd < 0) {
            continue;
        }
        pfd[n].fd = c->fd;
        /* POLLOUT only for output flush_out would write: during the grace it writes
         * nothing, and poll would return at once, again and again (a busy loop) */
        pfd[n].events = (short)((c->rx_paused ? 0 : POLLIN) |
                                (c->out_len > 0 && !output_held(c, now_us) ? POLLOUT : 0));
        pfd[n].revents = 0;
        n++;
    }
    return n;
}

static void drop_client(scd_client_t *c)
{
    if (c->fd >= 0) {
        close(c->fd);
    }
    client_reset(c);
}

uint64_t scd_next_wakeup_us(const scd_server_t *s)
{
    uint64_t t = UINT64_MAX;
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        const scd_client_t *c = &s->client[i];
        if (c->fd >= 0 && c->out_len > 0 && c->stage == 2 && c->frames_after_us != 0 && c->frames_after_us < t) {
            t = c->frames_after_us;
        }
    }
    return t;
}

void scd_expire(scd_server_t *s, uint64_t now_us)
{
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        scd_client_t *c = &s->client[i];
        if (c->fd >= 0 && c->stage != 2 && now_us - c->accepted_us > SCD_HANDSHAKE_US) {
            drop_client(c);
            s->handshake_timeouts++;
        }
    }
}

/* A slot for a new connection: a free one, else the longest-silent client still in its
 * handshake if silent for SCD_EVICT_IDLE_US (evicted), else -1. */
static int free_slot(scd_server_t *s, uint64_t now_us)
{
    int victim = -1;
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        const scd_client_t *c = &s->client[i];
        if (c->fd < 0) {
            return i;
        }
        if (c->stage != 2 && now_us - c->last_rx_us >= SCD_EVICT_IDLE_US &&
            (victim < 0 || c->last_rx_us < s->client[victim].last_rx_us)) {
            victim = i;
        }
    }
    if (victim >= 0) {
        drop_client(&s->client[victim]);
        s->evicted++;
    }
    return victim;
}

/* Write as much of the output buffer as the socket takes (at most budget bytes, 0: no
 * limit). */
static void flush_out(scd_client_t *c, uint64_t now_us, size_t budget)
{
    if (c->fd < 0 || c->out_len == 0) {
        return;
    }
    if (output_held(c, now_us)) {
        return; /* grace after "< ok >": python-can reads the handshake with one recv() */
    }
    size_t written = 0;
    while (c->out_len > 0 && (budget == 0u || written < budget)) {
        size_t first = c->out_len;
        if (c->out_head + first > SCD_OUT_BUF) {
            first = SCD_OUT_BUF - c->out_head;
        }
        if (budget != 0u && first > budget - written) {
            first = budget - written;
        }
        ssize_t w = send(c->fd, &c->out[c->out_head], first, MSG_NOSIGNAL | MSG_DONTWAIT);
        if (w < 0) {
            if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) {
                return;
            }
            drop_client(c);
            return;
        }
        c->out_head = (c->out_head + (size_t)w) % SCD_OUT_BUF;
        c->out_len -= (size_t)w;
        written += (size_t)w;
        if ((size_t)w < first) {
            return;
        }
    }
    if (c->out_len == 0) {
        c->out_head = 0;
    }
}

static bool queue_out(scd_client_t *c, const char *text, size_t len)
{
    if (len > SCD_OUT_BUF - c->out_len) {
        return false;
    }
    size_t tail = (c->out_head + c->out_len) % SCD_OUT_BUF;
    for (size_t i = 0; i < len; i++) {
        c->out[(tail + i) % SCD_OUT_BUF] = (uint8_t)text[i];
    }
    c->out_len += len;
    return true;
}

/* Handshake replies go out at once, alone. */
static void reply(scd_client_t *c, const char *text)
{
    if (c->fd < 0) {
        return;
    }
    if (c->out_len != 0 || send(c->fd, text, strlen(text), MSG_NOSIGNAL | MSG_DONTWAIT) != (ssize_t)strlen(text)) {
        drop_client(c); /* a client that cannot take 6 bytes during the handshake */
    }
}

static int hexval(char ch)
{
    if (ch >= '0' && ch <= '9') {
        return ch - '0';
    }
    if (ch >= 'a' && ch <= 'f') {
        return ch - 'a' + 10;
    }
    if (ch >= 'A' && ch <= 'F') {
        return ch - 'A' + 10;
    }
    return -1;
}

/* Next space-separated token of cmd[*pos..len). */
static bool token(const char *cmd, size_t len, size_t *pos, const char **tok, size_t *tlen)
{
    size_t p = *pos;
    while (p < len && cmd[p] == ' ') {
        p++;
    }
    if (p >= len) {
        return false;
    }
    size_t st = p;
    while (p < len && cmd[p] != ' ') {
        p++;
    }
    *tok = &cmd[st];
    *tlen = p - st;
    *pos = p;
    return true;
}

static bool parse_hex(const char *t, size_t n, size_t max_digits, uint32_t *v)
{
    if (n == 0 || n > max_digits) {
        return false;
    }
    uint32_t x = 0;
    for (size_t i = 0; i < n; i++) {
        int h = hexval(t[i]);
        if (h < 0) {
            return false;
        }
        x = (x << 4) | (uint32_t)h;
    }
    *v = x;
    return true;
}

int scd_parse_send(const char *cmd, size_t len, scd_frame_t *f)
{
    size_t pos = 0, tl;
    const char *t;
    uint32_t v;
    if (!token(cmd, len, &pos, &t, &tl) || tl != 4 || memcmp(t, "send", 4) != 0) {
        return -1;
    }
    if (!token(cmd, len, &pos, &t, &tl) || !parse_hex(t, tl, 8, &v)) {
        return -1;
    }
    f->ext = tl > 3;
    if ((f->ext && v > 0x1FFFFFFFu) || (!f->ext && v > 0x7FFu)) {
        return -1;
    }
    f->id = v;
    if (!token(cmd, len, &pos, &t, &tl) || !parse_hex(t, tl, 1, &v) || v > 8u) {
        return -1;
    }
    f->len = (uint8_t)v;
    memset(f->data, 0, sizeof f->data);
    for (uint8_t i = 0; i < f->len; i++) {
        if (!token(cmd, len, &pos, &t, &tl) || !parse_hex(t, tl, 2, &v)) {
            return -1;
        }
        f->data[i] = (uint8_t)v;
    }
    if (token(cmd, len, &pos, &t, &tl)) {
        return -1; /* more bytes than the DLC says */
    }
    return 0;
}

static void format_frame(const scd_frame_t *f, uint64_t stamp_us, char *buf, size_t cap, size_t *len)
{
    struct timeval tv;
    if (stamp_us == 0u) {
        gettimeofday(&tv, NULL);
    } else {
        tv.tv_sec = (time_t)(stamp_us / 1000000u);
        tv.tv_usec = (suseconds_t)(stamp_us % 1000000u);
    }
    static const char hx[] = "0123456789ABCDEF";
    char data[17];
    for (uint8_t i = 0; i < f->len && i < 8; i++) {
        data[2 * i] = hx[f->data[i] >> 4];
        data[2 * i + 1] = hx[f->data[i] & 15];
    }
    data[2 * (f->len > 8 ? 8 : f->len)] = '\0';
    int n = f->ext ? snprintf(buf, cap, "< frame %08X %ld.%06ld %s >", (unsigned)f->id, (long)tv.tv_sec, (long)tv.tv_usec, data)
                   : snprintf(buf, cap, "< frame %03X %ld.%06ld %s >", (unsigned)f->id, (long)tv.tv_sec, (long)tv.tv_usec, data);
    *len = n > 0 ? (size_t)n : 0;
}

void scd_broadcast(scd_server_t *s, const scd_frame_t *f, int except, uint64_t stamp_us)
{
    char buf[80];
    size_t len;
    format_frame(f, stamp_us, buf, sizeof buf, &len);
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        scd_client_t *c = &s->client[i];
        if (i == except || c->fd < 0 || c->stage != 2) {
            continue;
        }
        if (!queue_out(c, buf, len)) {
            c->dropped++;
            s->dropped++;
        }
    }
    /* written by scd_flush, batched per main-loop pass */
}

static void command(scd_server_t *s, int ci, const char *cmd, size_t len, uint64_t now_us,
                    scd_rx_fn rx, void *ctx)
{
    scd_client_t *c = &s->client[ci];
    /* trim the spaces inside "< ... >" */
    while (len > 0 && cmd[0] == ' ') {
        cmd++;
        len--;
    }
    while (len > 0 && cmd[len - 1] == ' ') {
        len--;
    }
    if (c->stage == 2 && len > 5 && memcmp(cmd, "send ", 5) == 0) {
        scd_frame_t f;
        if (scd_parse_send(cmd, len, &f) != 0) {
            s->garbage++;
            return;
        }
        rx(ctx, ci, &f);
        return;
    }
    if (c->stage == 0 && len > 5 && memcmp(cmd, "open ", 5) == 0) {
        size_t n = len - 5;
        if (n == 0 || n >= sizeof s->channel) {
            s->garbage++;
            return;
        }
        c->stage = 1;
        reply(c, "< ok >");
        return;
    }
    if (c->stage == 1 && len == 7 && memcmp(cmd, "rawmode", 7) == 0) {
        c->stage = 2;
        c->frames_after_us = now_us + SCD_GRACE_US;
        reply(c, "< ok >");
        return;
    }
    if (len == 4 && memcmp(cmd, "echo", 4) == 0 && c->out_len == 0) {
        reply(c, "< echo >");
        return;
    }
    s->garbage++;
}

static void read_client(scd_server_t *s, int ci, uint64_t now_us, scd_rx_fn rx, void *ctx)
{
    scd_client_t *c = &s->client[ci];
    char buf[SCD_READ_BUDGET];
    size_t want = s->read_budget > 0u && s->read_budget < sizeof buf ? s->read_budget : sizeof buf;
    ssize_t r = recv(c->fd, buf, want, MSG_DONTWAIT);
    if (r == 0 || (r < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) {
        drop_client(c);
        return;
    }
    if (r < 0) {
        return;
    }
    scd_feed(s, ci, buf, (size_t)r, now_us, rx, ctx);
}

void scd_feed(scd_server_t *s, int ci, const char *buf, size_t r, uint64_t now_us, scd_rx_fn rx, void *ctx)
{
    scd_client_t *c = &s->client[ci];
    c->frames_after_us = 0; /* the client spoke: the handshake is over for it */
    c->last_rx_us = now_us;
    for (size_t i = 0; i < r && c->fd >= 0; i++) {
        char ch = buf[i];
        if (!c->in_cmd) {
            if (ch == '<') {
                c->in_cmd = true;
                c->discard = false;
                c->line_len = 0;
            } else if (ch != ' ' && ch != '\n' && ch != '\r' && ch != '\t') {
                s->garbage++; /* bytes outside "< >" */
            }
            continue;
        }
        if (ch == '>') {
            c->in_cmd = false;
            if (c->discard) {
                s->garbage++;
            } else {
                command(s, ci, c->line, c->line_len, now_us, rx, ctx);
            }
            continue;
        }
        if (ch == '<') { /* a new command before the old one ended: drop the old one */
            s->garbage++;
            c->line_len = 0;
            c->discard = false;
            continue;
        }
        if (c->line_len + 1 >= SCD_LINE_MAX) {
            c->discard = true;
            continue;
        }
        if (!c->discard) {
            c->line[c->line_len++] = ch;
        }
    }
}

void scd_handle(scd_server_t *s, const struct pollfd *pfd, int npfd, uint64_t now_us,
                scd_rx_fn rx, void *ctx)
{
    for (int k = 0; k < npfd; k++) {
        if (pfd[k].revents == 0) {
            continue;
        }
        if (pfd[k].fd == s->listen_fd) {
            int fd = accept4(s->listen_fd, NULL, NULL, SOCK_NONBLOCK | SOCK_CLOEXEC);
            if (fd < 0) {
                continue;
            }
            int slot = free_slot(s, now_us);
            if (slot < 0) {
                s->refused++;
                close(fd);
                continue;
            }
            int one = 1;
            (void)setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
            client_reset(&s->client[slot]);
            s->client[slot].fd = fd;
            s->client[slot].accepted_us = now_us;
            s->client[slot].last_rx_us = now_us;
            reply(&s->client[slot], "< hi >");
            continue;
        }
        for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
            scd_client_t *c = &s->client[i];
            if (c->fd != pfd[k].fd) {
                continue;
            }
            if (pfd[k].revents & (POLLERR | POLLNVAL)) {
                drop_client(c);
                break;
            }
            if (pfd[k].revents & (POLLIN | POLLHUP)) {
                read_client(s, i, now_us, rx, ctx);
            }
            if (c->fd >= 0 && (pfd[k].revents & POLLOUT)) {
                flush_out(c, now_us, s->write_budget);
            }
            break;
        }
    }
}

void scd_flush(scd_server_t *s, uint64_t now_us)
{
    for (int i = 0; i < SCD_MAX_CLIENTS; i++) {
        flush_out(&s->client[i], now_us, s->write_budget);
    }
}
