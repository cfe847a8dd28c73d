/*
 * fmu_model.h - the example FMUs' model interface (HOST ONLY; docs/fmu.md).
 *
 * fmu_slave.c implements the FMI 2.0 co-simulation functions once; each model (fmu/NAME/
 * model.c) supplies its state and three functions, and fmugen.py writes the model's
 * variable table (vars.c: value references = indices into r[], start values, causality)
 * and modelDescription.xml from the one spec fmu/NAME/model.yaml.
 *
 * All variables are Real; r[] holds every variable's present value (parameters and the
 * input set by the importer, outputs written by the model).
 */
#ifndef FMU_MODEL_H
#define FMU_MODEL_H

#include <stddef.h>

enum { FMU_PARAMETER = 0, FMU_INPUT = 1, FMU_OUTPUT = 2 };

/* vars.c (generated) */
extern const char fmu_guid[];
extern const unsigned fmu_nvars;
extern const double fmu_start[];
extern const unsigned char fmu_causality[];
extern const char *const fmu_names[];

/* model.c */
size_t model_size(void);
/* At fmi2ExitInitializationMode: check the parameters in r, set the state, write the
 * outputs to r. 0, or -1 with a message naming the parameter. */
int model_init(void *m, double *r, char *msg, size_t msglen);
/* Advance from t by h with the input r held; write the outputs. 0, or -1 with a message. */
int model_step(void *m, double *r, double t, double h, char *msg, size_t msglen);

#endif /* FMU_MODEL_H */
