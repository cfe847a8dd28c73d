/*
 * fmu_bench.c - closed-loop steps per CPU second of drive_sim's simulation with a plant file's
 * plant: the built-in plant, or an FMU plant through port/fmu_plant.c as drive_sim loads it
 * (run by tests/bench/bench_fmu.py).
 *   fmu_bench CONFIG [STEPS]     CONFIG: a drive_sim plant file (for an FMU plant: the file
 *                                fftune writes, host/fmu.py drive_sim_plant)
 * A sine reference run (0.5 rad, 1 Hz), median of 5 repetitions of STEPS (default 1e6) steps.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "drv.h"
#include "fmu_plant.h"
#include "sim.h"

static double cpu_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int cmp_d(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv)
{
    if (argc < 2) {
        fprintf(stderr, "usage: fmu_bench CONFIG [STEPS]\n");
        return 2;
    }
    uint64_t steps = argc > 2 ? strtoull(argv[2], NULL, 10) : 1000000u;
    char err[3000];
    plant_config_t cfg;
    if (plant_config_load(argv[1], &cfg, err, sizeof err) != 0) {
        fprintf(stderr, "fmu_bench: %s\n", err);
        return 2;
    }
    float *rec = calloc(cfg.rec_capacity ? cfg.rec_capacity : 1u, sizeof(float));
    float *tab = calloc(cfg.table_capacity ? cfg.table_capacity : 1u, sizeof(float));
    sim_t *sim = calloc(1, sizeof *sim);
    fmup_t *fmu = NULL;
    if (rec == NULL || tab == NULL || sim == NULL) {
        fprintf(stderr, "fmu_bench: out of memory\n");
        return 2;
    }
    if (cfg.fmu && (fmu = fmup_open_file(argv[1], 1.0 / (double)(float)cfg.fs_hz, err, sizeof err)) == NULL) {
        fprintf(stderr, "fmu_bench: %s\n", err);
        return 2;
    }
    double rates[5];
    for (int r = 0; r < 5; r++) {
        if ((fmu != NULL && fmup_restart(fmu, err, sizeof err) != 0) ||
            sim_init_ext(sim, &cfg, fmu ? fmup_ext(fmu) : NULL, rec, tab, err, sizeof err) != 0) {
            fprintf(stderr, "fmu_bench: %s\n", err);
            return 2;
        }
        drv_t *drv = sim_drv(sim);
        drv_enable(drv, true);
        (void)drv_set_u32(drv, DRV_P_EXC_KIND, DRV_EXC_SINE);
        (void)drv_set_u32(drv, DRV_P_EXC_PERIOD, (uint32_t)cfg.fs_hz);
        (void)drv_set_u32(drv, DRV_P_EXC_SINE_CYCLES, 1u);
        (void)drv_set_f32(drv, DRV_P_EXC_AMPLITUDE, 0.5f);
        (void)drv_set_u32(drv, DRV_P_EXC_SETTLE_PERIODS, 100000u);
        (void)drv_set_u32(drv, DRV_P_EXC_RECORD_PERIODS, 1u);
        if (drv_run_start(drv) != DRV_OK) {
            fprintf(stderr, "fmu_bench: run refused\n");
            return 2;
        }
        double c0 = cpu_s();
        sim_run(sim, steps);
        double c1 = cpu_s();
        if (sim->ext_failed) {
            fprintf(stderr, "fmu_bench: %s\n", fmup_error(fmu));
            return 2;
        }
        rates[r] = (double)steps / (c1 - c0);
    }
    qsort(rates, 5, sizeof rates[0], cmp_d);
    printf("closed-loop steps per CPU second (%s, %s plant, sine reference 0.5 rad at 1 Hz): median %.4g "
           "(min %.4g, max %.4g) over 5 x %llu steps\n", argv[1], fmu ? "FMU" : "built-in", rates[2], rates[0],
           rates[4], (unsigned long long)steps);
    printf("RATE %.6g\n", rates[2]);
    fmup_close(fmu);
    free(sim);
    free(rec);
    free(tab);
    return 0;
}
