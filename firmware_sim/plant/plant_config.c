#define _POSIX_C_SOURCE 200809L /* fileno, fstat: a directory is refused where a file is expected */
/* plant_config.c - see plant_config.h. */
#include "plant_config.h"

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

typedef enum { PC_F64, PC_U32, PC_U64 } pc_type_t;

typedef struct {
    const char *section;
    const char *key;
    pc_type_t type;
    size_t offset;
    double lo, hi; /* inclusive */
} pc_key_t;

#define PC_F(sec, key, field, lo, hi) {sec, key, PC_F64, offsetof(plant_config_t, field), lo, hi}
#define PC_U(sec, key, field, lo, hi) {sec, key, PC_U32, offsetof(plant_config_t, field), lo, hi}

static const pc_key_t PC_KEYS[] = {
    PC_F("drive", "fs_hz", fs_hz, 1.0, 1.0e6),
    PC_U("drive", "rec_capacity", rec_capacity, 0.0, 268435456.0),
    PC_U("drive", "table_capacity", table_capacity, 0.0, 8192.0),
    PC_F("controller", "kp", kp, 0.0, 1.0e5),
    PC_F("controller", "kd", kd, 0.0, 1.0e4),
    PC_F("controller", "tau_d", tau_d, 0.0, 1.0),
    PC_F("controller", "kfc", kfc, 0.0, 100.0),
    PC_F("controller", "kv", kv, 0.0, 100.0),
    PC_F("controller", "fc_smooth", fc_smooth, 0.0, 1000.0),
    PC_F("controller", "u_max", u_max, 0.0, 1000.0),
    PC_F("plant", "j1", plant.j1, 1e-12, 1e6),
    PC_F("plant", "j2", plant.j2, 1e-12, 1e6),
    PC_F("plant", "k", plant.k, 0.0, 1e9),
    PC_F("plant", "c", plant.c, 0.0, 1e9),
    PC_F("plant", "km", plant.km, 1e-12, 1e6),
    PC_F("plant", "coulomb", plant.coulomb, 0.0, 1e6),
    PC_F("plant", "coulomb_asymmetry", plant.coulomb_asym, -0.9, 0.9),
    PC_F("plant", "coulomb_position", plant.coulomb_pos, -0.9, 0.9),
    PC_F("plant", "static", plant.stat, 0.0, 1e6),
    PC_F("plant", "stribeck_velocity", plant.stribeck_vel, 0.0, 1e6),
    PC_F("plant", "viscous", plant.viscous, 0.0, 1e6),
    PC_F("plant", "load_viscous", plant.load_viscous, 0.0, 1e6),
    PC_U("plant", "substeps", plant.substeps, 1.0, 10000.0),
    PC_U("sensor", "counts_per_rev", plant.counts_per_rev, 0.0, 4294967295.0),
    PC_F("sensor", "noise_std", plant.noise_std, 0.0, 1.0),
    {"sensor", "seed", PC_U64, offsetof(plant_config_t, plant.seed), 0.0, 18446744073709551615.0},
    PC_F("drift", "coulomb_step", drift_coulomb.step, -0.9, 10.0),
    PC_F("drift", "coulomb_step_time_s", drift_coulomb.step_time_s, 0.0, 1e9),
    PC_F("drift", "coulomb_ramp", drift_coulomb.ramp, -0.9, 10.0),
    PC_F("drift", "coulomb_ramp_start_s", drift_coulomb.ramp_start_s, 0.0, 1e9),
    PC_F("drift", "coulomb_ramp_end_s", drift_coulomb.ramp_end_s, 0.0, 1e9),
    PC_F("drift", "coulomb_exp", drift_coulomb.exp, -0.9, 10.0),
    PC_F("drift", "coulomb_exp_start_s", drift_coulomb.exp_start_s, 0.0, 1e9),
    PC_F("drift", "coulomb_exp_tau_s", drift_coulomb.exp_tau_s, 1e-3, 1e9),
    PC_F("drift", "viscous_step", drift_viscous.step, -0.9, 10.0),
    PC_F("drift", "viscous_step_time_s", drift_viscous.step_time_s, 0.0, 1e9),
    PC_F("drift", "viscous_ramp", drift_viscous.ramp, -0.9, 10.0),
    PC_F("drift", "viscous_ramp_start_s", drift_viscous.ramp_start_s, 0.0, 1e9),
    PC_F("drift", "viscous_ramp_end_s", drift_viscous.ramp_end_s, 0.0, 1e9),
    PC_F("drift", "viscous_exp", drift_viscous.exp, -0.9, 10.0),
    PC_F("drift", "viscous_exp_start_s", drift_viscous.exp_start_s, 0.0, 1e9),
    PC_F("drift", "viscous_exp_tau_s", drift_viscous.exp_tau_s, 1e-3, 1e9),
    PC_F("truth", "kfc_v", truth_kfc_v, 0.0, 1e6),
    PC_F("truth", "kv_v", truth_kv_v, 0.0, 1e6),
    PC_F("truth", "ks_v", truth_ks_v, 0.0, 1e6),
};
#define PC_NKEYS (sizeof PC_KEYS / sizeof PC_KEYS[0])

void plant_config_defaults(plant_config_t *cfg)
{
    memset(cfg, 0, sizeof *cfg);
    cfg->fs_hz = 2560.0;
    cfg->rec_capacity = 4u * 1024u * 1024u;
    cfg->table_capacity = 8192u;
    cfg->kp = 2.0;
    cfg->kd = 0.05;
    cfg->tau_d = 0.002;
    cfg->kfc = 0.0;
    cfg->kv = 0.0;
    cfg->fc_smooth = 0.0;
    cfg->u_max = 10.0;
    cfg->plant.j1 = 1.0e-4;
    cfg->plant.j2 = 2.0e-4;
    cfg->plant.k = 0.5;
    cfg->plant.c = 2.0e-4;
    cfg->plant.km = 0.05;
    cfg->plant.coulomb = 0.05 * 0.1157;
    cfg->plant.coulomb_asym = 0.0;
    cfg->plant.coulomb_pos = 0.0;
    cfg->plant.stat = 0.05 * 0.1157;
    cfg->plant.stribeck_vel = 0.0;
    cfg->plant.viscous = 1.0e-4;
    cfg->plant.load_viscous = 0.0;
    cfg->plant.substeps = 8u;
    cfg->plant.counts_per_rev = 2000u;
    cfg->plant.noise_std = 0.0;
    cfg->plant.seed = 1u;
    cfg->drift_coulomb.exp_tau_s = 60.0;
    cfg->drift_viscous.exp_tau_s = 60.0;
    cfg->truth_kfc_v = NAN;
    cfg->truth_kv_v = NAN;
    cfg->truth_ks_v = NAN;
}

static char *pc_trim(char *s)
{
    while (*s == ' ' || *s == '\t') {
        s++;
    }
    char *e = s + strlen(s);
    while (e > s && (e[-1] == ' ' || e[-1] == '\t' || e[-1] == '\r' || e[-1] == '\n')) {
        *--e = '\0';
    }
    return s;
}

static int pc_valid_name(const char *s)
{
    if (!*s) {
        return 0;
    }
    for (; *s; s++) {
        if (!(isalnum((unsigned char)*s) || *s == '_')) {
            return 0;
        }
    }
    return 1;
}

static int pc_store(plant_config_t *cfg, const pc_key_t *k, const char *text, char *msg, size_t msglen)
{
    char *end;
    errno = 0;
    double v = strtod(text, &end);
    if (end == text || *end != '\0' || errno == ERANGE || !isfinite(v)) {
        snprintf(msg, msglen, "%s.%s: '%s' is not a finite number", k->section, k->key, text);
        return -1;
    }
    if (v < k->lo || v > k->hi) {
        snprintf(msg, msglen, "%s.%s = %s: out of range [%g, %g]", k->section, k->key, text, k->lo, k->hi);
        return -1;
    }
    char *dst = (char *)cfg + k->offset;
    if (k->type == PC_F64) {
        memcpy(dst, &v, sizeof v);
        return 0;
    }
    if (v != floor(v)) {
        snprintf(msg, msglen, "%s.%s = %s: must be an integer", k->section, k->key, text);
        return -1;
    }
    if (k->type == PC_U32) {
        uint32_t u = (uint32_t)v;
        memcpy(dst, &u, sizeof u);
    } else {
        /* 64-bit seeds: parse the digits exactly (a double has 53 bits) */
        errno = 0;
        unsigned long long u = strtoull(text, &end, 10);
        if (*end != '\0' || errno == ERANGE || text[0] == '-') {
            snprintf(msg, msglen, "%s.%s = %s: must be an unsigned 64-bit integer", k->section, k->key, text);
            return -1;
        }
        uint64_t u64 = (uint64_t)u;
        memcpy(dst, &u64, sizeof u64);
    }
    return 0;
}

int plant_config_load(const char *path, plant_config_t *out, char *err, size_t errlen)
{
    FILE *f = fopen(path, "r");
    if (f == NULL) {
        snprintf(err, errlen, "%s: cannot open: %s", path, strerror(errno));
        return -1;
    }
    /* a directory opens (and then reads as nothing: the built-in plant, silently) */
    struct stat st;
    memset(&st, 0, sizeof st);
    if (fstat(fileno(f), &st) != 0 || !S_ISREG(st.st_mode)) {
        snprintf(err, errlen, "%s: not a regular file%s", path,
                 S_ISDIR(st.st_mode) ? " (a directory)" : "");
        fclose(f);
        return -1;
    }
    plant_config_t cfg;
    plant_config_defaults(&cfg);
    unsigned char seen[PC_NKEYS];
    memset(seen, 0, sizeof seen);
    char line[512], section[64] = "", msg[256];
    int lineno = 0, rc = 0, truth_line = 0;
    while (fgets(line, sizeof line, f) != NULL) {
        lineno++;
        if (strchr(line, '\n') == NULL && !feof(f)) {
            snprintf(msg, sizeof msg, "line too long");
            rc = -1;
            break;
        }
        char *hash = strchr(line, '#');
        if (hash != NULL) {
            *hash = '\0';
        }
        size_t indent = strspn(line, " ");
        if (line[indent] == '\t') {
            snprintf(msg, sizeof msg, "tab in indentation (YAML forbids it)");
            rc = -1;
            break;
        }
        char *body = pc_trim(line);
        if (*body == '\0') {
            continue;
        }
        char *colon = strchr(body, ':');
        if (colon == NULL) {
            snprintf(msg, sizeof msg, "expected 'key: value' or 'section:', got '%s'", body);
            rc = -1;
            break;
        }
        *colon = '\0';
        char *name = pc_trim(body);
        char *value = pc_trim(colon + 1);
        if (!pc_valid_name(name)) {
            snprintf(msg, sizeof msg, "bad key name '%s'", name);
            rc = -1;
            break;
        }
        if (indent == 0) {
            if (*value != '\0') {
                snprintf(msg, sizeof msg, "top-level '%s' must be a section (nothing after the colon)", name);
                rc = -1;
                break;
            }
            if (strcmp(name, "fmu") == 0) {
                /* an FMU plant: the section's keys are port/fmu_plant.c's (drive_sim) */
                if (cfg.fmu) {
                    snprintf(msg, sizeof msg, "duplicate section 'fmu'");
                    rc = -1;
                    break;
                }
                cfg.fmu = 1;
                snprintf(section, sizeof section, "%s", name);
                continue;
            }
            if (strcmp(name, "truth") == 0 && truth_line == 0) {
                truth_line = lineno;
            }
            int known = 0;
            for (size_t i = 0; i < PC_NKEYS; i++) {
                known |= strcmp(PC_KEYS[i].section, name) == 0;
            }
            if (!known) {
                snprintf(msg, sizeof msg, "unknown section '%s' (drive, controller, plant, sensor, drift, fmu, truth)", name);
                rc = -1;
                break;
            }
            snprintf(section, sizeof section, "%s", name);
            continue;
        }
        if (section[0] == '\0') {
            snprintf(msg, sizeof msg, "key '%s' outside a section", name);
            rc = -1;
            break;
        }
        if (strcmp(section, "fmu") == 0) {
            continue; /* read by port/fmu_plant.c */
        }
        if (*value == '\0') {
            snprintf(msg, sizeof msg, "%s.%s: missing value (only two levels are supported)", section, name);
            rc = -1;
            break;
        }
        size_t i;
        for (i = 0; i < PC_NKEYS; i++) {
            if (strcmp(PC_KEYS[i].section, section) == 0 && strcmp(PC_KEYS[i].key, name) == 0) {
                break;
            }
        }
        if (i == PC_NKEYS) {
            snprintf(msg, sizeof msg, "unknown key '%s' in section '%s'", name, section);
            rc = -1;
            break;
        }
        if (seen[i]) {
            snprintf(msg, sizeof msg, "duplicate key '%s.%s'", section, name);
            rc = -1;
            break;
        }
        seen[i] = 1;
        if (pc_store(&cfg, &PC_KEYS[i], value, msg, sizeof msg) != 0) {
            rc = -1;
            break;
        }
    }
    fclose(f);
    if (rc != 0) {
        snprintf(err, errlen, "%s:%d: %s%s", path, lineno, msg,
                 cfg.fmu ? " (a plant file naming an FMU goes to fftune sim|demo --plant FILE, which hands drive_sim "
                           "its checked view: docs/fmu.md)" : "");
        return -1;
    }
    if (cfg.drift_coulomb.ramp_end_s < cfg.drift_coulomb.ramp_start_s ||
        cfg.drift_viscous.ramp_end_s < cfg.drift_viscous.ramp_start_s) {
        snprintf(err, errlen, "%s: drift: a ramp's end (%s_ramp_end_s) before its start", path,
                 cfg.drift_coulomb.ramp_end_s < cfg.drift_coulomb.ramp_start_s ? "coulomb" : "viscous");
        return -1;
    }
    if (truth_line != 0 && !cfg.fmu) {
        snprintf(err, errlen, "%s:%d: section 'truth' is for an FMU plant (section fmu); the built-in "
                 "plant's truth is its own parameters", path, truth_line);
        return -1;
    }
    if (plant_check_params(&cfg.plant, msg, sizeof msg) != 0) {
        snprintf(err, errlen, "%s: plant: %s", path, msg);
        return -1;
    }
    *out = cfg;
    return 0;
}
