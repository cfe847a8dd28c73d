/* msm_plant: two-mass stage with Maxwell-slip friction, current-loop lag, one-step delay (model.c) */
#ifndef MODEL_H
#define MODEL_H
#define MODEL_GUID "msm-plant-2.1.0-7f3e"
#define MODEL_DEFAULT_TOLERANCE 1e-4
#define MSM_MAX 8
enum { R_U, R_PHI1, R_PHI2, R_W1, R_W2, R_TAU, R_TAUI, R_J1, R_J2, R_K, R_D, R_KM, R_B, R_FTOT, R_FAILT, NR };
enum { I_NELEM, I_FAILMODE, NI };
enum { B_DELAY, NB };
typedef struct {
    double r[NR];
    int i[NI];
    int b[NB];
    double tolerance;
    char resources[1024];
    double k[MSM_MAX], fmax[MSM_MAX], z[MSM_MAX];
    int n_file;
    double u_prev;
} Model;
void model_defaults(Model *m);
int model_settable(const Model *m, int type, unsigned vr, int stepping);
int model_init(Model *m, char *msg, unsigned long n);
int model_step(Model *m, double t, double h, char *msg, unsigned long n);
#endif
