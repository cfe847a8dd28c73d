/*
 * co_node.h - the CANopen slave (CiA 301 NMT, heartbeat, SDO, PDO, EMCY + CiA 402 basics)
 * wrapped around the drive (drv.h).
 *
 * Deployable: no OS call, no heap, one state struct (co_node_t) passed explicitly.
 * The integrator (port/, or a drive MCU's main loop) provides:
 *   - a transmit hook (cfg.tx): hands one classic CAN frame to the CAN driver; returns false
 *     when the driver's queue is full (the node retries later; only SDO block upload uses
 *     this back-pressure, other frames are dropped and counted);
 *   - received frames: co_node_rx() for every frame on the bus (11-bit ids);
 *   - time: co_node_process(now_us) regularly (every 1 ms or faster) with a free-running
 *     microsecond counter (uint32 wrap-around is fine);
 */
#ifndef CO_NODE_H
#define CO_NODE_H

#include <stdbool.h>
#include <stdint.h>

#include "drv.h"
#include "od_table.h"

typedef struct {
    uint16_t id;  /* 11-bit CAN identifier */
    uint8_t len;  /* 0..8 */
    uint8_t data[8];
} co_frame_t;

typedef bool (*co_tx_fn)(void *ctx, const co_frame_t *frame);
/* Simulation-only objects (0x2100): value of a sim_only parameter; false if unknown. */
typedef bool (*co_sim_get_fn)(void *ctx, drv_param_id_t id, float *value);
/* NMT "reset node": re-initialise the application (drive parameters to defaults). */
typedef void (*co_reset_app_fn)(void *ctx);

typedef struct {
    uint8_t node_id; /* 1..127 */
    co_tx_fn tx;
    void *tx_ctx;
    co_sim_get_fn sim_get; /* may be NULL (deployable build) */
    void *sim_ctx;
    co_reset_app_fn reset_app; /* may be NULL */
    void *app_ctx;
    uint32_t sdo_timeout_us;       /* 0: 1 s */
    uint32_t table_capacity_bytes; /* waveform table (0x2002) size limit */
} co_cfg_t;

typedef enum {
    CO_NMT_INITIALISING = 0,
    CO_NMT_STOPPED = 4,
    CO_NMT_OPERATIONAL = 5,
    CO_NMT_PRE_OPERATIONAL = 127
} co_nmt_state_t;

/* 0x6007 abort connection option codes (CiA 402). */
enum {
    CO402_ABORT_NONE = 0,
    CO402_ABORT_FAULT = 1,
    CO402_ABORT_DISABLE_VOLTAGE = 2,
    CO402_ABORT_QUICK_STOP = 3
};

/* CiA 402 power states. */
typedef enum {
    CO402_NOT_READY = 0,
    CO402_SWITCH_ON_DISABLED,
    CO402_READY_TO_SWITCH_ON,
    CO402_SWITCHED_ON,
    CO402_OPERATION_ENABLED,
    CO402_QUICK_STOP_ACTIVE,
    CO402_FAULT_REACTION_ACTIVE,
    CO402_FAULT
} co402_state_t;

/* SDO abort codes (CiA 301). */
#define CO_SDO_AB_TOGGLE 0x05030000u
#define CO_SDO_AB_TIMEOUT 0x05040000u
#define CO_SDO_AB_CMD 0x05040001u
#define CO_SDO_AB_BLKSIZE 0x05040002u
#define CO_SDO_AB_SEQNO 0x05040003u
#define CO_SDO_AB_CRC 0x05040004u
#define CO_SDO_AB_UNSUPPORTED 0x06010000u
#define CO_SDO_AB_WRITEONLY 0x06010001u
#define CO_SDO_AB_READONLY 0x06010002u
#define CO_SDO_AB_NO_OBJECT 0x06020000u
#define CO_SDO_AB_NO_MAP 0x06040041u
#define CO_SDO_AB_MAP_LEN 0x06040042u
#define CO_SDO_AB_PARAM_INCOMPAT 0x06040043u
#define CO_SDO_AB_TYPE_MISMATCH 0x06070010u
#define CO_SDO_AB_DATA_LONG 0x06070012u
#define CO_SDO_AB_DATA_SHORT 0x06070013u
#define CO_SDO_AB_SUB_UNKNOWN 0x06090011u
#define CO_SDO_AB_INVALID_VALUE 0x06090030u
#define CO_SDO_AB_VALUE_HIGH 0x06090031u
#define CO_SDO_AB_VALUE_LOW 0x06090032u
#define CO_SDO_AB_GENERAL 0x08000000u
#define CO_SDO_AB_DATA_DEV_STATE 0x08000022u

/* EMCY error codes used. */
#define CO_EMCY_NO_ERROR 0x0000u
#define CO_EMCY_HEARTBEAT 0x8130u
#define CO_EMCY_PDO_LENGTH 0x8210u
#define CO_EMCY_RUN_FAULT 0xFF00u

/* Error register (0x1001) bits. */
#define CO_ERR_REG_GENERIC 0x01u
#define CO_ERR_REG_COMM 0x10u
#define CO_ERR_REG_MANUFACTURER 0x80u

#define CO_SDO_BUF 32u /* largest non-DOMAIN value (strings) */

typedef struct {
    uint8_t state;
    uint16_t index;
    uint8_t sub;
    const void *entry; /* const co_od_entry_t * */
    uint32_t size;     /* total bytes (0 if not indicated, download) */
    bool size_indicated;
    uint32_t generation; /* recorder upload: run counter when the transfer began */
    uint32_t offset;  /* bytes transferred so far */
    uint8_t toggle;
    uint8_t buf[CO_SDO_BUF]; /* non-DOMAIN values */
    uint32_t last_us;
    /* repeated-request handling (a client retry after a lost response) */
    uint8_t last_req[8];
    co_frame_t last_resp;
    bool have_last;
    uint32_t last_resp_us;
    /* block transfer */
    uint8_t blksize;
    uint8_t seqno;       /* download: last good seqno; upload: segments sent in this block */
    bool crc_on;
    uint16_t crc;
    uint32_t crc_pos;     /* upload: bytes covered by crc */
    uint32_t block_start; /* upload: offset at the start of this sub-block */
    bool last_sent;       /* upload: segment with c=1 sent in this sub-block */
    uint8_t last_bytes;   /* bytes in the final segment */
    uint8_t held[7];      /* download: last segment, written when the next one or the end arrives */
    bool have_held;
    bool got_last;
} co_sdo_t;

typedef struct {
    uint8_t data[8];
    uint8_t len;
    bool sent_once;
    bool force;
    uint32_t last_tx_us;
} co_tpdo_state_t;

typedef struct {
    bool active;      /* first heartbeat seen, monitoring */
    bool timed_out;
    uint32_t last_us;
} co_hb_consumer_t;

/* Heartbeat producer (0x1017) and consumers (0x1016): co_nmt.c. */
typedef struct {
    uint32_t producer_last_us;
    co_hb_consumer_t consumer[CO_NUM_HB_CONSUMERS > 0 ? CO_NUM_HB_CONSUMERS : 1];
} co_hb_t;

/* PDOs: co_pdo.c (their parameters live in co_od_ram_t, declared by od.yaml). */
typedef struct {
    co_tpdo_state_t tpdo[CO_NUM_TPDO > 0 ? CO_NUM_TPDO : 1];
    bool rpdo_length_error[CO_NUM_RPDO > 0 ? CO_NUM_RPDO : 1]; /* EMCY 0x8210 sent, not yet reset */
} co_pdo_t;

/* CiA 402 power state machine: co_402.c. */
typedef struct {
    co402_state_t state;
    bool cw_fault_reset_prev;
    bool fault_prev;
} co_402_t;

/* The node: one state struct per module (each with its init / process functions below),
 * the object values (ram) and the integrator's configuration. */
typedef struct co_node {
    co_cfg_t cfg;
    drv_t *drv;
    co_od_ram_t ram;
    co_nmt_state_t nmt;
    uint32_t now_us;
    bool time_valid;
    co_hb_t hb;
    co_sdo_t sdo;
    co_pdo_t pdo;
    co_402_t cia402;
    /* statistics */
    uint32_t tx_dropped;
    uint32_t rx_frames;
    uint32_t tx_frames;
    uint32_t emcy_count;
    uint16_t last_emcy_code;
} co_node_t;

/* co_node_init's refusal of its configuration (node id outside 1..127). */
#define CO_NODE_EINVAL (-1)

/* Initialise (drv already initialised) and send the boot-up message; enters PRE-OPERATIONAL.
 * Returns 0, or CO_NODE_EINVAL for a node id outside 1..127: then nothing is sent, the node
 * stays INITIALISING (co_node_rx ignores every frame but NMT) and must not be used. */
int co_node_init(co_node_t *n, const co_cfg_t *cfg, drv_t *drv, uint32_t now_us);
/* One received frame (any id; those not for this node are ignored). */
void co_node_rx(co_node_t *n, const co_frame_t *f);
/* Timers, SDO block upload progress, TPDO events, run-state monitoring. */
void co_node_process(co_node_t *n, uint32_t now_us);

/* ---- internal, shared between the co_* modules ---- */
bool co_node_send(co_node_t *n, uint16_t id, const uint8_t *data, uint8_t len);
bool co_node_run_active(const co_node_t *n);

/* co_od.c: typed access through the table (abort code, 0 = ok) */
const co_od_entry_t *co_od_lookup(uint16_t index, uint8_t sub, uint32_t *abort_code);
uint32_t co_od_read(co_node_t *n, const co_od_entry_t *e, uint8_t *dst, uint32_t cap, uint32_t *len);
uint32_t co_od_write(co_node_t *n, const co_od_entry_t *e, const uint8_t *src, uint32_t len);
uint32_t co_od_domain_size(co_node_t *n, const co_od_entry_t *e, uint32_t *size);
uint32_t co_od_domain_generation(co_node_t *n, const co_od_entry_t *e);
uint32_t co_od_domain_read(co_node_t *n, const co_od_entry_t *e, uint32_t off, uint8_t *dst, uint32_t len);
uint32_t co_od_domain_begin(co_node_t *n, const co_od_entry_t *e, uint32_t size, bool size_known);
uint32_t co_od_domain_write(co_node_t *n, const co_od_entry_t *e, uint32_t off, const uint8_t *src, uint32_t len);
uint32_t co_od_domain_commit(co_node_t *n, const co_od_entry_t *e, uint32_t total);
void co_od_reset_ram(co_node_t *n, uint16_t index_lo, uint16_t index_hi);
uint32_t co_od_abort_from_drv(drv_status_t st);

/* co_nmt.c */
void co_nmt_rx(co_node_t *n, const co_frame_t *f);
void co_nmt_set_state(co_node_t *n, co_nmt_state_t s);
void co_nmt_boot(co_node_t *n);
void co_hb_init(co_hb_t *hb, uint32_t now_us);
void co_hb_rx(co_node_t *n, const co_frame_t *f);
void co_hb_process(co_node_t *n);

/* co_sdo.c */
void co_sdo_init(co_sdo_t *s);
void co_sdo_rx(co_node_t *n, const co_frame_t *f);
void co_sdo_process(co_node_t *n);
uint16_t co_sdo_crc16(uint16_t crc, const uint8_t *data, uint32_t len); /* CRC-16 CCITT (XMODEM) */

/* co_pdo.c */
void co_pdo_init(co_pdo_t *pdo);
void co_pdo_rx(co_node_t *n, const co_frame_t *f);
void co_pdo_process(co_node_t *n);
void co_pdo_on_operational(co_node_t *n);

/* co_emcy.c */
void co_emcy_send(co_node_t *n, uint16_t code, uint8_t set_reg, uint8_t clear_reg,
                  const uint8_t mfr[5]);
/* A communication error went away: EMCY 0x0000, communication bit cleared if none remains. */
void co_emcy_reset_comm(co_node_t *n);

/* co_402.c */
void co_402_init(co_node_t *n);
void co_402_process(co_node_t *n);
void co_402_refresh(co_node_t *n);
void co_402_fault(co_node_t *n);
/* Connection to the master lost / ended (heartbeat, NMT): act per 0x6007. */
void co_402_abort_connection(co_node_t *n);

#endif /* CO_NODE_H */
