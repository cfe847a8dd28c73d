/*
 * bench_fw.c - firmware_sim benchmarks (run by `make bench` through the core-bench rule
 * and by tests/bench/bench_firmware.py).
 *   bench_fw rate CONFIG          closed-loop steps/s: plant + drive, free run, median of 5
 *   bench_fw instr table LEN N    N drive steps (controller + generator + recorder, no
 *   bench_fw instr sine N         plant) inside bench_fw_drive_steps, for callgrind
 *   bench_fw instr sine-stats N   the sine with the harmonic statistics on (K = 8, 3 signals:
 *                                 reference, plant input, motor angle; power of the error)
 *   bench_fw lines N [L [P]]      P (1 or 2, default 1) recorded periods of a multisine run
 *                                 (N samples, r, u, y) through the line statistics (L lines
 *                                 1 .. L, default 128, at most LSTAT_LINES_MAX and N/2 - 1;
 *                                 core/lstat.h): the background's drv_background after the
 *                                 run, for callgrind --toggle-collect=lstat_process. Period 0
 *                                 is the base (X_0), period 1 a shifted one (x_1 - x_0): the
 *                                 difference of P = 2 and P = 1 is the cost of every later
 *                                 period
 *   bench_fw fft N                the per-period spectra of a multisine run's 3 signals:
 *                                 2 complex FFTs of N points (u + j y, r) inside bench_fw_fft
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "drv.h"
#include "fft.h"
#include "sim.h"

static double clock_s(clockid_t id)
{
    struct timespec ts;
    clock_gettime(id, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int cmp_d(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static void setup_sine_run(drv_t *drv, uint32_t periods)
{
    drv_enable(drv, true);
    (void)drv_set_u32(drv, DRV_P_EXC_KIND, DRV_EXC_SINE);
    (void)drv_set_u32(drv, DRV_P_EXC_PERIOD, 2560u);
    (void)drv_set_u32(drv, DRV_P_EXC_SINE_CYCLES, 1u);
    (void)drv_set_f32(drv, DRV_P_EXC_AMPLITUDE, 0.5f);
    (void)drv_set_u32(drv, DRV_P_EXC_SETTLE_PERIODS, periods);
    (void)drv_set_u32(drv, DRV_P_EXC_RECORD_PERIODS, 1u);
}

static int bench_rate(const char *cfg_path)
{
    char err[300];
    plant_config_t cfg;
    if (plant_config_load(cfg_path, &cfg, err, sizeof err) != 0) {
        fprintf(stderr, "bench_fw: %s\n", err);
        return 2;
    }
    const uint64_t steps = 2000000u;
    double rates[5], cpu_rates[5];
    for (int r = 0; r < 5; r++) {
        sim_t *sim = sim_new(&cfg, err, sizeof err);
        if (sim == NULL) {
            fprintf(stderr, "bench_fw: %s\n", err);
            return 2;
        }
        setup_sine_run(sim_drv(sim), 1000u);
        if (drv_run_start(sim_drv(sim)) != DRV_OK) {
            fprintf(stderr, "bench_fw: run refused\n");
            return 2;
        }
        double t0 = clock_s(CLOCK_MONOTONIC), c0 = clock_s(CLOCK_PROCESS_CPUTIME_ID);
        sim_run(sim, steps);
        double t1 = clock_s(CLOCK_MONOTONIC), c1 = clock_s(CLOCK_PROCESS_CPUTIME_ID);
        rates[r] = (double)steps / (t1 - t0);
        cpu_rates[r] = (double)steps / (c1 - c0);
        if (r == 0) {
            printf("plant: %llu stick/slip events in %llu steps; %llu steps on the RK4 sub-step path "
                   "(%u sub-steps), the rest exact ZOH steps\n",
                   (unsigned long long)sim_plant(sim)->events, (unsigned long long)steps,
                   (unsigned long long)sim_plant(sim)->slow_steps, (unsigned)cfg.plant.substeps);
        }
        sim_free(sim);
    }
    qsort(rates, 5, sizeof rates[0], cmp_d);
    qsort(cpu_rates, 5, sizeof cpu_rates[0], cmp_d);
    printf("closed-loop steps per CPU second (one core; plant + drive, sine reference, %s): "
           "median %.3g (min %.3g, max %.3g) over 5 x %llu steps\n",
           cfg_path, cpu_rates[2], cpu_rates[0], cpu_rates[4], (unsigned long long)steps);
    printf("closed-loop steps per wall second (depends on other load): median %.3g (min %.3g, max %.3g)\n",
           rates[2], rates[0], rates[4]);
    printf("RATE %.6g\n", cpu_rates[2]);
    return 0;
}

static float rec_buf[1u << 20];
static float tab_buf[8192];

/* The measured region for callgrind (--toggle-collect=bench_fw_drive_steps). */
__attribute__((noinline)) void bench_fw_drive_steps(drv_t *drv, uint32_t n);
__attribute__((noinline)) void bench_fw_drive_steps(drv_t *drv, uint32_t n)
{
    drv_meas_t m = {0.001f, 0.002f};
    for (uint32_t i = 0; i < n; i++) {
        float u = drv_step(drv, &m);
        m.motor_angle_rad += 1e-4f * u; /* keep the data moving, no plant */
    }
}

/* The same with the port's main-loop work between steps (drv_background: the statistics'
 * sums); callgrind counts drv_step (--toggle-collect=drv_step) and the background
 * (--toggle-collect=stat_process, per period: stat_period_end) separately. */
__attribute__((noinline)) void bench_fw_steps_and_background(drv_t *drv, uint32_t n);
__attribute__((noinline)) void bench_fw_steps_and_background(drv_t *drv, uint32_t n)
{
    drv_meas_t m = {0.001f, 0.002f};
    for (uint32_t i = 0; i < n; i++) {
        float u = drv_step(drv, &m);
        drv_background(drv);
        m.motor_angle_rad += 1e-4f * u;
    }
}

static int bench_instr(int argc, char **argv)
{
    drv_t drv;
    static float stage_buf[8192];
    drv_storage_t st = {rec_buf, (uint32_t)(sizeof rec_buf / sizeof rec_buf[0]), tab_buf, 8192u, 2560.0f, stage_buf};
    if (drv_init(&drv, &st) != DRV_OK) {
        return 2;
    }
    uint32_t n, len = 0u;
    int table = strcmp(argv[2], "table") == 0;
    int stats = strcmp(argv[2], "sine-stats") == 0;
    if (table && argc == 5) {
        len = (uint32_t)strtoul(argv[3], NULL, 10);
        n = (uint32_t)strtoul(argv[4], NULL, 10);
    } else if (!table && (stats || strcmp(argv[2], "sine") == 0) && argc == 4) {
        n = (uint32_t)strtoul(argv[3], NULL, 10);
    } else {
        fprintf(stderr, "usage: bench_fw instr table LEN N | bench_fw instr sine N | bench_fw instr sine-stats N\n");
        return 2;
    }
    drv_enable(&drv, true);
    (void)drv_set_f32(&drv, DRV_P_KFC, 0.1f);
    (void)drv_set_f32(&drv, DRV_P_KV, 0.01f);
    (void)drv_set_u32(&drv, DRV_P_REC_SIGNALS, 0x07u);
    (void)drv_set_f32(&drv, DRV_P_EXC_AMPLITUDE, 0.5f);
    uint32_t period = table ? len : 2048u;
    if (table) {
        for (uint32_t i = 0; i < len; i++) {
            tab_buf[i] = (float)(i % 97u) * 0.01f - 0.4f;
        }
        if (drv_table_write(&drv, 0u, (const uint8_t *)tab_buf, len * 4u) != DRV_OK ||
            drv_table_commit(&drv, len * 4u) != DRV_OK) {
            fprintf(stderr, "bench_fw: bad table length %u\n", (unsigned)len);
            return 2;
        }
    }
    (void)drv_set_u32(&drv, DRV_P_EXC_KIND, table ? DRV_EXC_TABLE : DRV_EXC_SINE);
    (void)drv_set_u32(&drv, DRV_P_EXC_PERIOD, period);
    (void)drv_set_u32(&drv, DRV_P_EXC_SETTLE_PERIODS, 0u);
    if (stats && (drv_set_u32(&drv, DRV_P_STAT_HARMONICS, STAT_K_MAX) != DRV_OK ||
                  drv_set_u32(&drv, DRV_P_STAT_SIGNALS, DRV_SIG_REFERENCE | DRV_SIG_PLANT_INPUT |
                                                          DRV_SIG_MOTOR_ANGLE) != DRV_OK ||
                  drv_set_u32(&drv, DRV_P_STAT_POWER, DRV_SIG_ERROR) != DRV_OK)) {
        fprintf(stderr, "bench_fw: statistics refused\n");
        return 2;
    }
    uint32_t rec_periods = (n + period - 1u) / period + 1u;
    if (drv_set_u32(&drv, DRV_P_EXC_RECORD_PERIODS, rec_periods) != DRV_OK) {
        fprintf(stderr, "bench_fw: %u steps need %u periods of %u: more than EXC_RECORD_PERIODS allows\n",
                (unsigned)n, (unsigned)rec_periods, (unsigned)period);
        return 2;
    }
    if (drv_run_start(&drv) != DRV_OK) {
        fprintf(stderr, "bench_fw: run refused (recorder %u floats)\n", (unsigned)st.rec_capacity);
        return 2;
    }
    if (stats) {
        bench_fw_steps_and_background(&drv, n);
    } else {
        bench_fw_drive_steps(&drv, n);
    }
    uint32_t state;
    (void)drv_get_u32(&drv, DRV_P_RUN_STATE, &state);
    printf("steps %u, run state %u\n", (unsigned)n, (unsigned)state);
    if (stats) {
        uint32_t periods, overruns;
        (void)drv_get_u32(&drv, DRV_P_STAT_PERIODS, &periods);
        (void)drv_get_u32(&drv, DRV_P_STAT_OVERRUNS, &overruns);
        printf("statistics: %u periods accumulated, %u background overruns\n", (unsigned)periods,
               (unsigned)overruns);
        if (overruns != 0u || periods != n / period) {
            fprintf(stderr, "bench_fw: the statistics were not accumulated (%u periods of %u, %u overruns)\n",
                    (unsigned)periods, (unsigned)(n / period), (unsigned)overruns);
            return 2;
        }
    }
    if (state != DRV_RUN_RECORDING) {
        fprintf(stderr, "bench_fw: the run was not recording through all measured steps\n");
        return 2;
    }
    return 0;
}

/* The measured region for callgrind (--toggle-collect=bench_fw_fft): one period's spectra
 * of 3 real signals, packed two per complex FFT (u + j y, r + j 0). */
static float fft_buf[2u * 2u * 8192u];
__attribute__((noinline)) int bench_fw_fft(float *a, uint32_t n);
__attribute__((noinline)) int bench_fw_fft(float *a, uint32_t n)
{
    return (fft_inverse_complex(a, n) && fft_inverse_complex(a + 2u * n, n)) ? 0 : 2;
}

static int bench_fft(uint32_t n)
{
    if (!fft_is_pow2(n) || n < 4u || n > 8192u) {
        fprintf(stderr, "bench_fw: fft N: a power of two in 4 .. 8192\n");
        return 2;
    }
    for (uint32_t i = 0; i < 4u * n; i++) {
        fft_buf[i] = (float)(i % 101u) * 0.01f - 0.5f;
    }
    int st = bench_fw_fft(fft_buf, n);
    printf("fft: 2 complex FFTs of %u points, status %d\n", (unsigned)n, st);
    return st;
}

static int bench_lines(uint32_t n, uint32_t nl, uint32_t np)
{
    static drv_t drv; /* about 80 kB with 1024 lines: not on the stack */
    static float stage_buf[8192];
    drv_storage_t st = {rec_buf, (uint32_t)(sizeof rec_buf / sizeof rec_buf[0]), tab_buf, 8192u, 2560.0f, stage_buf};
    if (!fft_is_pow2(n) || n < 512u || n > 8192u || nl < 1u || nl > LSTAT_LINES_MAX || 2u * nl >= n ||
        np < 1u || np > 2u || drv_init(&drv, &st) != DRV_OK) {
        fprintf(stderr, "bench_fw: lines N [L [P]]: N a power of two in 512 .. 8192, 1 <= L <= %u, L < N/2, "
                "P 1 or 2\n", (unsigned)LSTAT_LINES_MAX);
        return 2;
    }
    static uint16_t bins[LSTAT_LINES_MAX];
    for (uint32_t i = 0; i < nl; i++) {
        bins[i] = (uint16_t)(1u + i);
    }
    drv_enable(&drv, true);
    (void)drv_set_u32(&drv, DRV_P_REC_SIGNALS, 0x07u);
    (void)drv_set_u32(&drv, DRV_P_EXC_KIND, DRV_EXC_MULTISINE);
    (void)drv_set_u32(&drv, DRV_P_EXC_PERIOD, n);
    (void)drv_set_u32(&drv, DRV_P_MS_K_MIN, 1u);
    (void)drv_set_u32(&drv, DRV_P_MS_K_MAX, 100u);
    (void)drv_set_f32(&drv, DRV_P_EXC_AMPLITUDE, 0.3f);
    (void)drv_set_u32(&drv, DRV_P_EXC_SETTLE_PERIODS, 0u);
    (void)drv_set_u32(&drv, DRV_P_EXC_RECORD_PERIODS, np);
    if (drv_lines_write(&drv, 0u, (const uint8_t *)bins, 2u * nl) != DRV_OK ||
        drv_lines_commit(&drv, 2u * nl) != DRV_OK || drv_set_u32(&drv, DRV_P_STAT_LINE_MODE, 1u) != DRV_OK ||
        drv_run_start(&drv) != DRV_OK) {
        fprintf(stderr, "bench_fw: line statistics run refused\n");
        return 2;
    }
    bench_fw_drive_steps(&drv, np * n); /* records the periods; no background yet */
    for (uint32_t p = 0; p < np; p++) {
        drv_background(&drv); /* one period's spectra at the lines per call */
    }
    uint32_t periods = 0u;
    (void)drv_get_u32(&drv, DRV_P_STAT_LINE_PERIODS, &periods);
    printf("lines: N = %u, %u lines, %u period(s) accumulated; lstat_t %u bytes for LSTAT_LINES_MAX = %u lines: "
           "%u per line (accumulators %u + 2 x 2 of line list) + %u; drv_t %u bytes\n",
           (unsigned)n, (unsigned)nl, (unsigned)periods, (unsigned)sizeof(lstat_t), (unsigned)LSTAT_LINES_MAX,
           (unsigned)(sizeof(lstat_line_t) + 4u), (unsigned)sizeof(lstat_line_t),
           (unsigned)(sizeof(lstat_t) - (sizeof(lstat_line_t) + 4u) * LSTAT_LINES_MAX), (unsigned)sizeof(drv_t));
    return periods == np ? 0 : 2;
}

int main(int argc, char **argv)
{
    if (argc >= 3 && argc <= 5 && strcmp(argv[1], "lines") == 0) {
        return bench_lines((uint32_t)strtoul(argv[2], NULL, 10), argc > 3 ? (uint32_t)strtoul(argv[3], NULL, 10) : 128u,
                           argc > 4 ? (uint32_t)strtoul(argv[4], NULL, 10) : 1u);
    }
    if (argc == 3 && strcmp(argv[1], "fft") == 0) {
        return bench_fft((uint32_t)strtoul(argv[2], NULL, 10));
    }
    if (argc >= 3 && strcmp(argv[1], "rate") == 0) {
        return bench_rate(argv[2]);
    }
    if (argc >= 3 && strcmp(argv[1], "instr") == 0) {
        return bench_instr(argc, argv);
    }
    fprintf(stderr, "usage: bench_fw rate CONFIG | bench_fw instr table LEN N | bench_fw instr sine[-stats] N | bench_fw lines N [L [P]] | bench_fw fft N\n");
    return 2;
}
