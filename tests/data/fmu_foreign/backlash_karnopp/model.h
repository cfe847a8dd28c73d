/* bls_cs: motor with Karnopp stick-slip Coulomb friction, backlash to the load (model.c) */
#ifndef MODEL_H
#define MODEL_H
#define MODEL_GUID "{0b7d2c55-91aa-4e0e-b1f4-2d6a8c3e5f70}"
#define MODEL_DEFAULT_TOLERANCE 1e-5
enum { R_U, R_QM, R_QL, R_WM, R_WL, R_JM, R_JL, R_K, R_D, R_GAP, R_KM, R_FC, R_FS, R_BM, R_BL, R_HMAX, NR };
enum { I_IMPACTS, NI };
enum { B_WARN, NB };
typedef struct {
    double r[NR];
    int i[NI];
    int b[NB];
    double tolerance;
    char resources[1024];
    int contact;
} Model;
void model_defaults(Model *m);
int model_settable(const Model *m, int type, unsigned vr, int stepping);
int model_init(Model *m, char *msg, unsigned long n);
int model_step(Model *m, double t, double h, char *msg, unsigned long n);
#endif
