/* test_plant.c - unit tests of the simulated plant, its config reader and the sim coupling. */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "plant.h"
#include "plant_config.h"
#include "sim.h"
#include "th.h"

static plant_params_t base_params(void)
{
    plant_config_t cfg;
    plant_config_defaults(&cfg);
    cfg.plant.counts_per_rev = 0u;
    cfg.plant.noise_std = 0.0;
    return cfg.plant;
}

/* write text to a temp file, return its path in buf */
static const char *tmp_config(const char *text, char *buf, size_t len)
{
    snprintf(buf, len, "/tmp/fwsim_cfg_XXXXXX");
    int fd = mkstemp(buf);
    TH_ASSERT(fd >= 0);
    FILE *f = fdopen(fd, "w");
    fputs(text, f);
    fclose(f);
    return buf;
}

static void test_stiction_holds_without_creep(void)
{
    plant_params_t p = base_params();
    p.coulomb = 0.01;
    p.stat = 0.012;
    plant_t pl;
    char err[200];
    TH_EQ(plant_init(&pl, &p, err, sizeof err), 0);
    /* applied torque 95 % of static friction: stuck, the motor angle never moves by one bit */
    double u = 0.95 * p.stat / p.km;
    for (int i = 0; i < 25600; i++) { /* 10 s at 2560 Hz */
        plant_advance(&pl, u, 1.0 / 2560.0);
        TH_ASSERT(pl.x[0] == 0.0 && pl.x[1] == 0.0);
        if (pl.x[0] != 0.0) {
            break;
        }
    }
    TH_EQ(plant_mode(&pl), 0);
    /* the load side swings on the spring (it is free) and settles at th2 = 0 */
    TH_NEAR(pl.x[2], 0.0, 1e-6);
    /* 5 % above static friction: breaks away in the direction of the torque */
    u = 1.05 * p.stat / p.km;
    plant_advance(&pl, u, 1.0 / 2560.0);
    TH_ASSERT(pl.x[1] > 0.0);
    TH_EQ(plant_mode(&pl), 1);
}

/* With a Stribeck term (sub-step path only: the fast step is off) the stick/slip decision
 * is the event logic's alone. A torque between Coulomb and static friction must not break
 * the motor away (release at Fs, not at Fc); above Fs it slips in the torque's direction. */
static void test_stiction_with_stribeck_holds_between_coulomb_and_static(void)
{
    plant_params_t p = base_params();
    p.coulomb = 0.01;
    p.stat = 0.02;
    p.stribeck_vel = 0.05;
    plant_t pl;
    char err[200];
    for (int dir = -1; dir <= 1; dir += 2) {
        TH_EQ(plant_init(&pl, &p, err, sizeof err), 0);
        /* 1.5 Fc = 0.75 Fs: above Coulomb, below static friction */
        double u = (double)dir * 1.5 * p.coulomb / p.km;
        int moved = 0;
        for (int i = 0; i < 2560 && !moved; i++) { /* 1 s at 2560 Hz */
            plant_advance(&pl, u, 1.0 / 2560.0);
            moved = pl.x[0] != 0.0 || pl.x[1] != 0.0;
        }
        TH_ASSERT(!moved);
        TH_EQ(plant_mode(&pl), 0);
        TH_EQ(pl.events, 0u);
        TH_ASSERT(pl.slow_steps == 2560u); /* the Stribeck plant never takes the fast step */
        /* 1.05 Fs: breaks away at once, in the direction of the torque */
        u = (double)dir * 1.05 * p.stat / p.km;
        plant_advance(&pl, u, 1.0 / 2560.0);
        TH_EQ(plant_mode(&pl), dir);
        TH_ASSERT((double)dir * pl.x[1] > 0.0);
    }
}

static void test_coulomb_slide_to_rest_analytic(void)
{
    /* free motor (no spring), initial velocity v0, no input: constant deceleration Fc/J1,
     * stops at t = v0 J1 / Fc after travelling v0^2 J1 / (2 Fc), then sticks */
    plant_params_t p = base_params();
    p.k = 0.0;
    p.c = 0.0;
    p.viscous = 0.0;
    p.coulomb = 0.02;
    p.stat = 0.03;
    p.substeps = 4u;
    plant_t pl;
    char err[200];
    TH_EQ(plant_init(&pl, &p, err, sizeof err), 0);
    double v0 = 3.0;
    plant_set_state(&pl, 0.0, v0, 0.0, 0.0);
    for (int i = 0; i < 2560; i++) {
        plant_advance(&pl, 0.0, 1.0 / 2560.0);
    }
    double dist = v0 * v0 * p.j1 / (2.0 * p.coulomb);
    TH_NEAR(pl.x[0], dist, 1e-12);
    TH_NEAR(pl.x[1], 0.0, 0.0);
    TH_EQ(plant_mode(&pl), 0);
    TH_EQ(pl.events, 1u);
    /* reversal without sticking, direction-dependent Coulomb friction (a = 0.25):
     * input torque 2 Fs against the motion */
    p.coulomb_asym = 0.25;
    TH_EQ(plant_init(&pl, &p, err, sizeof err), 0);
    plant_set_state(&pl, 0.0, v0, 0.0, 0.0);
    double tq = -2.0 * p.stat;
    for (int i = 0; i < 2560; i++) {
        plant_advance(&pl, tq / p.km, 1.0 / 2560.0);
    }
    /* phase 1: decel (|tq| + Fc+)/J1 to rest; phase 2: accel (|tq| - Fc-)/J1 backwards */
    double a1 = (2.0 * p.stat + 1.25 * p.coulomb) / p.j1, a2 = (2.0 * p.stat - 0.75 * p.coulomb) / p.j1;
    double t1 = v0 / a1, x1 = v0 * t1 / 2.0, t2 = 1.0 - t1;
    TH_NEAR(pl.x[0], x1 - 0.5 * a2 * t2 * t2, 1e-9);
    TH_NEAR(pl.x[1], -a2 * t2, 1e-9);
}

static void test_measurement_quantisation_and_noise(void)
{
    plant_params_t p = base_params();
    p.counts_per_rev = 500u;
    plant_t pl;
    char err[200];
    TH_EQ(plant_init(&pl, &p, err, sizeof err), 0);
    double q = 2.0 * M_PI / 500.0, m1, m2;
    plant_set_state(&pl, 0.3 * q + 5 * q, 0.0, -0.7 * q, 0.0);
    plant_measure(&pl, &m1, &m2);
    TH_NEAR(m1, 5 * q, 1e-15);
    TH_NEAR(m2, -q, 1e-15);
    /* seeded noise: same seed, same sequence; std as configured */
    p.counts_per_rev = 0u;
    p.noise_std = 1e-3;
    plant_t a, b;
    TH_EQ(plant_init(&a, &p, err, sizeof err), 0);
    TH_EQ(plant_init(&b, &p, err, sizeof err), 0);
    double s2 = 0.0, s1 = 0.0;
    const int n = 20000;
    for (int i = 0; i < n; i++) {
        double x1, x2, y1, y2;
        plant_measure(&a, &x1, &x2);
        plant_measure(&b, &y1, &y2);
        TH_ASSERT(x1 == y1 && x2 == y2);
        s1 += x1;
        s2 += x1 * x1;
    }
    double mean = s1 / n, sd = sqrt(s2 / n - mean * mean);
    TH_NEAR(mean, 0.0, 4.0 * 1e-3 / sqrt(n));
    TH_NEAR(sd, 1e-3, 0.03e-3);
}

static void test_config_files_load(void)
{
    const char *files[] = {"../configs/plant_twomass.yaml", "../configs/plant_stage.yaml"};
    for (size_t i = 0; i < 2; i++) {
        plant_config_t cfg;
        char err[300] = "";
        int rc = plant_config_load(files[i], &cfg, err, sizeof err);
        TH_EQ(rc, 0);
        if (rc != 0) {
            fprintf(stderr, "  %s\n", err);
            continue;
        }
        char err2[300];
        sim_t *sim = sim_new(&cfg, err2, sizeof err2);
        TH_ASSERT(sim != NULL);
        sim_free(sim);
    }
}

static void test_defaults_equal_twomass_file(void)
{
    /* drive_sim without --config runs the built-in defaults: they must be plant_twomass.yaml */
    plant_config_t file, def;
    char err[300];
    TH_EQ(plant_config_load("../configs/plant_twomass.yaml", &file, err, sizeof err), 0);
    plant_config_defaults(&def);
    TH_ASSERT(memcmp(&file, &def, sizeof def) == 0);
}

static void test_config_errors_name_file_line_key(void)
{
    const struct {
        const char *text;
        const char *expect; /* substring of the message */
    } cases[] = {
        {"plant:\n  j1: 1e-4\n  jj: 3\n", ":3: unknown key 'jj' in section 'plant'"},
        {"motor:\n  j1: 1\n", ":1: unknown section 'motor'"},
        {"plant:\n  j1: abc\n", ":2: plant.j1: 'abc' is not a finite number"},
        {"plant:\n  j1: -1\n", ":2: plant.j1 = -1: out of range"},
        {"plant:\n  j1: 1\n  j1: 2\n", ":3: duplicate key 'plant.j1'"},
        {"plant:\n\tj1: 1\n", ":2: tab in indentation"},
        {"  j1: 1\n", ":1: key 'j1' outside a section"},
        {"plant:\n  substeps: 2.5\n", ":2: plant.substeps = 2.5: must be an integer"},
        {"plant:\n  j1: .nan\n", ":2: plant.j1: '.nan' is not a finite number"},
        {"plant:\n  coulomb: 0.2\n  static: 0.1\n", "static = 0.1: must be >= coulomb"},
        {"plant:\n  coulomb_asymmetry: 0.95\n", ":2: plant.coulomb_asymmetry = 0.95: out of range [-0.9, 0.9]"},
        {"plant:\n  coulomb_position: -0.91\n", ":2: plant.coulomb_position = -0.91: out of range [-0.9, 0.9]"},
        {"plant:\n  coulomb: 0.1\n  coulomb_asymmetry: 0.5\n  static: 0.12\n", "static = 0.12: must be >= coulomb (1 + |coulomb_asymmetry|) = 0.15"},
        {"drive: 3\n", ":1: top-level 'drive' must be a section"},
    };
    for (size_t i = 0; i < sizeof cases / sizeof cases[0]; i++) {
        char path[64], err[300] = "";
        tmp_config(cases[i].text, path, sizeof path);
        plant_config_t cfg;
        plant_config_defaults(&cfg);
        plant_config_t before = cfg;
        TH_EQ(plant_config_load(path, &cfg, err, sizeof err), -1);
        TH_ASSERT(strstr(err, path) == err);
        TH_ASSERT(strstr(err, cases[i].expect) != NULL);
        if (strstr(err, cases[i].expect) == NULL) {
            fprintf(stderr, "  got: %s\n  want: %s\n", err, cases[i].expect);
        }
        TH_ASSERT(memcmp(&before, &cfg, sizeof cfg) == 0); /* untouched */
        unlink(path);
    }
    char err[300];
    plant_config_t cfg;
    TH_EQ(plant_config_load("/nonexistent/x.yaml", &cfg, err, sizeof err), -1);
    TH_ASSERT(strstr(err, "/nonexistent/x.yaml: cannot open") != NULL);
    /* comments, blank lines and a 64-bit seed */
    char path[64];
    tmp_config("# c\n\nsensor:   # s\n  seed: 18446744073709551615  # max\n  counts_per_rev: 0\n", path, sizeof path);
    TH_EQ(plant_config_load(path, &cfg, err, sizeof err), 0);
    TH_ASSERT(cfg.plant.seed == UINT64_MAX);
    TH_EQ(cfg.plant.counts_per_rev, 0u);
    unlink(path);
}

static void test_sim_truth_and_holding(void)
{
    plant_config_t cfg;
    plant_config_defaults(&cfg);
    cfg.rec_capacity = 1000u;
    char err[300];
    sim_t *sim = sim_new(&cfg, err, sizeof err);
    TH_ASSERT(sim != NULL);
    if (sim == NULL) {
        return;
    }
    float v;
    TH_EQ(sim_get_f32(sim, DRV_P_SIM_FC_VOLT, &v), DRV_OK);
    TH_NEAR(v, cfg.plant.coulomb / cfg.plant.km, 1e-7);
    TH_EQ(sim_get_f32(sim, DRV_P_SIM_FS_VOLT, &v), DRV_OK);
    TH_NEAR(v, cfg.plant.stat / cfg.plant.km, 1e-7);
    TH_EQ(sim_get_f32(sim, DRV_P_SIM_FV_VOLT, &v), DRV_OK);
    TH_NEAR(v, cfg.plant.viscous / cfg.plant.km, 1e-7);
    TH_EQ(sim_get_f32(sim, DRV_P_SIM_FC_TORQUE, &v), DRV_OK);
    TH_NEAR(v, cfg.plant.coulomb, 1e-9);
    TH_EQ(sim_get_f32(sim, DRV_P_SIM_NOISE_STD, &v), DRV_OK);
    TH_EQ(sim_get_f32(sim, DRV_P_KP, &v), DRV_E_NO_PARAM);
    TH_EQ(drv_get_f32(sim_drv(sim), DRV_P_SIM_FC_VOLT, &v), DRV_E_NO_PARAM);
    TH_EQ(drv_get_f32(sim_drv(sim), DRV_P_KP, &v), DRV_OK);
    TH_NEAR(v, cfg.kp, 1e-6);
    /* closed loop to a set-point 0.5 rad: settles there within the friction dead band */
    drv_enable(sim_drv(sim), true);
    TH_EQ(drv_set_target(sim_drv(sim), 0.5f), DRV_OK);
    sim_run(sim, 5u * 2560u);
    double x[4];
    plant_get_state(sim_plant(sim), x);
    double band = cfg.plant.stat / (cfg.kp * cfg.plant.km) + 2.0 * M_PI / cfg.plant.counts_per_rev;
    TH_NEAR(x[0], 0.5, band);
    TH_NEAR(x[1], 0.0, 1e-3);
    sim_free(sim);
}

int main(void)
{
    TH_RUN(test_stiction_holds_without_creep);
    TH_RUN(test_stiction_with_stribeck_holds_between_coulomb_and_static);
    TH_RUN(test_coulomb_slide_to_rest_analytic);
    TH_RUN(test_measurement_quantisation_and_noise);
    TH_RUN(test_config_files_load);
    TH_RUN(test_defaults_equal_twomass_file);
    TH_RUN(test_config_errors_name_file_line_key);
    TH_RUN(test_sim_truth_and_holding);
    return th_finish();
}
