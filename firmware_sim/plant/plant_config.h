/*
 * plant_config.h - simulation configuration from configs/plant_*.yaml (HOST ONLY).
 *
 * C has no YAML library here, so this reads a documented SUBSET of YAML that Python's
 * yaml.safe_load reads the same way:
 *   # comment lines and blank lines
 *   section:                 (a top-level key with nothing after the colon)
 *     key: number  # comment (indented by spaces; decimal / exponent numbers only)
 * Sections and keys are fixed (docs/firmware.md); an unknown section or key, a duplicate,
 * a malformed line or an out-of-range value is an error naming file:line and the key.
 * Keys left out keep the defaults of plant_config_defaults() (the twomass set-up).
 */
#ifndef PLANT_CONFIG_H
#define PLANT_CONFIG_H

#include <stddef.h>
#include <stdint.h>

#include "plant.h"

/* Friction drift of the simulated plant (section `drift:`, issue 26): the Coulomb level
 * (with the static level) and the viscous coefficient are the configured values times
 *   m(t) = (1 + step H(t - step_time)) (1 + ramp clamp((t - ramp_start) / (ramp_end - ramp_start), 0, 1))
 *          (1 + exp (1 - e^(-(t - exp_start) / exp_tau)) H(t - exp_start))
 * of the simulated time t [s] (relative changes; all 0: no drift). */
typedef struct {
    double step, step_time_s;
    double ramp, ramp_start_s, ramp_end_s;
    double exp, exp_start_s, exp_tau_s;
} plant_drift_t;

/* m(t) of one drift profile (1 when all changes are 0). Defined in sim.c (linked by the
 * processor-in-the-loop build too, which has no plant_config.c). */
double plant_drift_factor(const plant_drift_t *d, double t_s);

typedef struct {
    /* drive: */
    double fs_hz;            /* controller rate */
    uint32_t rec_capacity;   /* recorder RAM, float values */
    uint32_t table_capacity; /* waveform table, samples (<= 8192) */
    /* controller: initial controller parameters (V, rad, s) */
    double kp, kd, tau_d, kfc, kv, fc_smooth, u_max;
    /* plant: + sensor: */
    plant_params_t plant;
    /* drift: (coulomb_*, viscous_*) */
    plant_drift_t drift_coulomb, drift_viscous;
    /* fmu: the file names an FMU plant (docs/fmu.md): its keys are read by drive_sim's
     * port/fmu_plant.c, not here; sim_init refuses such a config without the FMU attached */
    int fmu;
    /* truth: (FMU plants only) what a report compares K_fc*, K_v, the static level with [V];
     * NaN = not given */
    double truth_kfc_v, truth_kv_v, truth_ks_v;
} plant_config_t;

void plant_config_defaults(plant_config_t *cfg);
/* 0 on success; -1 with "file:line: message" in err (cfg then holds no partial file). */
int plant_config_load(const char *path, plant_config_t *cfg, char *err, size_t errlen);

#endif /* PLANT_CONFIG_H */
