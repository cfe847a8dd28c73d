/*
 * main.c - the drive on an STM32F405 (Cortex-M4F) as a processor-in-the-loop target:
 * the same drive core (core/) and CANopen node (canopen/) as drive_sim, with the simulated
 * plant (plant/) compiled into the control interrupt, and an SLCAN (Lawicel) link on
 * USART1 instead of a CAN controller. Runs on QEMU's netduinoplus2 (port/mcu/pil_run.py).
 *
 * Control interrupt: SysTick at fs (168 MHz / PIL_SYSTICK_CYCLES): measure the plant ->
 *   drv_step -> advance the plant (sim_step, as drive_sim). As in drive_sim's default
 *   free-run mode the plant only advances while a run is settling or recording
 *   (PIL_HOLD_IDLE 1): simulated time holds in between, so a sequence of runs gives the
 *   same samples whatever the host's timing between them (the determinism check compares
 *   them with drive_sim's bit for bit). Build with -DPIL_HOLD_IDLE=0 for a control loop
 *   that steps at every tick, as on a real drive.
 * Main loop: drv_background (the statistics' sums, with the control interrupt enabled: it
 *   only takes blocks the interrupt has handed over); bytes from the UART receive ring ->
 *   SLCAN parser -> co_node_rx; replies and
 *   the node's frames -> transmit ring -> UART; co_node_process with the tick time; WFI
 *   when there is nothing to do. co_node_rx / co_node_process run with the control
 *   interrupt masked (BASEPRI), as docs/porting.md asks of every port; the UART interrupt
 *   stays enabled above it, so no received byte waits for CANopen work.
 * No heap: every buffer is static; the plant's configuration is compiled in
 *   (build/mcu/pil_config.h, generated from configs/pil.yaml by port/mcu/cfggen).
 */
#include <stdatomic.h> /* atomic_signal_fence: compiler barrier only */
#include <stdbool.h>
#include <stdint.h>
#include <string.h>

#include "co_node.h"
#include "mcu_hw.h"
#include "pil_config.h"
#include "sim.h"
#include "slcan.h"
#include "uart.h"

#ifndef PIL_HOLD_IDLE
#define PIL_HOLD_IDLE 1
#endif

#define PIL_BAUD 115200u
#define PIL_TXQ 2048u /* power of two */
/* Room the SDO server's frames leave free in the transmit ring: an SDO block upload fills
 * the ring in one co_node_process call (back-pressure), and the heartbeat, TPDOs and EMCY
 * that follow in the same call must still fit (as on a CAN bus, where they find a gap). */
#define PIL_TXQ_RESERVE 128u
/* a partial SLCAN line older than this is dropped (the sender went away mid-line) */
#define PIL_PARTIAL_LINE_US 1000000u

/* State the debugger (and tests through gdb, if wanted) can read: counters only. */
typedef struct {
    volatile uint32_t ticks;      /* control interrupts */
    volatile uint32_t steps;      /* plant + drive steps */
    volatile uint32_t overruns;   /* a control interrupt that lasted longer than 1/fs */
    uint32_t tx_queue_full;       /* node frames refused (back-pressure) */
    uint32_t tx_closed_dropped;   /* node frames while the SLCAN channel was closed */
    uint32_t reply_dropped;       /* SLCAN replies that found the transmit ring full */
    uint32_t boot_error;          /* sim_init refused the compiled-in configuration */
    uint32_t bg_in_isr;           /* statistics blocks taken in the control interrupt (catch-up) */
} pil_stats_t;

typedef struct {
    uint8_t buf[PIL_TXQ];
    uint32_t head, tail; /* main loop only */
} pil_txq_t;

static sim_t g_sim;
static float g_rec[PIL_REC_CAPACITY];
static float g_table[PIL_TABLE_CAPACITY];
static co_node_t g_node;
static uart_t g_uart;
static slcan_t g_slcan;
static pil_txq_t g_txq;
static bool g_tx_refused;
/* the main loop is inside drv_background: the control interrupt must not catch up then */
static volatile bool g_bg_active;
pil_stats_t pil_stats;

/* ---- transmit ring (main loop only) ---- */

static uint32_t txq_free(const pil_txq_t *q)
{
    return PIL_TXQ - (q->head - q->tail);
}

static bool txq_put(pil_txq_t *q, const char *text, size_t n)
{
    if (n > txq_free(q)) {
        return false;
    }
    for (size_t i = 0; i < n; i++) {
        q->buf[(q->head + i) & (PIL_TXQ - 1u)] = (uint8_t)text[i];
    }
    q->head += (uint32_t)n;
    return true;
}

static void txq_drain(pil_txq_t *q)
{
    while (q->tail != q->head && uart_try_write(q->buf[q->tail & (PIL_TXQ - 1u)])) {
        q->tail++;
    }
}

/* ---- time: control ticks -> microseconds (wraps at 2^32 us as co_node expects) ---- */

static uint32_t pil_now_us(void)
{
    return (uint32_t)((uint64_t)pil_stats.ticks * (uint64_t)PIL_SYSTICK_CYCLES / (MCU_CPU_HZ / 1000000u));
}

/* ---- CANopen critical sections: the control interrupt masked ---- */

static void pil_lock(void)
{
    mcu_set_basepri(MCU_PRIO_CONTROL);
}

static void pil_unlock(void)
{
    mcu_set_basepri(0u);
}

/* ---- CANopen hooks ---- */

static bool pil_tx(void *ctx, const co_frame_t *f)
{
    (void)ctx;
    if (!g_slcan.open) {
        pil_stats.tx_closed_dropped++; /* no adapter on the bus: the frame goes nowhere */
        return true;
    }
    slcan_frame_t sf;
    memset(&sf, 0, sizeof sf);
    sf.id = f->id;
    sf.len = f->len;
    memcpy(sf.data, f->data, f->len <= 8u ? f->len : 8u);
    char text[SLCAN_FRAME_TEXT_MAX];
    size_t n = slcan_encode(&sf, text, sizeof text);
    if (n == 0u) {
        return true; /* not a valid frame: nothing to send */
    }
    uint32_t reserve = (f->id == 0x580u + PIL_NODE_ID) ? PIL_TXQ_RESERVE : 0u;
    if (n + reserve > txq_free(&g_txq) || !txq_put(&g_txq, text, n)) {
        pil_stats.tx_queue_full++;
        g_tx_refused = true;
        return false;
    }
    return true;
}

static bool pil_sim_get(void *ctx, drv_param_id_t id, float *value)
{
    (void)ctx;
    return sim_get_f32(&g_sim, id, value) == DRV_OK;
}

static void pil_reset_app(void *ctx)
{
    /* NMT reset node: the drive and the plant start again from the configuration
     * (called inside co_node_rx, so the control interrupt is masked) */
    (void)ctx;
    char err[4];
    if (sim_init(&g_sim, &pil_config, g_rec, g_table, err, sizeof err) != 0) {
        pil_stats.boot_error = 1u;
    }
}

/* ---- interrupts ---- */

void mcu_systick_handler(void)
{
    (void)MCU_SYST_CSR; /* reading clears COUNTFLAG */
    pil_stats.ticks++;
    if (PIL_HOLD_IDLE && !co_node_run_active(&g_node)) {
        return;
    }
    (void)sim_step(&g_sim);
    pil_stats.steps++;
    /* Under host load qemu can run this interrupt back to back (each one longer than a tick
     * in host time) and the main loop never gets to drv_background: then take the waiting
     * statistics block here, so the run's statistics stay valid (the same operations in
     * the same order; the main loop is not inside drv_background, so nothing overlaps). */
    if (!g_bg_active && drv_background_catch_up(sim_drv(&g_sim))) {
        pil_stats.bg_in_isr++;
    }
    if (MCU_SYST_CSR & MCU_SYST_CSR_COUNTFLAG) {
        pil_stats.overruns++; /* the counter wrapped while this step ran */
    }
}

void mcu_usart1_handler(void)
{
    uart_irq(&g_uart);
}

/* ---- the link: SLCAN bytes -> frames for the node ---- */

static void pil_link_rx(void)
{
    static uint32_t last_byte_us;
    uint8_t b;
    for (int budget = 0; budget < 64 && uart_read(&g_uart, &b); budget++) {
        slcan_frame_t sf;
        char reply[SLCAN_REPLY_MAX];
        size_t reply_len;
        last_byte_us = pil_now_us();
        slcan_event_t ev = slcan_feed(&g_slcan, b, &sf, reply, &reply_len);
        if (ev == SLCAN_NONE) {
            continue;
        }
        if (reply_len > 0u && !txq_put(&g_txq, reply, reply_len)) {
            pil_stats.reply_dropped++;
        }
        if (ev == SLCAN_FRAME && !sf.ext && !sf.rtr) { /* CANopen: 11-bit data frames */
            co_frame_t cf;
            cf.id = (uint16_t)sf.id;
            cf.len = sf.len;
            memcpy(cf.data, sf.data, sizeof cf.data);
            pil_lock();
            co_node_rx(&g_node, &cf);
            pil_unlock();
        }
        txq_drain(&g_txq);
    }
    if ((g_slcan.len != 0u || g_slcan.overlong) && pil_now_us() - last_byte_us > PIL_PARTIAL_LINE_US) {
        slcan_drop_partial(&g_slcan);
    }
}

int mcu_main(void)
{
    char err[4];
    if (sim_init(&g_sim, &pil_config, g_rec, g_table, err, sizeof err) != 0) {
        pil_stats.boot_error = 1u; /* cfggen checked the configuration on the host: not reached */
        for (;;) {
            mcu_wfi();
        }
    }
    slcan_init(&g_slcan);
    uart_init(&g_uart, PIL_BAUD);

    co_cfg_t cc;
    memset(&cc, 0, sizeof cc);
    cc.node_id = (uint8_t)PIL_NODE_ID;
    cc.tx = pil_tx;
    cc.sim_get = pil_sim_get;
    cc.reset_app = pil_reset_app;
    cc.table_capacity_bytes = PIL_TABLE_CAPACITY * 4u;
    co_node_init(&g_node, &cc, sim_drv(&g_sim), 0u);

    MCU_SCB_SHPR3 = (MCU_SCB_SHPR3 & 0x00FFFFFFu) | (MCU_PRIO_CONTROL << 24);
    MCU_SYST_RVR = PIL_SYSTICK_CYCLES - 1u;
    MCU_SYST_CVR = 0u;
    MCU_SYST_CSR = MCU_SYST_CSR_CLKSOURCE | MCU_SYST_CSR_TICKINT | MCU_SYST_CSR_ENABLE;

    uint32_t last_tick = 0u;
    for (;;) {
        g_bg_active = true;
        atomic_signal_fence(memory_order_seq_cst);
        drv_background(sim_drv(&g_sim));
        atomic_signal_fence(memory_order_seq_cst);
        g_bg_active = false;
        pil_link_rx();
        g_tx_refused = false;
        pil_lock();
        co_node_process(&g_node, pil_now_us());
        pil_unlock();
        txq_drain(&g_txq);
        /* sleep until the next interrupt unless there is work: received bytes, unsent
         * text, or a block upload that stopped at a full transmit ring */
        mcu_irq_disable();
        if (uart_rx_pending(&g_uart) == 0u && g_txq.head == g_txq.tail && !g_tx_refused &&
            pil_stats.ticks == last_tick) {
            mcu_wfi();
        }
        mcu_irq_enable();
        last_tick = pil_stats.ticks;
    }
}
