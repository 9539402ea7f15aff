/*
 * proprio.h -- the one public header of the C port of the proprioception chain.
 *
 * C99, no heap, no globals: every function works on caller-owned structs and takes its
 * inputs as const. Build with -DPS_FLOAT for a float32 build (ps_real = float); the default
 * is double, which matches the numpy core to round-off.
 *
 * Sections: (1) common types and status codes, (2) the Mileusnic 2006 spindle
 * (spindle.c), (3) the on-prosthesis chain: median filter, f(x), fitted lengths, tracking
 * low-pass, fusimotor, one arm (chain.c).
 */
#ifndef PROPRIO_H
#define PROPRIO_H

#ifdef __cplusplus
extern "C" {
#endif

/* ======================================================================================
 * (1) Common
 * ====================================================================================== */

#ifdef PS_FLOAT
typedef float ps_real;
#else
typedef double ps_real;
#endif

/* Status codes: every function that can fail returns one; on failure the state it was
 * given is left exactly as it was. */
enum ps_status {
    PS_OK = 0,
    PS_ERR_NULL = 1,          /* a required pointer is NULL */
    PS_ERR_NONFINITE = 2,     /* an input is NaN or infinite */
    PS_ERR_LENGTH_RANGE = 3,  /* a length outside [PS_LENGTH_MIN_L0, PS_LENGTH_MAX_L0] */
    PS_ERR_NEGATIVE_DRIVE = 4,/* a fusimotor rate < 0 */
    PS_ERR_STEP = 5,          /* a step <= 0 or above the method's limit */
    PS_ERR_SPEED = 6,         /* a length change faster than PS_MAX_SPEED_L0_S */
    PS_ERR_NO_CONVERGENCE = 7,/* the implicit solve did not converge */
    PS_ERR_METHOD = 8,        /* theta outside [0, 1] */
    PS_ERR_CONFIG = 9         /* an unusable configuration (chain) */
};

#define PS_LENGTH_MIN_L0 0.5
#define PS_LENGTH_MAX_L0 1.5
#define PS_MAX_SPEED_L0_S 10.0
#define PS_NFIBRES 3 /* bag1, bag2, chain */

/* ======================================================================================
 * (2) Spindle (spindle.c) -- same model, state layout and order of operations as
 *     spindle/core.py. Fibre arrays are indexed bag1, bag2, chain.
 * ====================================================================================== */

/* Constants of one spindle: the fields of spindle.FibreParams per fibre, plus S. */
typedef struct ps_params {
    ps_real KSR[PS_NFIBRES], KPR[PS_NFIBRES], M[PS_NFIBRES];
    ps_real beta0[PS_NFIBRES], beta_drive[PS_NFIBRES], Gamma_drive[PS_NFIBRES];
    ps_real CL[PS_NFIBRES], CS[PS_NFIBRES], R[PS_NFIBRES], a[PS_NFIBRES];
    ps_real LSR0[PS_NFIBRES], LPR0[PS_NFIBRES], LNSR[PS_NFIBRES], LNPR[PS_NFIBRES];
    ps_real X[PS_NFIBRES], Lsec[PS_NFIBRES], G_pri[PS_NFIBRES], G_sec[PS_NFIBRES];
    ps_real freq[PS_NFIBRES], p[PS_NFIBRES], tau[PS_NFIBRES];
    ps_real S;
} ps_params;

/* State of one spindle (the fields of spindle.SpindleState for one spindle). */
typedef struct ps_spindle {
    ps_real T[PS_NFIBRES]; /* sensory-region tension (FU) */
    ps_real v[PS_NFIBRES]; /* polar-region velocity (L0/s) */
    ps_real z[PS_NFIBRES]; /* sgn(v)|v|^(a/3) */
    ps_real f[PS_NFIBRES]; /* fusimotor activation */
    ps_real L;             /* fascicle length at the state's time (L0) */
    ps_real gd, gs;        /* fusimotor drive at the state's time (pps) */
} ps_spindle;

/* At rest at length L with drive (gd, gs): spindle.equilibrium_state. */
int ps_spindle_init(ps_spindle *s, const ps_params *p, ps_real L, ps_real gd, ps_real gs);

/* One theta-method step of h seconds to (L1, gd1, gs1): spindle.step without its checks of
 * the method's step limit (the caller's choice). theta = 0, 0.5, 1: forward Euler,
 * trapezoidal, backward Euler. Writes Ia, II (pps) if the pointers are not NULL. */
int ps_spindle_step(ps_spindle *s, const ps_params *p, ps_real L1, ps_real gd1, ps_real gs1,
                    ps_real h, ps_real theta, ps_real *ia, ps_real *ii);

/* Ia and II (pps) of the state: spindle.afferents. */
void ps_spindle_afferents(const ps_spindle *s, const ps_params *p, ps_real *ia, ps_real *ii);

/* ---- spindle section: further declarations go below this line (spindle.c owner) ---- */

/* PS_OK if every constant of p is finite and KSR, M, freq, p, CL, CS > 0, 0 < a < 1,
 * tau >= 0 (the checks of spindle.FibreParams); PS_ERR_CONFIG otherwise. The step functions
 * assume valid constants (bad ones give a status or non-finite rates, never UB). */
int ps_params_check(const ps_params *p);

/* n_steps steps of h seconds through L[j], gd[j], gs[j] (j = 0 .. n_steps-1, the values at
 * the end of step j): ps_spindle_step in a loop. After every `every`-th step (every >= 1)
 * the rates are written to ia[k], ii[k], k = (j+1)/every - 1 (NULL outputs are skipped).
 * Stops at the first failing step and returns its status; *done (if not NULL) receives the
 * number of steps completed, and the state is the one after the last of them. */
int ps_spindle_run(ps_spindle *s, const ps_params *p, const ps_real *L, const ps_real *gd,
                   const ps_real *gs, long n_steps, ps_real h, ps_real theta, long every,
                   ps_real *ia, ps_real *ii, long *done);


/* ---- embedded fast path ---------------------------------------------------------------
 * Everything of a step that depends only on (params, h, theta), precomputed once by
 * ps_plan_init (reciprocals, products, the activation filter's coefficients), so that
 * ps_spindle_step_plan does one divide per fibre for the activation target (none when the
 * drive did not change since the last step... apart from the target of the new drive) and
 * one per Newton iteration. Same equations and state as ps_spindle_step; the results differ
 * from it by round-off only (x * (1/k) for x / k). A plan is read-only after init: it can
 * live in flash (const) and be shared by any number of spindles with the same constants.
 *
 * Compile-time options (both paths): PS_NEWTON_ITER=n takes exactly n Newton iterations
 * and never reports PS_ERR_NO_CONVERGENCE (default: iterate to |dz| <= PS_NEWTON_TOL_Z,
 * at most 60); PS_FAST_CBRT replaces the C library's cbrt of the starting guess by a bit
 * estimate refined by PS_CBRT_REFINE Newton steps (default 2; no libm call on the implicit
 * path). */
typedef struct ps_plan {
    ps_real h, theta, one_minus_theta, th_h, max_dL, S;
    int p_is_2, a_is_03, explicit_step, uses_F0; /* theta == 0, theta < 1 */
    ps_real KSR[PS_NFIBRES], inv_KSR[PS_NFIBRES];
    ps_real c_f0[PS_NFIBRES], c_a0[PS_NFIBRES], c_a1[PS_NFIBRES]; /* f1 = c_f0 f0 + ... */
    ps_real c_a01[PS_NFIBRES];                                     /* c_a0 + c_a1 */
    int lagged[PS_NFIBRES];
    ps_real freq_p[PS_NFIBRES], p[PS_NFIBRES], a[PS_NFIBRES];
    ps_real beta0[PS_NFIBRES], beta_drive[PS_NFIBRES], Gamma_drive[PS_NFIBRES];
    ps_real CL[PS_NFIBRES], CS[PS_NFIBRES], KPR[PS_NFIBRES], LPR0[PS_NFIBRES], R[PS_NFIBRES];
    ps_real LSR0[PS_NFIBRES], LSR0_R[PS_NFIBRES], LSR0_LPR0[PS_NFIBRES];
    ps_real h_KSR[PS_NFIBRES], h_M[PS_NFIBRES];          /* forward Euler */
    ps_real c_Av[PS_NFIBRES], a2[PS_NFIBRES], inv_a2[PS_NFIBRES], M_h[PS_NFIBRES];
    ps_real th_h_KSR[PS_NFIBRES];
    ps_real th_k1[PS_NFIBRES], th_KPR[PS_NFIBRES], th_CS[PS_NFIBRES], th_dC[PS_NFIBRES];
    ps_real stretch0[PS_NFIBRES], G_pri[PS_NFIBRES], c_sec1[PS_NFIBRES], c_sec2[PS_NFIBRES];
    ps_real sec_off[PS_NFIBRES];
} ps_plan;

/* Fill q for constants p, step h (s) and theta. PS_ERR_NULL, PS_ERR_CONFIG (p refused by
 * ps_params_check), PS_ERR_STEP (h not finite and > 0), PS_ERR_METHOD (theta outside
 * [0, 1]); q is untouched on failure. */
int ps_plan_init(ps_plan *q, const ps_params *p, ps_real h, ps_real theta);

/* ps_spindle_step with a plan: one step of q->h to (L1, gd1, gs1). Same status codes and
 * failure rule (state and outputs untouched). */
int ps_spindle_step_plan(ps_spindle *s, const ps_plan *q, ps_real L1, ps_real gd1,
                         ps_real gs1, ps_real *ia, ps_real *ii);

/* ---- end of spindle section ---- */


/* ======================================================================================
 * (3) Chain (chain.c) -- spindle/chain.py, spindle/sensor.py, spindle/derivatives.py,
 *     spindle/fusimotor.py, spindle/length_fits.py for one arm (BRA, TRImed).
 * ====================================================================================== */

/* ---- chain section: declarations go below this line (chain.c owner) ---- */


/* ---- end of chain section ---- */

#ifdef __cplusplus
}
#endif

#endif /* PROPRIO_H */
