/* test_slcan.c - the SLCAN parser on the host (make -C firmware_sim pil-test). */
#include <string.h>

#include "slcan.h"
#include "th.h"

typedef struct {
    slcan_frame_t frames[16];
    int nframes;
    char replies[256];
    size_t nreply;
} feed_out_t;

static void feed(slcan_t *s, const char *text, size_t n, feed_out_t *o)
{
    memset(o, 0, sizeof *o);
    for (size_t i = 0; i < n; i++) {
        slcan_frame_t f;
        char r[SLCAN_REPLY_MAX];
        size_t rl = 99;
        slcan_event_t ev = slcan_feed(s, (uint8_t)text[i], &f, r, &rl);
        TH_ASSERT(rl <= SLCAN_REPLY_MAX);
        if (ev == SLCAN_NONE) {
            TH_EQ(rl, 0);
            continue;
        }
        if (o->nreply + rl < sizeof o->replies) {
            memcpy(o->replies + o->nreply, r, rl);
            o->nreply += rl;
        }
        if (ev == SLCAN_FRAME && o->nframes < 16) {
            o->frames[o->nframes++] = f;
        }
    }
    o->replies[o->nreply] = '\0';
}

#define FEED(s, lit, o) feed((s), (lit), sizeof(lit) - 1u, (o))

static void test_python_can_open_sequence(void)
{
    slcan_t s;
    feed_out_t o;
    slcan_init(&s);
    /* python-can 4.6 with bitrate=1000000: C, S8, "" (no data bitrate), O, then O again */
    FEED(&s, "C\rS8\r\rO\rO\r", &o);
    TH_ASSERT(strcmp(o.replies, "\r\r\r\r") == 0); /* empty line: no reply */
    TH_ASSERT(s.open && !s.listen_only);
    TH_EQ(s.bitrate_code, 8);
    TH_EQ(s.bad_lines, 0);
    FEED(&s, "V\rN\rF\r", &o);
    TH_ASSERT(strcmp(o.replies, "V1013\rNPIL1\rF00\r") == 0);
}

static void test_frames_parse_and_refuse_when_closed(void)
{
    slcan_t s;
    feed_out_t o;
    slcan_init(&s);
    FEED(&s, "t6014DEADBEEF\r", &o); /* closed: refused */
    TH_EQ(o.nframes, 0);
    TH_ASSERT(strcmp(o.replies, "\a") == 0);
    FEED(&s, "O\rt60184000100000000000\rT1ABCDEF02a1b2\rr7001\rt0000\r", &o);
    TH_EQ(o.nframes, 4);
    TH_EQ(o.frames[0].id, 0x601);
    TH_EQ(o.frames[0].len, 8);
    TH_EQ(o.frames[0].data[0], 0x40);
    TH_EQ(o.frames[0].data[2], 0x10);
    TH_ASSERT(!o.frames[0].ext && !o.frames[0].rtr);
    TH_EQ(o.frames[1].id, 0x1ABCDEF0);
    TH_ASSERT(o.frames[1].ext);
    TH_EQ(o.frames[1].len, 2);
    TH_EQ(o.frames[1].data[0], 0xA1); /* lower-case hex */
    TH_ASSERT(o.frames[2].rtr);
    TH_EQ(o.frames[3].len, 0);
    TH_ASSERT(strcmp(o.replies, "\rz\rZ\rz\rz\r") == 0);
    /* listen-only: frames refused */
    FEED(&s, "C\rL\rt0000\r", &o);
    TH_EQ(o.nframes, 0);
    TH_ASSERT(strcmp(o.replies, "\r\r\a") == 0);
}

static void test_malformed_lines_are_refused(void)
{
    static const char *bad[] = {
        "t60", "t6014DEADBE", "t6014DEADBEEF00", "t8000", "t6019", "t60G0", "tXYZ0",
        "T200000000", "T1ABCDEF0", "r7009", "S9", "S", "s12", "Z1", "M123", "Q", "\x01\xff", "OO", "V1",
    };
    slcan_t s;
    feed_out_t o;
    slcan_init(&s);
    FEED(&s, "O\r", &o);
    for (size_t i = 0; i < sizeof bad / sizeof bad[0]; i++) {
        char line[64];
        size_t n = strlen(bad[i]);
        memcpy(line, bad[i], n);
        line[n] = '\r';
        feed(&s, line, n + 1u, &o);
        TH_EQ(o.nframes, 0);
        if (strcmp(o.replies, "\a") != 0) {
            th_fail(__FILE__, __LINE__, bad[i]);
        }
    }
    TH_EQ(s.bad_lines, sizeof bad / sizeof bad[0]);
    /* S while open is refused, the bitrate stays */
    FEED(&s, "S4\r", &o);
    TH_ASSERT(strcmp(o.replies, "\a") == 0);
    TH_EQ(s.bitrate_code, 0);
    TH_ASSERT(s.open);
}

static void test_overlong_line_discarded_and_next_line_works(void)
{
    slcan_t s;
    feed_out_t o;
    slcan_init(&s);
    FEED(&s, "O\r", &o);
    char big[5000];
    memset(big, 't', sizeof big);
    big[sizeof big - 1] = '\r';
    feed(&s, big, sizeof big, &o);
    TH_ASSERT(strcmp(o.replies, "\a") == 0);
    TH_EQ(o.nframes, 0);
    TH_EQ(s.overlong_lines, 1);
    /* exactly SLCAN_LINE_MAX characters is still a line (the longest valid frame) */
    FEED(&s, "T1FFFFFFF81122334455667788\r", &o);
    TH_EQ(o.nframes, 1);
    TH_EQ(o.frames[0].data[7], 0x88);
    /* one more character is overlong */
    FEED(&s, "T1FFFFFFF811223344556677889\rt0000\r", &o);
    TH_EQ(o.nframes, 1);
    TH_ASSERT(strcmp(o.replies, "\az\r") == 0);
}

static void test_partial_line_dropped_and_lf_skipped(void)
{
    slcan_t s;
    feed_out_t o;
    slcan_init(&s);
    FEED(&s, "O\r\nt12", &o);
    slcan_drop_partial(&s); /* the sender went away mid-line */
    TH_EQ(s.partial_dropped, 1);
    FEED(&s, "t1230\r\n", &o);
    TH_EQ(o.nframes, 1);
    TH_EQ(o.frames[0].id, 0x123);
    TH_EQ(s.bad_lines, 0);
}

static void test_encode_round_trip(void)
{
    slcan_t s;
    feed_out_t o;
    slcan_init(&s);
    FEED(&s, "O\r", &o);
    slcan_frame_t f = {0x581, false, false, 8, {0x43, 0x00, 0x10, 0x00, 0x92, 0x01, 0x02, 0xFF}};
    char text[SLCAN_FRAME_TEXT_MAX];
    size_t n = slcan_encode(&f, text, sizeof text);
    TH_EQ(n, 22);
    TH_ASSERT(memcmp(text, "t581843001000920102FF\r", n) == 0);
    feed(&s, text, n, &o);
    TH_EQ(o.nframes, 1);
    TH_ASSERT(memcmp(&o.frames[0].data, f.data, 8) == 0);
    slcan_frame_t e = {0x1FFFFFFF, true, false, 8, {1, 2, 3, 4, 5, 6, 7, 8}};
    TH_EQ(slcan_encode(&e, text, sizeof text), SLCAN_FRAME_TEXT_MAX);
    TH_EQ(slcan_encode(&e, text, SLCAN_FRAME_TEXT_MAX - 1u), 0); /* does not fit */
    slcan_frame_t bad = {0x800, false, false, 0, {0}};
    TH_EQ(slcan_encode(&bad, text, sizeof text), 0);
    bad.id = 1;
    bad.len = 9;
    TH_EQ(slcan_encode(&bad, text, sizeof text), 0);
}

int main(void)
{
    TH_RUN(test_python_can_open_sequence);
    TH_RUN(test_frames_parse_and_refuse_when_closed);
    TH_RUN(test_malformed_lines_are_refused);
    TH_RUN(test_overlong_line_discarded_and_next_line_works);
    TH_RUN(test_partial_line_dropped_and_lf_skipped);
    TH_RUN(test_encode_round_trip);
    return th_finish();
}
