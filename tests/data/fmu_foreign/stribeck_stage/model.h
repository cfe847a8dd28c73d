/* StribeckStage: two-mass stage, motor friction smooth Stribeck + viscous (model.c) */
#ifndef MODEL_H
#define MODEL_H
#define MODEL_GUID "{5c1e7a8e-3f0b-4d6c-9a41-7b2f0e9d1c11}"
#define MODEL_DEFAULT_TOLERANCE 1e-6
#define CS2_CHATTY 1
/* Real value references */
enum { R_U, R_PHI, R_W, R_DPHI, R_LPHI, R_LW, R_J1, R_J2, R_K, R_D, R_KM, R_FC, R_FS, R_VS, R_VEPS, R_B, R_RATIO,
       R_TM, NR };
enum { I_NSUB, NI };
enum { B_VISCOUS, NB };
typedef struct {
    double r[NR];
    int i[NI];
    int b[NB];
    double tolerance;
    char resources[1024];
} Model;
void model_defaults(Model *m);
int model_settable(const Model *m, int type, unsigned vr, int stepping);
int model_init(Model *m, char *msg, unsigned long n);
int model_step(Model *m, double t, double h, char *msg, unsigned long n);
#endif
