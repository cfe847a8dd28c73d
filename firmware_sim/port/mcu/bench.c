/*
 * bench.c - instructions per drive step on the Cortex-M4F, counted by QEMU's -icount:
 * every instruction takes 2^shift ns of virtual time and SysTick counts that time at
 * 168 MHz, so instructions = SysTick ticks / (0.168 * 2^shift). tests/bench/bench_mcu.py
 * runs this under qemu-system-arm and converts; the x86 figure beside it is callgrind's
 * count of the same workload (firmware_sim/tests/bench_fw.c instr).
 *
 * Workloads (as bench_fw instr): drv_step alone (controller with every feed-forward term
 * on: Coulomb, asymmetry, position, viscous + generator + recorder of 3
 * signals, no plant) with a 64- and a 1024-sample table and with the sine generator,
 * counted over the loop bench_drive_steps (so the loop's call and feedback are included,
 * as in bench_fw's "benchmark loop" figure); the sine with the harmonic statistics on
 * (K = 8 of 3 signals, power of 1), drv_step timed alone per step with drv_background
 * between steps outside the timed region (as bench_fw's drv_step-alone figure), and the
 * background per step;
 * then the processor-in-the-loop interrupt's work (sim_step: the double-precision plant in
 * software floating point + drv_step) per step over a sine run of the PIL configuration.
 * Output on USART1 (the serial console), one line per figure; exit by semihosting.
 */
#include <stdint.h>
#include <string.h>

#include "drv.h"
#include "mcu_hw.h"
#include "pil_config.h"
#include "sim.h"
#include "uart.h"

#define BENCH_STEPS 4000u
#define BENCH_TABLE 1024u /* RAM: 3 signals x (4000 + 2048) samples, table + staging, sim_t fit 128 KiB */

static float g_rec[(BENCH_STEPS + 2048u) * 3u]; /* also the sine: period 2048 */
static float g_tab[BENCH_TABLE];
static float g_stage[BENCH_TABLE];
static sim_t g_sim;
static drv_t g_bench_drv;
static uart_t g_uart;

void mcu_systick_handler(void)
{
}

void mcu_usart1_handler(void)
{
    uart_irq(&g_uart);
}

static void put(const char *s)
{
    while (*s) {
        while (!uart_try_write((uint8_t)*s)) {
        }
        s++;
    }
}

static void put_u32(uint32_t v)
{
    char buf[11];
    int i = 10;
    buf[i] = '\0';
    do {
        buf[--i] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v != 0u);
    put(buf + i);
}

/* SysTick as a free-running down-counter at the core clock (no interrupt) */
static void ticks_start(void)
{
    MCU_SYST_CSR = 0u;
    MCU_SYST_RVR = 0x00FFFFFFu;
    MCU_SYST_CVR = 0u;
    MCU_SYST_CSR = MCU_SYST_CSR_CLKSOURCE | MCU_SYST_CSR_ENABLE;
    (void)MCU_SYST_CSR; /* clear COUNTFLAG */
}

static inline uint32_t ticks_now(void)
{
    return MCU_SYST_CVR;
}

/* elapsed ticks between two reads of the down-counter (no wrap: checked by COUNTFLAG) */
static uint32_t ticks_since(uint32_t t0, uint32_t t1)
{
    return (t0 - t1) & 0x00FFFFFFu;
}

__attribute__((noinline)) void bench_drive_steps(drv_t *drv, uint32_t n);
__attribute__((noinline)) void bench_drive_steps(drv_t *drv, uint32_t n)
{
    drv_meas_t m = {0.001f, 0.002f};
    for (uint32_t i = 0; i < n; i++) {
        float u = drv_step(drv, &m);
        m.motor_angle_rad += 1e-4f * u; /* keep the data moving, no plant */
    }
}

static void report(const char *what, uint32_t ticks, uint32_t steps, int wrapped)
{
    put("BENCH ");
    put(what);
    put(" ticks ");
    put_u32(ticks);
    put(" steps ");
    put_u32(steps);
    put(wrapped ? " WRAPPED\n" : "\n");
}

/* drv_step alone: as bench_fw instr (table LEN or sine) */
static void bench_drive(const char *what, uint32_t table_len)
{
    drv_t *const drvp = &g_bench_drv; /* one drive for the drv_step workloads (RAM) */
    drv_storage_t st = {g_rec, (uint32_t)(sizeof g_rec / sizeof g_rec[0]), g_tab, BENCH_TABLE, 2560.0f, g_stage};
    if (drv_init(drvp, &st) != DRV_OK) {
        put("BENCH error drv_init\n");
        return;
    }
    drv_enable(drvp, true);
    (void)drv_set_f32(drvp, DRV_P_KFC, 0.1f);
    (void)drv_set_f32(drvp, DRV_P_KV, 0.01f);
    (void)drv_set_f32(drvp, DRV_P_KFA, 0.02f); /* every feed-forward term on (issue 35) */
    (void)drv_set_f32(drvp, DRV_P_KPS, 0.03f);
    (void)drv_set_f32(drvp, DRV_P_KPC, -0.01f);
    (void)drv_set_u32(drvp, DRV_P_REC_SIGNALS, 0x07u);
    (void)drv_set_f32(drvp, DRV_P_EXC_AMPLITUDE, 0.5f);
    uint32_t period = table_len ? table_len : 2048u;
    if (table_len) {
        for (uint32_t i = 0; i < table_len; i++) {
            g_tab[i] = (float)(i % 97u) * 0.01f - 0.4f;
        }
        if (drv_table_write(drvp, 0u, (const uint8_t *)g_tab, table_len * 4u) != DRV_OK ||
            drv_table_commit(drvp, table_len * 4u) != DRV_OK) {
            put("BENCH error table\n");
            return;
        }
    }
    (void)drv_set_u32(drvp, DRV_P_EXC_KIND, table_len ? DRV_EXC_TABLE : DRV_EXC_SINE);
    (void)drv_set_u32(drvp, DRV_P_EXC_PERIOD, period);
    (void)drv_set_u32(drvp, DRV_P_EXC_SETTLE_PERIODS, 0u);
    (void)drv_set_u32(drvp, DRV_P_EXC_RECORD_PERIODS, BENCH_STEPS / period + 1u);
    if (drv_run_start(drvp) != DRV_OK) {
        put("BENCH error run refused\n");
        return;
    }
    ticks_start();
    uint32_t t0 = ticks_now();
    bench_drive_steps(drvp, BENCH_STEPS);
    uint32_t t1 = ticks_now();
    int wrapped = (MCU_SYST_CSR & MCU_SYST_CSR_COUNTFLAG) != 0u;
    uint32_t state = 0u;
    (void)drv_get_u32(drvp, DRV_P_RUN_STATE, &state);
    if (state != DRV_RUN_RECORDING) {
        put("BENCH error run not recording through the measured steps\n");
        return;
    }
    report(what, ticks_since(t0, t1), BENCH_STEPS, wrapped);
}

/* drv_step with the harmonic statistics on, drv_background between steps (the main loop);
 * each timed alone per call, the counter reads' own cost subtracted */
static void bench_drive_stats(void)
{
    drv_t *const drvp = &g_bench_drv; /* one drive for the drv_step workloads (RAM) */
    drv_storage_t st = {g_rec, (uint32_t)(sizeof g_rec / sizeof g_rec[0]), g_tab, BENCH_TABLE, 2560.0f, g_stage};
    if (drv_init(drvp, &st) != DRV_OK) {
        put("BENCH error drv_init\n");
        return;
    }
    drv_enable(drvp, true);
    (void)drv_set_f32(drvp, DRV_P_KFC, 0.1f);
    (void)drv_set_f32(drvp, DRV_P_KV, 0.01f);
    (void)drv_set_f32(drvp, DRV_P_KFA, 0.02f); /* every feed-forward term on (issue 35) */
    (void)drv_set_f32(drvp, DRV_P_KPS, 0.03f);
    (void)drv_set_f32(drvp, DRV_P_KPC, -0.01f);
    (void)drv_set_u32(drvp, DRV_P_REC_SIGNALS, 0x07u);
    (void)drv_set_f32(drvp, DRV_P_EXC_AMPLITUDE, 0.5f);
    (void)drv_set_u32(drvp, DRV_P_EXC_KIND, DRV_EXC_SINE);
    (void)drv_set_u32(drvp, DRV_P_EXC_PERIOD, 2048u);
    (void)drv_set_u32(drvp, DRV_P_EXC_SETTLE_PERIODS, 0u);
    (void)drv_set_u32(drvp, DRV_P_EXC_RECORD_PERIODS, BENCH_STEPS / 2048u + 1u);
    if (drv_set_u32(drvp, DRV_P_STAT_HARMONICS, 8u) != DRV_OK ||
        drv_set_u32(drvp, DRV_P_STAT_SIGNALS, DRV_SIG_REFERENCE | DRV_SIG_PLANT_INPUT | DRV_SIG_MOTOR_ANGLE) != DRV_OK ||
        drv_set_u32(drvp, DRV_P_STAT_POWER, DRV_SIG_ERROR) != DRV_OK || drv_run_start(drvp) != DRV_OK) {
        put("BENCH error statistics run refused\n");
        return;
    }
    /* one free-running count over all steps (no reset per step, so the 1-tick reading
     * granularity, ~6 instructions, averages out); the same number of empty read pairs
     * measures the reads' own cost */
    ticks_start();
    uint32_t read_total = 0u, step_total = 0u, bg_total = 0u;
    for (uint32_t i = 0; i < BENCH_STEPS; i++) {
        uint32_t t0 = ticks_now();
        uint32_t t1 = ticks_now();
        read_total += ticks_since(t0, t1);
    }
    drv_meas_t m = {0.001f, 0.002f};
    for (uint32_t i = 0; i < BENCH_STEPS; i++) {
        uint32_t t0 = ticks_now();
        float u = drv_step(drvp, &m);
        uint32_t t1 = ticks_now();
        drv_background(drvp);
        uint32_t t2 = ticks_now();
        step_total += ticks_since(t0, t1);
        bg_total += ticks_since(t1, t2);
        m.motor_angle_rad += 1e-4f * u;
    }
    int wrapped = (MCU_SYST_CSR & MCU_SYST_CSR_COUNTFLAG) != 0u;
    step_total -= read_total;
    bg_total -= read_total;
    uint32_t state = 0u, periods = 0u, overruns = 0u;
    (void)drv_get_u32(drvp, DRV_P_RUN_STATE, &state);
    (void)drv_get_u32(drvp, DRV_P_STAT_PERIODS, &periods);
    (void)drv_get_u32(drvp, DRV_P_STAT_OVERRUNS, &overruns);
    if (state != DRV_RUN_RECORDING || overruns != 0u || periods != BENCH_STEPS / 2048u) {
        put("BENCH error statistics not accumulated through the measured steps\n");
        return;
    }
    report("drv_step_sine_stats", step_total, BENCH_STEPS, wrapped);
    report("background_sine_stats", bg_total, BENCH_STEPS, wrapped);
}

/* line statistics (lstat.h) of a recorded multisine period of N = BENCH_TABLE: the
 * background's drv_background after a run of two periods (3 real FFTs of N, LSTAT_LINES_MAX
 * lines); the second call is timed: period 1, the shifted data x_1 - x_0 and Welford, the
 * cost of every period after the base period 0 */
static void bench_lines(void)
{
    drv_t *const drvp = &g_bench_drv; /* one drive for the drv_step workloads (RAM) */
    drv_storage_t st = {g_rec, (uint32_t)(sizeof g_rec / sizeof g_rec[0]), g_tab, BENCH_TABLE, 2560.0f, g_stage};
    uint16_t bins[LSTAT_LINES_MAX];
    for (uint32_t i = 0; i < LSTAT_LINES_MAX; i++) {
        bins[i] = (uint16_t)(1u + i);
    }
    if (drv_init(drvp, &st) != DRV_OK) {
        put("BENCH error drv_init\n");
        return;
    }
    drv_enable(drvp, true);
    (void)drv_set_u32(drvp, DRV_P_REC_SIGNALS, 0x07u);
    (void)drv_set_u32(drvp, DRV_P_EXC_KIND, DRV_EXC_MULTISINE);
    (void)drv_set_u32(drvp, DRV_P_EXC_PERIOD, BENCH_TABLE);
    (void)drv_set_u32(drvp, DRV_P_MS_K_MIN, 1u);
    (void)drv_set_u32(drvp, DRV_P_MS_K_MAX, 100u);
    (void)drv_set_f32(drvp, DRV_P_EXC_AMPLITUDE, 0.3f);
    (void)drv_set_u32(drvp, DRV_P_EXC_SETTLE_PERIODS, 0u);
    (void)drv_set_u32(drvp, DRV_P_EXC_RECORD_PERIODS, 2u);
    if (drv_lines_write(drvp, 0u, (const uint8_t *)bins, sizeof bins) != DRV_OK ||
        drv_lines_commit(drvp, sizeof bins) != DRV_OK || drv_set_u32(drvp, DRV_P_STAT_LINE_MODE, 1u) != DRV_OK ||
        drv_run_start(drvp) != DRV_OK) {
        put("BENCH error line statistics run refused\n");
        return;
    }
    bench_drive_steps(drvp, 2u * BENCH_TABLE);
    drv_background(drvp); /* period 0: the base spectra */
    ticks_start();
    uint32_t t0 = ticks_now();
    drv_background(drvp);
    uint32_t t1 = ticks_now();
    int wrapped = (MCU_SYST_CSR & MCU_SYST_CSR_COUNTFLAG) != 0u;
    uint32_t periods = 0u;
    (void)drv_get_u32(drvp, DRV_P_STAT_LINE_PERIODS, &periods);
    if (periods != 2u) {
        put("BENCH error line statistics not computed\n");
        return;
    }
    report("lines_period_1024", ticks_since(t0, t1), 1u, wrapped);
    put("BENCH lines_count ");
    put_u32(LSTAT_LINES_MAX);
    put("\n");
}

/* the PIL interrupt's work per step: plant (software double) + drv_step; mean and max */
static void bench_closed_loop(void)
{
    char err[4];
    plant_config_t cfg = pil_config; /* the PIL plant and controller, in this program's buffers */
    cfg.rec_capacity = (uint32_t)(sizeof g_rec / sizeof g_rec[0]);
    cfg.table_capacity = BENCH_TABLE;
    if (sim_init(&g_sim, &cfg, g_rec, g_tab, err, sizeof err) != 0) {
        put("BENCH error sim_init\n");
        return;
    }
    drv_t *d = sim_drv(&g_sim);
    drv_enable(d, true);
    (void)drv_set_u32(d, DRV_P_EXC_KIND, DRV_EXC_SINE);
    (void)drv_set_u32(d, DRV_P_EXC_PERIOD, 2048u);
    (void)drv_set_u32(d, DRV_P_EXC_SINE_CYCLES, 1u);
    (void)drv_set_f32(d, DRV_P_EXC_AMPLITUDE, 0.5f);
    (void)drv_set_f32(d, DRV_P_KFC, 0.1157f);
    (void)drv_set_u32(d, DRV_P_EXC_SETTLE_PERIODS, 1u);
    (void)drv_set_u32(d, DRV_P_EXC_RECORD_PERIODS, 1u);
    (void)drv_set_u32(d, DRV_P_REC_SIGNALS, 0x17u);
    if (drv_run_start(d) != DRV_OK) {
        put("BENCH error closed-loop run refused\n");
        return;
    }
    /* overhead of one pair of counter reads, subtracted per step */
    ticks_start();
    uint32_t a = ticks_now();
    uint32_t b = ticks_now();
    uint32_t read_cost = ticks_since(a, b);
    uint32_t total = 0u, worst = 0u, n = 0u;
    for (; n < 4096u; n++) {
        ticks_start();
        uint32_t t0 = ticks_now();
        (void)sim_step(&g_sim);
        uint32_t t1 = ticks_now();
        uint32_t dt = ticks_since(t0, t1) - read_cost;
        total += dt;
        worst = dt > worst ? dt : worst;
    }
    report("closed_loop_total", total, n, 0);
    report("closed_loop_worst", worst, 1u, 0);
    uint32_t slow = (uint32_t)sim_plant(&g_sim)->slow_steps;
    put("BENCH closed_loop_slow_steps ");
    put_u32(slow);
    put("\n");
}

static void semihost_exit(void)
{
    static const uint32_t args[2] = {0x20026u, 0u}; /* ADP_Stopped_ApplicationExit, status 0 */
    register uint32_t r0 __asm("r0") = 0x20u;        /* SYS_EXIT_EXTENDED */
    register const uint32_t *r1 __asm("r1") = args;
    __asm volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
}

int mcu_main(void)
{
    uart_init(&g_uart, 115200u);
    bench_drive("drv_step_table_64", 64u);
    bench_drive("drv_step_table_1024", 1024u);
    bench_drive("drv_step_sine", 0u);
    bench_drive_stats();
    bench_lines();
    bench_closed_loop();
    put("BENCH done\n");
    semihost_exit();
    return 0;
}
