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

typedef struct {
    /* drive: */
    double fs_hz;            /* controller rate */
    uint32_t rec_capacity;   /* recorder RAM, float values */
    uint32_t table_capacity; /* waveform table, samples (<= 8192) */
    /* controller: initial controller parameters (V, rad, s) */
    double kp, kd, tau_d, kfc, kv, fc_smooth, u_max;
    /* plant: + sensor: */
    plant_params_t plant;
} plant_config_t;

void plant_config_defaults(plant_config_t *cfg);
/* 0 on success; -1 with "file:line: message" in err (cfg then holds no partial file). */
int plant_config_load(const char *path, plant_config_t *cfg, char *err, size_t errlen);

#endif /* PLANT_CONFIG_H */
