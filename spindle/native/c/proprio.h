/*
 * proprio.h -- the one public header of the C port of the proprioception chain.
 *
 * C99, no heap, no globals: every function works on caller-owned structs and takes its
 * inputs as const. Build with -DPS_FLOAT for a float32 build (ps_real = float); the default
 * is double, which matches the numpy core to round-off.
 *
 * Sections: (1) common types and status codes, (2) the Mileusnic 2006 spindle
 * (spindle.c), (3) the on-prosthesis chain: median filter, f(x), fitted lengths, tracking
 * low-pass, fusimotor, one arm (chain.c), (4) the Lin & Crago 2002 Golgi tendon organ
 * (tendon_organ.c), (5) the stimulator stage: rates into charge-balanced pulse events
 * (stimulation.c).
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
    PS_ERR_CONFIG = 9,        /* an unusable configuration (chain) */
    PS_ERR_ANGLE_RANGE = 10,  /* reserved (ps_chain_reset now clamps the angle) */
    PS_ERR_NOT_RESET = 11,    /* a chain used before ps_chain_init and ps_chain_reset */
    PS_ERR_INTERVAL = 12,     /* an interval needing more than PS_CHAIN_MAX_UPDATES spindle
                                 sub-steps or predictor updates: a guard, not reached with a
                                 config ps_chain_init accepted (longer intervals restart) */
    PS_ERR_ARGUMENT = 13,     /* a count or index argument out of range (batch calls: a
                                 negative n_arms or k, n_samples[i] outside 0..k, an arm
                                 index outside 0..n_arms-1) */
    PS_ERR_FORCE_RANGE = 14,  /* a tendon force above PS_GTO_MAX_FORCE_N (tendon organ) */
    PS_ERR_BUFFER_FULL = 15,  /* an event buffer cannot hold a call's pulses (stimulation):
                                 nothing was changed */
    PS_ERR_CHARGE = 16        /* a channel's largest pulse exceeds a charge-safety limit
                                 (charge per phase, or the Shannon criterion) */
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

/* ---- batches of independent spindles ------------------------------------------------
 * n spindles in one caller-owned array, all with the constants and step of plan q.
 * Compiled unless PS_NO_BATCH is defined (a one-muscle device build does not need them).
 *
 * ps_spindle_batch_step: spindle j takes ps_spindle_step_plan(&s[j], q, L1[j], gd1[j],
 * gs1[j], ia + j, ii + j) (ia, ii may be NULL: no rates), bit for bit; on x86-64 CPUs with
 * AVX2 (GCC or Clang) and the implicit a = 0.3, p = 2 plan it computes 8 spindles at a time
 * in SIMD lanes (the same operations per lane). Atomic: if spindle j fails, every
 * spindle is left exactly as it was before the call, the status of j's step is returned,
 * *failed (if not NULL) receives j (-1 on success) and the contents of ia, ii are
 * unspecified. No heap: `backup` is n states of working memory (ignored on entry,
 * meaningless after). PS_ERR_ARGUMENT for n < 0, PS_ERR_NULL for a NULL s, q, L1, gd1, gs1
 * or backup when n > 0.
 *
 * ps_spindle_batch_steps: `steps` calls of ps_spindle_batch_step in one, step t on
 * L1 + t*n, gd1 + t*n, gs1 + t*n (row-major (steps, n) arrays); Ia and II of the last step
 * only (ia, ii may be NULL). Atomic over all steps: if step t fails, every spindle is left
 * as it was before the call, *failed_step (if not NULL) receives t and *failed the spindle
 * (both -1 on success). `start` and `backup` are n states of working memory each.
 * PS_ERR_ARGUMENT for n < 0 or steps < 0, PS_ERR_NULL for a NULL pointer other than ia,
 * ii, failed_step, failed when n, steps > 0.
 *
 * ps_spindle_batch_afferents: Ia and II (pps) of each state into ia[j], ii[j] (the rates
 * ps_spindle_step_plan reports). PS_ERR_ARGUMENT for n < 0, PS_ERR_NULL as above. */
#ifndef PS_NO_BATCH
int ps_spindle_batch_step(ps_spindle *s, long n, const ps_plan *q, const ps_real *L1,
                          const ps_real *gd1, const ps_real *gs1, ps_spindle *backup,
                          ps_real *ia, ps_real *ii, long *failed);
int ps_spindle_batch_steps(ps_spindle *s, long n, long steps, const ps_plan *q,
                           const ps_real *L1, const ps_real *gd1, const ps_real *gs1,
                           ps_spindle *start, ps_spindle *backup, ps_real *ia, ps_real *ii,
                           long *failed_step, long *failed);
int ps_spindle_batch_afferents(const ps_spindle *s, long n, const ps_plan *q, ps_real *ia,
                               ps_real *ii);
#endif /* PS_NO_BATCH */

/* ---- fixed-point step (Cortex-M0+ and other cores without an FPU) ---------------------
 * The trapezoidal-family step of ps_spindle_step_plan (theta in (0, 1], a = 0.3, p = 2) in
 * int32 arithmetic: products round(a * b / 2^24) from 16-bit halves (the M0+ multiplies
 * 32x32->32 only), divides by a reciprocal (a linear estimate and two Newton-Raphson steps);
 * no float, no libgcc call on the step's path. Same model, same state quantities, same status codes. Q formats (value = int / 2^k):
 *   Q24 (PS_FX_ONE): lengths L (L0), T (tension), v (L0/s), z = sgn(v)|v|^0.1, f, targets
 *                    and every plan constant except the gains;
 *   Q8  (PS_FX_DRIVE_ONE): fusimotor drives gd, gs (pps);
 *   Q16 (PS_FX_RATE_ONE): the rates Ia, II (pps) and the gains G_pri, c_sec1, c_sec2.
 * ps_plan_fx_init computes, from the constants, worst-case bounds of every intermediate of
 * the step over the state and input ranges below and refuses (PS_ERR_CONFIG) constants for
 * which one could leave +-64 in Q24 (2^30) or a rate +-32767 pps: with a plan it accepted,
 * no int32 overflows. State ranges (checked at each step; outside: PS_ERR_NONFINITE, the
 * fixed-point analogue of a non-finite state): |T| <= PS_FX_T_MAX, |z| <= PS_FX_Y_MAX
 * (so |v| <= PS_FX_Y_MAX^10 = 80.1 L0/s), 0 <= f, target <= 1, L in [0.5, 1.5] L0, drives in
 * [0, 2^31). A step whose result leaves those ranges returns PS_ERR_NONFINITE and writes
 * nothing. */
#include <stdint.h>

#define PS_FX_Q 24
#define PS_FX_ONE 16777216L          /* 1.0 in Q24 */
#define PS_FX_DRIVE_ONE 256L         /* 1 pps in Q8 */
#define PS_FX_RATE_ONE 65536L        /* 1 pps in Q16 */
#define PS_FX_T_MAX 4                /* |T| bound of the state */
#define PS_FX_Y_MAX 1.55             /* |z| bound of the state */
#define PS_FX_ROOT_TABLE 31

/* State of one spindle in fixed point: the fields of ps_spindle in the Q formats above, plus
 * the activation targets of the current drives (a function of gd, gs kept so that a step
 * with unchanged drives needs no divide). */
typedef struct ps_spindle_fx {
    int32_t T[PS_NFIBRES], v[PS_NFIBRES], z[PS_NFIBRES], f[PS_NFIBRES], target[PS_NFIBRES];
    int32_t L, gd, gs;
} ps_spindle_fx;

/* Precomputed constants of the fixed-point step (read-only after ps_plan_fx_init; can be a
 * const in flash). All Q24 except freq (pps, Q8) and the rate gains G_T .. s_0 (Q16). The
 * step's equation is written in the state (fx_fibre in spindle.c says how). One struct per
 * fibre: the Cortex-M0+ loads a word at an offset of at most 124 bytes from a pointer in one
 * instruction, so a fibre's constants are all one load away. */
typedef struct ps_plan_fx_fibre {
    int32_t KSR, inv_KSR, inv_k1, thKSR, c_f0, c_fa, freq;
    int32_t Gamma_drive, KPR, LSR0_R, LSR0_LPR0, cv, c_Av, th_h_KSR, a2, inv_a2, r_cap;
    int32_t thCL_b0, thCL_bd, thCS_b0, thCS_bd, omCL_b0, omCL_bd, omCS_b0, omCS_bd;
    int32_t G_T, G_0, cs_T, c_sec2, s_0;
} ps_plan_fx_fibre;

typedef struct ps_plan_fx {
    int32_t max_dL, one_minus_theta, th_h, om_h, S, tol, y_max, v_max;
    int32_t dg_shift; /* Newton's derivative is computed divided by 2^dg_shift */
    ps_plan_fx_fibre fibre[PS_NFIBRES];
    int32_t root10[PS_FX_ROOT_TABLE]; /* 2^((k - 23)/10): bounds of x^(1/10), x < 2^(k+1) */
} ps_plan_fx;

/* Fill q for constants p, step h (s) and theta in (0, 1] (computed in ps_real: on the host,
 * or once at start-up). PS_ERR_NULL; PS_ERR_CONFIG (p refused by ps_params_check, a != 0.3,
 * p != 2, or a constant or a worst-case intermediate outside its Q range); PS_ERR_STEP (h not
 * finite and > 0); PS_ERR_METHOD (theta outside (0, 1]). q is untouched on failure. */
int ps_plan_fx_init(ps_plan_fx *q, const ps_params *p, ps_real h, ps_real theta);

/* At rest at length L (Q24) with drives gd, gs (Q8): ps_spindle_init in fixed point.
 * PS_ERR_NULL, PS_ERR_LENGTH_RANGE, PS_ERR_NEGATIVE_DRIVE; s is untouched on failure. */
int ps_spindle_fx_init(ps_spindle_fx *s, const ps_plan_fx *q, int32_t L, int32_t gd,
                       int32_t gs);

/* One step of the plan's h to (L1 Q24, gd1 Q8, gs1 Q8); rates in Q16 pps (NULL outputs
 * skipped). Checks in this order: PS_ERR_NULL, PS_ERR_LENGTH_RANGE, PS_ERR_NEGATIVE_DRIVE,
 * PS_ERR_NONFINITE (the state outside its ranges), PS_ERR_SPEED; then at run time
 * PS_ERR_NO_CONVERGENCE or PS_ERR_NONFINITE (a result outside its range). On failure the
 * state and outputs are untouched. */
int ps_spindle_step_fx(ps_spindle_fx *s, const ps_plan_fx *q, int32_t L1, int32_t gd1,
                       int32_t gs1, int32_t *ia, int32_t *ii);

/* Ia and II (Q16 pps) of a state; writes nothing if s or q is NULL or the state is outside
 * its ranges. */
void ps_spindle_fx_afferents(const ps_spindle_fx *s, const ps_plan_fx *q, int32_t *ia,
                             int32_t *ii);

/* ---- end of spindle section ---- */


/* ======================================================================================
 * (3) Chain (chain.c) -- spindle/chain/ (arm.py, sensor.py, length_model.py,
 *     conditioning.py, fusimotor.py) for one arm (BRA, TRImed).
 * ====================================================================================== */

#define PS_MUSCLES 2                 /* BRA, TRImed: the order of every per-muscle array */
#define PS_MEDIAN_MAX_WINDOW 15      /* largest median window (odd) */
#define PS_FIT_MAX_COEFFS 16         /* largest Chebyshev series of a length fit */
#define PS_PREDICTOR_MAX_SEGMENTS 16 /* ceil(delay_s * predictor_rate_hz) + 2 must fit */
#define PS_CHAIN_MAX_UPDATES 1000000L
/* ps_chain_init refuses a max_bridge_s needing more spindle sub-steps or predictor updates
 * than this (chain.MAX_BRIDGE_UPDATES): a push's work is bounded by it. */
#define PS_CHAIN_MAX_BRIDGE_UPDATES 100000L
/* Largest resync_after_samples (chain.MAX_RESYNC_AFTER_SAMPLES). */
#define PS_CHAIN_MAX_RESYNC 1000000L
/* Longest moment-arm table of the force sense (spindle/chain/force.py; the bundled one: 262). */
#define PS_MOMENT_ARM_MAX_POINTS 320
/* The servo's load word (spindle/chain/sensor.py): bits 0-9 the magnitude, bit 10 set for a
 * clockwise load; valid words are the integers 0..PS_LOAD_MAX_WORD. */
#define PS_LOAD_MAGNITUDE_MAX 1023
#define PS_LOAD_MAX_WORD 2047
/* The shortest moment arm a force is divided by (m; force.MIN_MOMENT_ARM_M). */
#define PS_MIN_MOMENT_ARM_M 1e-3

/* Times are double in both builds: a float clock cannot resolve 2 ms after a few hours. */
typedef double ps_time;

/* ---- sensor (spindle/chain/sensor.py) ---- */

/* Streaming causal median of the last `window` samples (MedianFilter). */
typedef struct ps_median {
    ps_real values[PS_MEDIAN_MAX_WINDOW]; /* ring buffer */
    int window;                           /* odd, 1..PS_MEDIAN_MAX_WINDOW */
    int next;                             /* slot the next sample overwrites */
} ps_median;

/* Fill the window with `value` (a signal at rest). PS_ERR_CONFIG for a bad window. */
int ps_median_reset(ps_median *m, int window, ps_real value);
/* Add one sample; returns the median (the sample itself if m is NULL or never reset). */
ps_real ps_median_push(ps_median *m, ps_real value);

/* is_valid_reading: 1 for an integer reading in 0..max_count, else 0 (NaN included). */
int ps_is_valid_reading(ps_real counts, ps_real max_count);

/* ---- length model (spindle/chain/length_model.py): Chebyshev series in the elbow angle ---- */

/* sum_k c_k T_k(x) by Clenshaw's recurrence, in numpy.polynomial.chebyshev.chebval's
 * order of operations; n >= 1 coefficients, lowest first. */
ps_real ps_chebval(ps_real x, const ps_real *coefficients, int n);

/* ---- tracking low-pass (spindle/chain/conditioning.py) ---- */

/* tracking_step for one signal: advance (x, v) by dt_s while the input goes linearly from
 * u0 to u1; writes x1, v1, a1. dt_s > 0 and omega > 0 are the caller's duty. */
void ps_tracking_step(ps_real x, ps_real v, ps_real u0, ps_real u1, ps_real dt_s,
                      ps_real omega_rad_s, ps_real *x1, ps_real *v1, ps_real *a1);

/* ---- the tendon organ's types (section 4 declares its functions; the chain holds them) ---- */

#define PS_GTO_MAX_FORCE_N 1.0e5 /* larger finite forces: PS_ERR_FORCE_RANGE */
#define PS_GTO_MAX_STEP_S 0.1    /* longest step (s): PS_ERR_STEP above */
#define PS_GTO_MIN_FORCE_SCALE_N 1.0e-6 /* smaller G2: PS_ERR_CONFIG (MAX_FORCE_N / G2 stays finite) */

/* Constants of spindle.tendon_organ_params.TendonOrganParams (G2 is per muscle, passed to
 * each call). num = (b2, b1, b0), den = (a1, a0) of H(s). */
typedef struct ps_gto_params {
    ps_real gain_pps, tau_lowpass_s;
    ps_real num[3], den[2];
} ps_gto_params;

/* The step's constants for one (params, h), computed by ps_gto_plan_init in double (a
 * matrix exponential: a 20-term Taylor series after scaling to 1-norm <= 1/2, then
 * squarings, as spindle.tendon_organ.expm_taylor). Read-only after init. */
typedef struct ps_gto_plan {
    ps_real phi[3][3], g0[3], g1[3], c[3];
    ps_real gain_pps, inv_a0, h;
} ps_gto_plan;

/* State of one tendon organ: z = (x, w1, w2) (pps, pps s^2, pps s: the numpy state's z),
 * the rectified force (N) and the log stage (pps) at the state's time. */
typedef struct ps_gto {
    ps_real z[3], force_N, r_pps;
} ps_gto;

/* ---- chain (spindle/chain/arm.py, spindle/chain/fusimotor.py) ---- */

/* Every setting of one arm's chain: chain.ChainConfig resolved to numbers. Fill it (the
 * Python binding shows how: spindle/native/chain.py, chain_config_struct) and pass it to
 * ps_chain_init, which checks it. */
typedef struct ps_chain_config {
    /* sensor: valid readings are the integers 0..max_count; f(x) = sign (x - zero) dpc */
    ps_real max_count;
    ps_real zero_count, count_sign, deg_per_count;
    int median_window;
    /* length fits: per muscle a Chebyshev series in x = (2 angle - (lo + hi)) / (hi - lo) */
    int n_coefficients[PS_MUSCLES];
    ps_real coefficients[PS_MUSCLES][PS_FIT_MAX_COEFFS];
    ps_real fit_lo_rad, fit_hi_rad;
    /* conditioning */
    ps_real lowpass_rad_s;   /* natural frequency of the tracking low-pass; 0: none */
    ps_time gap_s;           /* intervals longer than this count as gaps */
    ps_time max_bridge_s;    /* longer intervals restart the chain at rest (restarts) */
    long resync_after_samples; /* the n-th earlier time since the last accepted sample
                                  resyncs the clock (clock_resyncs) */
    ps_real max_speed_deg_s; /* slew limit of the angle */
    ps_real max_speed_L0_s;  /* slew limit of the lengths, <= PS_MAX_SPEED_L0_S */
    /* fusimotor (FusimotorParams) */
    ps_real gamma_static_min_pps, gamma_static_max_pps, gamma_dynamic_pps;
    ps_time delay_s;
    ps_real shortening_threshold_L0;
    ps_real predictor_rate_hz, predictor_kp_1_s, predictor_ki_1_s2;
    /* spindles */
    ps_params params;
    ps_real theta;           /* 0, 0.5, 1: forward Euler, trapezoidal, backward Euler */
    ps_time step_s;          /* largest spindle sub-step */
    /* force sense: load word -> torque (count_sign * direction * magnitude *
     * load_Nm_per_count) -> tendon forces through the moment arms at the angle (flexion
     * torque to BRA, extension to TRImed) -> tendon organs; max_bridge_s <= PS_GTO_MAX_STEP_S */
    ps_real load_Nm_per_count;
    ps_gto_params gto;
    ps_real force_scale_N[PS_MUSCLES]; /* G2 per muscle */
    int n_moment_arm_points;           /* 2..PS_MOMENT_ARM_MAX_POINTS, a uniform grid */
    ps_real moment_arm_lo_rad, moment_arm_hi_rad;
    ps_real moment_arm_m[PS_MUSCLES][PS_MOMENT_ARM_MAX_POINTS]; /* flexor positive */
} ps_chain_config;

/* The down-sampled PI predictor of both muscles (MotionPredictor): the last segments
 * (t_k, p_k, u_k) of its piecewise-linear template, oldest first from `first`. */
typedef struct ps_predictor {
    ps_time t[PS_PREDICTOR_MAX_SEGMENTS];
    ps_real p[PS_PREDICTOR_MAX_SEGMENTS][PS_MUSCLES];
    ps_real u[PS_PREDICTOR_MAX_SEGMENTS][PS_MUSCLES];
    ps_real integral[PS_MUSCLES];
    int first, count;
} ps_predictor;

/* chain.COUNTERS, in that order (see docs/c_chain.md for each rule). */
typedef struct ps_chain_counters {
    unsigned long accepted, invalid_reading, invalid_angle, invalid_length, repeated_time,
        time_backwards, bad_time, gaps, slew_limited, angle_clamped, restarts, clock_resyncs,
        invalid_load, missing_load;
} ps_chain_counters;

/* chain.ArmSample: the output after one sample; per-muscle arrays are BRA, TRImed. */
typedef struct ps_arm_sample {
    ps_time t_s;
    int accepted; /* 0: the sample was rejected and every other field repeats the last */
    ps_real counts, counts_filtered; /* -1 when the sample did not come from the encoder */
    ps_real angle_deg;
    ps_real torque_Nm; /* the load reading's joint torque (N m, flexion positive) */
    ps_real length_L0[PS_MUSCLES], velocity_L0_s[PS_MUSCLES],
        acceleration_L0_s2[PS_MUSCLES], template_L0[PS_MUSCLES];
    ps_real gamma_static_pps[PS_MUSCLES], gamma_dynamic_pps[PS_MUSCLES];
    ps_real ia_pps[PS_MUSCLES], ii_pps[PS_MUSCLES];
    ps_real force_N[PS_MUSCLES], ib_pps[PS_MUSCLES]; /* tendon forces (N), Ib (pps) */
} ps_arm_sample;

/* Everything a chain changes while it runs. */
typedef struct ps_chain_state {
    ps_median median;
    ps_predictor predictor;
    ps_spindle spindle[PS_MUSCLES];
    ps_real u[PS_MUSCLES];          /* last (slew-limited) input length */
    ps_real x[PS_MUSCLES], v[PS_MUSCLES], a[PS_MUSCLES]; /* low-passed length, derivatives */
    ps_real angle_deg;
    ps_time t_s;
    long behind; /* samples with an earlier time than t_s since the last accepted one */
    int has_intended;
    ps_real intended_L0[PS_MUSCLES];
    ps_gto gto[PS_MUSCLES];  /* the tendon organs */
    ps_gto_plan gto_plan;    /* their step for the last interval (gto_plan.h), kept while the
                                intervals repeat */
    ps_real torque_Nm;       /* the last accepted sample's torque, held over invalid words */
    ps_chain_counters counters;
    ps_arm_sample last;
} ps_chain_state;

/* One arm's chain (chain.ArmChain). Caller-owned; ps_chain_init, then ps_chain_reset. */
typedef struct ps_arm_chain {
    ps_chain_config config;
    ps_real angle_min_deg, angle_max_deg;             /* the fitted range in degrees */
    ps_real length_min_L0[PS_MUSCLES], length_max_L0[PS_MUSCLES]; /* h(x)'s Lmin, Lmax */
    int predictor_keep;                               /* segments kept for the delay */
    int stage;                                        /* 0: unusable, 1: init, 2: reset */
    ps_chain_state state;
} ps_arm_chain;

/* Check `config` and copy it into `c` (which needs no prior initialisation); computes the
 * fitted range in degrees and each muscle's length range over it (1301 points, as
 * ArmChain). PS_ERR_NULL, PS_ERR_NONFINITE or PS_ERR_CONFIG: `c` is marked unusable. */
int ps_chain_init(ps_arm_chain *c, const ps_chain_config *config);

/* The fibre lengths (L0) at an elbow angle (rad) by the fits; no range check. */
int ps_chain_length_L0(const ps_arm_chain *c, ps_real angle_rad, ps_real length_L0[PS_MUSCLES]);

/* The arm at rest at `angle_deg` (and, if not NULL, exact lengths `length_L0`) at `t_s`
 * (ArmChain.reset); counters restart at zero and the switch is off; without length_L0 an
 * angle outside the fitted range is clamped to it and counted (angle_clamped = 1); writes
 * the rest output to `out` if not NULL. PS_ERR_NONFINITE, PS_ERR_LENGTH_RANGE. */
int ps_chain_reset(ps_arm_chain *c, ps_real angle_deg, ps_time t_s,
                   const ps_real *length_L0, ps_arm_sample *out);

/* The switch (ArmChain.set_intended_angle): drive the template from an intended angle
 * (clamped to the fitted range); NULL returns to the measured motion. PS_ERR_NONFINITE. */
int ps_chain_set_intended_angle(ps_arm_chain *c, const ps_real *angle_deg);

/* One sample (ArmChain.push_counts / push_angle / push_lengths). A bad sample is handled by
 * its documented rule (counted, out->accepted = 0) and returns PS_OK. An interval longer
 * than max_bridge_s restarts the chain at rest at the sample (counted in restarts), so a
 * push costs at most max_bridge_s / step_s spindle sub-steps, whatever the times. Errors: PS_ERR_NULL,
 * PS_ERR_NOT_RESET, PS_ERR_INTERVAL, or a spindle step's failure; on an error the chain is
 * left exactly as it was and `out` is not written. `angle_deg` of push_lengths is only
 * recorded (NULL or non-finite: the last angle). */
int ps_chain_push_counts(ps_arm_chain *c, ps_time t_s, ps_real counts, ps_arm_sample *out);
int ps_chain_push_angle(ps_arm_chain *c, ps_time t_s, ps_real angle_deg, ps_arm_sample *out);
int ps_chain_push_lengths(ps_arm_chain *c, ps_time t_s, const ps_real length_L0[PS_MUSCLES],
                          const ps_real *angle_deg, ps_arm_sample *out);

/* n samples in one call, exactly the single pushes in order; writes the last output to
 * `out` and the number of samples pushed to `n_done` (each may be NULL). On an error the
 * samples before the failing one stay pushed. `length_L0` is n rows of PS_MUSCLES. */
int ps_chain_push_counts_block(ps_arm_chain *c, long n, const ps_time *t_s,
                               const ps_real *counts, ps_arm_sample *out, long *n_done);
int ps_chain_push_angle_block(ps_arm_chain *c, long n, const ps_time *t_s,
                              const ps_real *angle_deg, ps_arm_sample *out, long *n_done);
int ps_chain_push_lengths_block(ps_arm_chain *c, long n, const ps_time *t_s,
                                const ps_real *length_L0, ps_arm_sample *out, long *n_done);

/* A whole trace in one call (chain.run_chain after its reset): for i = 0 .. n-1, if
 * `intended_deg` is not NULL the switch is first set to intended_deg[i] (NaN: the measured
 * motion; infinite: PS_ERR_NONFINITE), then sample i is pushed and its output written to
 * samples[i] (rejected samples too, with accepted = 0). Stops at the first error; *n_done
 * (if not NULL) receives the number of samples pushed. */
int ps_chain_run_counts(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *counts,
                        const ps_real *intended_deg, ps_arm_sample *samples, long *n_done);
int ps_chain_run_angle(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *angle_deg,
                       const ps_real *intended_deg, ps_arm_sample *samples, long *n_done);
int ps_chain_run_lengths(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *length_L0,
                         const ps_real *intended_deg, ps_arm_sample *samples, long *n_done);

/* The force sense's entry points: the forms above with the servo's load word read beside the
 * counts (`load` one word, or n words; NULL: no load reading). The load rules
 * (docs/faults.md): an accepted sample with an invalid word (not an integer in
 * 0..PS_LOAD_MAX_WORD) holds the last torque (invalid_load); an accepted counts sample
 * without one has zero torque (missing_load); a rejected sample changes nothing. The tendon
 * organs step once over each interval (ps_gto_step at h = the interval); restarts and resets
 * put them at rest at the sample's force (a reset's invalid word: zero torque, counted). The
 * forms without load are these with load NULL (angle and length pushes: zero torque, not
 * counted). */
int ps_chain_reset_load(ps_arm_chain *c, ps_real angle_deg, ps_time t_s,
                        const ps_real *length_L0, const ps_real *load, ps_arm_sample *out);
int ps_chain_push_counts_load(ps_arm_chain *c, ps_time t_s, ps_real counts,
                              const ps_real *load, ps_arm_sample *out);
int ps_chain_push_counts_load_block(ps_arm_chain *c, long n, const ps_time *t_s,
                                    const ps_real *counts, const ps_real *load,
                                    ps_arm_sample *out, long *n_done);
int ps_chain_run_counts_load(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *counts,
                             const ps_real *load, const ps_real *intended_deg,
                             ps_arm_sample *samples, long *n_done);


/* ---- batches: the chains of many arms in one array, advanced by one call ----------------
 * `chains` is an array of n_arms chains, each set up by ps_chain_init and ps_chain_reset (or
 * ps_chain_batch_reset). Arm i of every call below does exactly what the single-arm function
 * does on chains[i] alone (same outputs, counters and handling rules). The calls are atomic
 * across arms: they check every arm first (PS_ERR_NOT_RESET, PS_ERR_ARGUMENT), and if an
 * arm's push fails (a spindle step's status, PS_ERR_INTERVAL) every arm is put back exactly
 * as it was before the call; *failed_arm (and *failed_sample, the index within that arm's
 * block) then name where it failed (-1 on success; each pointer may be NULL), and the
 * contents of `out` are unspecified. No heap: the caller passes `backup` (pushes) or
 * `scratch` (reset), n_arms (or m) states of working memory whose contents are ignored on
 * entry and meaningless after. Compiled unless PS_NO_BATCH is defined (a one-arm device
 * build saves their code: 1.8 kB on a Cortex-M0+). */
#ifndef PS_NO_BATCH

/* Reset m arms: arm arms[j] (j = 0..m-1; arms NULL: arm j, and m must equal n_arms) at rest
 * at angle_deg[j], t_s[j] and, if length_L0 is not NULL, lengths length_L0[2j..2j+1]:
 * ps_chain_reset's work and checks; out[j] (if out is not NULL) receives its rest output.
 * The other arms are untouched. A repeated index is reset once (by its last entry). */
int ps_chain_batch_reset(ps_arm_chain *chains, long n_arms, const long *arms, long m,
                         const ps_real *angle_deg, const ps_time *t_s,
                         const ps_real *length_L0, ps_chain_state *scratch,
                         ps_arm_sample *out, long *failed_arm);

/* The switch of every arm: angle_deg[i] as ps_chain_set_intended_angle's angle, NaN (or
 * angle_deg NULL) for the measured motion; an infinite angle is PS_ERR_NONFINITE (no arm
 * changed). */
int ps_chain_batch_set_intended_angle(ps_arm_chain *chains, long n_arms,
                                      const ps_real *angle_deg, long *failed_arm);

/* Blocks: arm i pushes its first n_samples[i] (0..k; n_samples NULL: k) samples of row i of
 * t_s (n_arms, k) and counts / angle_deg (n_arms, k) or length_L0 (n_arms, k, 2), in order,
 * as ps_chain_push_*_block; entries past n_samples[i] are never read (padding). out[i]
 * receives the arm's last output (ArmChain.last); an arm given no sample repeats its last
 * output with accepted = 0. */
int ps_chain_batch_push_counts_block(ps_arm_chain *chains, long n_arms, long k,
                                     const long *n_samples, const ps_time *t_s,
                                     const ps_real *counts, ps_chain_state *backup,
                                     ps_arm_sample *out, long *failed_arm, long *failed_sample);
int ps_chain_batch_push_angle_block(ps_arm_chain *chains, long n_arms, long k,
                                    const long *n_samples, const ps_time *t_s,
                                    const ps_real *angle_deg, ps_chain_state *backup,
                                    ps_arm_sample *out, long *failed_arm, long *failed_sample);
int ps_chain_batch_push_lengths_block(ps_arm_chain *chains, long n_arms, long k,
                                      const long *n_samples, const ps_time *t_s,
                                      const ps_real *length_L0, ps_chain_state *backup,
                                      ps_arm_sample *out, long *failed_arm, long *failed_sample);

/* One sample per arm (t_s, counts / angle_deg (n_arms), length_L0 (n_arms, 2)) for the arms
 * with active[i] != 0 (active NULL: every arm), as ps_chain_push_counts / _angle / _lengths
 * (lengths: the angle is the last one); out[i] is that push's output (accepted = 0 if the
 * sample was rejected); an inactive arm gets no sample and repeats its last output with
 * accepted = 0. */
int ps_chain_batch_push_counts(ps_arm_chain *chains, long n_arms, const unsigned char *active,
                               const ps_time *t_s, const ps_real *counts,
                               ps_chain_state *backup, ps_arm_sample *out, long *failed_arm);
int ps_chain_batch_push_angle(ps_arm_chain *chains, long n_arms, const unsigned char *active,
                              const ps_time *t_s, const ps_real *angle_deg,
                              ps_chain_state *backup, ps_arm_sample *out, long *failed_arm);
int ps_chain_batch_push_lengths(ps_arm_chain *chains, long n_arms, const unsigned char *active,
                                const ps_time *t_s, const ps_real *length_L0,
                                ps_chain_state *backup, ps_arm_sample *out, long *failed_arm);

/* The batch forms with load words: load[j] (reset, m words), load (n_arms, k) beside the
 * counts (block) or load[i] (one sample per arm); NULL: no load readings. */
int ps_chain_batch_reset_load(ps_arm_chain *chains, long n_arms, const long *arms, long m,
                              const ps_real *angle_deg, const ps_time *t_s,
                              const ps_real *length_L0, const ps_real *load,
                              ps_chain_state *scratch, ps_arm_sample *out, long *failed_arm);
int ps_chain_batch_push_counts_load_block(ps_arm_chain *chains, long n_arms, long k,
                                          const long *n_samples, const ps_time *t_s,
                                          const ps_real *counts, const ps_real *load,
                                          ps_chain_state *backup, ps_arm_sample *out,
                                          long *failed_arm, long *failed_sample);
int ps_chain_batch_push_counts_load(ps_arm_chain *chains, long n_arms,
                                    const unsigned char *active, const ps_time *t_s,
                                    const ps_real *counts, const ps_real *load,
                                    ps_chain_state *backup, ps_arm_sample *out,
                                    long *failed_arm);
#endif /* PS_NO_BATCH */

/* ---- end of chain section ---- */

/* ======================================================================================
 * (4) Golgi tendon organ (tendon_organ.c) -- same model, state and order of operations as
 *     spindle/tendon_organ.py: r = G1 ln(F+/G2 + 1), a low-pass, H(s); the linear part as
 *     z = (x, w1, w2) stepped exactly: z1 = phi z0 + g0 alpha + g1 beta, y = c z,
 *     Ib = max(0, y), with beta = r1 - r0, alpha = r0 + (2/3)(r_mid - (r0 + r1)/2) (the
 *     force a line over the step, its log's mean and first moment by Simpson's rule),
 *     computed as alpha = r0 + (2 G1/3) ln cosh((r1 - r0) / (2 G1)).
 * ====================================================================================== */

/* The types above (PS_GTO_MAX_*, ps_gto_params, ps_gto_plan, ps_gto) are declared before
 * the chain section, whose state holds them. */

/* PS_ERR_NULL; PS_ERR_CONFIG (a constant not finite, gain or tau <= 0, a1 <= 0, a0 <= 0,
 * b0 <= 0); PS_ERR_STEP (h not finite or outside (0, PS_GTO_MAX_STEP_S]). q untouched on
 * failure. */
int ps_gto_plan_init(ps_gto_plan *q, const ps_gto_params *p, ps_real h);

/* At rest at force_N (negative: 0) with force scale G2 = force_scale_N (N): x = r,
 * w1 = r / a0, w2 = 0. PS_ERR_NULL, PS_ERR_NONFINITE, PS_ERR_FORCE_RANGE, PS_ERR_CONFIG
 * (force_scale_N not finite and > 0); s untouched on failure. */
int ps_gto_init(ps_gto *s, const ps_gto_plan *q, ps_real force_N, ps_real force_scale_N);

/* One step of q->h to force_N at the step's end; Ib (pps) to *ib if not NULL. Errors as
 * ps_gto_init; s and *ib untouched on failure. */
int ps_gto_step(ps_gto *s, const ps_gto_plan *q, ps_real force_N, ps_real force_scale_N,
                ps_real *ib);

/* Ib (pps) of a state: max(0, c z); 0 for a NULL argument. */
ps_real ps_gto_rate(const ps_gto *s, const ps_gto_plan *q);

/* ln(1 + x) for x >= 0, as the log stage takes it: the double build's own (inline in the
 * step and the batch's SIMD lanes; max 0.79 ulp), the float build's log1pf. */
ps_real ps_gto_log1p(ps_real x);

/* `steps` steps of n tendon organs: force_N is steps x n (row-major: step k's forces at
 * force_N + k n), force_scale_N n, ib steps x n (NULL: not written). Every input is checked
 * before any state changes: on failure nothing is written, *failed (if not NULL) is the
 * flat index of the first bad force. PS_ERR_ARGUMENT (n < 0 or steps < 0), PS_ERR_NULL, and
 * the errors of ps_gto_step. The results are ps_gto_step's bit for bit; the double build
 * runs 8 organs at a time in SIMD lanes (AVX-512 or AVX2 where the CPU has them). */
int ps_gto_batch_run(ps_gto *s, long n, const ps_gto_plan *q, long steps,
                     const ps_real *force_N, const ps_real *force_scale_N, ps_real *ib,
                     long *failed);

/* ---- fixed-point step (no FPU) ----------------------------------------------------------
 * The same step in int32 with int64 products (on a Cortex-M0+ the compiler's 64-bit multiply
 * helper). Formats: force Q8 N (PS_GTO_FX_FORCE_ONE), 1/G2 Q24 per N, rates and the state
 * Q16 pps (PS_GTO_FX_RATE_ONE), plan coefficients Q30. The log: log2 by its integer part and
 * 24 squarings of the mantissa, times ln 2. F/G2 saturates at PS_GTO_FX_MAX_RATIO (so
 * r <= G1 ln 32768). ps_gto_plan_fx_init bounds every state from the plan (real poles:
 * w1 <= r / a0, w2 <= 2 r / |p1 - p2| for an input line within 4/3 of the largest r) and
 * refuses (PS_ERR_CONFIG) plans whose bounds or coefficients leave their Q ranges. */
#define PS_GTO_FX_FORCE_ONE 256L    /* 1 N in Q8 */
#define PS_GTO_FX_RATE_ONE 65536L   /* 1 pps in Q16 */
#define PS_GTO_FX_INV_SCALE_ONE 16777216L /* 1 / N in Q24 */
#define PS_GTO_FX_COEF_ONE 1073741824L    /* 1.0 in Q30 */
#define PS_GTO_FX_MAX_RATIO 32767

/* a b exactly, as hi 2^32 + lo, from 16-bit halves: a core without a long multiply (the
 * Cortex-M0+) runs it inline in ~20 instructions, where the compiler's 64 x 64 helper took
 * ~45 and a call. a = ah 2^16 + al (al unsigned), likewise b; every partial product fits in
 * 32 bits. The fixed-point tendon organ's sums, the fixed-point stimulation encoder's phase
 * products and the system firmware's products use it. */
typedef struct ps_fx_wide {
    int32_t hi;
    uint32_t lo;
} ps_fx_wide;

#if defined(__GNUC__)
__attribute__((always_inline))
#endif
static inline ps_fx_wide ps_fx_mul_wide(int32_t a, int32_t b)
{
    int32_t ah = a >> 16, bh = b >> 16;
    uint32_t al = (uint32_t)a & 0xFFFFu, bl = (uint32_t)b & 0xFFFFu;
    int32_t hl = ah * (int32_t)bl, lh = (int32_t)al * bh;
    uint32_t ll = al * bl;
    uint32_t mid = ((uint32_t)hl & 0xFFFFu) + ((uint32_t)lh & 0xFFFFu) + (ll >> 16);
    ps_fx_wide out;
    out.hi = ah * bh + (hl >> 16) + (lh >> 16) + (int32_t)(mid >> 16);
    out.lo = (mid << 16) | (ll & 0xFFFFu);
    return out;
}

typedef struct ps_gto_plan_fx {
    int32_t phi[3][3], g0[3], g1[3], c[3]; /* Q30 */
    int32_t gain;                          /* G1, Q16 pps */
    int32_t inv_a0;                        /* 1 / a0, Q24 */
} ps_gto_plan_fx;

typedef struct ps_gto_fx {
    int32_t z[3];   /* Q16 */
    int32_t force;  /* Q8 N, rectified */
    int32_t r;      /* Q16 pps */
} ps_gto_fx;

/* From a double plan (on the host or at start-up). PS_ERR_NULL, PS_ERR_CONFIG. */
int ps_gto_plan_fx_init(ps_gto_plan_fx *qf, const ps_gto_plan *q);

/* At rest at force (Q8 N; negative: 0) with inv_scale = 1/G2 (Q24 / N, > 0). PS_ERR_NULL,
 * PS_ERR_FORCE_RANGE, PS_ERR_CONFIG (inv_scale <= 0); s untouched on failure. */
int ps_gto_fx_init(ps_gto_fx *s, const ps_gto_plan_fx *q, int32_t force, int32_t inv_scale);

/* One step to force (Q8 N); Ib (Q16 pps) to *ib if not NULL. Errors as ps_gto_fx_init. */
int ps_gto_step_fx(ps_gto_fx *s, const ps_gto_plan_fx *q, int32_t force, int32_t inv_scale,
                   int32_t *ib);

/* Ib (Q16 pps) of a state: max(0, c z), as the step writes it; 0 for a NULL argument. */
int32_t ps_gto_rate_fx(const ps_gto_fx *s, const ps_gto_plan_fx *q);

/* ---- end of tendon organ section ---- */

/* ======================================================================================
 * (5) Stimulation (stimulation.c) -- spindle/stimulation/ (encoder.py, generator.py,
 *     safety.py, modes.py): afferent rates (pps) into charge-balanced biphasic pulse events
 *     per electrode channel, within the stimulator's limits. Times are double (ps_time)
 *     and rates double in both builds: the double form equals the numpy encoder (same
 *     operations in the same order); the fixed-point form (ps_stim_fx_*) is the integer
 *     twin for the Cortex-M0+ (no float on its step's path).
 * ====================================================================================== */

#define PS_STIM_MAX_CHANNELS 16      /* channels of one configuration (config.MAX_CHANNELS) */
#define PS_STIM_COUNTERS 7           /* encoder.COUNTERS, in the order of PS_STIM_COUNT_* */
#define PS_STIM_MAX_GAMMA_SHAPE 16
#define PS_STIM_MAX_DT_S 1.0         /* longest interval of one call (config.MAX_DT_S) */
#define PS_STIM_MAX_RATE_PPS 10000.0 /* largest max_rate_pps (safety.MAX_RATE_CEILING_PPS) */
#define PS_STIM_MAX_AMPLITUDE_UA 10000
#define PS_STIM_MAX_PHASE_US 10000
/* modes (modes.MODES[...].code) */
#define PS_STIM_MODE_FREQUENCY 0
#define PS_STIM_MODE_STOCHASTIC 1
#define PS_STIM_MODE_AMPLITUDE 2
#define PS_STIM_MODE_BIOMIMETIC 3
/* counters: indices of ps_stim_state.counts[channel][.] */
#define PS_STIM_COUNT_PULSES 0
#define PS_STIM_COUNT_RATE_NONFINITE 1
#define PS_STIM_COUNT_RATE_NEGATIVE 2
#define PS_STIM_COUNT_RATE_CLIPPED 3
#define PS_STIM_COUNT_AMPLITUDE_CLIPPED 4
#define PS_STIM_COUNT_DROPPED_INTERVAL 5
#define PS_STIM_COUNT_DROPPED_TOTAL_RATE 6

/* One electrode channel (channels.Channel without its names). */
typedef struct ps_stim_channel {
    int32_t threshold_uA, max_uA; /* 1 <= threshold <= max <= PS_STIM_MAX_AMPLITUDE_UA */
    int32_t phase_us, gap_us;     /* each phase; interphase gap */
    double area_cm2;              /* geometric area (Shannon criterion) */
} ps_stim_channel;

/* Everything an encoder needs (config.StimConfig resolved to numbers). */
typedef struct ps_stim_config {
    int32_t n_channels;           /* 1..PS_STIM_MAX_CHANNELS */
    int32_t mode;                 /* PS_STIM_MODE_* */
    int32_t gamma_shape;          /* stochastic: 1..PS_STIM_MAX_GAMMA_SHAPE (1: Poisson) */
    int32_t min_interval_us;      /* extra wait after a pulse's last phase, >= 0 */
    ps_stim_channel channel[PS_STIM_MAX_CHANNELS];
    double max_rate_pps;          /* per channel, (0, PS_STIM_MAX_RATE_PPS] */
    double max_total_rate_pps;    /* summed over channels; 0: no limit */
    double shannon_k;             /* k_max of the Shannon criterion */
    double max_charge_nC;         /* charge per phase limit */
    double full_scale_pps, full_scale_change_pps_s, carrier_pps;
    double rate_level, rate_change, amp_level, amp_change; /* biomimetic weights */
    double dead_time_s;           /* stochastic */
    uint64_t seed;                /* stochastic */
} ps_stim_config;

/* One delivered pulse (events.PULSE_DTYPE): cathodic amplitude_uA for cathodic_us, gap_us
 * at zero, anodic amplitude_uA for anodic_us (= cathodic_us): charges equal exactly. */
typedef struct ps_pulse {
    ps_time time_s;
    int32_t channel, amplitude_uA, cathodic_us, gap_us, anodic_us;
} ps_pulse;

/* An encoder's state (encoder.EncoderState), per-channel arrays by channel index. */
typedef struct ps_stim_state {
    ps_time t_s, last_any_s;
    double phase[PS_STIM_MAX_CHANNELS], threshold[PS_STIM_MAX_CHANNELS];
    ps_time resume_s[PS_STIM_MAX_CHANNELS], last_pulse_s[PS_STIM_MAX_CHANNELS];
    double previous_pps[PS_STIM_MAX_CHANNELS];
    uint64_t draws[PS_STIM_MAX_CHANNELS];
    uint64_t counts[PS_STIM_MAX_CHANNELS][PS_STIM_COUNTERS];
    int32_t ready;                /* 1 after ps_stim_init */
} ps_stim_state;

/* The generator (generator.py): 64 bits of draw `index` of `channel`, the uniform in (0, 1)
 * they give, log(u) by the series both languages share, and the gamma(shape, 1/shape)
 * threshold of draw `draw`. */
uint64_t ps_stim_bits(uint64_t seed, uint64_t channel, uint64_t index);
double ps_stim_uniform(uint64_t seed, uint64_t channel, uint64_t index);
double ps_stim_log_unit(double u);
double ps_stim_gamma_threshold(uint64_t seed, uint64_t channel, uint64_t draw, int32_t shape);

/* PS_OK for a usable configuration; PS_ERR_NULL; PS_ERR_CHARGE for a channel whose largest
 * pulse exceeds max_charge_nC or shannon_k; PS_ERR_CONFIG for anything else out of range
 * (the checks of config.StimConfig). */
int ps_stim_config_check(const ps_stim_config *c);

/* Every channel at rest at t0_s (encoder.initial_state); counters zero. The status of
 * ps_stim_config_check, or PS_ERR_NONFINITE for t0_s; s is untouched on failure. */
int ps_stim_init(ps_stim_state *s, const ps_stim_config *c, ps_time t0_s);

/* At most this many pulses come out of one ps_stim_step of dt_s (a buffer this large never
 * fills); -1 for a bad config or dt_s. */
long ps_stim_max_events(const ps_stim_config *c, ps_time dt_s);

/* One interval [t, t + dt_s) with rates_pps[n_channels] held over it (encoder.step): the
 * delivered pulses in time order into events[0 .. *n_events - 1]. `c` must be the config
 * `s` was initialised with (checked there, not at every step). Errors (nothing changed,
 * *n_events = 0): PS_ERR_NULL, PS_ERR_NOT_RESET, PS_ERR_STEP (dt_s not finite or outside
 * (0, PS_STIM_MAX_DT_S]), PS_ERR_BUFFER_FULL (more pulses than capacity). Bad rates are
 * handled by the counted rules, never an error. */
int ps_stim_step(ps_stim_state *s, const ps_stim_config *c, const double *rates_pps,
                 ps_time dt_s, ps_pulse *events, long capacity, long *n_events);

/* n intervals: rates_pps is n rows of n_channels, dt_s[i] the interval of row i; the steps
 * in order, their events one after another. Stops at the first failing step (its status);
 * *n_done (if not NULL) receives the steps completed and *n_events their events. */
int ps_stim_run(ps_stim_state *s, const ps_stim_config *c, long n, const double *rates_pps,
                const ps_time *dt_s, ps_pulse *events, long capacity, long *n_events,
                long *n_done);

/* ---- fixed point (the Cortex-M0+ device build) ---------------------------------------
 * The same encoders in integers: rates in Q16 pps (PS_STIM_FX_RATE_ONE), intervals and
 * times in whole µs, the phase in units of PS_STIM_FX_PULSE = 10^6 * 2^16 per pulse
 * (rate_q16 * dt_us adds exactly), the stochastic thresholds from the same 64-bit draws
 * with an integer log. A pulse comes at the first whole µs at or after
 * the crossing and keeps the overshoot, so the integral is exact (no drift against the
 * double form: times agree to a microsecond, amplitudes to 1 µA). Rates are int32:
 * negative ones are 0 (rate_negative), no rate is non-finite. */
#define PS_STIM_FX_RATE_ONE 65536L
#define PS_STIM_FX_PULSE 65536000000LL

typedef struct ps_stim_fx_config {
    int32_t n_channels, mode, gamma_shape;
    int32_t threshold_uA[PS_STIM_MAX_CHANNELS], max_uA[PS_STIM_MAX_CHANNELS];
    int32_t phase_us[PS_STIM_MAX_CHANNELS], gap_us[PS_STIM_MAX_CHANNELS];
    int32_t min_interval_us[PS_STIM_MAX_CHANNELS]; /* between a channel's pulse starts */
    int32_t max_rate_q16, carrier_q16, full_scale_q16;
    int32_t full_scale_change_pps_s;  /* whole pps/s */
    int32_t rate_level_q16, rate_change_q16, amp_level_q16, amp_change_q16;
    int32_t dead_us, min_total_us;    /* min_total_us 0: no total-rate limit */
    uint64_t seed;
} ps_stim_fx_config;

typedef struct ps_stim_fx_state {
    int64_t t_us, last_any_us;
    int64_t phase[PS_STIM_MAX_CHANNELS], threshold[PS_STIM_MAX_CHANNELS];
    int64_t resume_us[PS_STIM_MAX_CHANNELS], last_pulse_us[PS_STIM_MAX_CHANNELS];
    int32_t previous_q16[PS_STIM_MAX_CHANNELS]; /* -1: none */
    uint64_t draws[PS_STIM_MAX_CHANNELS];
    uint32_t counts[PS_STIM_MAX_CHANNELS][PS_STIM_COUNTERS];
    int32_t ready;
} ps_stim_fx_state;

/* One pulse of the fixed form: start in whole µs since the clock's zero. */
typedef struct ps_pulse_fx {
    int64_t time_us;
    int32_t channel, amplitude_uA, cathodic_us, gap_us, anodic_us;
} ps_pulse_fx;

/* The fixed-point config of a checked double config (host or start-up): rates rounded to
 * Q16, dead time and the total-rate spacing to whole µs (rounded up). The status of
 * ps_stim_config_check, or PS_ERR_CONFIG for what the integers cannot hold (full_scale_pps
 * above 32767, full_scale_change_pps_s outside 1..2e9, a weight above 3e4, a total rate below
 * 1e-3 pps, a dead time below 1 µs, stochastic max_rate_pps * dead_time_s above 0.99); q is
 * untouched on failure. */
int ps_stim_fx_config_init(ps_stim_fx_config *q, const ps_stim_config *c);
/* -log(u) in Q30 of the double form's uniform u = (2 (bits >> 12) + 1) / 2^53. */
int64_t ps_stim_fx_neg_log(uint64_t bits);
int ps_stim_fx_init(ps_stim_fx_state *s, const ps_stim_fx_config *q, int64_t t0_us);
/* ps_stim_step in integers: PS_ERR_NULL, PS_ERR_NOT_RESET, PS_ERR_STEP (dt_us outside
 * 1..10^6), PS_ERR_BUFFER_FULL; nothing changed on an error. */
int ps_stim_fx_step(ps_stim_fx_state *s, const ps_stim_fx_config *q, const int32_t *rates_q16,
                    int32_t dt_us, ps_pulse_fx *events, long capacity, long *n_events);

/* ---- end of stimulation section ---- */

#ifdef __cplusplus
}
#endif

#endif /* PROPRIO_H */
