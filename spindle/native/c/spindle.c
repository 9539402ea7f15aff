/*
 * spindle.c -- the Mileusnic (2006) spindle of spindle/core.py in C99.
 *
 * Three steps, each kept because it is what one target needs (the figures below):
 * - ps_spindle_step follows spindle.core.advance operation by operation (same state, same
 *   theta-method, same Newton iteration in z = sgn(v)|v|^(a/3), same starting guess), so the
 *   double build matches the numpy core to round-off;
 * - ps_spindle_step_plan, the embedded float step: the same equations with every constant
 *   that depends only on (params, h, theta) precomputed by ps_plan_init (no divide left but
 *   one per Newton iteration), optionally a fixed Newton iteration count (PS_NEWTON_ITER) and
 *   a polynomial cube root;
 * - ps_spindle_step_fx, the int32 Q24 step for cores without an FPU: ~3,970 instructions per
 *   step on the Cortex-M0+ at 5 ms on the demo motion (3,790 on the two --quick Fig. 3 runs;
 *   8,100 before issue 26: Newton now stops on its predicted residual, divides by a reciprocal,
 *   starts from the state's powers; scripts/bench_embedded.py --system-only: spindle stage
 *   3,755 instr/sample, was 6,992) against 36,389 for the float plan step with every lever
 *   (docs/c_port.md), at the same accuracy (1.42 pps RMS against the stiff reference).
 * The pieces they share (activation target, force, Newton start and solve, the combination of
 * the potentials into Ia and II, commit) are the small static functions of the first section.
 * The host's batch (ps_spindle_batch_step) runs ps_spindle_step_plan for 8 spindles at a time
 * in SIMD lanes, from the same pieces, bit for bit (3-3.8x faster with AVX2, see there).
 *
 * No heap, no globals, no input is modified; on failure nothing is written.
 */
#include "proprio.h"

#include <float.h>
#include <math.h>
#include <stddef.h>
#include <string.h>

#define R_(x) ((ps_real)(x))

/* The small pieces shared by the scalar step and the lanes of the batch: always inlined where
 * speed is the aim (the lanes need them inline to become SIMD), the compiler's choice under
 * -Os (the embedded builds). */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define PS_INLINE static inline __attribute__((always_inline))
#else
#define PS_INLINE static
#endif

#ifdef PS_FLOAT
#define ps_fabs fabsf
#define ps_pow powf
#define ps_cbrt cbrtf
#define PS_TINY FLT_MIN
#else
#define ps_fabs fabs
#define ps_pow pow
#define ps_cbrt cbrt
#define PS_TINY 1e-300
#endif

/* Newton settings of spindle/core.py. The float build stops at a tolerance it can reach:
 * z is O(1), and float resolves it to ~1e-7. */
#define PS_NEWTON_MAX_ITER 60
#ifndef PS_NEWTON_TOL_Z
#ifdef PS_FLOAT
#define PS_NEWTON_TOL_Z 2e-6
#else
#define PS_NEWTON_TOL_Z 1e-9
#endif
#endif
#define PS_NEWTON_MAX_DZ 0.25

/* ---- shared small pieces ------------------------------------------------------------ */

PS_INLINE ps_real max_r(ps_real a, ps_real b) { return a < b ? b : a; }

PS_INLINE ps_real min_r(ps_real a, ps_real b) { return b < a ? b : a; }

/* The Newton step g/g' of both implicit paths: g' kept above PS_TINY (g' = 0 at z = 0 when the
 * polar region is no longer than R) and the step capped at PS_NEWTON_MAX_DZ. NaN propagates
 * through both clamps, as np.maximum/np.minimum do. */
PS_INLINE ps_real newton_step(ps_real g, ps_real dg)
{
    ps_real d = g / (dg < R_(PS_TINY) ? R_(PS_TINY) : dg);
    if (d > R_(PS_NEWTON_MAX_DZ)) d = R_(PS_NEWTON_MAX_DZ);
    if (d < R_(-PS_NEWTON_MAX_DZ)) d = R_(-PS_NEWTON_MAX_DZ);
    return d;
}

static ps_real sign_r(ps_real x) { return x > R_(0) ? R_(1) : (x < R_(0) ? R_(-1) : R_(0)); }

static ps_real fibre_drive(int i, ps_real gd, ps_real gs) { return i == 0 ? gd : gs; }

PS_INLINE ps_real drive_power(ps_real drive, ps_real p, int p_is_2)
{
    return p_is_2 ? drive * drive : ps_pow(drive, p);
}

/* g^p / (g^p + freq^p) from gp = g^p (spindle.core.activation_target). A drive so large that
 * g^p overflows is saturated (numpy would give inf/inf = NaN). */
PS_INLINE ps_real target_from_power(ps_real gp, ps_real freq_p)
{
    if (!isfinite(gp)) return R_(1);
    return gp / (gp + freq_p);
}

static ps_real activation_target(ps_real drive, ps_real freq, ps_real p, int p_is_2)
{
    return target_from_power(drive_power(drive, p, p_is_2),
                             p_is_2 ? freq * freq : ps_pow(freq, p));
}

/* M dv/dt of a fibre (spindle.core.force) at tension T, z = sgn(v)|v|^(a/3) (z3 = z^3,
 * which the caller may need too), polar length `polar`, drive terms beta and Gamma: the
 * damping C*beta*sgn(v)|v|^a is C*beta*z^3, times the polar length beyond R clipped at 0 (no
 * damping, never a negative one, where the polar region is not longer than R). */
PS_INLINE ps_real force(ps_real T, ps_real z, ps_real z3, ps_real polar, ps_real beta,
                     ps_real Gamma, ps_real KPR, ps_real LPR0, ps_real R, ps_real CL, ps_real CS)
{
    ps_real damping = (z > R_(0) ? CL : CS) * beta * z3;
    return T - Gamma - KPR * (polar - LPR0) - damping * max_r(polar - R, R_(0));
}

/* z = sgn(v)|v|^(a/3) of the explicit step. */
static ps_real root_of_velocity(ps_real v, ps_real a)
{
    return sign_r(v) * ps_pow(ps_fabs(v), a / R_(3));
}

/* Ia and II from the fibres' primary and secondary potentials (pps): each clipped at 0, the
 * dynamic (bag1) and static (bag2 + chain) primaries combined with occlusion S. */
PS_INLINE void combine_rates(const ps_real primary[PS_NFIBRES], const ps_real sec[PS_NFIBRES],
                          ps_real S, ps_real *ia, ps_real *ii)
{
    ps_real a_dyn = primary[0];
    ps_real b_stat = primary[1] + primary[2];
    if (ia != NULL) *ia = max_r(a_dyn, b_stat) + S * min_r(a_dyn, b_stat);
    if (ii != NULL) *ii = max_r(sec[1], R_(0)) + max_r(sec[2], R_(0));
}

/* Straight-line on purpose: gcc -Os turns a copy loop into a memcpy call (~80 instructions
 * each on a Cortex-M0+). */
static void copy3(ps_real dst[PS_NFIBRES], const ps_real src[PS_NFIBRES])
{
    dst[0] = src[0];
    dst[1] = src[1];
    dst[2] = src[2];
}

PS_INLINE int fibre_finite(ps_real T, ps_real v, ps_real z, ps_real f)
{
    return isfinite(T) && isfinite(v) && isfinite(z) && isfinite(f);
}

/* The end of a step whose fibres are all finite: the state takes the new values only once
 * the rates are known to be finite too (a tension so large that they overflow, in float, is
 * a failure), so a failed step leaves it as it was. */
static int finish_step(ps_spindle *s, const ps_real T1[PS_NFIBRES],
                       const ps_real v1[PS_NFIBRES], const ps_real z1[PS_NFIBRES],
                       const ps_real f1[PS_NFIBRES], ps_real L1, ps_real gd1, ps_real gs1,
                       ps_real r_ia, ps_real r_ii, ps_real *ia, ps_real *ii)
{
    if (!isfinite(r_ia) || !isfinite(r_ii)) return PS_ERR_NONFINITE;
    copy3(s->T, T1);
    copy3(s->v, v1);
    copy3(s->z, z1);
    copy3(s->f, f1);
    s->L = L1;
    s->gd = gd1;
    s->gs = gs1;
    if (ia != NULL) *ia = r_ia;
    if (ii != NULL) *ii = r_ii;
    return PS_OK;
}

static int all_equal(const ps_real x[PS_NFIBRES], ps_real value)
{
    return x[0] == value && x[1] == value && x[2] == value;
}

/* The inputs of a step or of an equilibrium, checked in the order of spindle.core. */
PS_INLINE int check_inputs(ps_real L, ps_real gd, ps_real gs)
{
    if (!isfinite(L) || !isfinite(gd) || !isfinite(gs)) return PS_ERR_NONFINITE;
    if (L < R_(PS_LENGTH_MIN_L0) || L > R_(PS_LENGTH_MAX_L0)) return PS_ERR_LENGTH_RANGE;
    if (gd < R_(0) || gs < R_(0)) return PS_ERR_NEGATIVE_DRIVE;
    return PS_OK;
}

/* Cube root of the Newton starting guess. PS_FAST_CBRT: a bit-level estimate (exponent / 3
 * by shifts, ~3 % off) and PS_CBRT_REFINE Newton steps y <- (2y + x/y^2)/3; the result only
 * starts the Newton iteration on z, which corrects what is left. */
#ifndef PS_CBRT_REFINE
#define PS_CBRT_REFINE 2
#endif
/* A float's bits (C99 allows reading another member of a union; no memcpy call). */
typedef union ps_bits { float f; unsigned int u; } ps_bits;
typedef char ps_check_unsigned_is_32_bits[sizeof(unsigned int) == 4 ? 1 : -1];

#ifdef PS_FAST_CBRT
/* The bits of a float x in [1e-30, 1e30] -> those of ~x^(1/3): u/3 as a sum of shifts
 * (1/3 = 1/4 + 1/16 + ...; no divide on cores without one). The sum stays below 2^31. */
PS_INLINE unsigned int cbrt_bits(unsigned int u)
{
    return (u >> 2) + (u >> 4) + (u >> 6) + (u >> 8) + (u >> 10) + (u >> 12) + (u >> 14)
           + (u >> 16) + 709921077u;
}
#endif

static ps_real cube_root(ps_real x)
{
#ifdef PS_FAST_CBRT
    ps_bits b;
    ps_real ax = ps_fabs(x), y;
    int k;
    if (!(ax > R_(1e-30) && ax < R_(1e30))) return ps_cbrt(x); /* 0, huge, NaN: exact path */
    b.f = (float)ax;
    b.u = cbrt_bits(b.u);
    y = (ps_real)b.f;
    for (k = 0; k < PS_CBRT_REFINE; ++k) y = (R_(2) * y + ax / (y * y)) * R_(1.0 / 3.0);
    return x < R_(0) ? -y : y;
#else
    return ps_cbrt(x);
#endif
}

/* ---- public API of the contract ----------------------------------------------------- */

int ps_spindle_init(ps_spindle *s, const ps_params *p, ps_real L, ps_real gd, ps_real gs)
{
    int i, status, p_is_2;
    ps_spindle out;
    if (s == NULL || p == NULL) return PS_ERR_NULL;
    status = check_inputs(L, gd, gs);
    if (status != PS_OK) return status;
    p_is_2 = all_equal(p->p, R_(2));
    for (i = 0; i < PS_NFIBRES; ++i) {
        ps_real f = activation_target(fibre_drive(i, gd, gs), p->freq[i], p->p[i], p_is_2);
        ps_real k1 = R_(1) + p->KPR[i] / p->KSR[i];
        out.T[i] = (p->Gamma_drive[i] * f + p->KPR[i] * (L - p->LSR0[i] - p->LPR0[i])) / k1;
        out.v[i] = R_(0);
        out.z[i] = R_(0);
        out.f[i] = f;
    }
    out.L = L;
    out.gd = gd;
    out.gs = gs;
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (!isfinite(out.T[i]) || !isfinite(out.f[i])) return PS_ERR_CONFIG;
    }
    *s = out;
    return PS_OK;
}

static void afferents(const ps_real T[PS_NFIBRES], ps_real L, const ps_params *p, ps_real *ia,
                      ps_real *ii)
{
    ps_real stretch[PS_NFIBRES], primary[PS_NFIBRES], sec[PS_NFIBRES];
    int i;
    for (i = 0; i < PS_NFIBRES; ++i) {
        stretch[i] = T[i] / p->KSR[i] - (p->LNSR[i] - p->LSR0[i]);
        primary[i] = max_r(p->G_pri[i] * stretch[i], R_(0));
    }
    sec[0] = R_(0); /* bag1 has no secondary ending */
    for (i = 1; i < PS_NFIBRES; ++i) {
        sec[i] = p->G_sec[i] * (p->X[i] * (p->Lsec[i] / p->LSR0[i]) * stretch[i]
                                + (R_(1) - p->X[i]) * (p->Lsec[i] / p->LPR0[i])
                                  * (L - T[i] / p->KSR[i] - p->LSR0[i] - p->LNPR[i]));
    }
    combine_rates(primary, sec, p->S, ia, ii);
}

void ps_spindle_afferents(const ps_spindle *s, const ps_params *p, ps_real *ia, ps_real *ii)
{
    if (s == NULL || p == NULL) return;
    afferents(s->T, s->L, p, ia, ii);
}

/* v = sgn(z)|z|^(3/a) and dv/dz (spindle.core._velocity_from_z). */
static void velocity_from_z(ps_real z, ps_real a, int a_is_03, ps_real *w, ps_real *dw)
{
    if (a_is_03) {
        ps_real az = ps_fabs(z);
        ps_real z4 = z * z;
        ps_real z8az;
        z4 *= z4;
        z8az = z4 * z4;
        z8az *= az;
        *w = z8az * z;
        if (dw != NULL) *dw = R_(10) * z8az;
    } else {
        ps_real three_over_a = R_(3) / a;
        ps_real az_pow = ps_pow(ps_fabs(z), three_over_a - R_(1));
        *w = z * az_pow;
        if (dw != NULL) *dw = three_over_a * az_pow;
    }
}

/* Where the new polar region may end no longer than R (p0 <= theta*h*|w| with |w| <= |rhs|/a2
 * at the root, spindle.batched.needs_clip), the guess is limited to the root's bound
 * |z| <= (|rhs|/a2)^(a/3); this also replaces the NaN guess of a fibre at rest with p0 <= 0
 * (no slope). */
static ps_real bound_guess(ps_real z, ps_real p0, ps_real rhs, ps_real a2, ps_real th_h,
                           ps_real a)
{
    ps_real bound;
    if (!(p0 * a2 <= th_h * ps_fabs(rhs))) return z;
    bound = ps_pow(ps_fabs(rhs) / a2, a / R_(3));
    if (!(ps_fabs(z) <= bound)) z = rhs < R_(0) ? -bound : bound;
    return z;
}

/* One Newton iteration on g(z) (spindle.batched.newton_loop); returns the step taken. */
static ps_real newton_update(ps_real *z_io, ps_real a2, ps_real p0, ps_real rhs, ps_real cS,
                             ps_real dC, ps_real th_h, ps_real a, int a_is_03)
{
    ps_real z = *z_io;
    ps_real w, dw, z2, zp, phi, dphi, q, g, dg, dz;
    velocity_from_z(z, a, a_is_03, &w, &dw);
    z2 = z * z;
    zp = max_r(z, R_(0));
    phi = cS * (z2 * z) + dC * (zp * z2);
    dphi = R_(3) * (cS * z2 + dC * (zp * z));
    q = p0 + th_h * w;
    if (q > R_(0)) {
        g = a2 * w + phi * q - rhs;
        dg = a2 * dw + dphi * q + th_h * phi * dw;
    } else { /* the damping's polar-length factor clipped at 0 */
        g = a2 * w - rhs;
        dg = a2 * dw;
    }
    dz = newton_step(g, dg);
    *z_io = z - dz;
    return dz;
}

/* Newton iterations from z; PS_OK once |dz| <= tol (or after PS_NEWTON_ITER iterations). */
static int newton(ps_real *z, ps_real a2, ps_real p0, ps_real rhs, ps_real cS, ps_real dC,
                  ps_real th_h, ps_real a, int a_is_03)
{
    int it;
#if defined(PS_NEWTON_ITER) && PS_NEWTON_ITER > 0
    for (it = 0; it < PS_NEWTON_ITER; ++it) {
        (void)newton_update(z, a2, p0, rhs, cS, dC, th_h, a, a_is_03);
    }
    return PS_OK;
#else
    for (it = 0; it < PS_NEWTON_MAX_ITER; ++it) {
        ps_real dz = newton_update(z, a2, p0, rhs, cS, dC, th_h, a, a_is_03);
        if (ps_fabs(dz) <= R_(PS_NEWTON_TOL_Z)) return PS_OK;
    }
    return PS_ERR_NO_CONVERGENCE;
#endif
}

/* The linearised starting guess of Newton (spindle.core): z^3 times the slope of g near the
 * previous z, equal to rhs. */
PS_INLINE ps_real newton_start_cube(ps_real z0_7, ps_real a2, ps_real rhs, ps_real cS,
                                 ps_real dC, ps_real p0)
{
    ps_real slope = a2 * z0_7 + (rhs > R_(0) ? cS + dC : cS) * max_r(p0, R_(0));
    return rhs / slope;
}

static ps_real newton_start(ps_real z0_7, ps_real a2, ps_real rhs, ps_real cS, ps_real dC,
                            ps_real p0)
{
    return cube_root(newton_start_cube(z0_7, a2, rhs, cS, dC, p0));
}

/* The root z of g from the guess in *z (bounded first), and v = sgn(z)|z|^(3/a). */
static int solve_z(ps_real *z, ps_real *v, ps_real a2, ps_real p0, ps_real rhs, ps_real cS,
                   ps_real dC, ps_real th_h, ps_real a, int a_is_03)
{
    int status;
    *z = bound_guess(*z, p0, rhs, a2, th_h, a);
    status = newton(z, a2, p0, rhs, cS, dC, th_h, a, a_is_03);
    if (status != PS_OK) return status;
    velocity_from_z(*z, a, a_is_03, v, NULL);
    return PS_OK;
}

/* The activation of fibre i after the step: the theta-method on df/dt = (a* - f)/tau, or the
 * target a* itself when there is no lag (tau = 0). */
static ps_real activation_step(const ps_params *p, int i, const ps_spindle *s, ps_real drive1,
                               ps_real h, ps_real theta, int p_is_2)
{
    const ps_real f0 = s->f[i];
    const ps_real a1 = activation_target(drive1, p->freq[i], p->p[i], p_is_2);
    ps_real rate, a0;
    if (!(p->tau[i] > R_(0))) return a1;
    rate = h / p->tau[i];
    if (!(theta < R_(1))) return (f0 + rate * a1) / (R_(1) + rate);
    a0 = activation_target(fibre_drive(i, s->gd, s->gs), p->freq[i], p->p[i], p_is_2);
    return (f0 + rate * ((R_(1) - theta) * (a0 - f0) + theta * a1)) / (R_(1) + theta * rate);
}

/* The force of fibre i at the start of the step (the explicit part of the theta-method). */
static ps_real start_force(const ps_params *p, int i, const ps_spindle *s)
{
    const ps_real f0 = s->f[i], z0 = s->z[i];
    return force(s->T[i], z0, z0 * z0 * z0, s->L - p->LSR0[i] - s->T[i] / p->KSR[i],
                 p->beta0[i] + p->beta_drive[i] * f0, p->Gamma_drive[i] * f0, p->KPR[i],
                 p->LPR0[i], p->R[i], p->CL[i], p->CS[i]);
}

/* Forward Euler (theta = 0) of fibre i. */
static void explicit_fibre(const ps_params *p, int i, const ps_spindle *s, ps_real L1,
                           ps_real h, ps_real *T1, ps_real *v1, ps_real *z1)
{
    const ps_real KSR = p->KSR[i];
    const ps_real A = s->T[i] + KSR * (L1 - s->L); /* the exact integral of dL over the step */
    *T1 = A - (h * KSR) * s->v[i];
    *v1 = s->v[i] + (h / p->M[i]) * start_force(p, i, s);
    *z1 = root_of_velocity(*v1, p->a[i]);
}

/* The implicit theta-method (theta > 0) of fibre i with its new activation f1: Newton on
 * z = sgn(v)|v|^(a/3) for the new velocity (spindle.batched.newton_loop), then the tension. */
static int implicit_fibre(const ps_params *p, int i, const ps_spindle *s, ps_real L1,
                          ps_real f1, ps_real h, ps_real theta, int a_is_03, ps_real *T1,
                          ps_real *v1, ps_real *z1)
{
    const ps_real KSR = p->KSR[i], v0 = s->v[i], z0 = s->z[i];
    const ps_real k1 = R_(1) + p->KPR[i] / KSR;
    const ps_real beta1 = p->beta0[i] + p->beta_drive[i] * f1;
    const ps_real th_h = theta * h;
    ps_real A = s->T[i] + KSR * (L1 - s->L); /* the exact integral of dL over the step */
    ps_real F0 = R_(0), a2, p0, rhs, cS, dC, z0_7, z;
    int status;
    if (theta < R_(1)) {
        F0 = start_force(p, i, s);
        A = A - ((R_(1) - theta) * h) * KSR * v0;
    }
    a2 = p->M[i] / h + (theta * theta * h) * k1 * KSR;
    p0 = L1 - p->LSR0[i] - p->R[i] - A / KSR;
    rhs = (p->M[i] / h) * v0
          + theta * (k1 * A - p->Gamma_drive[i] * f1
                     - p->KPR[i] * (L1 - p->LSR0[i] - p->LPR0[i]));
    if (theta < R_(1)) rhs += (R_(1) - theta) * F0;
    cS = (theta * p->CS[i]) * beta1;
    dC = (theta * (p->CL[i] - p->CS[i])) * beta1;
    /* Starting guess as in spindle.core (for a != 0.3 it also keeps its exponent). */
    z0_7 = z0 * z0;
    z0_7 *= a_is_03 ? z0_7 * z0_7 * ps_fabs(z0) : ps_pow(ps_fabs(z0), R_(3) / p->a[i] - R_(3));
    z = newton_start(z0_7, a2, rhs, cS, dC, p0);
    status = solve_z(&z, v1, a2, p0, rhs, cS, dC, th_h, p->a[i], a_is_03);
    if (status != PS_OK) return status;
    *T1 = A - th_h * KSR * *v1;
    *z1 = z;
    return PS_OK;
}

/* The checks of ps_spindle_step, in the order of spindle.core.advance. */
static int check_step(const ps_spindle *s, ps_real L1, ps_real gd1, ps_real gs1, ps_real h,
                      ps_real theta)
{
    int status;
    if (!(theta >= R_(0) && theta <= R_(1))) return PS_ERR_METHOD;
    if (!(isfinite(h) && h > R_(0))) return PS_ERR_STEP;
    status = check_inputs(L1, gd1, gs1);
    if (status != PS_OK) return status;
    if (ps_fabs(L1 - s->L) / h > R_(PS_MAX_SPEED_L0_S)) return PS_ERR_SPEED;
    return PS_OK;
}

int ps_spindle_step(ps_spindle *s, const ps_params *p, ps_real L1, ps_real gd1, ps_real gs1,
                    ps_real h, ps_real theta, ps_real *ia, ps_real *ii)
{
    ps_real T1[PS_NFIBRES], v1[PS_NFIBRES], z1[PS_NFIBRES], f1[PS_NFIBRES], r_ia, r_ii;
    int i, status, p_is_2, a_is_03;

    if (s == NULL || p == NULL) return PS_ERR_NULL;
    status = check_step(s, L1, gd1, gs1, h, theta);
    if (status != PS_OK) return status;
    p_is_2 = all_equal(p->p, R_(2));
    a_is_03 = all_equal(p->a, R_(0.3));
    for (i = 0; i < PS_NFIBRES; ++i) {
        f1[i] = activation_step(p, i, s, fibre_drive(i, gd1, gs1), h, theta, p_is_2);
        if (theta == R_(0)) {
            explicit_fibre(p, i, s, L1, h, &T1[i], &v1[i], &z1[i]);
        } else {
            status = implicit_fibre(p, i, s, L1, f1[i], h, theta, a_is_03, &T1[i], &v1[i],
                                    &z1[i]);
            if (status != PS_OK) return status;
        }
        if (!fibre_finite(T1[i], v1[i], z1[i], f1[i])) return PS_ERR_NONFINITE;
    }
    afferents(T1, L1, p, &r_ia, &r_ii);
    return finish_step(s, T1, v1, z1, f1, L1, gd1, gs1, r_ia, r_ii, ia, ii);
}

static int positive_all(const ps_real x[PS_NFIBRES])
{
    return x[0] > R_(0) && x[1] > R_(0) && x[2] > R_(0);
}

int ps_params_check(const ps_params *p)
{
    const ps_real *fields[21];
    int i, k;
    if (p == NULL) return PS_ERR_NULL;
    fields[0] = p->KSR; fields[1] = p->KPR; fields[2] = p->M; fields[3] = p->beta0;
    fields[4] = p->beta_drive; fields[5] = p->Gamma_drive; fields[6] = p->CL;
    fields[7] = p->CS; fields[8] = p->R; fields[9] = p->a; fields[10] = p->LSR0;
    fields[11] = p->LPR0; fields[12] = p->LNSR; fields[13] = p->LNPR; fields[14] = p->X;
    fields[15] = p->Lsec; fields[16] = p->G_pri; fields[17] = p->G_sec; fields[18] = p->freq;
    fields[19] = p->p; fields[20] = p->tau;
    for (k = 0; k < 21; ++k) {
        for (i = 0; i < PS_NFIBRES; ++i) {
            if (!isfinite(fields[k][i])) return PS_ERR_CONFIG;
        }
    }
    if (!isfinite(p->S)) return PS_ERR_CONFIG;
    if (!(positive_all(p->KSR) && positive_all(p->M) && positive_all(p->freq)
          && positive_all(p->p) && positive_all(p->CL) && positive_all(p->CS)
          && positive_all(p->a))) {
        return PS_ERR_CONFIG;
    }
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (!(p->a[i] < R_(1)) || p->tau[i] < R_(0)) return PS_ERR_CONFIG;
    }
    return PS_OK;
}

int ps_spindle_run(ps_spindle *s, const ps_params *p, const ps_real *L, const ps_real *gd,
                   const ps_real *gs, long n_steps, ps_real h, ps_real theta, long every,
                   ps_real *ia, ps_real *ii, long *done)
{
    long j;
    int status = PS_OK;
    if (done != NULL) *done = 0;
    if (s == NULL || p == NULL || L == NULL || gd == NULL || gs == NULL) return PS_ERR_NULL;
    if (every < 1 || n_steps < 0) return PS_ERR_CONFIG;
    for (j = 0; j < n_steps; ++j) {
        ps_real r_ia, r_ii;
        status = ps_spindle_step(s, p, L[j], gd[j], gs[j], h, theta, &r_ia, &r_ii);
        if (status != PS_OK) break;
        if ((j + 1) % every == 0) {
            long k = (j + 1) / every - 1;
            if (ia != NULL) ia[k] = r_ia;
            if (ii != NULL) ii[k] = r_ii;
        }
        if (done != NULL) *done = j + 1;
    }
    return status;
}

/* ---- embedded fast path ---------------------------------------------------------------
 * ps_spindle_step_plan is a second implementation of the float step, kept because it pays on
 * the FPU-less target: on the Cortex-M0+ (scripts/bench_embedded.py --only 1 2, trapezoidal,
 * 1 ms, float32) it takes 41,825 instructions per step against ps_spindle_step's 62,910
 * (41.8 vs 62.9 MIPS per muscle, -34 %) at the same accuracy (0.064 pps RMS), and the
 * embedded levers (PS_FAST_CBRT, PS_NEWTON_TOL_Z, the plan in flash) build on it. It uses the
 * shared pieces above (activation target, force, Newton start, the solve for a != 0.3, the
 * rate combination, commit); what differs is the arithmetic the plan precomputes and, for
 * a = 0.3, Newton in y = |z| from a bound above the root (solve_03). */

/* Fibre i's activation filter: f1 = c_f0 f0 + c_a0 a*(g0) + c_a1 a*(g1) (the theta-method on
 * df/dt = (a* - f)/tau; without lag f is the target itself). */
static void plan_activation_coefficients(ps_plan *out, int i, const ps_params *p, ps_real h,
                                         ps_real theta)
{
    ps_real rate = p->tau[i] > R_(0) ? h / p->tau[i] : R_(0);
    ps_real den = R_(1) + theta * rate;
    out->lagged[i] = p->tau[i] > R_(0);
    if (out->lagged[i]) {
        out->c_f0[i] = (R_(1) - (R_(1) - theta) * rate) / den;
        out->c_a0[i] = (R_(1) - theta) * rate / den;
        out->c_a1[i] = theta * rate / den;
    } else {
        out->c_f0[i] = R_(0);
        out->c_a0[i] = R_(0);
        out->c_a1[i] = R_(1);
    }
    out->c_a01[i] = out->c_a0[i] + out->c_a1[i];
}

/* Fibre i's constants of the step and of the rates at step h, theta. */
static void plan_fibre_constants(ps_plan *out, int i, const ps_params *p, ps_real h,
                                 ps_real theta)
{
    const ps_real KSR = p->KSR[i];
    const ps_real k1 = R_(1) + p->KPR[i] / KSR;
    out->KSR[i] = KSR;
    out->inv_KSR[i] = R_(1) / KSR;
    out->freq_p[i] = out->p_is_2 ? p->freq[i] * p->freq[i] : ps_pow(p->freq[i], p->p[i]);
    out->p[i] = p->p[i];
    out->a[i] = p->a[i];
    out->beta0[i] = p->beta0[i];
    out->beta_drive[i] = p->beta_drive[i];
    out->Gamma_drive[i] = p->Gamma_drive[i];
    out->CL[i] = p->CL[i];
    out->CS[i] = p->CS[i];
    out->KPR[i] = p->KPR[i];
    out->LPR0[i] = p->LPR0[i];
    out->R[i] = p->R[i];
    out->LSR0[i] = p->LSR0[i];
    out->LSR0_R[i] = p->LSR0[i] + p->R[i];
    out->LSR0_LPR0[i] = p->LSR0[i] + p->LPR0[i];
    out->h_KSR[i] = h * KSR;
    out->h_M[i] = h / p->M[i];
    out->c_Av[i] = (R_(1) - theta) * h * KSR;
    out->a2[i] = p->M[i] / h + theta * theta * h * k1 * KSR;
    out->inv_a2[i] = R_(1) / out->a2[i];
    out->M_h[i] = p->M[i] / h;
    out->th_h_KSR[i] = theta * h * KSR;
    out->th_k1[i] = theta * k1;
    out->th_KPR[i] = theta * p->KPR[i];
    out->th_CS[i] = theta * p->CS[i];
    out->th_dC[i] = theta * (p->CL[i] - p->CS[i]);
    out->stretch0[i] = p->LNSR[i] - p->LSR0[i];
    out->G_pri[i] = p->G_pri[i];
    out->c_sec1[i] = p->G_sec[i] * p->X[i] * (p->Lsec[i] / p->LSR0[i]);
    out->c_sec2[i] = p->G_sec[i] * (R_(1) - p->X[i]) * (p->Lsec[i] / p->LPR0[i]);
    out->sec_off[i] = p->LSR0[i] + p->LNPR[i];
}

int ps_plan_init(ps_plan *q, const ps_params *p, ps_real h, ps_real theta)
{
    ps_plan out;
    int i;
    if (q == NULL || p == NULL) return PS_ERR_NULL;
    if (ps_params_check(p) != PS_OK) return PS_ERR_CONFIG;
    if (!(theta >= R_(0) && theta <= R_(1))) return PS_ERR_METHOD;
    if (!(isfinite(h) && h > R_(0))) return PS_ERR_STEP;
    memset(&out, 0, sizeof out);
    out.h = h;
    out.theta = theta;
    out.one_minus_theta = R_(1) - theta;
    out.th_h = theta * h;
    out.max_dL = R_(PS_MAX_SPEED_L0_S) * h;
    out.S = p->S;
    out.p_is_2 = all_equal(p->p, R_(2));
    out.a_is_03 = all_equal(p->a, R_(0.3));
    out.explicit_step = theta == R_(0);
    out.uses_F0 = theta < R_(1);
    for (i = 0; i < PS_NFIBRES; ++i) {
        plan_activation_coefficients(&out, i, p, h, theta);
        plan_fibre_constants(&out, i, p, h, theta);
    }
    *q = out;
    return PS_OK;
}

/* The bits of a float x in [1e-30, 1e30] -> those of ~x^(1/10): u/10 = u * 0.000110011...b
 * (the sum stays below 2^31). */
PS_INLINE unsigned int tenth_root_bits(unsigned int u)
{
    return (u >> 4) + (u >> 5) + (u >> 8) + (u >> 9) + (u >> 12) + (u >> 13) + (u >> 16)
           + (u >> 17) + (u >> 20) + (u >> 21) + 958817894u;
}

/* x^(1/10) to ~1 %: the exponent bits divided by 10 (shifts), no refinement. Only a bound
 * for the starting guess below. */
static ps_real tenth_root_estimate(ps_real x)
{
    ps_bits b;
    if (!(x > R_(1e-30) && x < R_(1e30))) return x > R_(1) ? ps_pow(x, R_(0.1)) : R_(0);
    b.f = (float)x;
    b.u = tenth_root_bits(b.u);
    return (ps_real)b.f;
}

/* The implicit equation for a = 0.3, solved for y = |z| (the root has the sign of rhs, since
 * g rises through g(0) = -rhs, so the damping coefficient c = C*theta*beta is known before
 * iterating): a2*y^10 + c*y^3*(p0 + s*th_h*y^10) = |rhs|. Each term alone would reach |rhs|
 * at a larger y than the root, so (|rhs|/a2)^(1/10) bounds it from above; the start is the
 * smaller of that and the linearised guess z (spindle.core's), and Newton from above on this
 * convex function needs few iterations.
 *
 * The three fibres' equations are solved side by side, one iteration of each per pass, each
 * fibre stopping on its own test (so each takes exactly the iterations it would alone): one
 * iteration is a chain of dependent multiplies and a divide, and three independent chains
 * keep a superscalar core busy where one leaves it waiting. Measured on the host (x86-64,
 * gcc -O2, ps_spindle_batch_step on the 864 spindles of the legs under random controls, 1 ms,
 * 4.4 iterations per solve): 440 -> 330 ns per spindle step (275 with the host build's cube
 * root). The fibres of 2, 4 or 8 spindles of a batch side by side as scalar code gained
 * nothing (266, 292, 298 ns); as SIMD lanes they do: see ps_spindle_batch_step. The
 * Cortex-M0+ gains nothing (one instruction at a time) and pays for the
 * work kept in memory: the float plan step (scripts/bench_embedded.py --only 2 9) 41,861 ->
 * 42,594 instructions per step at 1 ms, 36,926 -> 37,473 at 5 ms (+1.5 %); the fixed-point
 * step, the device's configuration (--quick), is not this code (1.7224 MIPS, unchanged).
 * Writes z[i], v[i] = sgn(z)|z|^10 and status[i] (PS_OK or PS_ERR_NO_CONVERGENCE). */
typedef struct plan_eq {
    ps_real A;        /* tension before the velocity term */
    ps_real p0, rhs;  /* g's polar-length offset and right-hand side */
    ps_real cS, dC;   /* damping coefficients (shortening, lengthening minus shortening) */
    ps_real z;        /* Newton's start */
} plan_eq;

/* One fibre's equation in solve_03: its coefficients (set once), Newton's iterate y. */
typedef struct solve_03_work {
    ps_real a2, ten_a2, r, p0, s_th_h, c, ten_c_th_h, three_c, y;
    int active;
} solve_03_work;

/* Fibre i's equation from its terms and Newton's start z, bounded by `bound` (the estimate of
 * (|rhs|/a2)^(1/10)). */
PS_INLINE void solve_03_setup(solve_03_work *w, const ps_plan *q, int i, ps_real p0, ps_real rhs,
                           ps_real cS, ps_real dC, ps_real z, ps_real bound)
{
    w->a2 = q->a2[i];
    w->ten_a2 = R_(10) * w->a2;
    w->r = ps_fabs(rhs);
    w->p0 = p0;
    w->s_th_h = rhs < R_(0) ? -q->th_h : q->th_h;
    w->c = rhs > R_(0) ? cS + dC : cS;
    w->ten_c_th_h = R_(10) * w->c * w->s_th_h;
    w->three_c = R_(3) * w->c;
    w->y = ps_fabs(z);
    if (!(w->y <= bound)) w->y = bound; /* also replaces a NaN guess */
    w->active = 1;
}

/* Newton's step dy at w->y (the new iterate is max(y - dy, 0)). */
PS_INLINE ps_real solve_03_step(const solve_03_work *w)
{
    const ps_real y = w->y, y2 = y * y, y3 = y2 * y, y4 = y2 * y2, y9 = y4 * y4 * y;
    const ps_real y10 = y9 * y, qy = w->p0 + w->s_th_h * y10;
    ps_real g, dg;
    if (qy > R_(0)) {
        g = w->a2 * y10 + w->c * y3 * qy - w->r;
        dg = y9 * (w->ten_a2 + w->ten_c_th_h * y3) + w->three_c * y2 * qy;
    } else { /* the damping's polar-length factor clipped at 0 */
        g = w->a2 * y10 - w->r;
        dg = y9 * w->ten_a2;
    }
    return newton_step(g, dg);
}

/* y^10 (the velocity's magnitude at the root y = |z|). */
PS_INLINE ps_real tenth_power(ps_real y)
{
    const ps_real y2 = y * y, y4 = y2 * y2;
    return y4 * y4 * y2;
}

static void solve_03(const ps_plan *q, const plan_eq e[PS_NFIBRES], ps_real z[PS_NFIBRES],
                     ps_real v[PS_NFIBRES], int status[PS_NFIBRES])
{
    solve_03_work work[PS_NFIBRES];
    int left = PS_NFIBRES, i, it;
    for (i = 0; i < PS_NFIBRES; ++i) {
        solve_03_setup(&work[i], q, i, e[i].p0, e[i].rhs, e[i].cS, e[i].dC, e[i].z,
                       tenth_root_estimate(ps_fabs(e[i].rhs) * q->inv_a2[i]));
        status[i] = PS_ERR_NO_CONVERGENCE;
    }
#if defined(PS_NEWTON_ITER) && PS_NEWTON_ITER > 0
    for (it = 0; it < PS_NEWTON_ITER; ++it) {
#else
    for (it = 0; it < PS_NEWTON_MAX_ITER && left > 0; ++it) {
#endif
        for (i = 0; i < PS_NFIBRES; ++i) {
            solve_03_work *w = &work[i];
            ps_real y, dy;
            if (!w->active) continue;
            dy = solve_03_step(w);
            y = w->y - dy;
            w->y = y < R_(0) ? R_(0) : y;
#if defined(PS_NEWTON_ITER) && PS_NEWTON_ITER > 0
            status[i] = PS_OK;
#else
            if (ps_fabs(dy) <= R_(PS_NEWTON_TOL_Z)) {
                status[i] = PS_OK;
                w->active = 0;
                --left;
            }
#endif
        }
    }
    (void)left;
    for (i = 0; i < PS_NFIBRES; ++i) {
        const ps_real y = work[i].y, y10 = tenth_power(y);
        z[i] = e[i].rhs < R_(0) ? -y : y;
        v[i] = e[i].rhs < R_(0) ? -y10 : y10;
    }
}

PS_INLINE ps_real plan_target(const ps_plan *q, int i, ps_real drive)
{
    return target_from_power(drive_power(drive, q->p[i], q->p_is_2), q->freq_p[i]);
}

/* Fibre i's activation after the step; a target is computed only for a drive that changed
 * (one divide each). */
static ps_real plan_activation(const ps_plan *q, int i, const ps_spindle *s, ps_real drive1)
{
    const ps_real f0 = s->f[i];
    const ps_real drive0 = fibre_drive(i, s->gd, s->gs);
    const int same_drive = drive1 == drive0;
    ps_real f;
    if (!q->lagged[i]) {
        /* f is the target itself: unchanged with the drive */
        return same_drive ? f0 : plan_target(q, i, drive1);
    }
    if (same_drive) { /* the previous target is the new one */
        return q->c_f0[i] * f0 + q->c_a01[i] * plan_target(q, i, drive1);
    }
    f = q->c_f0[i] * f0 + q->c_a1[i] * plan_target(q, i, drive1);
    if (q->c_a0[i] != R_(0)) f += q->c_a0[i] * plan_target(q, i, drive0);
    return f;
}

/* Fibre i's force at the start of the step from its state T0, z0 (z03 = z0^3), f0 and the
 * length L0. */
PS_INLINE ps_real plan_start_force(const ps_plan *q, int i, ps_real T0, ps_real z0, ps_real z03,
                                ps_real f0, ps_real L0)
{
    return force(T0, z0, z03, L0 - q->LSR0[i] - T0 * q->inv_KSR[i],
                 q->beta0[i] + q->beta_drive[i] * f0, q->Gamma_drive[i] * f0, q->KPR[i],
                 q->LPR0[i], q->R[i], q->CL[i], q->CS[i]);
}

/* Fibre i's implicit equation for the step with its new activation f1 (the equations of
 * implicit_fibre, constants from the plan) from its state values T0, v0, z0, f0 and length
 * L0; returns the cube of Newton's start (newton_start_cube). For a = 0.3 only when
 * `a_is_03`, with the start's force only when `uses_F0` (constants to the caller: the lanes
 * inline it without the pow and without a branch). */
PS_INLINE ps_real plan_equation_terms(const ps_plan *q, int i, int a_is_03, int uses_F0,
                                      ps_real T0, ps_real v0, ps_real z0, ps_real f0,
                                      ps_real L0, ps_real L1, ps_real f1, ps_real *A_out,
                                      ps_real *p0, ps_real *rhs, ps_real *cS, ps_real *dC)
{
    const ps_real z02 = z0 * z0, z03 = z02 * z0;
    const ps_real beta1 = q->beta0[i] + q->beta_drive[i] * f1;
    const ps_real F0 = uses_F0 ? plan_start_force(q, i, T0, z0, z03, f0, L0) : R_(0);
    const ps_real A = T0 + q->KSR[i] * (L1 - L0) - q->c_Av[i] * v0;
    const ps_real z0_7 = a_is_03 ? z03 * z03 * ps_fabs(z0)
                                 : z02 * ps_pow(ps_fabs(z0), R_(3) / q->a[i] - R_(3));
    *A_out = A;
    *p0 = L1 - q->LSR0_R[i] - A * q->inv_KSR[i];
    *rhs = q->M_h[i] * v0 + q->th_k1[i] * A - q->theta * (q->Gamma_drive[i] * f1)
           - q->th_KPR[i] * (L1 - q->LSR0_LPR0[i]) + q->one_minus_theta * F0;
    *cS = q->th_CS[i] * beta1;
    *dC = q->th_dC[i] * beta1;
    return newton_start_cube(z0_7, q->a2[i], *rhs, *cS, *dC, *p0);
}

static void plan_equation(const ps_plan *q, int i, const ps_spindle *s, ps_real L1, ps_real f1,
                          plan_eq *e)
{
    e->z = cube_root(plan_equation_terms(q, i, q->a_is_03, q->uses_F0, s->T[i], s->v[i],
                                         s->z[i], s->f[i], s->L, L1, f1, &e->A, &e->p0,
                                         &e->rhs, &e->cS, &e->dC));
}

/* Fibre i's step with its new activation f1 when a != 0.3 or theta = 0 (the equations of
 * explicit_fibre and implicit_fibre, constants from the plan). */
static int plan_fibre(const ps_plan *q, int i, const ps_spindle *s, ps_real L1, ps_real f1,
                      ps_real *T1, ps_real *v1, ps_real *z1)
{
    plan_eq e;
    int status;
    if (q->explicit_step) {
        const ps_real v0 = s->v[i], z0 = s->z[i];
        const ps_real F0 = plan_start_force(q, i, s->T[i], z0, z0 * z0 * z0, s->f[i], s->L);
        *T1 = s->T[i] + q->KSR[i] * (L1 - s->L) - q->h_KSR[i] * v0;
        *v1 = v0 + q->h_M[i] * F0;
        *z1 = root_of_velocity(*v1, q->a[i]);
        return PS_OK;
    }
    plan_equation(q, i, s, L1, f1, &e);
    status = solve_z(&e.z, v1, q->a2[i], e.p0, e.rhs, e.cS, e.dC, q->th_h, q->a[i], 0);
    if (status != PS_OK) return status;
    *T1 = e.A - q->th_h_KSR[i] * *v1;
    *z1 = e.z;
    return PS_OK;
}

/* Fibre i's primary and secondary potentials at tension T and length L. */
PS_INLINE void plan_potentials(const ps_plan *q, int i, ps_real T, ps_real L, ps_real *primary,
                               ps_real *sec)
{
    ps_real t_ksr = T * q->inv_KSR[i];
    ps_real stretch = t_ksr - q->stretch0[i];
    *primary = max_r(q->G_pri[i] * stretch, R_(0));
    *sec = q->c_sec1[i] * stretch + q->c_sec2[i] * (L - t_ksr - q->sec_off[i]);
}

PS_INLINE void plan_afferents(const ps_plan *q, const ps_real T[PS_NFIBRES], ps_real L,
                              ps_real *ia, ps_real *ii)
{
    ps_real primary[PS_NFIBRES], sec[PS_NFIBRES];
    int i;
    for (i = 0; i < PS_NFIBRES; ++i) plan_potentials(q, i, T[i], L, &primary[i], &sec[i]);
    combine_rates(primary, sec, q->S, ia, ii);
}

int ps_spindle_step_plan(ps_spindle *s, const ps_plan *q, ps_real L1, ps_real gd1,
                         ps_real gs1, ps_real *ia, ps_real *ii)
{
    ps_real T1[PS_NFIBRES], v1[PS_NFIBRES], z1[PS_NFIBRES], f1[PS_NFIBRES], r_ia, r_ii;
    int i, status;

    if (s == NULL || q == NULL) return PS_ERR_NULL;
    status = check_inputs(L1, gd1, gs1);
    if (status != PS_OK) return status;
    if (ps_fabs(L1 - s->L) > q->max_dL) return PS_ERR_SPEED;
    for (i = 0; i < PS_NFIBRES; ++i) f1[i] = plan_activation(q, i, s, fibre_drive(i, gd1, gs1));
    if (q->a_is_03 && !q->explicit_step) {
        plan_eq e[PS_NFIBRES];
        int solved[PS_NFIBRES];
        for (i = 0; i < PS_NFIBRES; ++i) plan_equation(q, i, s, L1, f1[i], &e[i]);
        solve_03(q, e, z1, v1, solved);
        /* the first failure in fibre order, as if the fibres were solved one by one */
        for (i = 0; i < PS_NFIBRES; ++i) {
            if (solved[i] != PS_OK) return solved[i];
            T1[i] = e[i].A - q->th_h_KSR[i] * v1[i];
            if (!fibre_finite(T1[i], v1[i], z1[i], f1[i])) return PS_ERR_NONFINITE;
        }
    } else {
        for (i = 0; i < PS_NFIBRES; ++i) {
            status = plan_fibre(q, i, s, L1, f1[i], &T1[i], &v1[i], &z1[i]);
            if (status != PS_OK) return status;
            if (!fibre_finite(T1[i], v1[i], z1[i], f1[i])) return PS_ERR_NONFINITE;
        }
    }
    plan_afferents(q, T1, L1, &r_ia, &r_ii);
    return finish_step(s, T1, v1, z1, f1, L1, gd1, gs1, r_ia, r_ii, ia, ii);
}

/* ---- batches of independent spindles ---------------------------------------------------
 * Many spindles with one plan, one call per step: what a host running the spindles of many
 * muscles (and many simulated bodies) needs, without a foreign call per spindle. Each
 * spindle's step is ps_spindle_step_plan itself. Not needed on a one-muscle device
 * (PS_NO_BATCH). */
#ifndef PS_NO_BATCH

/* ---- the batch in lanes (host) ----------------------------------------------------------
 * A second form of the planned step, kept because it pays on the host: replaying the 300
 * ps_spindle_batch_step calls of myo-sim's 54-muscle legs in 16 envs (864 spindles, 1 ms,
 * trapezoidal, random controls; PYTHONPATH=. python scripts/bench_batch_step.py, x86-64 AMD
 * EPYC with AVX2, gcc 12 -O2, shared 2-core machine, medians of 9 and 15 rounds) the scalar
 * loop takes 381 and 328 ns per spindle step, these lanes 101 and 109 ns (3.8x, 3.0x);
 * 8 lanes: 2, 4, 16 lanes gave 209, 116, 108 ns against 101 in one run. Without AVX2
 * (SSE2 only, -DPS_LANES_NO_AVX2) the lanes gave 285 and 351 ns against the scalar loop's
 * 381 and 328: no clear gain, so a CPU without AVX2 runs the scalar loop.
 * The step of ps_spindle_step_plan for the a = 0.3 implicit plan (p = 2), PS_LANES spindles
 * at a time: each quantity of the scalar step is an array [fibre][lane] and each line of it a
 * loop over the lanes that the compiler turns into SIMD (an AVX2 copy of the code, chosen at
 * run time with __builtin_cpu_supports: the cached library must load on any x86-64, so no
 * -march). Bit-identical to the scalar step lane by lane: the same helpers (inlined) and so
 * the same IEEE operations in the same order, no contraction (-ffp-contract=off in the
 * build, and target("avx2") does not enable FMA); every branch of the scalar step is a
 * per-lane select of values both computed (activation targets of both drives, both Newton
 * forms; -fno-trapping-math lets the compiler compute both), a lane whose Newton iteration
 * converged keeps its y while the others iterate. The rare cube and tenth roots the bit
 * estimate does not cover (tiny, huge, NaN) are redone lane by lane by the scalar
 * functions. lanes_run stops at a block with any lane that would fail (inputs, speed, no
 * convergence, non-finite): the caller then undoes the blocks before it and runs the scalar
 * loop, which finds the status and the failing spindle as before. The tail (n mod PS_LANES)
 * is one more block, padded (lanes_tail), when it is long enough to pay, else the scalar
 * loop's. */
#if defined(PS_LANES_NO_AVX2) && !defined(PS_BATCH_SCALAR)
#define PS_LANES_MODE 1 /* the lanes in the baseline instruction set, always */
#elif !defined(PS_BATCH_SCALAR) && defined(__GNUC__) && defined(__x86_64__) \
    && (!defined(__clang__) || __clang_major__ >= 6)
#define PS_LANES_MODE 2 /* the AVX2 lanes where the CPU has AVX2, else the scalar loop */
#endif

#ifdef PS_LANES_MODE
#ifndef PS_LANES
#define PS_LANES 8
#endif

#if defined(__GNUC__)
#define PS_LANE_FN static inline __attribute__((always_inline))
#else
#define PS_LANE_FN static
#endif

/* A lane's flag: an integer as wide as ps_real, so that selects on it stay in one vector. */
#ifdef PS_FLOAT
typedef int lane_flag;
#else
typedef long long lane_flag;
#endif

#define LANE_LOOP(l) for ((l) = 0; (l) < PS_LANES; ++(l))

typedef struct lane_block {
    ps_real L0[PS_LANES], L1[PS_LANES];
    ps_real T0[PS_NFIBRES][PS_LANES], v0[PS_NFIBRES][PS_LANES], z0[PS_NFIBRES][PS_LANES];
    ps_real f0[PS_NFIBRES][PS_LANES], f1[PS_NFIBRES][PS_LANES];
    ps_real drive0[PS_NFIBRES][PS_LANES], drive1[PS_NFIBRES][PS_LANES];
    ps_real A[PS_NFIBRES][PS_LANES], p0[PS_NFIBRES][PS_LANES], rhs[PS_NFIBRES][PS_LANES];
    ps_real cS[PS_NFIBRES][PS_LANES], dC[PS_NFIBRES][PS_LANES];
    ps_real x[PS_NFIBRES][PS_LANES]; /* a root's argument */
    ps_real z[PS_NFIBRES][PS_LANES], bound[PS_NFIBRES][PS_LANES];
    /* solve_03_work by fields */
    ps_real r[PS_NFIBRES][PS_LANES], s_th_h[PS_NFIBRES][PS_LANES], c[PS_NFIBRES][PS_LANES];
    ps_real ten_c_th_h[PS_NFIBRES][PS_LANES], three_c[PS_NFIBRES][PS_LANES];
    ps_real y[PS_NFIBRES][PS_LANES];
    lane_flag active[PS_NFIBRES][PS_LANES];
    ps_real T1[PS_NFIBRES][PS_LANES], v1[PS_NFIBRES][PS_LANES];
    ps_real pri[PS_NFIBRES][PS_LANES], sec[PS_NFIBRES][PS_LANES];
    ps_real ia[PS_LANES], ii[PS_LANES];
} lane_block;

/* 1 if every lane's inputs pass the scalar step's checks (check_inputs, speed). */
PS_LANE_FN int lanes_inputs_ok(const ps_plan *q, const lane_block *b)
{
    int l, bad = 0;
    for (l = 0; l < PS_LANES; ++l) {
        bad |= check_inputs(b->L1[l], b->drive1[0][l], b->drive1[1][l]) != PS_OK;
        bad |= ps_fabs(b->L1[l] - b->L0[l]) > q->max_dL;
    }
    return !bad;
}

/* plan_activation with both targets computed and the branches as selects. */
PS_LANE_FN void lanes_activation(const ps_plan *q, lane_block *b)
{
    int i, l;
    for (i = 0; i < PS_NFIBRES; ++i) {
        const ps_real *d0 = b->drive0[i], *d1 = b->drive1[i], freq_p = q->freq_p[i];
        const ps_real c_f0 = q->c_f0[i], c_a0 = q->c_a0[i], c_a1 = q->c_a1[i];
        const ps_real c_a01 = q->c_a01[i];
        ps_real t0[PS_LANES], t1[PS_LANES];
        /* plan_target for p = 2 */
        LANE_LOOP(l) t1[l] = target_from_power(d1[l] * d1[l], freq_p);
        LANE_LOOP(l) t0[l] = target_from_power(d0[l] * d0[l], freq_p);
        if (!q->lagged[i]) {
            LANE_LOOP(l) b->f1[i][l] = d1[l] == d0[l] ? b->f0[i][l] : t1[l];
        } else if (c_a0 != R_(0)) {
            LANE_LOOP(l) {
                const ps_real f0 = b->f0[i][l];
                const ps_real f_diff = c_f0 * f0 + c_a1 * t1[l] + c_a0 * t0[l];
                b->f1[i][l] = d1[l] == d0[l] ? c_f0 * f0 + c_a01 * t1[l] : f_diff;
            }
        } else {
            LANE_LOOP(l) {
                const ps_real f0 = b->f0[i][l];
                const ps_real f_diff = c_f0 * f0 + c_a1 * t1[l];
                b->f1[i][l] = d1[l] == d0[l] ? c_f0 * f0 + c_a01 * t1[l] : f_diff;
            }
        }
    }
}

#ifdef PS_FAST_CBRT
/* cube_root's estimate for |x| in (1e-30, 1e30); x itself elsewhere (fixed by the caller). */
PS_LANE_FN ps_real lane_cube_root(ps_real x)
{
    const ps_real ax = ps_fabs(x);
    ps_bits b;
    ps_real y;
    int k;
    b.f = (float)ax;
    b.u = cbrt_bits(b.u);
    y = (ps_real)b.f;
    for (k = 0; k < PS_CBRT_REFINE; ++k) y = (R_(2) * y + ax / (y * y)) * R_(1.0 / 3.0);
    y = x < R_(0) ? -y : y;
    return ax > R_(1e-30) && ax < R_(1e30) ? y : x;
}
#endif

/* tenth_root_estimate for x in (1e-30, 1e30), 0 for x <= 1 outside, x above (fixed by the
 * caller). */
PS_LANE_FN ps_real lane_tenth_root(ps_real x)
{
    ps_bits b;
    b.f = (float)x;
    b.u = tenth_root_bits(b.u);
    return x > R_(1e-30) && x < R_(1e30) ? (ps_real)b.f : (x > R_(1) ? x : R_(0));
}

/* plan_equation and solve_03's set-up. */
PS_LANE_FN void lanes_equation(const ps_plan *q, lane_block *b)
{
    int i, l;
    lane_flag fix;
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (q->uses_F0) {
            LANE_LOOP(l) {
                b->x[i][l] = plan_equation_terms(
                    q, i, 1, 1, b->T0[i][l], b->v0[i][l], b->z0[i][l], b->f0[i][l], b->L0[l],
                    b->L1[l], b->f1[i][l], &b->A[i][l], &b->p0[i][l], &b->rhs[i][l],
                    &b->cS[i][l], &b->dC[i][l]);
            }
        } else {
            LANE_LOOP(l) {
                b->x[i][l] = plan_equation_terms(
                    q, i, 1, 0, b->T0[i][l], b->v0[i][l], b->z0[i][l], b->f0[i][l], b->L0[l],
                    b->L1[l], b->f1[i][l], &b->A[i][l], &b->p0[i][l], &b->rhs[i][l],
                    &b->cS[i][l], &b->dC[i][l]);
            }
        }
#ifdef PS_FAST_CBRT
        fix = 0;
        LANE_LOOP(l) {
            const ps_real ax = ps_fabs(b->x[i][l]);
            b->z[i][l] = lane_cube_root(b->x[i][l]);
            fix |= !(ax > R_(1e-30) && ax < R_(1e30));
        }
        if (fix) {
            LANE_LOOP(l) b->z[i][l] = cube_root(b->x[i][l]);
        }
#else
        LANE_LOOP(l) b->z[i][l] = cube_root(b->x[i][l]);
#endif
        fix = 0;
        LANE_LOOP(l) {
            const ps_real x = ps_fabs(b->rhs[i][l]) * q->inv_a2[i];
            b->bound[i][l] = lane_tenth_root(x);
            fix |= x > R_(1) && !(x < R_(1e30));
        }
        if (fix) {
            LANE_LOOP(l) {
                b->bound[i][l] = tenth_root_estimate(ps_fabs(b->rhs[i][l]) * q->inv_a2[i]);
            }
        }
        LANE_LOOP(l) {
            solve_03_work w;
            solve_03_setup(&w, q, i, b->p0[i][l], b->rhs[i][l], b->cS[i][l], b->dC[i][l],
                           b->z[i][l], b->bound[i][l]);
            b->r[i][l] = w.r;
            b->s_th_h[i][l] = w.s_th_h;
            b->c[i][l] = w.c;
            b->ten_c_th_h[i][l] = w.ten_c_th_h;
            b->three_c[i][l] = w.three_c;
            b->y[i][l] = w.y;
            b->active[i][l] = 1;
        }
    }
}

/* solve_03's iterations, all fibres of all lanes side by side; a lane that converged keeps
 * its y. 1 if every lane converged. */
PS_LANE_FN int lanes_solve_03(const ps_plan *q, lane_block *b)
{
    int i, l, it;
    lane_flag left = 1;
#if defined(PS_NEWTON_ITER) && PS_NEWTON_ITER > 0
    for (it = 0; it < PS_NEWTON_ITER; ++it) {
#else
    for (it = 0; it < PS_NEWTON_MAX_ITER && left; ++it) {
#endif
        for (i = 0; i < PS_NFIBRES; ++i) {
            const ps_real a2 = q->a2[i], ten_a2 = R_(10) * a2;
            LANE_LOOP(l) {
                solve_03_work w;
                ps_real dy, y;
                w.a2 = a2;
                w.ten_a2 = ten_a2;
                w.r = b->r[i][l];
                w.p0 = b->p0[i][l];
                w.s_th_h = b->s_th_h[i][l];
                w.c = b->c[i][l];
                w.ten_c_th_h = b->ten_c_th_h[i][l];
                w.three_c = b->three_c[i][l];
                w.y = b->y[i][l];
                dy = solve_03_step(&w);
                y = w.y - dy;
                y = y < R_(0) ? R_(0) : y;
                b->y[i][l] = b->active[i][l] ? y : w.y;
#if !(defined(PS_NEWTON_ITER) && PS_NEWTON_ITER > 0)
                b->active[i][l] = ps_fabs(dy) <= R_(PS_NEWTON_TOL_Z) ? 0 : b->active[i][l];
#endif
            }
        }
        left = 0;
        for (i = 0; i < PS_NFIBRES; ++i) {
            LANE_LOOP(l) left |= b->active[i][l];
        }
    }
#if defined(PS_NEWTON_ITER) && PS_NEWTON_ITER > 0
    (void)left;
    return 1;
#else
    return !left;
#endif
}

/* The end of ps_spindle_step_plan: T, the checks of finiteness, the rates. 1 if all pass. */
PS_LANE_FN int lanes_finish(const ps_plan *q, lane_block *b)
{
    int i, l;
    lane_flag bad = 0;
    for (i = 0; i < PS_NFIBRES; ++i) {
        const ps_real th_h_KSR = q->th_h_KSR[i];
        LANE_LOOP(l) {
            const ps_real y = b->y[i][l], y10 = tenth_power(y);
            const int negative = b->rhs[i][l] < R_(0);
            b->z[i][l] = negative ? -y : y;
            b->v1[i][l] = negative ? -y10 : y10;
            b->T1[i][l] = b->A[i][l] - th_h_KSR * b->v1[i][l];
            bad |= !fibre_finite(b->T1[i][l], b->v1[i][l], b->z[i][l], b->f1[i][l]);
        }
    }
    for (i = 0; i < PS_NFIBRES; ++i) {
        LANE_LOOP(l) plan_potentials(q, i, b->T1[i][l], b->L1[l], &b->pri[i][l], &b->sec[i][l]);
    }
    LANE_LOOP(l) {
        ps_real pri[PS_NFIBRES], sec[PS_NFIBRES];
        pri[0] = b->pri[0][l];
        pri[1] = b->pri[1][l];
        pri[2] = b->pri[2][l];
        sec[0] = b->sec[0][l];
        sec[1] = b->sec[1][l];
        sec[2] = b->sec[2][l];
        combine_rates(pri, sec, q->S, &b->ia[l], &b->ii[l]);
        bad |= !(isfinite(b->ia[l]) && isfinite(b->ii[l]));
    }
    return !bad;
}

/* Spindles [0, m) (m a multiple of PS_LANES) block by block, each saved to backup before it
 * is written; returns m, or the first spindle of the first block with a failing lane (the
 * spindles before it advanced, the others untouched). */
PS_LANE_FN long lanes_run(ps_spindle *s, long m, const ps_plan *q, const ps_real *L1,
                          const ps_real *gd1, const ps_real *gs1, ps_spindle *backup,
                          ps_real *ia, ps_real *ii)
{
    lane_block b;
    long j0;
    int i, l;
    for (j0 = 0; j0 < m; j0 += PS_LANES) {
        const ps_spindle *sb = &s[j0];
        /* field by field: strided loads the compiler assembles into vectors */
        LANE_LOOP(l) b.L0[l] = sb[l].L;
        LANE_LOOP(l) b.L1[l] = L1[j0 + l];
        for (i = 0; i < PS_NFIBRES; ++i) {
            LANE_LOOP(l) b.drive0[i][l] = fibre_drive(i, sb[l].gd, sb[l].gs);
            LANE_LOOP(l) b.drive1[i][l] = fibre_drive(i, gd1[j0 + l], gs1[j0 + l]);
            LANE_LOOP(l) b.T0[i][l] = sb[l].T[i];
            LANE_LOOP(l) b.v0[i][l] = sb[l].v[i];
            LANE_LOOP(l) b.z0[i][l] = sb[l].z[i];
            LANE_LOOP(l) b.f0[i][l] = sb[l].f[i];
        }
        if (!lanes_inputs_ok(q, &b)) return j0;
        lanes_activation(q, &b);
        lanes_equation(q, &b);
        if (!lanes_solve_03(q, &b) || !lanes_finish(q, &b)) return j0;
        LANE_LOOP(l) backup[j0 + l] = s[j0 + l];
        for (i = 0; i < PS_NFIBRES; ++i) {
            LANE_LOOP(l) s[j0 + l].T[i] = b.T1[i][l];
            LANE_LOOP(l) s[j0 + l].v[i] = b.v1[i][l];
            LANE_LOOP(l) s[j0 + l].z[i] = b.z[i][l];
            LANE_LOOP(l) s[j0 + l].f[i] = b.f1[i][l];
        }
        LANE_LOOP(l) s[j0 + l].L = b.L1[l];
        LANE_LOOP(l) s[j0 + l].gd = b.drive1[0][l];
        LANE_LOOP(l) s[j0 + l].gs = b.drive1[1][l];
        if (ia != NULL) LANE_LOOP(l) ia[j0 + l] = b.ia[l];
        if (ii != NULL) LANE_LOOP(l) ii[j0 + l] = b.ii[l];
    }
    return m;
}

#if PS_LANES_MODE == 2
__attribute__((target("avx2"))) static long lanes_run_avx2(
    ps_spindle *s, long m, const ps_plan *q, const ps_real *L1, const ps_real *gd1,
    const ps_real *gs1, ps_spindle *backup, ps_real *ia, ps_real *ii)
{
    return lanes_run(s, m, q, L1, gd1, gs1, backup, ia, ii);
}
#endif

/* lanes_run in the best instruction set the CPU has; -1 where the lanes do not pay (SSE2
 * alone: slower than the scalar loop, see above), for the scalar loop to do it all. */
static long lanes_dispatch(ps_spindle *s, long m, const ps_plan *q, const ps_real *L1,
                           const ps_real *gd1, const ps_real *gs1, ps_spindle *backup,
                           ps_real *ia, ps_real *ii)
{
#if PS_LANES_MODE == 2
    if (__builtin_cpu_supports("avx2")) {
        return lanes_run_avx2(s, m, q, L1, gd1, gs1, backup, ia, ii);
    }
    return -1;
#else
    return lanes_run(s, m, q, L1, gd1, gs1, backup, ia, ii);
#endif
}

/* The fewest tail spindles worth a padded block: a block of PS_LANES lanes costs as much as
 * 2.1-2.7 spindles of the scalar loop (8 x 101-109 ns against 328-381 ns per spindle step,
 * the figures above), so a tail of 3 or more is cheaper as one block padded to PS_LANES. */
#ifndef PS_LANES_TAIL_MIN
#define PS_LANES_TAIL_MIN 3
#endif

/* The tail [j, n) (fewer than PS_LANES spindles) as one block of lanes, padded with copies of
 * its last spindle and inputs, in caller-owned scratch on the stack; the tail's spindles
 * saved to backup before they are written. Returns n, or j (the tail untouched, for the
 * scalar loop) if the tail is too short to pay or a lane would fail. On myo-sim's 54-muscle
 * legs the tail is 6 of every 54 spindles: run by the scalar loop it was 110k of the 460k
 * instructions of a wrapped env step's 540 spindle steps (valgrind). */
static long lanes_tail(ps_spindle *s, long n, long j, const ps_plan *q, const ps_real *L1,
                       const ps_real *gd1, const ps_real *gs1, ps_spindle *backup,
                       ps_real *ia, ps_real *ii)
{
    ps_spindle block[PS_LANES], spare[PS_LANES];
    ps_real L[PS_LANES], gd[PS_LANES], gs[PS_LANES], bia[PS_LANES], bii[PS_LANES];
    const long r = n - j;
    long l;
    if (r < PS_LANES_TAIL_MIN) return j;
    for (l = 0; l < PS_LANES; ++l) {
        const long k = j + (l < r ? l : r - 1);
        block[l] = s[k];
        L[l] = L1[k];
        gd[l] = gd1[k];
        gs[l] = gs1[k];
    }
    if (lanes_dispatch(block, PS_LANES, q, L, gd, gs, spare, ia != NULL ? bia : NULL,
                       ii != NULL ? bii : NULL) != PS_LANES) {
        return j;
    }
    for (l = 0; l < r; ++l) {
        backup[j + l] = s[j + l];
        s[j + l] = block[l];
        if (ia != NULL) ia[j + l] = bia[l];
        if (ii != NULL) ii[j + l] = bii[l];
    }
    return n;
}
#endif /* PS_LANES_MODE */

int ps_spindle_batch_step(ps_spindle *s, long n, const ps_plan *q, const ps_real *L1,
                          const ps_real *gd1, const ps_real *gs1, ps_spindle *backup,
                          ps_real *ia, ps_real *ii, long *failed)
{
    long j = 0, k;
    int status;

    if (failed != NULL) *failed = -1;
    if (n < 0) return PS_ERR_ARGUMENT;
    if (n == 0) return PS_OK;
    if (s == NULL || q == NULL || L1 == NULL || gd1 == NULL || gs1 == NULL || backup == NULL) {
        return PS_ERR_NULL;
    }
#ifdef PS_LANES_MODE
    if (q->a_is_03 && !q->explicit_step && q->p_is_2) {
        const long m = n - n % PS_LANES;
        j = lanes_dispatch(s, m, q, L1, gd1, gs1, backup, ia, ii);
        if (j < m) { /* a lane fails (or no lanes): undo, and let the scalar loop do it all */
            for (k = 0; k < j; ++k) s[k] = backup[k];
            j = 0;
        } else if (j < n) {
            j = lanes_tail(s, n, j, q, L1, gd1, gs1, backup, ia, ii);
        }
    }
#endif
    for (; j < n; ++j) {
        backup[j] = s[j];
        status = ps_spindle_step_plan(&s[j], q, L1[j], gd1[j], gs1[j],
                                      ia != NULL ? &ia[j] : NULL, ii != NULL ? &ii[j] : NULL);
        if (status != PS_OK) {
            /* spindle j is untouched by its failed step; put the ones before it back */
            for (k = 0; k < j; ++k) s[k] = backup[k];
            if (failed != NULL) *failed = j;
            return status;
        }
    }
    return PS_OK;
}

/* One foreign call for the sub-steps of a host's env step instead of one per sub-step: on
 * the wrappers' 864 leg spindles the Python around each ps_spindle_batch_step call cost about
 * a third as much as the call itself. */
int ps_spindle_batch_steps(ps_spindle *s, long n, long steps, const ps_plan *q,
                           const ps_real *L1, const ps_real *gd1, const ps_real *gs1,
                           ps_spindle *start, ps_spindle *backup, ps_real *ia, ps_real *ii,
                           long *failed_step, long *failed)
{
    long t, k;
    int status;

    if (failed_step != NULL) *failed_step = -1;
    if (failed != NULL) *failed = -1;
    if (n < 0 || steps < 0) return PS_ERR_ARGUMENT;
    if (n == 0 || steps == 0) return PS_OK;
    if (s == NULL || q == NULL || L1 == NULL || gd1 == NULL || gs1 == NULL || start == NULL
        || backup == NULL) {
        return PS_ERR_NULL;
    }
    for (k = 0; k < n; ++k) start[k] = s[k];
    for (t = 0; t < steps; ++t) {
        const int last = t == steps - 1;
        status = ps_spindle_batch_step(s, n, q, L1 + t * n, gd1 + t * n, gs1 + t * n, backup,
                                       last ? ia : NULL, last ? ii : NULL, failed);
        if (status != PS_OK) {
            for (k = 0; k < n; ++k) s[k] = start[k];
            if (failed_step != NULL) *failed_step = t;
            return status;
        }
    }
    return PS_OK;
}

int ps_spindle_batch_afferents(const ps_spindle *s, long n, const ps_plan *q, ps_real *ia,
                               ps_real *ii)
{
    long j;

    if (n < 0) return PS_ERR_ARGUMENT;
    if (n == 0) return PS_OK;
    if (s == NULL || q == NULL || ia == NULL || ii == NULL) return PS_ERR_NULL;
    for (j = 0; j < n; ++j) plan_afferents(q, s[j].T, s[j].L, &ia[j], &ii[j]);
    return PS_OK;
}

#endif /* PS_NO_BATCH */

/* ---- fixed-point step ------------------------------------------------------------------
 * Q formats and ranges: see proprio.h. The bound analysis of ps_plan_fx_init guarantees that
 * every product and sum below stays within +-2^30 (Q24: +-64) for states and inputs in range;
 * the step checks those ranges first. Right shifts of negative int32 are arithmetic (C99
 * leaves that to the implementation; gcc and clang define it so). */

#define FX_ONE ((int32_t)PS_FX_ONE)
#define FX_LIMIT 64.0 /* every Q24 intermediate, in units of 1 */
#define FX_V_LIMIT 127.0 /* v = y^10, only ever a factor of a product, never a term of a sum */
#define FX_MAX_DG_SHIFT 6
#define FX_RATE_LIMIT 32767.0
/* Newton's stopping rule in y = |z|: the step dy just taken is accepted once |dy| <= y/8 and
 * |dy| y^5 <= PS_FX_TOL_G. Newton's error after a step is about (g''/2g') dy^2 <= 6 dy^2/y
 * (g is a sum of y^3, y^10, y^13 terms), i.e. an error of v = y^10 of about 60 y^8 dy^2:
 * scaling the tolerance on dy by y^5 keeps that error, not the error of y, below ~60 tol^2
 * (5e-6 L0/s at 3e-4) at every speed. (A fixed tolerance in y must be 1e-4 for the moves at
 * 10 L0/s, where |v| reaches 40 L0/s and one LSB of y is 3e-5 L0/s of v, and is then 100x
 * tighter than needed at the speeds of use: 2.2 Newton iterations per fibre and step instead of
 * 1.3.) FX_G_TOL: the residual (Q24 LSB) at which the iteration stops anyway: near v = 0 the
 * residual g is a few LSB, rounding noise, and y cannot be resolved better (v = y^10 is then
 * below 1e-9 L0/s). */
#ifndef PS_FX_TOL_G
#define PS_FX_TOL_G 3e-6
#endif
#define FX_G_TOL 8

/* round(a * b / 2^24) without a 64-bit product (the M0+ multiplies 32x32->32 only):
 * a = ah 2^16 + al, b = bh 2^16 + bl with al, bl unsigned 16-bit, |ah|, |bh| <= 2^15, so each
 * partial product fits in 32 bits. Exact round-half-up: a floor here would bias every product
 * by -1.5 LSB, and the bias accumulates in the state (measured: 5x larger errors at 1 ms than
 * at 5 ms). Two forms with the same result bits:
 * - fx_mul, the step's: a*b = hh 2^32 + mid 2^16 + (ll mod 2^16) with
 *   mid = hl + lh + ll/2^16 in one int32, which needs |ah| + |bh| < 2^15, i.e.
 *   |a| + |b| < 2^31 (128 in Q24). Every product of the step has |a|, |b| <= 80.2 (plan
 *   constants and intermediates <= 64, v and y^10 <= 80.2) and |a b| <= 127 (the bounds of
 *   fx_bounds_ok), so |a| + |b| <= 80.2 + 127 / 80.2 < 82. 17 instructions on the M0+.
 * - fx_mul_wide, any int32 operands (the rates: Q16 gains up to 2^31): m = the low halves of
 *   hl and lh plus ll/2^16 kept apart, 22 instructions.
 * The caller keeps the result within +-2^30 (v: 2^31). PS_FX_INLINE_MUL (gcc/clang):
 * inlined at every use; on the Cortex-M0+ the call, the push and the pop cost ~15 cycles
 * (the system firmware's option; the results are the same bits). */
#if defined(PS_FX_INLINE_MUL) && defined(__GNUC__)
#define FX_MUL_DECL __attribute__((always_inline)) static inline int32_t
#else
#define FX_MUL_DECL static int32_t
#endif
FX_MUL_DECL fx_mul(int32_t a, int32_t b)
{
    const int32_t ah = a >> 16, bh = b >> 16;
    const uint32_t al = (uint32_t)a & 0xFFFFu, bl = (uint32_t)b & 0xFFFFu;
    const int32_t mid = ah * (int32_t)bl + (int32_t)al * bh + (int32_t)((al * bl) >> 16);
    return ah * bh * 256 + ((mid + 128) >> 8);
}

FX_MUL_DECL fx_mul_wide(int32_t a, int32_t b)
{
    int32_t ah = a >> 16, bh = b >> 16;
    uint32_t al = (uint32_t)a & 0xFFFFu, bl = (uint32_t)b & 0xFFFFu;
    int32_t hl = ah * (int32_t)bl;
    int32_t lh = (int32_t)al * bh;
    uint32_t ll = al * bl;
    uint32_t m = ((uint32_t)hl & 0xFFFFu) + ((uint32_t)lh & 0xFFFFu) + (ll >> 16);
    int32_t H = ah * bh + (hl >> 16) + (lh >> 16);
    return H * 256 + (int32_t)((m + 128u) >> 8);
}

/* Straight-line for the reason of copy3 (no memcpy call). */
static void fx_copy3(int32_t dst[PS_NFIBRES], const int32_t src[PS_NFIBRES])
{
    dst[0] = src[0];
    dst[1] = src[1];
    dst[2] = src[2];
}

static int32_t fx_max(int32_t a, int32_t b) { return a < b ? b : a; }

static int32_t fx_min(int32_t a, int32_t b) { return b < a ? b : a; }

static int32_t fx_abs(int32_t a) { return a < 0 ? -a : a; }

/* Index of the highest set bit of x > 0 (binary search; the M0+ has no CLZ). */
static int fx_log2(uint32_t x)
{
    int k = 0;
    if (x >> 16) { x >>= 16; k += 16; }
    if (x >> 8) { x >>= 8; k += 8; }
    if (x >> 4) { x >>= 4; k += 4; }
    if (x >> 2) { x >>= 2; k += 2; }
    if (x >> 1) { k += 1; }
    return k;
}

/* num / den in Q24 for 0 <= num < den < 2^31, to ~3e-5 relative and 2 LSB (the Newton step
 * and the activation targets; a 24-iteration shift-subtract loop cost ~190 instructions on the
 * M0+, which has no divide, this ~50): den normalised to [2^30, 2^31) (num shifted alike), its
 * top 16 bits d give 1/delta, delta = d / 2^16 in [0.5, 1], in Q15 from the linear estimate
 * 48/17 - 32/17 delta (relative error <= 1/17) and two Newton-Raphson refinements
 * r (2 - delta r) (error 1/17^2, then ~1e-5, the rest from the 16-bit d). Every product is
 * unsigned below 2^32 or signed below 2^31: d r < 2^31 (1 + 1/17), halved before the
 * subtraction; r <= 2^16 - 1 for the last product. */
static int32_t fx_quot(uint32_t num, uint32_t den)
{
    const int k = 30 - fx_log2(den);
    const uint32_t dn = den << k, nn = num << k; /* nn < 2^31 */
    const uint32_t d = (dn + (1u << 14)) >> 15;  /* [2^15, 2^16] */
    int32_t r = 92521 - (int32_t)((d * 61681u) >> 16), e;
    e = (1 << 30) - (int32_t)((d * (uint32_t)r) >> 1); /* |e| < 2^30 / 17 */
    r += (r * (e >> 14)) >> 16;
    e = (1 << 30) - (int32_t)((d * (uint32_t)r) >> 1); /* |e| < 2^30 / 280 */
    r += (r * (e >> 8)) >> 22;
    if (r > 65535) r = 65535;
    /* nn r / 2^22 from nn = nh 2^15 + nl (nh < 2^16, nl < 2^15) */
    return (int32_t)((((nn >> 15) * (uint32_t)r) >> 7) + (((nn & 0x7FFFu) * (uint32_t)r) >> 22));
}

/* g^2 / (g^2 + freq^2) in Q24 for a drive g >= 0 and freq > 0, both Q8: both are shifted
 * right (rounded) by the same k until the larger is below 2^15, so that g^2 + freq^2 <= 2^31
 * (any int32 drive; the ratio keeps >= 15 significant bits of the larger one). */
static int32_t fx_target(const ps_plan_fx *q, int i, int32_t drive)
{
    uint32_t g = (uint32_t)drive, F = (uint32_t)q->fibre[i].freq, big = g > F ? g : F, g2;
    int k = 0;
    if (g == 0) return 0;
    while ((big >> k) >= 32768u) ++k;
    if (k > 0) {
        const uint32_t half = 1u << (k - 1);
        g = (g + half) >> k;
        F = (F + half) >> k;
    }
    g2 = g * g;
    return fx_min(fx_quot(g2, g2 + F * F), FX_ONE); /* the quotient's error can reach 1 */
}

static int32_t fx_round(double x) { return (int32_t)(x < 0.0 ? x - 0.5 : x + 0.5); }

/* x in Q24 if |x| <= limit, else PS_ERR_CONFIG. */
static int fx_const(int32_t *out, double x, double limit)
{
    if (!(x >= -limit && x <= limit)) return PS_ERR_CONFIG;
    *out = fx_round(x * (double)PS_FX_ONE);
    return PS_OK;
}

static int fx_gain(int32_t *out, double x)
{
    if (!(x >= -FX_RATE_LIMIT && x <= FX_RATE_LIMIT)) return PS_ERR_CONFIG;
    *out = fx_round(x * (double)PS_FX_RATE_ONE);
    return PS_OK;
}

#define D_(x) ((double)(x))

static double fx_absd(double x) { return x < 0.0 ? -x : x; }

/* The largest of the two damping coefficients x * C (beta0 + beta_drive f), f in [0, 1], of
 * fibre i. */
static double fx_damping_bound(const ps_params *p, int i, double x)
{
    const double beta = fx_absd(D_(p->beta0[i])) + fx_absd(D_(p->beta_drive[i]));
    const double C = fx_absd(D_(p->CL[i])) > fx_absd(D_(p->CS[i])) ? fx_absd(D_(p->CL[i]))
                                                                   : fx_absd(D_(p->CS[i]));
    return fx_absd(x) * C * beta;
}

/* Worst-case magnitudes of the step's intermediates for fibre i over the state and input
 * ranges of proprio.h (|T| <= T_MAX, |z| <= Y_MAX, |v| <= Y_MAX^10, f in [0, 1], L in
 * [0.5, 1.5], |dL| <= 10 h): sums of the magnitudes of their terms, so that every partial
 * sum and every fx_mul result of ps_spindle_step_fx (and of ps_spindle_fx_init) is bounded
 * by one of them. 1 if all are <= FX_LIMIT (2^30 in Q24) and the equilibria are states in
 * range; the rate bounds go to prim_out, sec_out. */
static int fx_bounds_ok(const ps_params *p, int i, double h, double theta, double *prim_out,
                        double *sec_out, int *dg_shift)
{
    const double KSR = D_(p->KSR[i]), inv_KSR = fx_absd(1.0 / KSR), KPR = D_(p->KPR[i]);
    const double k1 = 1.0 + KPR / KSR, T = PS_FX_T_MAX, Y = PS_FX_Y_MAX, Y3 = Y * Y * Y;
    const double V = pow(Y, 10.0), Lmax = PS_LENGTH_MAX_L0, max_dL = PS_MAX_SPEED_L0_S * h;
    const double Gam = fx_absd(D_(p->Gamma_drive[i]));
    const double LSR0_R = fx_absd(D_(p->LSR0[i]) + D_(p->R[i]));
    const double X = fx_absd(D_(p->LSR0[i]) + D_(p->LPR0[i]));
    const double a2 = fx_absd(D_(p->M[i]) / h + theta * theta * h * k1 * KSR);
    const double cv = fx_absd(D_(p->M[i]) / h - theta * k1 * (1.0 - theta) * h * KSR);
    const double kpr_arg = Lmax + X + T * inv_KSR; /* L0 - LSR0 - LPR0 - T0/KSR */
    const double c = fx_damping_bound(p, i, theta), c0 = fx_damping_bound(p, i, 1.0 - theta);
    const double init_sum = Gam + fx_absd(KPR) * (Lmax + X);
    double pr0, p0, D0, rhs, qy, P, Q, WU, g, dg, stretch, L_sec;
    double bound[25];
    int k;
    pr0 = Lmax + LSR0_R + T * inv_KSR;
    p0 = pr0 + (1.0 - theta) * h * V;
    D0 = c0 * Y3 * pr0;
    rhs = cv * V + T + theta * fx_absd(KSR) * max_dL + Gam + fx_absd(KPR) * kpr_arg + D0;
    qy = p0 + theta * h * V;
    P = a2 * V;
    Q = c * Y3 * qy;
    WU = c * Y3 * theta * h * V;
    g = P + Q + rhs;
    /* dg = y g' is computed divided by 2^shift (the Newton step does not change): at small
     * steps M/h makes it the largest intermediate */
    dg = 10.0 * P + 3.0 * Q + 10.0 * WU;
    for (*dg_shift = 0; *dg_shift < FX_MAX_DG_SHIFT && dg > FX_LIMIT; ++*dg_shift) dg *= 0.5;
    stretch = T * inv_KSR + fx_absd(D_(p->LNSR[i]) - D_(p->LSR0[i]));
    L_sec = Lmax + T * inv_KSR + fx_absd(D_(p->LSR0[i]) + D_(p->LNPR[i]));
    bound[0] = pr0; bound[1] = p0; bound[2] = c0; bound[3] = c0 * Y3; bound[4] = D0;
    bound[5] = rhs; bound[6] = c; bound[7] = c * Y3; bound[8] = qy; bound[9] = P;
    bound[10] = Q; bound[11] = WU; bound[12] = g; bound[13] = dg;
    /* T1 = T0 + KSR (dL - (1 - theta) h v0 - theta h v1) */
    bound[14] = T + fx_absd(KSR) * (max_dL + h * V);
    bound[15] = V * (FX_LIMIT / FX_V_LIMIT);
    /* |g| y (the Newton step's numerator): a product, compared and divided only */
    bound[16] = g * Y * (FX_LIMIT / FX_V_LIMIT);
    bound[17] = stretch; bound[18] = L_sec; bound[19] = init_sum; bound[20] = cv * V;
    bound[21] = kpr_arg;
    /* the equilibria must be states in range: |T| = |init_sum / k1| <= T_MAX */
    bound[22] = init_sum / fx_absd(k1) <= T ? 0.0 : FX_LIMIT + 1.0;
    bound[23] = 1.0 / fx_absd(k1);
    bound[24] = max_dL + h * V;
    for (k = 0; k < 25; ++k) {
        if (!(bound[k] <= FX_LIMIT)) return 0;
    }
    *prim_out = fx_absd(D_(p->G_pri[i])) * stretch;
    *sec_out = fx_absd(D_(p->G_sec[i]) * D_(p->X[i]) * D_(p->Lsec[i]) / D_(p->LSR0[i])) * stretch
               + fx_absd(D_(p->G_sec[i]) * (1.0 - D_(p->X[i])) * D_(p->Lsec[i])
                         / D_(p->LPR0[i])) * L_sec;
    return 1;
}

/* The plan's step-wide constants. */
static int fx_plan_scalars(ps_plan_fx *out, const ps_params *p, double h, double theta)
{
    int st = PS_OK;
    st |= fx_const(&out->max_dL, PS_MAX_SPEED_L0_S * h, 1.0);
    st |= fx_const(&out->one_minus_theta, 1.0 - theta, 1.0);
    st |= fx_const(&out->th_h, theta * h, 1.0);
    st |= fx_const(&out->om_h, (1.0 - theta) * h, 1.0);
    st |= fx_const(&out->S, D_(p->S), FX_LIMIT);
    st |= fx_const(&out->y_max, PS_FX_Y_MAX, FX_LIMIT);
    st |= fx_const(&out->v_max, pow(PS_FX_Y_MAX, 10.0), FX_V_LIMIT);
    out->v_max += 16; /* z^10 in Q24 is rounded */
    st |= fx_const(&out->tol, PS_FX_TOL_G, 1.0);
    if (out->tol < 1) out->tol = 1;
    return st;
}

/* Fibre i's activation filter (as plan_activation_coefficients, written as
 * f = tg + c_f0 (f0 - tg0) + c_fa (tg0 - tg), so that held drives cost one product and a
 * fibre without a filter none) and drive scale. */
static int fx_plan_activation(ps_plan_fx *out, int i, const ps_params *p, double h,
                              double theta)
{
    const double rate = p->tau[i] > R_(0) ? h / D_(p->tau[i]) : 0.0;
    const double den = 1.0 + theta * rate, freq = D_(p->freq[i]);
    int st = PS_OK;
    if (p->tau[i] > R_(0)) {
        st |= fx_const(&out->fibre[i].c_f0, (1.0 - (1.0 - theta) * rate) / den, 1.0);
        st |= fx_const(&out->fibre[i].c_fa, 1.0 / den, 1.0);
    }
    if (!(freq * 256.0 <= 2147483000.0)) return PS_ERR_CONFIG;
    out->fibre[i].freq = fx_round(freq * 256.0);
    return st;
}

/* Fibre i's damping coefficients x C (beta0 + beta_drive f) = *b0 + *bd f for C = CL, CS. */
static int fx_plan_damping(int32_t *L_b0, int32_t *L_bd, int32_t *S_b0, int32_t *S_bd,
                           const ps_params *p, int i, double x)
{
    int st = PS_OK;
    st |= fx_const(L_b0, x * D_(p->CL[i]) * D_(p->beta0[i]), FX_LIMIT);
    st |= fx_const(L_bd, x * D_(p->CL[i]) * D_(p->beta_drive[i]), FX_LIMIT);
    st |= fx_const(S_b0, x * D_(p->CS[i]) * D_(p->beta0[i]), FX_LIMIT);
    st |= fx_const(S_bd, x * D_(p->CS[i]) * D_(p->beta_drive[i]), FX_LIMIT);
    return st;
}

/* Fibre i's rate gains (Q16): Ia's potential G_T T - G_0, II's cs_T T + c_sec2 L - s_0
 * (the stretch T/KSR - (LNSR - LSR0) and the secondary length folded into the gains). */
static int fx_plan_rates(ps_plan_fx *out, int i, const ps_params *p)
{
    const double inv_KSR = 1.0 / D_(p->KSR[i]), stretch0 = D_(p->LNSR[i]) - D_(p->LSR0[i]);
    const double c1 = D_(p->G_sec[i]) * D_(p->X[i]) * (D_(p->Lsec[i]) / D_(p->LSR0[i]));
    const double c2 = D_(p->G_sec[i]) * (1.0 - D_(p->X[i])) * (D_(p->Lsec[i]) / D_(p->LPR0[i]));
    int st = PS_OK;
    st |= fx_gain(&out->fibre[i].G_T, D_(p->G_pri[i]) * inv_KSR);
    st |= fx_gain(&out->fibre[i].G_0, D_(p->G_pri[i]) * stretch0);
    st |= fx_gain(&out->fibre[i].cs_T, (c1 - c2) * inv_KSR);
    st |= fx_gain(&out->fibre[i].c_sec2, c2);
    st |= fx_gain(&out->fibre[i].s_0, c1 * stretch0 + c2 * (D_(p->LSR0[i]) + D_(p->LNPR[i])));
    return st;
}

/* Fibre i's constants of the step (Q24): the theta-method's rhs written in the state
 * (cv v0 + k1 T0 + cdL dL - Gamma f_theta - KPR (L1 - LSR0 - LPR0) - the start's damping). */
static int fx_plan_fibre(ps_plan_fx *out, int i, const ps_params *p, double h, double theta)
{
    const double KSR = D_(p->KSR[i]), KPR = D_(p->KPR[i]), k1 = 1.0 + KPR / KSR;
    const double a2 = D_(p->M[i]) / h + theta * theta * h * k1 * KSR;
    int st = PS_OK;
    st |= fx_const(&out->fibre[i].KSR, KSR, FX_LIMIT);
    st |= fx_const(&out->fibre[i].inv_KSR, 1.0 / KSR, FX_LIMIT);
    st |= fx_const(&out->fibre[i].inv_k1, 1.0 / k1, FX_LIMIT);
    st |= fx_const(&out->fibre[i].Gamma_drive, D_(p->Gamma_drive[i]), FX_LIMIT);
    st |= fx_const(&out->fibre[i].KPR, KPR, FX_LIMIT);
    st |= fx_const(&out->fibre[i].LSR0_R, D_(p->LSR0[i]) + D_(p->R[i]), FX_LIMIT);
    st |= fx_const(&out->fibre[i].LSR0_LPR0, D_(p->LSR0[i]) + D_(p->LPR0[i]), FX_LIMIT);
    st |= fx_const(&out->fibre[i].cv, D_(p->M[i]) / h - theta * k1 * (1.0 - theta) * h * KSR,
                   FX_LIMIT);
    st |= fx_const(&out->fibre[i].thKSR, theta * KSR, FX_LIMIT);
    st |= fx_const(&out->fibre[i].c_Av, (1.0 - theta) * h * KSR, FX_LIMIT);
    st |= fx_const(&out->fibre[i].th_h_KSR, theta * h * KSR, FX_LIMIT);
    st |= fx_const(&out->fibre[i].a2, a2, FX_LIMIT);
    st |= fx_const(&out->fibre[i].inv_a2, 1.0 / a2, FX_LIMIT);
    st |= fx_const(&out->fibre[i].r_cap, a2 * pow(PS_FX_Y_MAX, 10.0), FX_LIMIT);
    st |= fx_plan_damping(&out->fibre[i].thCL_b0, &out->fibre[i].thCL_bd, &out->fibre[i].thCS_b0,
                          &out->fibre[i].thCS_bd, p, i, theta);
    st |= fx_plan_damping(&out->fibre[i].omCL_b0, &out->fibre[i].omCL_bd, &out->fibre[i].omCS_b0,
                          &out->fibre[i].omCS_bd, p, i, 1.0 - theta);
    st |= fx_plan_rates(out, i, p);
    return st;
}

/* 1 if the rates fit Q16: the primary and secondary sums of fx_bounds_ok, with
 * Ia = max + S min <= (1 + |S|) max(a_dyn, b_stat). */
static int fx_rates_fit(const double prim[PS_NFIBRES], const double sec[PS_NFIBRES], double S)
{
    const double big = prim[1] + prim[2] > prim[0] ? prim[1] + prim[2] : prim[0];
    return (1.0 + fx_absd(S)) * big <= FX_RATE_LIMIT && sec[1] + sec[2] <= FX_RATE_LIMIT;
}

int ps_plan_fx_init(ps_plan_fx *q, const ps_params *p, ps_real h_in, ps_real theta_in)
{
    ps_plan_fx out;
    const double h = (double)h_in, theta = (double)theta_in;
    double prim[PS_NFIBRES], sec[PS_NFIBRES];
    int i, k, st, shift;
    if (q == NULL || p == NULL) return PS_ERR_NULL;
    if (ps_params_check(p) != PS_OK) return PS_ERR_CONFIG;
    if (!(theta > 0.0 && theta <= 1.0)) return PS_ERR_METHOD;
    if (!(isfinite(h_in) && h > 0.0)) return PS_ERR_STEP;
    if (!all_equal(p->a, R_(0.3)) || !all_equal(p->p, R_(2))) return PS_ERR_CONFIG;
    memset(&out, 0, sizeof out);
    st = fx_plan_scalars(&out, p, h, theta);
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (!fx_bounds_ok(p, i, h, theta, &prim[i], &sec[i], &shift)) return PS_ERR_CONFIG;
        if (shift > out.dg_shift) out.dg_shift = shift;
        st |= fx_plan_activation(&out, i, p, h, theta);
        st |= fx_plan_fibre(&out, i, p, h, theta);
    }
    if (!fx_rates_fit(prim, sec, D_(p->S))) return PS_ERR_CONFIG;
    for (k = 0; k < PS_FX_ROOT_TABLE; ++k) {
        st |= fx_const(&out.root10[k], pow(2.0, (k - 23) / 10.0), FX_LIMIT);
    }
    if (st != PS_OK) return PS_ERR_CONFIG;
    *q = out;
    return PS_OK;
}

static int fx_check_inputs(const ps_plan_fx *q, int32_t L, int32_t gd, int32_t gs)
{
    (void)q;
    if (L < FX_ONE / 2 || L > FX_ONE + FX_ONE / 2) return PS_ERR_LENGTH_RANGE;
    if (gd < 0 || gs < 0) return PS_ERR_NEGATIVE_DRIVE;
    return PS_OK;
}

static int fx_state_ok(const ps_spindle_fx *s, const ps_plan_fx *q);

/* Ia and II (Q16) at tensions T and length L: the potentials are linear in T and L with the
 * plan's folded gains (bag1 has no secondary ending; II sums bag2's and chain's). */
static void fx_afferents(const ps_plan_fx *q, const int32_t T[PS_NFIBRES], int32_t L,
                         int32_t *ia, int32_t *ii)
{
    int32_t primary[PS_NFIBRES], sec[PS_NFIBRES], a_dyn, b_stat;
    int i;
    for (i = 0; i < PS_NFIBRES; ++i) {
        primary[i] = fx_max(fx_mul_wide(T[i], q->fibre[i].G_T) - q->fibre[i].G_0, 0);
        sec[i] = i == 0 ? 0
                        : fx_mul_wide(T[i], q->fibre[i].cs_T) + fx_mul_wide(L, q->fibre[i].c_sec2)
                              - q->fibre[i].s_0;
    }
    a_dyn = primary[0];
    b_stat = primary[1] + primary[2];
    if (ia != NULL) *ia = fx_max(a_dyn, b_stat) + fx_mul_wide(q->S, fx_min(a_dyn, b_stat));
    if (ii != NULL) *ii = fx_max(sec[1], 0) + fx_max(sec[2], 0);
}

void ps_spindle_fx_afferents(const ps_spindle_fx *s, const ps_plan_fx *q, int32_t *ia,
                             int32_t *ii)
{
    if (s == NULL || q == NULL || !fx_state_ok(s, q)) return;
    fx_afferents(q, s->T, s->L, ia, ii);
}

int ps_spindle_fx_init(ps_spindle_fx *s, const ps_plan_fx *q, int32_t L, int32_t gd,
                       int32_t gs)
{
    ps_spindle_fx out;
    int i, status;
    if (s == NULL || q == NULL) return PS_ERR_NULL;
    status = fx_check_inputs(q, L, gd, gs);
    if (status != PS_OK) return status;
    for (i = 0; i < PS_NFIBRES; ++i) {
        const ps_plan_fx_fibre *k = &q->fibre[i];
        const int32_t f = fx_target(q, i, i == 0 ? gd : gs);
        out.target[i] = f;
        out.f[i] = f;
        out.T[i] = fx_mul(fx_mul(k->Gamma_drive, f) + fx_mul(k->KPR, L - k->LSR0_LPR0), k->inv_k1);
        out.v[i] = 0;
        out.z[i] = 0;
    }
    out.L = L;
    out.gd = gd;
    out.gs = gs;
    *s = out;
    return PS_OK;
}

/* A state a step can work on without overflow (the ranges of proprio.h). */
static int fx_state_ok(const ps_spindle_fx *s, const ps_plan_fx *q)
{
    const int32_t t_max = PS_FX_T_MAX * FX_ONE;
    int i;
    if (fx_check_inputs(q, s->L, s->gd, s->gs) != PS_OK) return 0;
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (s->T[i] < -t_max || s->T[i] > t_max || s->z[i] < -q->y_max || s->z[i] > q->y_max) {
            return 0;
        }
        if (s->f[i] < 0 || s->f[i] > FX_ONE || s->target[i] < 0 || s->target[i] > FX_ONE) {
            return 0;
        }
        /* v is z^10 (a few LSB of rounding): its own bound */
        if (s->v[i] < -q->v_max || s->v[i] > q->v_max) return 0;
    }
    return 1;
}

/* y^10 and y^3 (Q24) for 0 <= y <= y_max. */
static int32_t fx_pow10(int32_t y, int32_t *y3)
{
    const int32_t y2 = fx_mul(y, y), y5 = fx_mul(y2, *y3 = fx_mul(y2, y));
    return fx_mul(y5, y5);
}

/* Newton for a = 0.3 in y = |z| (the fixed-point solve_03): g(y) = a2 y^10 + c y^3 qy - |rhs|
 * with qy = p0 + s th_h y^10 (clipped at 0), from y = |z0| (its y^10 = |v0| and y^3 = |y3_0|,
 * if known, from the state and the start's damping: a first iteration without powers), or
 * from an upper bound of the root from (|rhs|/a2)^(1/10) where a2 |v0| > |rhs|. With
 * P = a2 y^10, W = c y^3, U = s th_h y^10 and Q = W qy, g = P + Q - r and
 * y g' = 10 P + 3 Q + 10 W U: nine products an iteration, the relative step t = |g| / (y g')
 * by fx_quot. Stops as PS_FX_TOL_G says; *v_io: v0 in, the new v out. */
static int fx_solve_03(int32_t *z_io, int32_t *v_io, const ps_plan_fx *q, int i, int32_t p0,
                       int32_t rhs, int32_t c, int32_t y3_0)
{
    const ps_plan_fx_fibre *k = &q->fibre[i];
    const int32_t r = fx_abs(rhs), s_th_h = rhs < 0 ? -q->th_h : q->th_h, a2 = k->a2;
    const int sh = (int)q->dg_shift; /* y g' and |g| are divided by 2^sh */
    const int32_t quarter = FX_ONE / 4;
    int32_t y = fx_abs(*z_io), y10 = fx_abs(*v_io), y3 = y3_0 < 0 ? 0 : fx_abs(y3_0), P;
    int it, done = 0;
    if (y3_0 < 0 && y > 0) y10 = fx_pow10(y, &y3);
    P = fx_mul(a2, y10);
    if (P > r) { /* y is above the root's bound (x = r/a2 < y_max^10; + 3: rounding) */
        const int32_t bound = r < k->r_cap
                                  ? q->root10[fx_log2((uint32_t)(fx_mul(r, k->inv_a2) + 3))]
                                  : q->y_max;
        if (y > bound) {
            y = bound > q->y_max ? q->y_max : bound;
            y10 = fx_pow10(y, &y3);
            P = fx_mul(a2, y10);
        }
    }
    for (it = 0; it < PS_NEWTON_MAX_ITER; ++it) {
        const int32_t W = fx_mul(c, y3), U = fx_mul(s_th_h, y10), qy = p0 + U;
        int32_t g = P - r, dg = 10 * (P >> sh), num, t, dy;
        if (qy > 0) { /* else the damping's polar-length factor is clipped at 0 */
            const int32_t Q = fx_mul(W, qy);
            g += Q;
            dg += 3 * (Q >> sh) + 10 * (fx_mul(W, U) >> sh);
        }
        if (fx_abs(g) <= FX_G_TOL) break;
        /* t = dy / y = |g| / (y g'); the residual after the step is about
         * g''/2 dy^2 <= 6 y g' t^2 = 6 |g| t (g''y^2 <= 12 y g': y^3, y^10, y^13 terms) */
        num = fx_abs(g) >> sh;
        if (dg < 1 || num >= dg) { /* dy >= y, or no slope: clamped (at 0 or 1/4) */
            t = FX_ONE;
            dy = quarter;
        } else {
            t = fx_quot((uint32_t)num, (uint32_t)dg);
            dy = fx_min(fx_mul(t, y), quarter);
        }
        done = t <= FX_ONE / 8 && 6 * fx_mul(fx_abs(g), t) <= q->tol;
        y += g < 0 ? dy : -dy;
        if (y < 0) y = 0;
        if (y > q->y_max) y = q->y_max;
        y10 = fx_pow10(y, &y3);
        if (done) break;
        P = fx_mul(a2, y10);
    }
    if (it == PS_NEWTON_MAX_ITER) return PS_ERR_NO_CONVERGENCE;
    if (y == q->y_max) return PS_ERR_NONFINITE; /* the root is outside the Q range */
    *z_io = rhs < 0 ? -y : y;
    *v_io = rhs < 0 ? -y10 : y10;
    return PS_OK;
}

/* The fibres after a fixed-point step, until it commits. */
typedef struct fx_fibres {
    int32_t T[PS_NFIBRES], v[PS_NFIBRES], z[PS_NFIBRES], f[PS_NFIBRES], target[PS_NFIBRES];
} fx_fibres;

/* Fibre i's activation f after the step toward its target tg (the theta-method filter). */
static int32_t fx_activation(const ps_plan_fx_fibre *k, int32_t f0, int32_t tg0, int32_t tg)
{
    int32_t f = tg;
    if (f0 != tg0) f += fx_mul(k->c_f0, f0 - tg0);
    if (tg != tg0) f += fx_mul(k->c_fa, tg0 - tg);
    return fx_min(fx_max(f, 0), FX_ONE);
}

/* The damping at the start of the step, (1 - theta) C beta(f0) z0^3 times the polar length
 * beyond R, pr0 > 0 (the explicit part of the theta-method's damping term); z0^3 to *z03. */
static int32_t fx_start_damping(const ps_plan_fx_fibre *k, int32_t z0, int32_t f0, int32_t pr0,
                                int32_t *z03)
{
    const int32_t cb = z0 > 0 ? k->omCL_b0 + fx_mul(k->omCL_bd, f0)
                              : k->omCS_b0 + fx_mul(k->omCS_bd, f0);
    *z03 = fx_mul(fx_mul(z0, z0), z0);
    return fx_mul(fx_mul(cb, *z03), pr0);
}

/* Fibre i's step by dL from the state's length with its drive drive1 (the equations of
 * plan_fibre for a = 0.3, p = 2, theta in (0, 1]; the rhs with the start's force and
 * A = T0 + KSR dL - (1 - theta) h KSR v0 expanded:
 *   rhs = cv v0 + T0 + theta KSR dL - Gamma f_theta - KPR (L0 - LSR0 - LPR0 - T0/KSR) - D0,
 *   T1 = T0 + KSR (dL - (1 - theta) h v0 - theta h v1));
 * its new T, v, z, f, target go to next. */
static int fx_fibre(const ps_spindle_fx *s, const ps_plan_fx *q, int i, int32_t dL, int32_t drive1,
                    fx_fibres *next)
{
    const ps_plan_fx_fibre *k = &q->fibre[i];
    const int32_t t_max = PS_FX_T_MAX * FX_ONE;
    const int32_t T0 = s->T[i], v0 = s->v[i], z0 = s->z[i], f0 = s->f[i], tg0 = s->target[i];
    const int32_t tg = drive1 == (i == 0 ? s->gd : s->gs) ? tg0 : fx_target(q, i, drive1);
    const int32_t tk0 = fx_mul(T0, k->inv_KSR), ov0 = fx_mul(q->om_h, v0);
    /* the polar length beyond R at the start, and at the end but for the new velocity */
    const int32_t pr0 = s->L - k->LSR0_R - tk0, p0 = pr0 + ov0;
    int32_t f, f_th, rhs, c, T1, z = z0, v = v0, z03 = -1;
    int status;
    f = fx_activation(k, f0, tg0, tg);
    f_th = f == f0 ? f : f + fx_mul(q->one_minus_theta, f0 - f); /* theta f + (1 - theta) f0 */
    rhs = fx_mul(k->cv, v0) + T0 + fx_mul(k->thKSR, dL) - fx_mul(k->Gamma_drive, f_th)
          - fx_mul(k->KPR, s->L - k->LSR0_LPR0 - tk0);
    if (z0 != 0 && pr0 > 0) rhs -= fx_start_damping(k, z0, f0, pr0, &z03);
    c = rhs > 0 ? k->thCL_b0 + fx_mul(k->thCL_bd, f)
                : k->thCS_b0 + fx_mul(k->thCS_bd, f);
    status = fx_solve_03(&z, &v, q, i, p0, rhs, c, z03);
    if (status != PS_OK) return status;
    T1 = T0 + fx_mul(k->KSR, dL) - fx_mul(k->c_Av, v0) - fx_mul(k->th_h_KSR, v);
    if (T1 < -t_max || T1 > t_max) return PS_ERR_NONFINITE;
    next->T[i] = T1;
    next->v[i] = v;
    next->z[i] = z;
    next->f[i] = f;
    next->target[i] = tg;
    return PS_OK;
}

int ps_spindle_step_fx(ps_spindle_fx *s, const ps_plan_fx *q, int32_t L1, int32_t gd1,
                       int32_t gs1, int32_t *ia, int32_t *ii)
{
    fx_fibres next;
    int32_t dL, r_ia, r_ii;
    int i, status;

    if (s == NULL || q == NULL) return PS_ERR_NULL;
    status = fx_check_inputs(q, L1, gd1, gs1);
    if (status != PS_OK) return status;
    if (!fx_state_ok(s, q)) return PS_ERR_NONFINITE;
    dL = L1 - s->L;
    if (fx_abs(dL) > q->max_dL) return PS_ERR_SPEED;
    for (i = 0; i < PS_NFIBRES; ++i) {
        status = fx_fibre(s, q, i, dL, i == 0 ? gd1 : gs1, &next);
        if (status != PS_OK) return status;
    }
    fx_afferents(q, next.T, L1, &r_ia, &r_ii);
    fx_copy3(s->T, next.T);
    fx_copy3(s->v, next.v);
    fx_copy3(s->z, next.z);
    fx_copy3(s->f, next.f);
    fx_copy3(s->target, next.target);
    s->L = L1;
    s->gd = gd1;
    s->gs = gs1;
    if (ia != NULL) *ia = r_ia;
    if (ii != NULL) *ii = r_ii;
    return PS_OK;
}
