/* EPStage: two-mass stage, elasto-plastic friction (Dupont et al. 2002) at the motor (model.c) */
#ifndef MODEL_H
#define MODEL_H
#define MODEL_GUID "{e1a5b0c2-7d3f-4b8e-a9c6-3f2e1d0c9b8a}"
#define MODEL_DEFAULT_TOLERANCE 1e-6
#define CS2_ONCE_PER_PROCESS 1
enum { R_U, R_PHI, R_W, R_LPHI, R_LW, R_Z, R_F, R_J1, R_J2, R_K, R_D, R_KM, R_FC, R_FS, R_VS, R_S0, R_S1, R_S2,
       R_ZBA, NR };
enum { I_NSUB, NI };
enum { B_DUMMY, NB };
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
