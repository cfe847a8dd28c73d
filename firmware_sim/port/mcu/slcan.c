/* slcan.c - see slcan.h. */
#include "slcan.h"

#include <stddef.h>
#include <string.h>

/* tests/test_mcu_pil.py reads the statistics of the running MCU at this offset */
_Static_assert(offsetof(slcan_t, frames_in) == 32u, "slcan_t statistics moved");

#define SLCAN_CR '\r'
#define SLCAN_BEL '\a'

void slcan_init(slcan_t *s)
{
    memset(s, 0, sizeof *s);
}

void slcan_drop_partial(slcan_t *s)
{
    if (s->len != 0u || s->overlong) {
        s->partial_dropped++;
    }
    s->len = 0u;
    s->overlong = false;
}

static int slcan_hex(char c)
{
    if (c >= '0' && c <= '9') {
        return c - '0';
    }
    if (c >= 'A' && c <= 'F') {
        return c - 'A' + 10;
    }
    if (c >= 'a' && c <= 'f') {
        return c - 'a' + 10;
    }
    return -1;
}

/* n hex digits at p; false on a non-hex character */
static bool slcan_hex_n(const char *p, size_t n, uint32_t *out)
{
    uint32_t v = 0u;
    for (size_t i = 0; i < n; i++) {
        int d = slcan_hex(p[i]);
        if (d < 0) {
            return false;
        }
        v = (v << 4) | (uint32_t)d;
    }
    *out = v;
    return true;
}

static size_t slcan_put(char *reply, const char *text)
{
    size_t n = strlen(text);
    memcpy(reply, text, n);
    return n;
}

/* t/T/r/R line -> frame; false if malformed */
static bool slcan_parse_frame(const char *l, size_t len, slcan_frame_t *f)
{
    bool ext = (l[0] == 'T' || l[0] == 'R');
    bool rtr = (l[0] == 'r' || l[0] == 'R');
    size_t id_digits = ext ? 8u : 3u;
    if (len < 1u + id_digits + 1u) {
        return false;
    }
    uint32_t id, dlc;
    if (!slcan_hex_n(l + 1, id_digits, &id) || !slcan_hex_n(l + 1 + id_digits, 1u, &dlc)) {
        return false;
    }
    if (id > (ext ? 0x1FFFFFFFu : 0x7FFu) || dlc > 8u) {
        return false;
    }
    size_t data_at = 1u + id_digits + 1u;
    if (len != data_at + (rtr ? 0u : 2u * dlc)) {
        return false;
    }
    memset(f, 0, sizeof *f);
    f->id = id;
    f->ext = ext;
    f->rtr = rtr;
    f->len = (uint8_t)dlc;
    if (!rtr) {
        for (uint32_t i = 0; i < dlc; i++) {
            uint32_t b;
            if (!slcan_hex_n(l + data_at + 2u * i, 2u, &b)) {
                return false;
            }
            f->data[i] = (uint8_t)b;
        }
    }
    return true;
}

static slcan_event_t slcan_line(slcan_t *s, slcan_frame_t *frame, char *reply, size_t *reply_len)
{
    const char *l = s->line;
    size_t len = s->len;
    static const char bel[] = {SLCAN_BEL, '\0'};
    static const char ok[] = {SLCAN_CR, '\0'};
    *reply_len = 0u;
    if (len == 0u) {
        return SLCAN_REPLY; /* empty line: no reply */
    }
    switch (l[0]) {
    case 't':
    case 'T':
    case 'r':
    case 'R':
        if (!s->open || s->listen_only || !slcan_parse_frame(l, len, frame)) {
            break;
        }
        s->frames_in++;
        *reply_len = slcan_put(reply, frame->ext ? "Z\r" : "z\r");
        return SLCAN_FRAME;
    case 'O':
    case 'L':
        if (len != 1u) {
            break;
        }
        s->open = true; /* again while open: still OK (python-can sends O twice) */
        s->listen_only = (l[0] == 'L');
        s->commands++;
        *reply_len = slcan_put(reply, ok);
        return SLCAN_REPLY;
    case 'C':
        if (len != 1u) {
            break;
        }
        s->open = false;
        s->listen_only = false;
        s->commands++;
        *reply_len = slcan_put(reply, ok);
        return SLCAN_REPLY;
    case 'S':
        if (len != 2u || s->open || l[1] < '0' || l[1] > '8') {
            break;
        }
        s->bitrate_code = (uint8_t)(l[1] - '0');
        s->commands++;
        *reply_len = slcan_put(reply, ok);
        return SLCAN_REPLY;
    case 's': {
        uint32_t btr;
        if (len != 5u || s->open || !slcan_hex_n(l + 1, 4u, &btr)) {
            break;
        }
        s->commands++;
        *reply_len = slcan_put(reply, ok);
        return SLCAN_REPLY;
    }
    case 'V':
        if (len != 1u) {
            break;
        }
        s->commands++;
        *reply_len = slcan_put(reply, "V1013\r");
        return SLCAN_REPLY;
    case 'N':
        if (len != 1u) {
            break;
        }
        s->commands++;
        *reply_len = slcan_put(reply, "NPIL1\r");
        return SLCAN_REPLY;
    case 'F':
        if (len != 1u) {
            break;
        }
        s->commands++;
        *reply_len = slcan_put(reply, "F00\r");
        return SLCAN_REPLY;
    case 'Z':
        if (len != 2u || l[1] != '0') {
            break; /* Z1: timestamps are not supported */
        }
        s->commands++;
        *reply_len = slcan_put(reply, ok);
        return SLCAN_REPLY;
    case 'M':
    case 'm': {
        uint32_t v;
        if (len != 9u || !slcan_hex_n(l + 1, 8u, &v)) {
            break;
        }
        s->commands++;
        *reply_len = slcan_put(reply, ok);
        return SLCAN_REPLY;
    }
    default:
        break;
    }
    s->bad_lines++;
    *reply_len = slcan_put(reply, bel);
    return SLCAN_REPLY;
}

slcan_event_t slcan_feed(slcan_t *s, uint8_t byte, slcan_frame_t *frame, char *reply, size_t *reply_len)
{
    *reply_len = 0u;
    if (byte == (uint8_t)SLCAN_CR) {
        slcan_event_t ev;
        if (s->overlong) {
            s->overlong_lines++;
            s->bad_lines++;
            reply[0] = SLCAN_BEL;
            *reply_len = 1u;
            ev = SLCAN_REPLY;
        } else {
            ev = slcan_line(s, frame, reply, reply_len);
        }
        s->len = 0u;
        s->overlong = false;
        return ev;
    }
    if (byte == (uint8_t)'\n' && s->len == 0u && !s->overlong) {
        return SLCAN_NONE; /* the LF of a CR LF sender */
    }
    if (s->overlong) {
        return SLCAN_NONE;
    }
    if (s->len >= SLCAN_LINE_MAX) {
        s->overlong = true;
        return SLCAN_NONE;
    }
    s->line[s->len++] = (char)byte;
    return SLCAN_NONE;
}

size_t slcan_encode(const slcan_frame_t *f, char *out, size_t cap)
{
    static const char hex[] = "0123456789ABCDEF";
    if (f->len > 8u || f->id > (f->ext ? 0x1FFFFFFFu : 0x7FFu)) {
        return 0u;
    }
    size_t id_digits = f->ext ? 8u : 3u;
    size_t need = 1u + id_digits + 1u + (f->rtr ? 0u : 2u * f->len) + 1u;
    if (need > cap) {
        return 0u;
    }
    size_t n = 0u;
    out[n++] = f->rtr ? (f->ext ? 'R' : 'r') : (f->ext ? 'T' : 't');
    for (size_t i = id_digits; i-- > 0u;) {
        out[n++] = hex[(f->id >> (4u * i)) & 0xFu];
    }
    out[n++] = (char)('0' + f->len);
    if (!f->rtr) {
        for (uint8_t i = 0; i < f->len; i++) {
            out[n++] = hex[f->data[i] >> 4];
            out[n++] = hex[f->data[i] & 0xFu];
        }
    }
    out[n++] = '\r';
    return n;
}
