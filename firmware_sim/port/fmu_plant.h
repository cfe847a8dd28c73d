/*
 * fmu_plant.h - an FMI 2.0 / 3.0 co-simulation FMU as drive_sim's plant (HOST ONLY, docs/fmu.md).
 *
 * The host (fftune, host/sim.py prepare_plant) unpacks the FMU, checks its
 * modelDescription.xml with FMPy and writes drive_sim a plant file whose `fmu:` section names
 * what this module needs (one `key: value` a line, strings in double quotes):
 *
 *   fmu:
 *     source: "configs/plant_lugre_fmu.yaml"   the user's plant file (messages)
 *     path: "build/fmu/lugre.fmu"              the FMU (messages)
 *     fmi_version: 2                           2 or 3
 *     unzipdir: "/root/.cache/fftune/fmu/..."  the unpacked FMU
 *     model_identifier: "fftune_lugre"         binaries/linux64/<model_identifier>.so
 *                                              (FMI 3.0: binaries/x86_64-linux/)
 *     guid: "{...}"                            (FMI 3.0: the instantiation token)
 *     input: "u"                               the drive's output [V] (Real, causality input)
 *     input_vr: 0
 *     output: "theta1"                         the motor encoder [rad] (Real, output)
 *     output_vr: 1
 *     load_output: "theta2"                    optional: the load encoder (else = output)
 *     load_output_vr: 3
 *     tolerance: 1e-06                         optional: the FMU's DefaultExperiment tolerance, passed
 *                                              to fmi2SetupExperiment / fmi3EnterInitializationMode (as FMPy does)
 *     once_per_process: 1                      optional: canBeInstantiatedOnlyOncePerProcess: one
 *                                              instance for the process' life (trial and NMT reset
 *                                              through fmi2Reset / fmi3Reset; a second axis refused)
 *     p0_name: "Fc"                            start values, p0 .. p31: name, value
 *     p0_vr: 7                                 reference, type (real, integer, boolean: FMI 3.0 Float64, Int32, Boolean)
 *     p0_type: "real"
 *     p0_value: 0.0058
 *
 * fmup_open loads the library, instantiates (fmi2Instantiate / fmi3InstantiateCoSimulation), sets the start values,
 * initialises (SetupExperiment at t = 0, Enter/ExitInitializationMode) and reads the output;
 * fmup_trial also takes one step of dt with u = 0 on a throw-away instance first, so an FMU
 * that cannot step fails before the drive exists. Every failure is one message naming the
 * user's plant file, the FMU and the function or variable; so is a crash inside the FMU
 * (SIGSEGV, SIGBUS, SIGFPE, SIGILL, SIGABRT) and a call that hangs (SIGALRM every second,
 * installed by fmup_open: a step may take 1 to 2 s, loading and initialising 8 s), with
 * drive_sim's exit status 2.
 *
 *   fmup_t f; fmup_cfg_t c;
 *   fmup_config_load(path, &c, err, n);  fmup_open(&f, &c, dt, err, n);
 *   sim_init_ext(&sim, &cfg, fmup_ext(&f), ...);   ... fmup_close(&f);
 */
#ifndef FMU_PLANT_H
#define FMU_PLANT_H

#include <stddef.h>

#include "sim.h"

#define FMUP_PARAMS_MAX 32
#define FMUP_STR 512

typedef enum { FMUP_REAL, FMUP_INTEGER, FMUP_BOOLEAN } fmup_type_t;

typedef struct {
    char name[FMUP_STR];
    unsigned vr;
    fmup_type_t type;
    double value;
} fmup_param_t;

typedef struct {
    char source[FMUP_STR];
    char path[FMUP_STR];
    int fmi_version;
    char unzipdir[FMUP_STR];
    char model_identifier[FMUP_STR];
    char guid[FMUP_STR];
    char input[FMUP_STR];
    unsigned input_vr;
    char output[FMUP_STR];
    unsigned output_vr;
    char load_output[FMUP_STR];
    unsigned load_output_vr;
    int has_load_output;
    double tolerance;       /* > 0 if has_tolerance */
    int has_tolerance;
    int once_per_process;
    int n_params;
    fmup_param_t param[FMUP_PARAMS_MAX];
} fmup_cfg_t;

typedef struct fmup fmup_t;

/* 0, or -1 with "file:line: message" in err. */
int fmup_config_load(const char *path, fmup_cfg_t *cfg, char *err, size_t errlen);
/* Load, trial step (u = 0 for dt_s on a throw-away instance), instantiate and initialise.
 * NULL with the message in err. */
fmup_t *fmup_open(const fmup_cfg_t *cfg, double dt_s, char *err, size_t errlen);
/* fmup_config_load + fmup_open. */
fmup_t *fmup_open_file(const char *path, double dt_s, char *err, size_t errlen);
/* A fresh instance at t = 0 (NMT reset node); 0, or -1 with the message in err. */
int fmup_restart(fmup_t *f, char *err, size_t errlen);
/* The sim's external plant (plant/sim.h) of this FMU. */
const sim_plant_ext_t *fmup_ext(fmup_t *f);
/* The message of the last failure ("" if none). */
const char *fmup_error(const fmup_t *f);
/* Steps taken and simulated time [s] of the present instance. */
double fmup_time(const fmup_t *f);
void fmup_close(fmup_t *f);

#endif /* FMU_PLANT_H */
