/*
 * co_sdo.c - SDO server (CiA 301): expedited, segmented, block upload and block download
 * with CRC-16 CCITT, abort codes, timeout. One server channel (0x600+id / 0x580+id).
 *
 * Repeated requests (a client retrying after a lost response), one rule:
 *  - inside a segmented transfer the toggle bit is checked as CiA 301 says: a segment whose
 *    toggle is not alternated aborts the transfer with 0x05030000 (upload and download);
 *  - after a transfer completed, an exact repeat of its last request (the expedited
 *    download, the final download or upload segment, the block download end) within the
 *    SDO timeout is answered with the same response and NOT executed again: the client
 *    learns that its write (or run start) was done, and nothing is done twice;
 *  - an upload initiate is always executed again (a repeated read returns the present value).
 *
 * DOMAIN objects are streamed from / to the drive (no copy of the whole object); block
 * upload re-reads data from the drive on a retransmission, so it needs no block buffer.
 */
#include <string.h>

#include "co_node.h"

enum {
    SDO_IDLE = 0,
    SDO_DL_SEG,
    SDO_UL_SEG,
    SDO_BDL_SUB,
    SDO_BDL_END,
    SDO_BUL_INIT,
    SDO_BUL_SEND,
    SDO_BUL_ACK,
    SDO_BUL_END
};

#define SDO_MAX_BLKSIZE 127u

uint16_t co_sdo_crc16(uint16_t crc, const uint8_t *data, uint32_t len)
{
    for (uint32_t i = 0u; i < len; i++) {
        crc ^= (uint16_t)((uint16_t)data[i] << 8);
        for (uint8_t b = 0u; b < 8u; b++) {
            crc = (crc & 0x8000u) ? (uint16_t)((crc << 1) ^ 0x1021u) : (uint16_t)(crc << 1);
        }
    }
    return crc;
}

void co_sdo_init(co_sdo_t *s)
{
    memset(s, 0, sizeof *s);
    s->state = SDO_IDLE;
}

static const co_od_entry_t *entry_of(const co_sdo_t *s)
{
    return (const co_od_entry_t *)s->entry;
}

static bool send_resp(co_node_t *n, const uint8_t d[8])
{
    co_sdo_t *s = &n->sdo;
    memcpy(s->last_resp.data, d, 8u);
    s->last_resp.len = 8u;
    s->last_resp.id = (uint16_t)(0x580u + n->cfg.node_id);
    s->have_last = true;
    s->last_resp_us = n->now_us;
    return co_node_send(n, s->last_resp.id, d, 8u);
}

static void abort_transfer(co_node_t *n, uint16_t index, uint8_t sub, uint32_t code)
{
    uint8_t d[8] = {0x80u, (uint8_t)index, (uint8_t)(index >> 8), sub, 0, 0, 0, 0};
    co_put_u32(&d[4], code);
    (void)co_node_send(n, (uint16_t)(0x580u + n->cfg.node_id), d, 8u);
    n->sdo.state = SDO_IDLE;
    n->sdo.have_last = false;
}

static void mux(uint8_t d[8], uint8_t cmd, const co_sdo_t *s)
{
    memset(d, 0, 8u);
    d[0] = cmd;
    d[1] = (uint8_t)s->index;
    d[2] = (uint8_t)(s->index >> 8);
    d[3] = s->sub;
}

/* Read upload data at offset: a DOMAIN from the drive, anything else from the buffer. */
static uint32_t src_read(co_node_t *n, uint32_t off, uint8_t *dst, uint32_t len)
{
    co_sdo_t *s = &n->sdo;
    const co_od_entry_t *e = entry_of(s);
    if (len == 0u) {
        return 0u;
    }
    if (e->type == CO_T_DOMAIN) {
        uint32_t ab = co_od_domain_read(n, e, off, dst, len);
        if (ab == 0u && co_od_domain_generation(n, e) != s->generation) {
            ab = CO_SDO_AB_GENERAL; /* a new run replaced the data under the transfer */
        }
        return ab;
    }
    if ((uint64_t)off + len > s->size || s->size > CO_SDO_BUF) {
        return CO_SDO_AB_GENERAL;
    }
    memcpy(dst, &s->buf[off], len);
    return 0u;
}

/* Write download data at offset: a DOMAIN to the drive, anything else into the buffer. */
static uint32_t sink_write(co_node_t *n, const uint8_t *src, uint32_t len)
{
    co_sdo_t *s = &n->sdo;
    const co_od_entry_t *e = entry_of(s);
    uint32_t ab = 0u;
    if (len == 0u) {
        return 0u;
    }
    if (e->type == CO_T_DOMAIN) {
        ab = co_od_domain_write(n, e, s->offset, src, len);
    } else if ((uint64_t)s->offset + len > CO_SDO_BUF) {
        ab = CO_SDO_AB_DATA_LONG;
    } else {
        memcpy(&s->buf[s->offset], src, len);
    }
    if (ab == 0u) {
        s->offset += len;
    }
    return ab;
}

/* End of a download: length checks, then store. */
static uint32_t finish_download(co_node_t *n)
{
    co_sdo_t *s = &n->sdo;
    const co_od_entry_t *e = entry_of(s);
    if (s->size_indicated && s->offset != s->size) {
        return s->offset > s->size ? CO_SDO_AB_DATA_LONG : CO_SDO_AB_DATA_SHORT;
    }
    if (e->type == CO_T_DOMAIN) {
        return co_od_domain_commit(n, e, s->offset);
    }
    return co_od_write(n, e, s->buf, s->offset);
}

/* Look up an entry for an initiate request; sends the abort itself on failure. */
static const co_od_entry_t *initiate_lookup(co_node_t *n, uint16_t index, uint8_t sub)
{
    uint32_t ab;
    const co_od_entry_t *e = co_od_lookup(index, sub, &ab);
    if (e == NULL) {
        abort_transfer(n, index, sub, ab);
    }
    return e;
}

/* Prepare an upload: size and (for non-DOMAIN values) the bytes. */
static uint32_t prepare_upload(co_node_t *n, const co_od_entry_t *e)
{
    co_sdo_t *s = &n->sdo;
    /* the access check (write-only: 0x06010001) is co_od_read's and co_od_domain_size's */
    if (e->type == CO_T_DOMAIN) {
        s->generation = co_od_domain_generation(n, e);
        return co_od_domain_size(n, e, &s->size);
    }
    return co_od_read(n, e, s->buf, CO_SDO_BUF, &s->size);
}

static uint32_t prepare_download(co_node_t *n, const co_od_entry_t *e, uint32_t size, bool known)
{
    if (!(e->access & CO_ACC_W)) {
        return CO_SDO_AB_READONLY;
    }
    if (e->type == CO_T_DOMAIN) {
        return co_od_domain_begin(n, e, size, known);
    }
    if (known && e->size != 0u) {
        if (size > e->size) {
            return CO_SDO_AB_DATA_LONG;
        }
        if (size < e->size) {
            return CO_SDO_AB_DATA_SHORT;
        }
    }
    return 0u;
}

static void start_transfer(co_sdo_t *s, const co_od_entry_t *e, uint16_t index, uint8_t sub)
{
    s->entry = e;
    s->index = index;
    s->sub = sub;
    s->offset = 0u;
    s->toggle = 0u;
    s->have_last = false;
}

/* Upload initiate (also the pst fallback of a block upload). */
static void upload_initiate(co_node_t *n, const co_od_entry_t *e, uint16_t index, uint8_t sub)
{
    co_sdo_t *s = &n->sdo;
    uint8_t d[8];
    start_transfer(s, e, index, sub);
    uint32_t ab = prepare_upload(n, e);
    if (ab != 0u) {
        abort_transfer(n, index, sub, ab);
        return;
    }
    if (s->size <= 4u && s->size > 0u && e->type != CO_T_DOMAIN) {
        mux(d, (uint8_t)(0x43u | ((4u - s->size) << 2)), s);
        memcpy(&d[4], s->buf, s->size);
        s->state = SDO_IDLE;
    } else {
        mux(d, 0x41u, s);
        co_put_u32(&d[4], s->size);
        s->state = SDO_UL_SEG;
    }
    (void)send_resp(n, d);
}

static void download_initiate(co_node_t *n, const co_od_entry_t *e, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint16_t index = co_get_u16(&r[1]);
    uint8_t sub = r[3];
    uint8_t d[8];
    bool expedited = (r[0] & 0x02u) != 0u;
    bool size_ind = (r[0] & 0x01u) != 0u;
    start_transfer(s, e, index, sub);
    if (expedited) {
        uint32_t len = size_ind ? 4u - ((r[0] >> 2) & 0x03u) : (e->size != 0u ? e->size : 4u);
        if (!size_ind && len > 4u) {
            len = 4u;
        }
        uint32_t ab = prepare_download(n, e, len, true);
        if (ab == 0u) {
            ab = co_od_write(n, e, &r[4], len);
        }
        if (ab != 0u) {
            abort_transfer(n, index, sub, ab);
            return;
        }
        mux(d, 0x60u, s);
        s->state = SDO_IDLE;
        (void)send_resp(n, d);
        return;
    }
    s->size_indicated = size_ind;
    s->size = size_ind ? co_get_u32(&r[4]) : 0u;
    uint32_t ab = prepare_download(n, e, s->size, size_ind);
    if (ab != 0u) {
        abort_transfer(n, index, sub, ab);
        return;
    }
    mux(d, 0x60u, s);
    s->state = SDO_DL_SEG;
    (void)send_resp(n, d);
}

static void download_segment(co_node_t *n, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint8_t t = r[0] & 0x10u;
    if (t != s->toggle) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_TOGGLE); /* CiA 301, also for a repeat */
        return;
    }
    uint32_t len = 7u - ((r[0] >> 1) & 0x07u);
    uint32_t ab = sink_write(n, &r[1], len);
    if (ab == 0u && (r[0] & 0x01u)) {
        ab = finish_download(n);
        if (ab == 0u) {
            s->state = SDO_IDLE;
        }
    }
    if (ab != 0u) {
        abort_transfer(n, s->index, s->sub, ab);
        return;
    }
    uint8_t d[8] = {(uint8_t)(0x20u | t), 0, 0, 0, 0, 0, 0, 0};
    s->toggle ^= 0x10u;
    (void)send_resp(n, d);
}

static void upload_segment(co_node_t *n, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint8_t t = r[0] & 0x10u;
    if (t != s->toggle) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_TOGGLE); /* CiA 301, also for a repeat */
        return;
    }
    uint32_t left = s->size - s->offset;
    uint32_t len = left > 7u ? 7u : left;
    uint8_t d[8] = {0};
    uint32_t ab = src_read(n, s->offset, &d[1], len);
    if (ab != 0u) {
        abort_transfer(n, s->index, s->sub, ab);
        return;
    }
    s->offset += len;
    d[0] = (uint8_t)(t | ((7u - len) << 1));
    if (s->offset >= s->size) {
        d[0] |= 0x01u;
        s->state = SDO_IDLE;
    }
    s->toggle ^= 0x10u;
    (void)send_resp(n, d);
}

/* ---- block download ---- */

static void block_download_initiate(co_node_t *n, const co_od_entry_t *e, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint16_t index = co_get_u16(&r[1]);
    uint8_t sub = r[3];
    start_transfer(s, e, index, sub);
    s->size_indicated = (r[0] & 0x02u) != 0u;
    s->size = s->size_indicated ? co_get_u32(&r[4]) : 0u;
    uint32_t ab = prepare_download(n, e, s->size, s->size_indicated);
    if (ab != 0u) {
        abort_transfer(n, index, sub, ab);
        return;
    }
    s->crc_on = (r[0] & 0x04u) != 0u;
    s->crc = 0u;
    s->seqno = 0u;
    s->blksize = SDO_MAX_BLKSIZE;
    s->have_held = false;
    s->got_last = false;
    uint8_t d[8];
    mux(d, 0xA4u, s); /* scs 5, sc: server supports CRC */
    d[4] = s->blksize;
    s->state = SDO_BDL_SUB;
    (void)send_resp(n, d);
}

static uint32_t flush_held(co_node_t *n, uint32_t len)
{
    co_sdo_t *s = &n->sdo;
    if (!s->have_held) {
        return 0u;
    }
    s->have_held = false;
    s->crc = co_sdo_crc16(s->crc, s->held, len);
    return sink_write(n, s->held, len);
}

static void block_download_segment(co_node_t *n, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint8_t seq = r[0] & 0x7Fu;
    bool last = (r[0] & 0x80u) != 0u;
    bool accepted = false;
    if (seq == 0u) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_SEQNO);
        return;
    }
    if (seq == (uint8_t)(s->seqno + 1u) && !s->got_last) {
        uint32_t ab = flush_held(n, 7u);
        if (ab != 0u) {
            abort_transfer(n, s->index, s->sub, ab);
            return;
        }
        memcpy(s->held, &r[1], 7u);
        s->have_held = true;
        s->seqno = seq;
        s->got_last = last;
        accepted = true;
    }
    /* end of sub-block: the client waits for our confirmation after seq == blksize or the
     * last segment; out-of-sequence segments are confirmed with the last good seqno */
    if (last || seq >= s->blksize) {
        uint8_t d[8] = {0xA2u, s->seqno, s->blksize, 0, 0, 0, 0, 0};
        s->seqno = 0u;
        if (s->got_last && accepted) {
            s->state = SDO_BDL_END;
        }
        (void)send_resp(n, d);
    }
}

static void block_download_end(co_node_t *n, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    if ((r[0] & 0xE3u) != 0xC1u) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_CMD);
        return;
    }
    uint32_t unused = (r[0] >> 2) & 0x07u;
    uint32_t ab = flush_held(n, 7u - unused);
    if (ab == 0u && s->crc_on && co_get_u16(&r[1]) != s->crc) {
        ab = CO_SDO_AB_CRC;
    }
    if (ab == 0u) {
        ab = finish_download(n);
    }
    if (ab != 0u) {
        abort_transfer(n, s->index, s->sub, ab);
        return;
    }
    uint8_t d[8] = {0xA1u, 0, 0, 0, 0, 0, 0, 0};
    s->state = SDO_IDLE;
    (void)send_resp(n, d);
}

/* ---- block upload ---- */

static void block_upload_initiate(co_node_t *n, const co_od_entry_t *e, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint16_t index = co_get_u16(&r[1]);
    uint8_t sub = r[3];
    uint8_t blksize = r[4];
    uint8_t pst = r[5];
    if (blksize == 0u || blksize > SDO_MAX_BLKSIZE) {
        abort_transfer(n, index, sub, CO_SDO_AB_BLKSIZE);
        return;
    }
    start_transfer(s, e, index, sub);
    uint32_t ab = prepare_upload(n, e);
    if (ab != 0u) {
        abort_transfer(n, index, sub, ab);
        return;
    }
    if (pst != 0u && s->size <= pst) {
        /* protocol switch threshold: the client accepts a normal upload for small data */
        upload_initiate(n, e, index, sub);
        return;
    }
    s->blksize = blksize;
    s->crc_on = (r[0] & 0x04u) != 0u;
    s->crc = 0u;
    s->crc_pos = 0u;
    s->block_start = 0u;
    s->seqno = 0u;
    s->last_sent = false;
    uint8_t d[8];
    mux(d, 0xC6u, s); /* scs 6, sc (CRC), s (size indicated) */
    co_put_u32(&d[4], s->size);
    s->state = SDO_BUL_INIT;
    (void)send_resp(n, d);
}

/* Send segments of the current sub-block while the CAN driver accepts them. */
static void block_upload_send(co_node_t *n)
{
    co_sdo_t *s = &n->sdo;
    while (s->state == SDO_BUL_SEND && s->seqno < s->blksize && !s->last_sent) {
        uint32_t left = s->size - s->offset;
        uint32_t len = left > 7u ? 7u : left;
        uint8_t d[8] = {0};
        uint32_t ab = src_read(n, s->offset, &d[1], len);
        if (ab != 0u) {
            abort_transfer(n, s->index, s->sub, ab);
            return;
        }
        d[0] = (uint8_t)(s->seqno + 1u);
        bool last = (s->offset + len >= s->size);
        if (last) {
            d[0] |= 0x80u;
        }
        if (!co_node_send(n, (uint16_t)(0x580u + n->cfg.node_id), d, 8u)) {
            return; /* driver queue full: continue in co_sdo_process */
        }
        if (s->offset == s->crc_pos) { /* first transmission of these bytes */
            s->crc = co_sdo_crc16(s->crc, &d[1], len);
            s->crc_pos += len;
        }
        s->offset += len;
        s->seqno++;
        if (last) {
            s->last_sent = true;
            s->last_bytes = (uint8_t)len;
        }
    }
    if (s->state == SDO_BUL_SEND) {
        s->state = SDO_BUL_ACK;
    }
}

static void block_upload_ack(co_node_t *n, const uint8_t *r)
{
    co_sdo_t *s = &n->sdo;
    uint8_t ackseq = r[1];
    uint8_t blksize = r[2];
    if ((r[0] & 0x03u) != 0x02u) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_CMD);
        return;
    }
    if (ackseq > s->seqno) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_SEQNO);
        return;
    }
    if (blksize == 0u || blksize > SDO_MAX_BLKSIZE) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_BLKSIZE);
        return;
    }
    if (ackseq == s->seqno && s->last_sent) {
        uint8_t d[8] = {(uint8_t)(0xC1u | ((7u - s->last_bytes) << 2)), 0, 0, 0, 0, 0, 0, 0};
        co_put_u16(&d[1], s->crc_on ? s->crc : 0u);
        s->state = SDO_BUL_END;
        (void)send_resp(n, d);
        return;
    }
    /* continue after the last confirmed segment (retransmits the rest if ackseq < sent) */
    s->offset = s->block_start + 7u * (uint32_t)ackseq;
    s->block_start = s->offset;
    s->last_sent = false;
    s->seqno = 0u;
    s->blksize = blksize;
    s->state = SDO_BUL_SEND;
    block_upload_send(n);
}

/* ---- dispatch ---- */

static void handle_initiate(co_node_t *n, const uint8_t *r)
{
    uint16_t index = co_get_u16(&r[1]);
    uint8_t sub = r[3];
    uint8_t ccs = r[0] >> 5;
    const co_od_entry_t *e;
    switch (ccs) {
    case 1u: /* initiate download */
        e = initiate_lookup(n, index, sub);
        if (e != NULL) {
            download_initiate(n, e, r);
        }
        break;
    case 2u: /* initiate upload */
        e = initiate_lookup(n, index, sub);
        if (e != NULL) {
            upload_initiate(n, e, index, sub);
        }
        break;
    case 5u: /* block upload: only "initiate" starts a transfer */
        if ((r[0] & 0x03u) != 0x00u) {
            abort_transfer(n, index, sub, CO_SDO_AB_CMD);
            break;
        }
        e = initiate_lookup(n, index, sub);
        if (e != NULL) {
            block_upload_initiate(n, e, r);
        }
        break;
    case 6u: /* block download: only "initiate" starts a transfer */
        if ((r[0] & 0x01u) != 0x00u) {
            abort_transfer(n, index, sub, CO_SDO_AB_CMD);
            break;
        }
        e = initiate_lookup(n, index, sub);
        if (e != NULL) {
            block_download_initiate(n, e, r);
        }
        break;
    default:
        abort_transfer(n, index, sub, CO_SDO_AB_CMD);
        break;
    }
}

/* An exact repeat of the last request of a completed transfer, within the SDO timeout, that
 * completed a download or an upload's last segment (not an upload initiate: a read is
 * executed again). */
static bool is_replayable_repeat(const co_node_t *n, const uint8_t *r)
{
    const co_sdo_t *s = &n->sdo;
    uint32_t timeout = n->cfg.sdo_timeout_us != 0u ? n->cfg.sdo_timeout_us : 1000000u;
    if (!s->have_last || memcmp(r, s->last_req, 8u) != 0 ||
        (uint32_t)(n->now_us - s->last_resp_us) > timeout) {
        return false;
    }
    uint8_t ccs = r[0] >> 5;
    return ccs == 0u || ccs == 3u || (ccs == 1u && (r[0] & 0x02u)) || (ccs == 6u && (r[0] & 0x01u));
}

void co_sdo_rx(co_node_t *n, const co_frame_t *f)
{
    co_sdo_t *s = &n->sdo;
    if (f->len != 8u) {
        return; /* CiA 301: SDO frames have 8 bytes; others are ignored */
    }
    const uint8_t *r = f->data;
    uint8_t ccs = r[0] >> 5;
    s->last_us = n->now_us;
    if (s->state == SDO_BDL_SUB) {
        if (ccs == 4u && r[0] == 0x80u) {
            s->state = SDO_IDLE; /* client abort: no answer, and nothing to repeat */
            s->have_last = false;
            return;
        }
        block_download_segment(n, r);
        memcpy(s->last_req, r, 8u);
        return;
    }
    if (ccs == 4u) { /* abort from the client: drop the transfer, no answer */
        s->state = SDO_IDLE;
        s->have_last = false;
        return;
    }
    switch (s->state) {
    case SDO_DL_SEG:
        if (ccs == 0u) {
            download_segment(n, r);
            memcpy(s->last_req, r, 8u);
            return;
        }
        break;
    case SDO_UL_SEG:
        if (ccs == 3u) {
            upload_segment(n, r);
            memcpy(s->last_req, r, 8u);
            return;
        }
        break;
    case SDO_BDL_END:
        if (ccs == 6u) {
            block_download_end(n, r);
            memcpy(s->last_req, r, 8u);
            return;
        }
        break;
    case SDO_BUL_INIT:
        if (ccs == 5u && (r[0] & 0x03u) == 0x03u) {
            s->state = SDO_BUL_SEND;
            block_upload_send(n);
            return;
        }
        break;
    case SDO_BUL_SEND:
    case SDO_BUL_ACK:
        if (ccs == 5u && (r[0] & 0x03u) == 0x02u) {
            block_upload_ack(n, r);
            return;
        }
        break;
    case SDO_BUL_END:
        if (ccs == 5u && (r[0] & 0x03u) == 0x01u) {
            s->state = SDO_IDLE; /* transfer confirmed */
            return;
        }
        break;
    default:
        break;
    }
    if (s->state != SDO_IDLE && ccs != 1u && ccs != 2u && ccs != 5u && ccs != 6u) {
        /* a request that does not belong to the running transfer */
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_CMD);
        return;
    }
    if (s->state == SDO_IDLE && is_replayable_repeat(n, r)) {
        (void)co_node_send(n, s->last_resp.id, s->last_resp.data, 8u); /* see the header */
        return;
    }
    if (s->state == SDO_IDLE && (ccs == 0u || ccs == 3u)) {
        /* a segment with no transfer in progress: its bytes 1-3 are data, not a
         * multiplexer; the abort names the last transfer's object (as CANopenNode) */
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_CMD);
        return;
    }
    /* a new initiate replaces whatever transfer was in progress */
    s->state = SDO_IDLE;
    handle_initiate(n, r);
    memcpy(s->last_req, r, 8u);
}

void co_sdo_process(co_node_t *n)
{
    co_sdo_t *s = &n->sdo;
    if (s->state == SDO_IDLE) {
        return;
    }
    if (s->state == SDO_BUL_SEND) {
        block_upload_send(n);
    }
    uint32_t timeout = n->cfg.sdo_timeout_us != 0u ? n->cfg.sdo_timeout_us : 1000000u;
    if (s->state == SDO_BUL_ACK) {
        /* the client has up to 127 segments to take in before it can confirm them: allow
         * 100 ms per segment on top (a slow client on a bus without bit rate, e.g. vcan in
         * an emulated guest, takes several ms per frame). A new request from the client
         * replaces the transfer at any time, so waiting long blocks nobody. */
        timeout += 100000u * s->seqno;
    }
    if ((uint32_t)(n->now_us - s->last_us) > timeout) {
        abort_transfer(n, s->index, s->sub, CO_SDO_AB_TIMEOUT);
    }
}
