/* twomass/model.c - the built-in plant (plant/plant.c, unchanged) behind fmu_model.h. */
#include <math.h>
#include <stdio.h>

#include "fmu_model.h"
#include "plant.h"
#include "vars.h"

size_t model_size(void)
{
    return sizeof(plant_t);
}

static void model_outputs(const plant_t *pl, double *r)
{
    r[VR_theta1] = pl->x[0];
    r[VR_omega1] = pl->x[1];
    r[VR_theta2] = pl->x[2];
    r[VR_omega2] = pl->x[3];
}

int model_init(void *m, double *r, char *msg, size_t msglen)
{
    double sub = r[VR_substeps];
    if (!(sub >= 1.0 && sub <= 10000.0) || sub != floor(sub)) {
        snprintf(msg, msglen, "parameter substeps = %g: a whole number 1 .. 10000", sub);
        return -1;
    }
    plant_params_t p = {
        .j1 = r[VR_j1], .j2 = r[VR_j2], .k = r[VR_k], .c = r[VR_c], .km = r[VR_km], .coulomb = r[VR_coulomb],
        .coulomb_asym = r[VR_coulomb_asymmetry], .coulomb_pos = r[VR_coulomb_position], .stat = r[VR_static],
        .stribeck_vel = r[VR_stribeck_velocity], .viscous = r[VR_viscous], .load_viscous = r[VR_load_viscous],
        .substeps = (uint32_t)sub,
    };
    char err[200];
    if (plant_init(m, &p, err, sizeof err) != 0) {
        snprintf(msg, msglen, "parameter %s", err);
        return -1;
    }
    model_outputs(m, r);
    return 0;
}

int model_step(void *m, double *r, double t, double h, char *msg, size_t msglen)
{
    (void)t;
    double u = r[VR_u];
    if (!isfinite(u)) {
        snprintf(msg, msglen, "input u = %g is not finite", u);
        return -1;
    }
    plant_advance(m, u, h);
    model_outputs(m, r);
    return 0;
}
