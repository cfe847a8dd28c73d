/*
 * fuzz_co_node.c - libFuzzer target: the CANopen node (canopen/co_*.c) with the real drive
 * core and the simulated plant behind it (plant/sim.h), driven by a sequence of operations
 * decoded from the fuzz input: received frames of every kind (NMT, SDO, heartbeat, PDO, any
 * id and length), timer ticks (co_node_process), controller steps and CAN driver
 * back-pressure. Built with -fsanitize=fuzzer,address,undefined (reliability.mk).
 *
 * Besides the sanitizers, these properties are checked after every operation (a violation
 * calls __builtin_trap, which libFuzzer reports as a crash):
 *   - every transmitted frame has len <= 8 and a COB-ID this node may send on;
 *   - after controller steps the plant input is finite and |u| <= u_max (the controller
 *     output stays saturated, whatever parameters were written or tables downloaded:
 *     "plant input finite");
 *   - when the host's heartbeat times out, no run is active afterwards (safe stop), and the
 *     drive is no longer OPERATION ENABLED unless 0x6007 says "no action" (issue 21).
 *
 * Input format: a stream of records, each an opcode byte followed by its operands (a
 * record cut short by the end of the input is ignored); fuzz/gen_seeds.py writes seeds:
 *   0 SDO request      8 data bytes                 -> id 0x600 + node, len 8
 *   1 any frame        id lo, id hi, len, 8 bytes    -> id & 0x7FF, len & 0x0F (may be > 8)
 *   2 NMT              command, node id              -> id 0x000, len 2
 *   3 heartbeat        node, state                   -> id 0x700 + (node & 0x7F), len 1
 *   4 time             lo, hi                        -> now += (lo | hi << 8) * 16 us; process
 *   5 steps            lo, hi                        -> (lo | hi << 8) controller steps (at
 *                                                       most 4 when no run is active; 512
 *                                                       per input); process
 *   6 back-pressure    flag                          -> bit 0: the transmit hook refuses
 *                                                       frames; bits 1..7: the background
 *                                                       schedule B (below)
 *   7 RPDO             which, len, 8 bytes           -> id 0x200 + 0x100 * (which & 3) + node
 * Opcodes are taken modulo 8.
 *
 * Background schedule (the way the MCU port's main loop can run, port/mcu/main.c: its
 * drv_background falls behind the control interrupt when the bus keeps it busy): B = 0 (the
 * start of every input) never calls drv_background, the background entirely behind (only the
 * readers' own catch-up, 0x2041 / 0x2043 uploads, computes anything); B >= 1 calls it after
 * every B-th controller step and once per time record (a main-loop turn between bus work),
 * so the background is anywhere from in step (B = 1, as drive_sim) to many periods behind
 * when the frames that follow change the configuration it reads (issue 21).
 *
 * Structure-aware mutation (LLVMFuzzerCustomMutator): half of the mutations are libFuzzer's
 * own; the other half walk the records and overwrite 4 bytes at a random place of the data
 * bytes of one frame record (SDO, any frame, RPDO) with a float from a list of values where
 * float arithmetic breaks (near +-FLT_MAX, 1e30, denormals, NaN, inf, the od.yaml limits),
 * or (an SDO record: its expedited value, bytes 4..7) with integers at the bounds the drive
 * checks (powers of two and neighbours: periods, bins, counts; one u32 or two u16, i.e. a
 * two-line list 0x2042). So table samples (in download segments) and amplitudes / gains (in
 * expedited writes) reach the overflow region, and periods / bins the index bounds, where
 * byte-level mutations almost never land (issue 21: libFuzzer's own mutations alone did not
 * reach the stale-list crash from the line-statistics seed in 200 000 executions).
 *
 * FUZZ_TRACE=1 in the environment prints every frame in and out (to check the seeds).
 */
#include <float.h>
#include <math.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "co_node.h"
#include "plant_config.h"
#include "sim.h"

#define FZ_NODE_ID 1u
#define FZ_REC_CAPACITY 16384u  /* float values: small, so that runs end quickly */
#define FZ_TABLE_CAPACITY 256u  /* samples */
#define FZ_MAX_STEPS 512u       /* controller steps per input (keeps executions fast) */

static float g_rec[FZ_REC_CAPACITY];
static float g_table[FZ_TABLE_CAPACITY];
static sim_t g_sim;
static co_node_t g_node;
static plant_config_t g_cfg;
static bool g_tx_full;
static uint32_t g_bg_every; /* background schedule B (op 6): 0 never, else every B-th step */
static uint32_t g_bg_count;
static bool g_trace;
static uint32_t g_now;

static void fz_check(bool ok, const char *what)
{
    if (!ok) {
        fprintf(stderr, "fuzz_co_node: property violated: %s\n", what);
        __builtin_trap();
    }
}

static void trace_frame(const char *dir, const co_frame_t *f)
{
    if (!g_trace) {
        return;
    }
    fprintf(stderr, "%10u %s %03X [%u]", (unsigned)g_now, dir, (unsigned)f->id, (unsigned)f->len);
    for (unsigned i = 0; i < f->len && i < 8u; i++) {
        fprintf(stderr, " %02X", f->data[i]);
    }
    fprintf(stderr, "\n");
}

static bool tx_hook(void *ctx, const co_frame_t *f)
{
    (void)ctx;
    fz_check(f->len <= 8u, "transmitted frame longer than 8 bytes");
    uint16_t id = f->id;
    /* CiA 301 restricted COB-IDs: only the node's own EMCY / SDO response / heartbeat may
     * appear there; TPDOs can be configured onto any other id */
    bool restricted = id <= 0x07Fu || (id >= 0x101u && id <= 0x180u) || (id >= 0x581u && id <= 0x5FFu) ||
                      (id >= 0x601u && id <= 0x67Fu) || (id >= 0x6E0u && id <= 0x6FFu) || id >= 0x701u;
    fz_check(id <= 0x7FFu, "11-bit identifier");
    fz_check(!restricted || id == 0x080u + FZ_NODE_ID || id == 0x580u + FZ_NODE_ID || id == 0x700u + FZ_NODE_ID,
             "frame sent on a restricted COB-ID this node does not own");
    if (g_tx_full) {
        return false;
    }
    trace_frame("tx", f);
    return true;
}

static bool sim_hook(void *ctx, drv_param_id_t id, float *value)
{
    (void)ctx;
    return sim_get_f32(&g_sim, id, value) == DRV_OK;
}

static void reset_hook(void *ctx)
{
    (void)ctx;
    char err[256];
    fz_check(sim_init(&g_sim, &g_cfg, g_rec, g_table, err, sizeof err) == 0, "sim_init on reset node");
}

/* After controller steps: the output of the last step respects the limit in force. (Right
 * after a write to u_max the monitor still shows the previous step's output.) */
static void check_output(void)
{
    drv_monitor_t mon;
    float u_max = 0.0f;
    drv_get_monitor(sim_drv(&g_sim), &mon);
    fz_check(drv_get_f32(sim_drv(&g_sim), DRV_P_U_MAX, &u_max) == DRV_OK, "u_max readable");
    fz_check(isfinite(mon.plant_input_v), "plant input finite");
    fz_check(fabsf(mon.plant_input_v) <= u_max * (1.0f + 1e-6f) + 1e-6f, "plant input saturated at u_max");
}

/* co_node_process, with the safe-stop property of the heartbeat consumer. */
static void process(void)
{
    bool was_timed_out[CO_NUM_HB_CONSUMERS];
    for (unsigned i = 0; i < CO_NUM_HB_CONSUMERS; i++) {
        was_timed_out[i] = g_node.hb.consumer[i].timed_out;
    }
    co_node_process(&g_node, g_now);
    for (unsigned i = 0; i < CO_NUM_HB_CONSUMERS; i++) {
        if (!was_timed_out[i] && g_node.hb.consumer[i].timed_out) {
            fz_check(!co_node_run_active(&g_node), "run still active after heartbeat loss");
            /* 0x6007 (abort connection option code) other than 0: the drive has left
             * OPERATION ENABLED (disabled, fault or quick stop) */
            fz_check(g_node.ram.abort_connection == 0 || g_node.cia402.state != CO402_OPERATION_ENABLED,
                     "drive still OPERATION ENABLED after heartbeat loss (0x6007 != 0)");
            uint32_t reason = 0;
            (void)drv_get_u32(sim_drv(&g_sim), DRV_P_RUN_LAST_ERROR, &reason);
            (void)reason;
        }
    }
}

static void rx(uint16_t id, uint8_t len, const uint8_t *data)
{
    co_frame_t f;
    f.id = id;
    f.len = len;
    memcpy(f.data, data, 8u);
    trace_frame("rx", &f);
    co_node_rx(&g_node, &f);
}

int LLVMFuzzerInitialize(int *argc, char ***argv)
{
    (void)argc;
    (void)argv;
    const char *t = getenv("FUZZ_TRACE");
    g_trace = t != NULL && t[0] == '1';
    plant_config_defaults(&g_cfg);
    g_cfg.rec_capacity = FZ_REC_CAPACITY;
    g_cfg.table_capacity = FZ_TABLE_CAPACITY;
    return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    char err[256];
    fz_check(sim_init(&g_sim, &g_cfg, g_rec, g_table, err, sizeof err) == 0, "sim_init");
    co_cfg_t cc;
    memset(&cc, 0, sizeof cc);
    cc.node_id = FZ_NODE_ID;
    cc.tx = tx_hook;
    cc.sim_get = sim_hook;
    cc.reset_app = reset_hook;
    cc.sdo_timeout_us = 500000u;
    cc.table_capacity_bytes = FZ_TABLE_CAPACITY * 4u;
    g_tx_full = false;
    g_bg_every = 0u;
    g_bg_count = 0u;
    g_now = 0xFFF00000u; /* wraps around during long inputs: the timers must not care */
    co_node_init(&g_node, &cc, sim_drv(&g_sim), g_now);

    uint32_t steps_left = FZ_MAX_STEPS;
    size_t p = 0;
    while (p < size) {
        uint8_t op = data[p++] & 7u;
        uint8_t d[8] = {0};
        switch (op) {
        case 0:
            if (size - p < 8) {
                return 0;
            }
            memcpy(d, &data[p], 8);
            p += 8;
            rx((uint16_t)(0x600u + FZ_NODE_ID), 8u, d);
            break;
        case 1: {
            if (size - p < 11) {
                return 0;
            }
            uint16_t id = (uint16_t)((data[p] | (data[p + 1] << 8)) & 0x7FFu);
            uint8_t len = data[p + 2] & 0x0Fu;
            memcpy(d, &data[p + 3], 8);
            p += 11;
            rx(id, len, d);
            break;
        }
        case 2:
            if (size - p < 2) {
                return 0;
            }
            d[0] = data[p];
            d[1] = data[p + 1];
            p += 2;
            rx(0x000u, 2u, d);
            break;
        case 3:
            if (size - p < 2) {
                return 0;
            }
            d[0] = data[p + 1];
            rx((uint16_t)(0x700u + (data[p] & 0x7Fu)), 1u, d);
            p += 2;
            break;
        case 4:
            if (size - p < 2) {
                return 0;
            }
            g_now += (uint32_t)(data[p] | (data[p + 1] << 8)) * 16u;
            p += 2;
            if (g_bg_every != 0u) {
                drv_background(sim_drv(&g_sim)); /* a main-loop turn */
            }
            process();
            break;
        case 5: {
            if (size - p < 2) {
                return 0;
            }
            /* controller steps: the run's steps, or (idle) a few holding steps as the
             * --realtime loop makes */
            uint32_t n = (uint32_t)(data[p] | (data[p + 1] << 8));
            p += 2;
            if (!co_node_run_active(&g_node) && n > 4u) {
                n = 4u;
            }
            bool stepped = false;
            while (n > 0 && steps_left > 0) {
                (void)sim_step(&g_sim);
                if (g_bg_every != 0u && ++g_bg_count % g_bg_every == 0u) {
                    drv_background(sim_drv(&g_sim));
                }
                stepped = true;
                n--;
                steps_left--;
            }
            if (stepped) {
                check_output();
            }
            process();
            break;
        }
        case 6:
            if (size - p < 1) {
                return 0;
            }
            g_tx_full = (data[p] & 1u) != 0u;
            g_bg_every = (uint32_t)(data[p] >> 1);
            p++;
            process();
            break;
        default: {
            if (size - p < 10) {
                return 0;
            }
            uint16_t id = (uint16_t)(0x200u + 0x100u * (data[p] & 3u) + FZ_NODE_ID);
            uint8_t len = data[p + 1] & 0x0Fu;
            memcpy(d, &data[p + 2], 8);
            p += 10;
            rx(id, len, d);
            break;
        }
        }
    }
    return 0;
}

/* ---- structure-aware mutator ---- */

size_t LLVMFuzzerMutate(uint8_t *data, size_t size, size_t max_size);

static const float FZ_EDGE_FLOATS[] = {
    FLT_MAX, -FLT_MAX, 3.0e38f, -3.0e38f, 1.7e38f, -1.7e38f, 1.0e30f, -1.0e30f, 1.0e20f,
    -1.0e20f, 1000.0f, -1000.0f, 999.99994f, 100000.0f, 1.0f, -1.0f, 0.0f, -0.0f, 1.0e-40f,
    -1.0e-40f, FLT_MIN, 1.0e-30f, INFINITY, -INFINITY, NAN,
};

/* Integers at and around the bounds the drive checks: powers of two (periods N, N/2, the
 * table and line capacities) and their neighbours, the u16 / u32 extremes. */
static const uint32_t FZ_EDGE_INTS[] = {
    0u, 1u, 2u, 3u, 4u, 5u, 7u, 8u, 9u, 15u, 16u, 17u, 31u, 32u, 33u, 40u, 63u, 64u, 65u, 100u,
    127u, 128u, 129u, 255u, 256u, 257u, 511u, 512u, 1023u, 1024u, 1025u, 2048u, 4095u, 4096u,
    8191u, 8192u, 8193u, 0x7FFFu, 0xFFFFu, 0x10000u, 0x7FFFFFFFu, 0xFFFFFFFFu,
};

/* Offset of the first data byte and the data length of the record at p (0 if none). */
static size_t fz_record_data(const uint8_t *data, size_t size, size_t p, size_t *len, size_t *next)
{
    static const uint8_t operands[8] = {8, 11, 2, 2, 2, 2, 1, 10};
    uint8_t op = data[p] & 7u;
    *next = p + 1u + operands[op];
    *len = 0;
    if (*next > size) {
        return 0;
    }
    switch (op) {
    case 0: *len = 8; return p + 1u;
    case 1: *len = 8; return p + 4u;
    case 7: *len = 8; return p + 3u;
    default: return 0;
    }
}

size_t LLVMFuzzerCustomMutator(uint8_t *data, size_t size, size_t max_size, unsigned int seed)
{
    uint32_t r = seed * 2654435761u + 12345u;
    if ((r & 1u) == 0u || size == 0u) {
        return LLVMFuzzerMutate(data, size, max_size);
    }
    /* count frame records, pick one */
    size_t count = 0, p = 0, next = 0, len = 0;
    while (p < size) {
        if (fz_record_data(data, size, p, &len, &next) != 0u) {
            count++;
        }
        p = next;
    }
    if (count == 0u) {
        return LLVMFuzzerMutate(data, size, max_size);
    }
    size_t pick = (r >> 1) % count;
    uint32_t r2 = r * 2246822519u + 3266489917u; /* a second draw */
    p = 0;
    while (p < size) {
        size_t at = fz_record_data(data, size, p, &len, &next);
        if (at != 0u && pick-- == 0u) {
            /* expedited SDO values sit at bytes 4..7, segment data at 1..7: any 4-byte
             * window of the 8 data bytes (also one straddling two samples) */
            size_t off = (r >> 8) % 5u;
            if ((r2 & 1u) == 0u) {
                float v = FZ_EDGE_FLOATS[(r >> 12) % (sizeof FZ_EDGE_FLOATS / sizeof FZ_EDGE_FLOATS[0])];
                memcpy(&data[at + off], &v, 4u); /* little-endian host, as the CAN payload */
            } else {
                /* integers where index checks break (periods, bins, counts, masks): one
                 * u32, or two u16 (a two-line list of an expedited 0x2042 download) */
                const size_t ni = sizeof FZ_EDGE_INTS / sizeof FZ_EDGE_INTS[0];
                uint32_t a = FZ_EDGE_INTS[(r2 >> 1) % ni], b = FZ_EDGE_INTS[(r2 >> 9) % ni];
                uint8_t w[4];
                if ((r2 >> 17) & 1u) {
                    w[0] = (uint8_t)a; w[1] = (uint8_t)(a >> 8); w[2] = (uint8_t)(a >> 16); w[3] = (uint8_t)(a >> 24);
                } else {
                    w[0] = (uint8_t)a; w[1] = (uint8_t)(a >> 8); w[2] = (uint8_t)b; w[3] = (uint8_t)(b >> 8);
                }
                memcpy(&data[at + (data[p] % 8u == 0u ? 4u : off)], w, 4u);
            }
            break;
        }
        p = next;
    }
    return size;
}
