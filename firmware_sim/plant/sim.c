/* sim.c - see sim.h. Host only. */
#include "sim.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* the measured angles: of the built-in plant, or the external plant's through its sensor */
static void sim_measure(sim_t *sim, double *m1, double *m2)
{
    if (sim->ext != NULL) {
        double th1, th2;
        sim->ext->angles(sim->ext->ctx, &th1, &th2);
        plant_measure_angles(&sim->plant, th1, th2, m1, m2);
    } else {
        plant_measure(&sim->plant, m1, m2);
    }
}

int sim_init(sim_t *sim, const plant_config_t *cfg, float *rec_buf, float *table_buf, char *err, size_t errlen)
{
    return sim_init_ext(sim, cfg, NULL, rec_buf, table_buf, err, errlen);
}

int sim_init_ext(sim_t *sim, const plant_config_t *cfg, const sim_plant_ext_t *ext, float *rec_buf,
                 float *table_buf, char *err, size_t errlen)
{
    char msg[200];
    memset(sim, 0, sizeof *sim);
    if (cfg->fmu && ext == NULL) {
        snprintf(err, errlen, "the configuration names an FMU plant (section fmu): drive_sim co-simulates it "
                 "(fftune sim|demo --plant FILE, docs/fmu.md); this build has the built-in plant only");
        return -1;
    }
    sim->cfg = *cfg;
    sim->ext = ext;
    if (plant_init(&sim->plant, &cfg->plant, msg, sizeof msg) != 0) {
        snprintf(err, errlen, "plant: %s", msg);
        return -1;
    }
    if (cfg->table_capacity > SIM_TABLE_STAGE_MAX) {
        snprintf(err, errlen, "drive.table_capacity = %u: this build's table staging buffer holds at most %u "
                 "samples (SIM_TABLE_STAGE_MAX)", (unsigned)cfg->table_capacity, (unsigned)SIM_TABLE_STAGE_MAX);
        return -1;
    }
    sim->storage.rec_buf = rec_buf;
    sim->storage.rec_capacity = cfg->rec_capacity;
    sim->storage.table_buf = table_buf;
    sim->storage.table_capacity = cfg->table_capacity;
    sim->storage.table_stage_buf = sim->table_stage;
    sim->storage.fs_hz = (float)cfg->fs_hz;
    drv_status_t st = drv_init(&sim->drv, &sim->storage);
    if (st != DRV_OK) {
        snprintf(err, errlen, "drive: drv_init refused the storage (fs_hz %g, table_capacity %u): status %d",
                 cfg->fs_hz, (unsigned)cfg->table_capacity, (int)st);
        return -1;
    }
    const struct {
        const char *key;
        drv_param_id_t id;
        double v;
    } ctl[] = {
        {"kp", DRV_P_KP, cfg->kp}, {"kd", DRV_P_KD, cfg->kd}, {"tau_d", DRV_P_TAU_D, cfg->tau_d},
        {"kfc", DRV_P_KFC, cfg->kfc}, {"kv", DRV_P_KV, cfg->kv}, {"fc_smooth", DRV_P_FC_SMOOTH, cfg->fc_smooth},
        {"u_max", DRV_P_U_MAX, cfg->u_max},
    };
    for (size_t i = 0; i < sizeof ctl / sizeof ctl[0]; i++) {
        st = drv_set_f32(&sim->drv, ctl[i].id, (float)ctl[i].v);
        if (st != DRV_OK) {
            snprintf(err, errlen, "controller.%s = %g: refused by the drive (status %d)", ctl[i].key, ctl[i].v, (int)st);
            return -1;
        }
    }
    sim->dt = 1.0 / (double)sim->storage.fs_hz;
    sim->drift = cfg->drift_coulomb.step != 0.0 ||
                 cfg->drift_coulomb.ramp != 0.0 || cfg->drift_coulomb.exp != 0.0 || cfg->drift_viscous.step != 0.0 ||
                 cfg->drift_viscous.ramp != 0.0 || cfg->drift_viscous.exp != 0.0;
    /* prime the drive with the first measurement so that enabling holds the true position */
    double m1, m2;
    sim_measure(sim, &m1, &m2);
    drv_meas_t meas = {(float)m1, (float)m2};
    (void)drv_step(&sim->drv, &meas);
    return 0;
}

sim_t *sim_new(const plant_config_t *cfg, char *err, size_t errlen)
{
    sim_t *sim = calloc(1, sizeof *sim);
    float *rec = calloc(cfg->rec_capacity ? cfg->rec_capacity : 1u, sizeof(float));
    float *tab = calloc(cfg->table_capacity ? cfg->table_capacity : 1u, sizeof(float));
    if (sim == NULL || rec == NULL || tab == NULL) {
        snprintf(err, errlen, "out of memory (rec_capacity %u floats)", (unsigned)cfg->rec_capacity);
        free(sim);
        free(rec);
        free(tab);
        return NULL;
    }
    if (sim_init(sim, cfg, rec, tab, err, errlen) != 0) {
        free(sim);
        free(rec);
        free(tab);
        return NULL;
    }
    sim->owned_rec = rec;
    sim->owned_table = tab;
    return sim;
}

sim_t *sim_new_from_file(const char *path, char *err, size_t errlen)
{
    plant_config_t cfg;
    if (plant_config_load(path, &cfg, err, errlen) != 0) {
        return NULL;
    }
    char msg[300];
    sim_t *sim = sim_new(&cfg, msg, sizeof msg);
    if (sim == NULL) {
        snprintf(err, errlen, "%s: %s", path, msg);
    }
    return sim;
}

void sim_free(sim_t *sim)
{
    if (sim == NULL) {
        return;
    }
    free(sim->owned_rec);
    free(sim->owned_table);
    free(sim);
}

drv_t *sim_drv(sim_t *sim)
{
    return &sim->drv;
}

plant_t *sim_plant(sim_t *sim)
{
    return &sim->plant;
}

/* m(t) of one drift profile (declared in plant_config.h; defined here, beside its only user,
 * because the processor-in-the-loop build links sim.c but not the file parser plant_config.c) */
double plant_drift_factor(const plant_drift_t *d, double t_s)
{
    double m = 1.0;
    if (d->step != 0.0 && t_s >= d->step_time_s) {
        m *= 1.0 + d->step;
    }
    if (d->ramp != 0.0 && t_s > d->ramp_start_s) {
        double span = d->ramp_end_s - d->ramp_start_s;
        double x = (span > 0.0 && t_s < d->ramp_end_s) ? (t_s - d->ramp_start_s) / span : 1.0;
        m *= 1.0 + d->ramp * x;
    }
    if (d->exp != 0.0 && t_s > d->exp_start_s) {
        m *= 1.0 + d->exp * (1.0 - exp(-(t_s - d->exp_start_s) / d->exp_tau_s));
    }
    return m;
}

/* Friction drift (plant_config.h, issue 26): the plant's friction follows the configured
 * profiles of the simulated time. The viscous term enters the exact-ZOH matrices: they are
 * recomputed only when it has changed by more than 1e-6 relative since the last time. */
static void sim_drift(sim_t *sim)
{
    const plant_config_t *c = &sim->cfg;
    plant_t *pl = &sim->plant;
    double mc = plant_drift_factor(&c->drift_coulomb, pl->t);
    pl->p.coulomb = c->plant.coulomb * mc;
    pl->p.stat = c->plant.stat * mc;
    double mv = plant_drift_factor(&c->drift_viscous, pl->t);
    double bv = c->plant.viscous * mv;
    if (fabs(bv - pl->p.viscous) > 1e-6 * fabs(pl->p.viscous) + 1e-300) {
        pl->p.viscous = bv;
        pl->fast_dt = 0.0; /* rediscretise at the next fast step */
    }
}

float sim_step(sim_t *sim)
{
    if (sim->ext != NULL) {
        double m1, m2;
        sim_measure(sim, &m1, &m2);
        drv_meas_t meas = {(float)m1, (float)m2};
        if (sim->ext_failed) {
            drv_enable(&sim->drv, false); /* a failed plant holds; the drive stays off */
        }
        float u = drv_step(&sim->drv, &meas);
        if (!sim->ext_failed) {
            if (sim->ext->advance(sim->ext->ctx, (double)u, sim->dt) != 0) {
                sim->ext_failed = 1;
                drv_enable(&sim->drv, false);
            } else {
                sim->plant.t += sim->dt;
            }
        }
        sim->steps++;
        return u;
    }
    if (sim->drift) {
        sim_drift(sim);
    }
    double m1, m2;
    plant_measure(&sim->plant, &m1, &m2);
    drv_meas_t meas = {(float)m1, (float)m2};
    float u = drv_step(&sim->drv, &meas);
    plant_advance(&sim->plant, (double)u, sim->dt);
    sim->steps++;
    return u;
}

void sim_run(sim_t *sim, uint64_t steps)
{
    for (uint64_t i = 0; i < steps; i++) {
        (void)sim_step(sim);
        drv_background(&sim->drv); /* the main loop's work between control steps */
    }
}

uint64_t sim_run_until_idle(sim_t *sim, uint64_t max_steps)
{
    uint64_t n = 0;
    uint32_t state = 0;
    while (n < max_steps) {
        (void)drv_get_u32(&sim->drv, DRV_P_RUN_STATE, &state);
        if (state != DRV_RUN_SETTLING && state != DRV_RUN_RECORDING) {
            break;
        }
        (void)sim_step(sim);
        drv_background(&sim->drv);
        n++;
    }
    return n;
}

drv_status_t sim_get_f32(const sim_t *sim, drv_param_id_t id, float *value)
{
    const plant_params_t *p = &sim->plant.p;
    double v;
    if (sim->ext != NULL) {
        switch (id) {
        case DRV_P_SIM_FC_VOLT: v = sim->cfg.truth_kfc_v; break;
        case DRV_P_SIM_FV_VOLT: v = sim->cfg.truth_kv_v; break;
        case DRV_P_SIM_FS_VOLT: v = sim->cfg.truth_ks_v; break;
        case DRV_P_SIM_NOISE_STD: v = p->noise_std; break;
        case DRV_P_SIM_FC_TORQUE: v = NAN; break;
        default: return DRV_E_NO_PARAM;
        }
        if (value == NULL) {
            return DRV_E_GENERAL;
        }
        *value = (float)v;
        return DRV_OK;
    }
    switch (id) {
    case DRV_P_SIM_FC_VOLT: v = p->coulomb / p->km; break;
    case DRV_P_SIM_FV_VOLT: v = p->viscous / p->km; break;
    case DRV_P_SIM_FS_VOLT: v = p->stat / p->km; break;
    case DRV_P_SIM_NOISE_STD: v = p->noise_std; break;
    case DRV_P_SIM_FC_TORQUE: v = p->coulomb; break;
    default: return DRV_E_NO_PARAM;
    }
    if (value == NULL) {
        return DRV_E_GENERAL;
    }
    *value = (float)v;
    return DRV_OK;
}
