/*
 * sim.h - host simulation: the simulated plant coupled to the drive core (HOST ONLY).
 *
 * One controller step (sim_step): measure the plant (quantised, noisy angles) ->
 * drv_step (the deployable controller, excitation, recorder) -> advance the plant by
 * 1/fs with the drive's output held. Used by port/main.c (drive_sim) and by the tests.
 *
 *   sim_t *sim = sim_new_from_file("configs/plant_twomass.yaml", err, sizeof err);
 *   drv_t *drv = sim_drv(sim);           // the drive: drv_set_*, drv_run_start, ...
 *   drv_enable(drv, true);
 *   sim_run(sim, 2560);                  // or sim_step() per tick
 *   sim_get_f32(sim, DRV_P_SIM_FC_VOLT, &fc_volt);   // the plant's truth (sim_only ids)
 *   sim_free(sim);
 */
#ifndef SIM_H
#define SIM_H

#include <stddef.h>
#include <stdint.h>

#include "drv.h"
#include "plant.h"
#include "plant_config.h"

/* Capacity of the drive's table download staging buffer in sim_t (floats): the largest
 * drive.table_capacity sim_init accepts. drive_sim holds the drive's maximum (DRV_TABLE_MAX);
 * a port short of RAM builds with -DSIM_TABLE_STAGE_MAX=n (the processor-in-the-loop build:
 * its table capacity, pil.mk MCU_TABLE_MAX; the host reads the drive's table capacity from
 * 0x2003:2). Every object that sees sim_t must be built with the same value. */
#ifndef SIM_TABLE_STAGE_MAX
#define SIM_TABLE_STAGE_MAX DRV_TABLE_MAX
#endif

/* An external plant (drive_sim's FMU plant, port/fmu_plant.h) in place of the built-in
 * two-mass model: sim_step reads its angles through the built-in plant's sensor
 * (quantisation, noise: plant_measure_angles), steps the drive, then advances it by 1/fs
 * with the drive's output held. advance returns 0, or -1 on a failure (the owner keeps the
 * message): the sim then latches ext_failed, disables the drive and holds the plant until
 * sim_init starts it again (the owner restarts its plant before that). */
typedef struct {
    void *ctx;
    int (*advance)(void *ctx, double u_volt, double dt_s);
    void (*angles)(void *ctx, double *motor_rad, double *load_rad);
} sim_plant_ext_t;

typedef struct {
    plant_config_t cfg;
    plant_t plant;          /* the built-in plant (with ext: its sensor only) */
    const sim_plant_ext_t *ext; /* NULL: the built-in plant */
    int ext_failed;         /* ext's advance failed: drive disabled, plant held */
    drv_t drv;
    drv_storage_t storage;
    double dt;               /* 1/fs */
    uint64_t steps;          /* controller steps so far */
    int drift;               /* the config has a friction drift (sim_step applies it) */
    float *owned_rec;        /* buffers allocated by sim_new (NULL with sim_init) */
    float *owned_table;
    float table_stage[SIM_TABLE_STAGE_MAX]; /* the drive's download staging buffer */
} sim_t;

/* Caller-provided buffers: rec_buf of cfg->rec_capacity floats, table_buf of
 * cfg->table_capacity floats (at most SIM_TABLE_STAGE_MAX). Applies the config's
 * controller values through drv_set_f32. 0 on success, -1 with a message naming the key in err. */
int sim_init(sim_t *sim, const plant_config_t *cfg, float *rec_buf, float *table_buf, char *err, size_t errlen);
/* sim_init with an external plant (ext NULL: as sim_init). A config naming an FMU plant
 * (cfg->fmu) needs one: sim_init refuses it. ext must outlive the sim. */
int sim_init_ext(sim_t *sim, const plant_config_t *cfg, const sim_plant_ext_t *ext, float *rec_buf,
                 float *table_buf, char *err, size_t errlen);
/* Heap-allocated sim (host): NULL with the message in err on failure. */
sim_t *sim_new(const plant_config_t *cfg, char *err, size_t errlen);
sim_t *sim_new_from_file(const char *path, char *err, size_t errlen);
void sim_free(sim_t *sim);

drv_t *sim_drv(sim_t *sim);
plant_t *sim_plant(sim_t *sim);

/* One controller step (the control interrupt's work, no drv_background); returns the plant
 * input [V]. A caller that steps with sim_step calls drv_background between steps. */
float sim_step(sim_t *sim);
/* steps x (sim_step, then drv_background: a main loop between control steps) */
void sim_run(sim_t *sim, uint64_t steps);
/* Steps (with drv_background) until the run is no longer settling/recording (at most
 * max_steps); returns steps taken. */
uint64_t sim_run_until_idle(sim_t *sim, uint64_t max_steps);

/* The simulated plant's truth for the sim_only ids of configs/od.yaml (DRV_P_SIM_*):
 * Coulomb / viscous / static friction expressed as input voltage (torque / km), so they
 * compare with K_fc and K_v directly; noise std [rad]; Coulomb torque [N m]. With an external
 * plant: the config's truth: section (NaN where not given; the Coulomb torque NaN).
 * DRV_E_NO_PARAM for any other id (those are the drive's: drv_get_f32). */
drv_status_t sim_get_f32(const sim_t *sim, drv_param_id_t id, float *value);

#endif /* SIM_H */
