/*
 * tendon_organ.c -- the Lin & Crago (2002) Golgi tendon organ (proprio.h section 4).
 *
 * The C twin of spindle/tendon_organ.py: the same plan (a matrix exponential of the
 * augmented 5 x 5 system by the same Taylor scaling and squaring), the same step, the same
 * input rules. The step's small pieces (its own log1p, ln cosh, the line, a row of the
 * transition, the rate) are shared by the scalar step and the batch's SIMD lanes, which run
 * 8 organs at a time bit for bit as the scalar step (4-8x faster than the scalar loop
 * was, see there). A fixed-point
 * form of the step for cores without an FPU follows.
 *
 * No heap, no globals, no input is modified; on failure nothing is written.
 */
#include "proprio.h"

#include <float.h>
#include <math.h>
#include <stddef.h>
#include <string.h>

/* the step's pieces inlined where speed is the aim, the compiler's choice under -Os */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define GTO_INLINE static inline __attribute__((always_inline))
#else
#define GTO_INLINE static
#endif

#ifdef PS_FLOAT
#define ps_fabs fabsf
#else
#define ps_fabs fabs
#endif

#define GTO_TAYLOR_TERMS 20
#define GTO_N 5 /* the augmented system: z (3), the line's value, its change over the step */

static int finite_d(double x) { return x == x && x - x == 0.0; }

/* matrices are flat, row-major: element (i, j) at [i * GTO_N + j] */
#define AT(m, i, j) ((m)[(i) * GTO_N + (j)])

/* out = a b for GTO_N x GTO_N matrices (out must not alias a or b) */
static void matmul5(double *out, const double *a, const double *b)
{
    int i, j, k;
    for (i = 0; i < GTO_N; ++i) {
        for (j = 0; j < GTO_N; ++j) {
            double sum = 0.0;
            for (k = 0; k < GTO_N; ++k) sum += AT(a, i, k) * AT(b, k, j);
            AT(out, i, j) = sum;
        }
    }
}

/* e^M: scaled by 2^-s to 1-norm <= 1/2, Taylor series, s squarings */
static void expm5(double *E, const double *M)
{
    double X[GTO_N * GTO_N], term[GTO_N * GTO_N], tmp[GTO_N * GTO_N];
    double norm = 0.0, scale = 1.0;
    int i, j, k, s = 0;
    for (j = 0; j < GTO_N; ++j) {
        double col = 0.0;
        for (i = 0; i < GTO_N; ++i) col += fabs(AT(M, i, j));
        if (col > norm) norm = col;
    }
    while (norm > 0.5) {
        norm *= 0.5;
        scale *= 2.0;
        ++s;
    }
    for (i = 0; i < GTO_N * GTO_N; ++i) {
        X[i] = M[i] / scale;
        E[i] = term[i] = (i % (GTO_N + 1) == 0) ? 1.0 : 0.0;
    }
    for (k = 1; k <= GTO_TAYLOR_TERMS; ++k) {
        matmul5(tmp, term, X);
        for (i = 0; i < GTO_N * GTO_N; ++i) {
            term[i] = tmp[i] / k;
            E[i] += term[i];
        }
    }
    for (k = 0; k < s; ++k) {
        matmul5(tmp, E, E);
        for (i = 0; i < GTO_N * GTO_N; ++i) E[i] = tmp[i];
    }
}

int ps_gto_plan_init(ps_gto_plan *q, const ps_gto_params *p, ps_real h)
{
    double M[GTO_N * GTO_N] = {0.0}, E[GTO_N * GTO_N];
    double b2, b1, b0, a1, a0, k, hd = (double)h;
    int i, j;
    if (q == NULL || p == NULL) return PS_ERR_NULL;
    b2 = p->num[0]; b1 = p->num[1]; b0 = p->num[2]; a1 = p->den[0]; a0 = p->den[1];
    if (!(finite_d(p->gain_pps) && finite_d(p->tau_lowpass_s) && finite_d(b2)
          && finite_d(b1) && finite_d(b0) && finite_d(a1) && finite_d(a0))
        || !(p->gain_pps > 0 && p->tau_lowpass_s > 0 && a1 > 0 && a0 > 0 && b0 > 0))
        return PS_ERR_CONFIG;
    if (!(finite_d(hd) && hd > 0.0 && hd <= PS_GTO_MAX_STEP_S)) return PS_ERR_STEP;
    k = 1.0 / (double)p->tau_lowpass_s;
    /* rows of A h, the column B h, and the line's change: dz/ds = h (A z + B u), du/ds = v */
    AT(M, 0, 0) = -k * hd;
    AT(M, 1, 2) = hd;
    AT(M, 2, 0) = hd; AT(M, 2, 1) = -a0 * hd; AT(M, 2, 2) = -a1 * hd;
    AT(M, 0, 3) = k * hd;
    AT(M, 3, 4) = 1.0;
    expm5(E, M);
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) q->phi[i][j] = (ps_real)AT(E, i, j);
        q->g0[i] = (ps_real)AT(E, i, 3);
        q->g1[i] = (ps_real)AT(E, i, 4);
    }
    q->c[0] = (ps_real)b2;
    q->c[1] = (ps_real)(b0 - b2 * a0);
    q->c[2] = (ps_real)(b1 - b2 * a1);
    q->gain_pps = p->gain_pps;
    q->inv_a0 = (ps_real)(1.0 / a0);
    q->h = h;
    return PS_OK;
}

/* The checks every entry makes on one force and its scale (negative forces are 0). */
GTO_INLINE int check_force(ps_real force_N, ps_real force_scale_N)
{
    if (!finite_d((double)force_N)) return PS_ERR_NONFINITE;
    if (force_N > (ps_real)PS_GTO_MAX_FORCE_N) return PS_ERR_FORCE_RANGE;
    if (!(finite_d((double)force_scale_N) && force_scale_N >= (ps_real)PS_GTO_MIN_FORCE_SCALE_N))
        return PS_ERR_CONFIG;
    return PS_OK;
}

GTO_INLINE ps_real rectified(ps_real force_N) { return force_N > 0 ? force_N : (ps_real)0; }

#ifdef PS_FLOAT
GTO_INLINE ps_real gto_log1p(ps_real x) { return log1pf(x); }
#else
#define GTO_SQRT_HALF_BITS 0x3fe6a09e667f3bcdULL /* sqrt(1/2), rounded */
/* ln 2 to 42 bits (k GTO_LN2_HI is exact) and the rest; Q(w) = 2 (atanh(s)/s - 1) / w,
 * s^2 = w, by its interpolant at the Chebyshev points of [0, 0.0294] (w's range), largest
 * error 4.7e-18 of ln m (0.04 ulp): all from python scripts/fit_log1p.py */
#define GTO_LN2_HI 0x1.62e42fefa3800p-1
#define GTO_LN2_LO 0x1.ef35793c76730p-45
#define GTO_LOG_Q0 0x1.5555555555558p-1
#define GTO_LOG_Q1 0x1.99999999952e2p-2
#define GTO_LOG_Q2 0x1.2492492df148dp-2
#define GTO_LOG_Q3 0x1.c71c62e5800a1p-3
#define GTO_LOG_Q4 0x1.7462b4ab2ef6bp-3
#define GTO_LOG_Q5 0x1.39fe606542ddep-3
#define GTO_LOG_Q6 0x1.2b584aae78a57p-3

/* ln(1 + x) for x >= 0 (+inf: +inf), the double build's own: inline, so that the batch's
 * lanes become SIMD (libm's log1p is a call per element). 1 + x = u + e with u = fl(1 + x)
 * and e = x - (u - 1), exact for u < 2^53 (u - 1 is, and e is the representable error of
 * the sum; above, e/u is under 2^-52 against a result over 36); u = 2^k m with m in
 * [sqrt(1/2), sqrt 2) from u's bits (k converted to double through the bits of
 * 2^52 + k + 1023: SIMD has no int64 to double); ln(1 + x) = k ln 2 + ln m + e/u with
 * ln m = f - f^2/2 + s (f^2/2 + w Q(w)), f = m - 1, s = f / (2 + f), w = s^2 (2 atanh s =
 * ln m). Measured against long-double log1pl on 0 .. 1e308 (tests/test_c_tendon_organ.py):
 * max 0.749 ulp (mean 0.176), libm's log1p 0.566 (0.173) on the same points. */
GTO_INLINE double gto_log1p(double x)
{
    const double u = 1.0 + x;
    const double e = x - (u - 1.0);
    uint64_t bits, top, m_bits;
    double k, m, f, s, w, R, hfsq, out;
    memcpy(&bits, &u, sizeof bits);
    top = bits + (0x3ff0000000000000ULL - GTO_SQRT_HALF_BITS);
    m_bits = (top & 0x000fffffffffffffULL) + GTO_SQRT_HALF_BITS;
    top = (top >> 52) | 0x4330000000000000ULL;
    memcpy(&k, &top, sizeof k);
    memcpy(&m, &m_bits, sizeof m);
    k -= 0x1p52 + 1023.0;
    f = m - 1.0;
    s = f / (2.0 + f);
    w = s * s;
    R = w * (GTO_LOG_Q0 + w * (GTO_LOG_Q1 + w * (GTO_LOG_Q2 + w * (GTO_LOG_Q3 + w * (GTO_LOG_Q4
        + w * (GTO_LOG_Q5 + w * GTO_LOG_Q6))))));
    hfsq = 0.5 * f * f;
    out = k * GTO_LN2_HI + (f - (hfsq - (s * (hfsq + R) + (k * GTO_LN2_LO + e / u))));
    return u < HUGE_VAL ? out : u;
}
#endif

ps_real ps_gto_log1p(ps_real x) { return gto_log1p(x); }

GTO_INLINE ps_real log_stage(const ps_gto_plan *q, ps_real force_N, ps_real force_scale_N)
{
    return q->gain_pps * gto_log1p(force_N / force_scale_N);
}

int ps_gto_init(ps_gto *s, const ps_gto_plan *q, ps_real force_N, ps_real force_scale_N)
{
    int code;
    ps_real f, r;
    if (s == NULL || q == NULL) return PS_ERR_NULL;
    code = check_force(force_N, force_scale_N);
    if (code != PS_OK) return code;
    f = rectified(force_N);
    r = log_stage(q, f, force_scale_N);
    s->z[0] = r;
    s->z[1] = r * q->inv_a0;
    s->z[2] = 0;
    s->force_N = f;
    s->r_pps = r;
    return PS_OK;
}

/* Ib (pps) of z: max(0, c z) */
GTO_INLINE ps_real rate_of(const ps_gto_plan *q, ps_real z0, ps_real z1, ps_real z2)
{
    const ps_real y = q->c[0] * z0 + q->c[1] * z1 + q->c[2] * z2;
    return y > 0 ? y : (ps_real)0;
}

ps_real ps_gto_rate(const ps_gto *s, const ps_gto_plan *q)
{
    if (s == NULL || q == NULL) return 0;
    return rate_of(q, s->z[0], s->z[1], s->z[2]);
}

/* ln cosh d: three terms of the series below |d| = 0.03 (spindle.tendon_organ.SERIES_D),
 * else |d| + ln(1 + e^{-2|d|}) - ln 2 */
GTO_INLINE int ln_cosh_series_holds(ps_real d) { return ps_fabs(d) < (ps_real)0.03; }

GTO_INLINE ps_real ln_cosh_series(ps_real d)
{
    const ps_real d2 = d * d;
    return d2 * ((ps_real)0.5 - d2 * ((ps_real)(1.0 / 12.0) - d2 * (ps_real)(1.0 / 45.0)));
}

GTO_INLINE ps_real gto_ln_cosh(ps_real d)
{
    const ps_real a = ps_fabs(d);
    if (ln_cosh_series_holds(d)) return ln_cosh_series(d);
#ifdef PS_FLOAT
    return a + gto_log1p(expf(-2.0f * a)) - logf(2.0f);
#else
    return a + gto_log1p(exp(-2.0 * a)) - log(2.0);
#endif
}

/* d = (r1 - r0) / (2 G1), the argument of ln cosh */
GTO_INLINE ps_real half_log_ratio(const ps_gto_plan *q, ps_real r0, ps_real r1)
{
    return (r1 - r0) * ((ps_real)0.5 / q->gain_pps);
}

/* alpha = r0 + (2 G1 / 3) ln cosh d, the line's value at the step's start */
GTO_INLINE ps_real line_start(const ps_gto_plan *q, ps_real r0, ps_real ln_cosh_d)
{
    return r0 + (ps_real)2 * q->gain_pps / (ps_real)3 * ln_cosh_d;
}

/* row i of z1 = phi z0 + g0 alpha + g1 beta */
GTO_INLINE ps_real advanced_z(const ps_gto_plan *q, int i, ps_real z0, ps_real z1, ps_real z2,
                              ps_real alpha, ps_real beta)
{
    ps_real z = q->phi[i][0] * z0 + q->phi[i][1] * z1 + q->phi[i][2] * z2;
    z += q->g0[i] * alpha;
    z += q->g1[i] * beta;
    return z;
}

/* the step on checked inputs */
GTO_INLINE void gto_advance(ps_gto *s, const ps_gto_plan *q, ps_real force_N, ps_real scale)
{
    const ps_real f1 = rectified(force_N);
    const ps_real r0 = s->r_pps, r1 = log_stage(q, f1, scale);
    const ps_real alpha = line_start(q, r0, gto_ln_cosh(half_log_ratio(q, r0, r1)));
    const ps_real beta = r1 - r0;
    const ps_real z0 = advanced_z(q, 0, s->z[0], s->z[1], s->z[2], alpha, beta);
    const ps_real z1 = advanced_z(q, 1, s->z[0], s->z[1], s->z[2], alpha, beta);
    const ps_real z2 = advanced_z(q, 2, s->z[0], s->z[1], s->z[2], alpha, beta);
    s->z[0] = z0;
    s->z[1] = z1;
    s->z[2] = z2;
    s->force_N = f1;
    s->r_pps = r1;
}

int ps_gto_step(ps_gto *s, const ps_gto_plan *q, ps_real force_N, ps_real force_scale_N,
                ps_real *ib)
{
    int code;
    if (s == NULL || q == NULL) return PS_ERR_NULL;
    code = check_force(force_N, force_scale_N);
    if (code != PS_OK) return code;
    gto_advance(s, q, force_N, force_scale_N);
    if (ib != NULL) *ib = ps_gto_rate(s, q);
    return PS_OK;
}

/* ---- the batch --------------------------------------------------------------------------
 * Organs [j0, n) through every step, one at a time (the tail of the lanes, or the whole batch
 * where there are none). */
static void scalar_run(ps_gto *s, long j0, long n, const ps_gto_plan *q, long steps,
                       const ps_real *force_N, const ps_real *force_scale_N, ps_real *ib)
{
    long i, k;
    for (i = j0; i < n; ++i) {
        for (k = 0; k < steps; ++k) {
            gto_advance(&s[i], q, force_N[k * n + i], force_scale_N[i]);
            if (ib != NULL) ib[k * n + i] = ps_gto_rate(&s[i], q);
        }
    }
}

#ifdef PS_FLOAT
#define GTO_REAL_MAX FLT_MAX
#else
#define GTO_REAL_MAX DBL_MAX
#endif

GTO_INLINE int force_in_range(ps_real f)
{
    return (f >= -GTO_REAL_MAX) & (f <= (ps_real)PS_GTO_MAX_FORCE_N);
}

/* 1 if every force and scale passes check_force: the same comparisons in one pass with no
 * exit inside, which the compiler vectorises with AVX2 (not with SSE2 alone: no vector type
 * for the comparisons' flags, gcc 12) */
GTO_INLINE int inputs_ok(long n, long steps, const ps_real *force_N,
                         const ps_real *force_scale_N)
{
    const long total = n * steps;
    long long bad = 0;
    long i;
    int l;
    for (i = 0; i < n; ++i)
        bad |= !((force_scale_N[i] >= (ps_real)PS_GTO_MIN_FORCE_SCALE_N)
                 & (force_scale_N[i] <= GTO_REAL_MAX));
    for (i = 0; i + 8 <= total; i += 8) { /* in blocks of a known length, for the vectoriser */
        for (l = 0; l < 8; ++l) bad |= !force_in_range(force_N[i + l]);
    }
    for (; i < total; ++i) bad |= !force_in_range(force_N[i]);
    return !bad;
}

/* The batch in lanes: a second form of the scalar loop, kept because it pays. ns per organ
 * and step of ps_gto_batch_run, n = 4096, 49 steps, x86-64 AMD EPYC, gcc 12 -O2, the shared
 * 2-core machine busy (PYTHONPATH=. python scripts/bench_gto.py, builds side by side): the
 * scalar loop with libm's log1p (before) 18-28, with this file's log1p 25-43 (libm's is
 * faster one at a time, but a call per element cannot be SIMD); these lanes in SSE2 8.9-17,
 * AVX2 5.3-8.1, AVX-512 3.6-6.0, against the spindle's batch step at 54-93. Timed alone
 * from C with the data in cache: 18.7-19.1, 22, 8.0-8.9, 3.7-4.1, 2.0-2.6. GTO_LANES organs
 * per block, their state in lanes from the first step to the last; within a block the log
 * stages of GTO_CHUNK steps are taken first, then their lines (ln cosh, alpha, beta), then
 * the recurrence step by step (the logs and lines do not depend on the state: independent
 * work for the SIMD units, 1.7x over one whole step at a time). Each line is a loop over
 * the lanes that the compiler turns into SIMD (copies for AVX-512 and AVX2 chosen at run
 * time with __builtin_cpu_supports: the cached library must load on any x86-64, so no
 * -march); the same IEEE operations in the same order as the scalar step (no contraction:
 * -ffp-contract=off, and neither target enables FMA), ln cosh off its series (a jump)
 * redone lane by lane by the scalar function. Nothing in the lanes can fail: every input is
 * checked before (batch_inputs_ok). 4 and 16 lanes, chunks of 8 and 32 gave the same within
 * the noise. The tail (n mod GTO_LANES) is the scalar loop's. */
/* Builds: -DPS_GTO_BATCH_SCALAR no lanes, -DPS_GTO_LANES_NO_AVX2 the baseline lanes only,
 * -DPS_GTO_LANES_NO_AVX512 no AVX-512 copy. The float build has none (log1pf: no SIMD), nor
 * do -Os builds (the embedded ones: no vectoriser, and a block takes 3.5 kB of stack). */
#if !defined(PS_FLOAT) && !defined(PS_GTO_BATCH_SCALAR) && !defined(__OPTIMIZE_SIZE__)
#if defined(__GNUC__) && defined(__x86_64__) && (!defined(__clang__) || __clang_major__ >= 6) \
    && !defined(PS_GTO_LANES_NO_AVX2)
#define GTO_LANES_MODE 2 /* copies for AVX-512 and AVX2 chosen at run time, else the baseline */
#else
#define GTO_LANES_MODE 1 /* the lanes in the baseline instruction set */
#endif
#endif

#if defined(__GNUC__)
#define GTO_LANE_FN static inline __attribute__((always_inline))
#else
#define GTO_LANE_FN static
#endif

#ifdef GTO_LANES_MODE
#ifndef GTO_LANES
#define GTO_LANES 8
#endif
#define GTO_LANE_LOOP(l) for ((l) = 0; (l) < GTO_LANES; ++(l))

typedef long long gto_lane_flag; /* as wide as a double: a select on it stays in one vector */

#ifndef GTO_CHUNK
#define GTO_CHUNK 16
#endif

typedef struct gto_lanes {
    double z0[GTO_LANES], z1[GTO_LANES], z2[GTO_LANES], force[GTO_LANES], scale[GTO_LANES];
    double r[GTO_CHUNK + 1][GTO_LANES]; /* r[0] at the chunk's start, r[k + 1] after step k */
    double alpha[GTO_CHUNK][GTO_LANES], beta[GTO_CHUNK][GTO_LANES]; /* step k's line */
    gto_lane_flag jump[GTO_LANES];
} gto_lanes;

/* The log stages of the chunk's `steps` steps (forces f, rows n apart). */
GTO_LANE_FN void lanes_logs(gto_lanes *b, const ps_gto_plan *q, const double *f, long n,
                            int steps)
{
    int k, l;
    for (k = 0; k < steps; ++k)
        GTO_LANE_LOOP(l) b->r[k + 1][l] = log_stage(q, rectified(f[k * n + l]), b->scale[l]);
    GTO_LANE_LOOP(l) b->force[l] = rectified(f[(steps - 1) * n + l]);
}

/* The lines (alpha, beta) of the chunk's steps from their logs. */
GTO_LANE_FN void lanes_lines(gto_lanes *b, const ps_gto_plan *q, int steps)
{
    gto_lane_flag any_jump = 0;
    int k, l;
    GTO_LANE_LOOP(l) b->jump[l] = 0;
    for (k = 0; k < steps; ++k) {
        GTO_LANE_LOOP(l) {
            const double d = half_log_ratio(q, b->r[k][l], b->r[k + 1][l]);
            b->alpha[k][l] = ln_cosh_series(d);
            b->jump[l] |= !ln_cosh_series_holds(d);
            b->beta[k][l] = b->r[k + 1][l] - b->r[k][l];
        }
    }
    GTO_LANE_LOOP(l) any_jump |= b->jump[l];
    if (any_jump) {
        for (k = 0; k < steps; ++k)
            GTO_LANE_LOOP(l) b->alpha[k][l] = gto_ln_cosh(half_log_ratio(q, b->r[k][l],
                                                                         b->r[k + 1][l]));
    }
    for (k = 0; k < steps; ++k)
        GTO_LANE_LOOP(l) b->alpha[k][l] = line_start(q, b->r[k][l], b->alpha[k][l]);
}

/* Step k of the chunk, Ib to ib if not NULL. */
GTO_LANE_FN void lanes_advance(gto_lanes *b, const ps_gto_plan *q, int k, double *ib)
{
    int l;
    GTO_LANE_LOOP(l) {
        const double alpha = b->alpha[k][l], beta = b->beta[k][l];
        const double z0 = advanced_z(q, 0, b->z0[l], b->z1[l], b->z2[l], alpha, beta);
        const double z1 = advanced_z(q, 1, b->z0[l], b->z1[l], b->z2[l], alpha, beta);
        const double z2 = advanced_z(q, 2, b->z0[l], b->z1[l], b->z2[l], alpha, beta);
        b->z0[l] = z0;
        b->z1[l] = z1;
        b->z2[l] = z2;
    }
    if (ib != NULL) GTO_LANE_LOOP(l) ib[l] = rate_of(q, b->z0[l], b->z1[l], b->z2[l]);
}

/* Organs [0, m) (m a multiple of GTO_LANES) through every step, GTO_LANES at a time, each
 * block's state in lanes from the first step to the last. */
GTO_LANE_FN void lanes_run(
    ps_gto *s, long m, long n, const ps_gto_plan *q, long steps, const double *force_N,
    const double *force_scale_N, double *ib)
{
    const ps_gto_plan p = *q; /* no store to ib can alias this copy: its loads leave loops */
    gto_lanes b;
    long j0, k0;
    int k, l;
    for (j0 = 0; j0 < m; j0 += GTO_LANES) {
        ps_gto *sb = &s[j0];
        GTO_LANE_LOOP(l) b.z0[l] = sb[l].z[0];
        GTO_LANE_LOOP(l) b.z1[l] = sb[l].z[1];
        GTO_LANE_LOOP(l) b.z2[l] = sb[l].z[2];
        GTO_LANE_LOOP(l) b.r[0][l] = sb[l].r_pps;
        GTO_LANE_LOOP(l) b.scale[l] = force_scale_N[j0 + l];
        for (k0 = 0; k0 < steps; k0 += GTO_CHUNK) {
            const int chunk = steps - k0 < GTO_CHUNK ? (int)(steps - k0) : GTO_CHUNK;
            lanes_logs(&b, &p, force_N + k0 * n + j0, n, chunk);
            lanes_lines(&b, &p, chunk);
            for (k = 0; k < chunk; ++k)
                lanes_advance(&b, &p, k, ib != NULL ? ib + (k0 + k) * n + j0 : NULL);
            GTO_LANE_LOOP(l) b.r[0][l] = b.r[chunk][l];
        }
        GTO_LANE_LOOP(l) {
            sb[l].z[0] = b.z0[l];
            sb[l].z[1] = b.z1[l];
            sb[l].z[2] = b.z2[l];
            sb[l].force_N = b.force[l];
            sb[l].r_pps = b.r[0][l];
        }
    }
}

#if GTO_LANES_MODE == 2
#ifndef PS_GTO_LANES_NO_AVX512
__attribute__((target("avx512f"))) static void lanes_run_avx512(
    ps_gto *s, long m, long n, const ps_gto_plan *q, long steps, const double *force_N,
    const double *force_scale_N, double *ib)
{
    lanes_run(s, m, n, q, steps, force_N, force_scale_N, ib);
}
#endif

__attribute__((target("avx2"))) static void lanes_run_avx2(
    ps_gto *s, long m, long n, const ps_gto_plan *q, long steps, const double *force_N,
    const double *force_scale_N, double *ib)
{
    lanes_run(s, m, n, q, steps, force_N, force_scale_N, ib);
}

__attribute__((target("avx2"))) static int inputs_ok_avx2(long n, long steps,
                                                          const double *force_N,
                                                          const double *force_scale_N)
{
    return inputs_ok(n, steps, force_N, force_scale_N);
}
#endif

/* lanes_run in the best instruction set the CPU has, on organs [0, n - n mod GTO_LANES);
 * returns that count */
static long lanes_dispatch(ps_gto *s, long n, const ps_gto_plan *q, long steps,
                           const double *force_N, const double *force_scale_N, double *ib)
{
    const long m = n - n % GTO_LANES;
#if GTO_LANES_MODE == 2
#ifndef PS_GTO_LANES_NO_AVX512
    if (__builtin_cpu_supports("avx512f")) {
        lanes_run_avx512(s, m, n, q, steps, force_N, force_scale_N, ib);
        return m;
    }
#endif
    if (__builtin_cpu_supports("avx2")) {
        lanes_run_avx2(s, m, n, q, steps, force_N, force_scale_N, ib);
        return m;
    }
#endif
    lanes_run(s, m, n, q, steps, force_N, force_scale_N, ib);
    return m;
}
#endif /* GTO_LANES_MODE */

/* inputs_ok in the best instruction set the CPU has */
static int batch_inputs_ok(long n, long steps, const ps_real *force_N,
                           const ps_real *force_scale_N)
{
#if defined(GTO_LANES_MODE) && GTO_LANES_MODE == 2
    if (__builtin_cpu_supports("avx2")) return inputs_ok_avx2(n, steps, force_N, force_scale_N);
#endif
    return inputs_ok(n, steps, force_N, force_scale_N);
}

int ps_gto_batch_run(ps_gto *s, long n, const ps_gto_plan *q, long steps,
                     const ps_real *force_N, const ps_real *force_scale_N, ps_real *ib,
                     long *failed)
{
    long i, k, j = 0;
    if (n < 0 || steps < 0) return PS_ERR_ARGUMENT;
    if (n == 0 || steps == 0) return PS_OK;
    if (s == NULL || q == NULL || force_N == NULL || force_scale_N == NULL) return PS_ERR_NULL;
    if (!batch_inputs_ok(n, steps, force_N, force_scale_N)) {
        for (k = 0; k < steps; ++k) { /* the first bad input in the order of the steps */
            for (i = 0; i < n; ++i) {
                int code = check_force(force_N[k * n + i], force_scale_N[i]);
                if (code != PS_OK) {
                    if (failed != NULL) *failed = k * n + i;
                    return code;
                }
            }
        }
    }
#ifdef GTO_LANES_MODE
    j = lanes_dispatch(s, n, q, steps, force_N, force_scale_N, ib);
#endif
    scalar_run(s, j, n, q, steps, force_N, force_scale_N, ib);
    return PS_OK;
}

/* ---- fixed point ---------------------------------------------------------------------- */

#define FX_Q30 1073741824.0
#define FX_INT32_LIMIT 2147483647.0
#define FX_LN2_Q30 744261118 /* ln 2 in Q30 */
#define FX_THIRD_Q30 357913941 /* 1/3 in Q30 */
#define FX_LOG_BITS 24

/* Exact 64-bit sums of 32 x 32 products as (hi 2^32 + lo), each product from 16-bit halves
 * (ps_fx_mul_wide): the compiler's 64 x 64 helper and int64 additions took ~45 instructions
 * and a call per product on the Cortex-M0+ (the results are the same bits). PS_FX_INLINE_MUL
 * (gcc/clang, the system firmware's option, as for spindle.c's fx_mul): inlined at every
 * use. */
#if defined(PS_FX_INLINE_MUL) && defined(__GNUC__)
#define FX_WIDE_INLINE __attribute__((always_inline)) static inline
#else
#define FX_WIDE_INLINE GTO_INLINE
#endif
typedef ps_fx_wide fx_wide;

/* acc += a b */
FX_WIDE_INLINE void fx_mac(fx_wide *acc, int32_t a, int32_t b)
{
    ps_fx_wide p = ps_fx_mul_wide(a, b);
    acc->lo += p.lo;
    acc->hi += p.hi + (acc->lo < p.lo ? 1 : 0);
}

/* round(acc / 2^shift) (half up) for 0 < shift < 32 and a result within int32 */
FX_WIDE_INLINE int32_t fx_round(fx_wide acc, int shift)
{
    uint32_t lo = acc.lo + (1u << (shift - 1));
    int32_t hi = acc.hi + (lo < acc.lo ? 1 : 0);
    return (int32_t)(((uint32_t)hi << (32 - shift)) | (lo >> shift));
}

/* round(a b / 2^30) */
FX_WIDE_INLINE int32_t mul_q30(int32_t a, int32_t b)
{
    fx_wide acc = {0, 0};
    fx_mac(&acc, a, b);
    return fx_round(acc, 30);
}

static int to_q30(double x, int32_t *out)
{
    double v = x * FX_Q30;
    if (!(finite_d(v) && fabs(v) < FX_INT32_LIMIT)) return 0;
    *out = (int32_t)(v < 0 ? v - 0.5 : v + 0.5);
    return 1;
}

int ps_gto_plan_fx_init(ps_gto_plan_fx *qf, const ps_gto_plan *q)
{
    ps_gto_plan_fx out;
    double a0, disc, r_max, line, w1, w2, y;
    int i, j, ok = 1;
    if (qf == NULL || q == NULL) return PS_ERR_NULL;
    a0 = 1.0 / (double)q->inv_a0;
    /* the poles p1, p2 of H from phi's w block (eigenvalues e^{p1 h}, e^{p2 h}: its trace
     * and determinant), for the bound on w2 */
    {
        double tr = (double)q->phi[1][1] + (double)q->phi[2][2];
        double det = (double)q->phi[1][1] * (double)q->phi[2][2]
                     - (double)q->phi[1][2] * (double)q->phi[2][1];
        double h = (double)q->h, m1, m2;
        disc = tr * tr - 4.0 * det;
        if (!(disc > 0.0 && det > 0.0)) return PS_ERR_CONFIG; /* the bound needs real poles */
        m1 = 0.5 * (tr + sqrt(disc));
        m2 = 0.5 * (tr - sqrt(disc));
        if (!(m1 > 0.0 && m2 > 0.0)) return PS_ERR_CONFIG;
        disc = fabs(log(m1) - log(m2)) / h; /* |p1 - p2| */
    }
    r_max = (double)q->gain_pps * log((double)PS_GTO_FX_MAX_RATIO + 1.0);
    line = 4.0 / 3.0 * r_max;
    w1 = line / a0;
    w2 = 2.0 * line / disc;
    y = fabs((double)q->c[0]) * line + fabs((double)q->c[1]) * w1
        + fabs((double)q->c[2]) * w2;
    if (!(y < 32767.0 && w1 < 32767.0 && w2 < 32767.0 && line < 32767.0))
        return PS_ERR_CONFIG;
    for (i = 0; i < 3; ++i) {
        for (j = 0; j < 3; ++j) ok &= to_q30((double)q->phi[i][j], &out.phi[i][j]);
        ok &= to_q30((double)q->g0[i], &out.g0[i]);
        ok &= to_q30((double)q->g1[i], &out.g1[i]);
        ok &= to_q30((double)q->c[i], &out.c[i]);
    }
    ok &= to_q30((double)q->inv_a0 / 64.0, &out.inv_a0); /* Q24 */
    out.gain = (int32_t)((double)q->gain_pps * PS_GTO_FX_RATE_ONE + 0.5);
    if (!ok) return PS_ERR_CONFIG;
    *qf = out;
    return PS_OK;
}

/* ln(1 + x) in Q24 for x = F / G2 in Q16, 0 <= x <= PS_GTO_FX_MAX_RATIO: u = 1 + x =
 * 2^k m with m in [1, 2) from the top bit, m = t (1 + d) with t = 1 + i/64 the table point
 * below m and 0 <= d < 1/64, ln u = k ln 2 + ln t + d - d^2/2 + d^3/3 (the first term left
 * out, d^4/4 < 2^-26, is below a quarter of the result's last bit). Four products where
 * 24 squarings of the mantissa took 24 long multiplies. */
#define FX_LN_TABLE_BITS 6
static const int32_t fx_ln_point_q30[1 << FX_LN_TABLE_BITS] = { /* ln(1 + i/64), Q30 */
    0, 16647494, 33040817, 49187615, 65095192, 80770534, 96220323, 111450959, 126468572,
    141279038, 155887996, 170300854, 184522808, 198558849, 212413774, 226092199, 239598564,
    252937143, 266112055, 279127266, 291986604, 304693756, 317252283, 329665621, 341937090,
    354069895, 366067135, 377931807, 389666807, 401274940, 412758919, 424121372, 435364845,
    446491803, 457504636, 468405662, 479197128, 489881214, 500460037, 510935650, 521310048,
    531585167, 541762891, 551845048, 561833416, 571729724, 581535654, 591252841, 600882877,
    610427311, 619887653, 629265371, 638561895, 647778619, 656916903, 665978069, 674963409,
    683874180, 692711611, 701476899, 710171213, 718795691, 727351448, 735839570};
static const int32_t fx_inv_point_q30[1 << FX_LN_TABLE_BITS] = { /* 1 / (1 + i/64), Q30 */
    1073741824, 1057222719, 1041204193, 1025663832, 1010580540, 995934445, 981706811,
    967879954, 954437177, 941362695, 928641578, 916259690, 904203641, 892460737, 881018933,
    869866794, 858993459, 848388602, 838042399, 827945503, 818089009, 808464432, 799063683,
    789879043, 780903145, 772128952, 763549742, 755159085, 746950834, 738919105, 731058263,
    723362913, 715827883, 708448214, 701219150, 694136129, 687194767, 680390859, 673720360,
    667179386, 660764199, 654471207, 648296950, 642238100, 636291451, 630453915, 624722516,
    619094385, 613566757, 608136962, 602802428, 597560667, 592409282, 587345955, 582368447,
    577474594, 572662306, 567929560, 563274399, 558694933, 554189329, 549755814, 545392673,
    541098242};
static int32_t ln1p_q24(uint32_t x_q16)
{
    uint32_t u = x_q16 + 65536u; /* 1 + x in Q16, in [1, 32768] */
    int32_t k = 0, i, m, d, d2, ln;
    while (k < 15 && (u >> (k + 17)) != 0u) ++k; /* u / 2^(k + 16) in [1, 2) */
    m = (int32_t)(k <= 14 ? u << (14 - k) : u >> (k - 14)); /* the mantissa in Q30 */
    i = (m >> (30 - FX_LN_TABLE_BITS)) & ((1 << FX_LN_TABLE_BITS) - 1);
    d = mul_q30(m - ((1 << 30) + (i << (30 - FX_LN_TABLE_BITS))), fx_inv_point_q30[i]);
    d2 = mul_q30(d, d);
    ln = fx_ln_point_q30[i] + d - (d2 >> 1) + mul_q30(mul_q30(d2, d), FX_THIRD_Q30);
    /* round((k ln2 + ln) / 64) without the 64-bit sum: ln 2 = 64 a + b in Q30 */
    return k * (FX_LN2_Q30 >> 6) + ((k * (FX_LN2_Q30 & 63) + ln + 32) >> 6);
}

static int32_t fx_log_stage(const ps_gto_plan_fx *q, int32_t force, int32_t inv_scale)
{
    fx_wide acc = {0, 0}, rate = {0, 0};
    uint32_t x; /* F / G2: Q8 * Q24 -> Q16, floored, saturated at PS_GTO_FX_MAX_RATIO */
    if (force == 0) return 0; /* ln 1 (the slack tendon of the unloaded muscle) */
    fx_mac(&acc, force, inv_scale); /* >= 0: force >= 0 and inv_scale > 0 */
    if (acc.hi > PS_GTO_FX_MAX_RATIO || (acc.hi == PS_GTO_FX_MAX_RATIO && acc.lo >= 65536u))
        x = (uint32_t)PS_GTO_FX_MAX_RATIO << 16;
    else
        x = ((uint32_t)acc.hi << 16) | (acc.lo >> 16);
    fx_mac(&rate, q->gain, ln1p_q24(x));
    return fx_round(rate, 24);
}

static int fx_check(int32_t force, int32_t inv_scale)
{
    /* (double)force > PS_GTO_MAX_FORCE_N * PS_GTO_FX_FORCE_ONE without soft float */
    if (force > (int32_t)(PS_GTO_MAX_FORCE_N * PS_GTO_FX_FORCE_ONE)) return PS_ERR_FORCE_RANGE;
    if (inv_scale <= 0) return PS_ERR_CONFIG;
    return PS_OK;
}

int ps_gto_fx_init(ps_gto_fx *s, const ps_gto_plan_fx *q, int32_t force, int32_t inv_scale)
{
    int code;
    int32_t f, r;
    if (s == NULL || q == NULL) return PS_ERR_NULL;
    code = fx_check(force, inv_scale);
    if (code != PS_OK) return code;
    f = force > 0 ? force : 0;
    r = fx_log_stage(q, f, inv_scale);
    s->z[0] = r;
    {
        fx_wide acc = {0, 0};
        fx_mac(&acc, r, q->inv_a0);
        s->z[1] = fx_round(acc, 24);
    }
    s->z[2] = 0;
    s->force = f;
    s->r = r;
    return PS_OK;
}

int ps_gto_step_fx(ps_gto_fx *s, const ps_gto_plan_fx *q, int32_t force, int32_t inv_scale,
                   int32_t *ib)
{
    int code, i;
    int32_t f1, r0, r1, r_mid, alpha, beta, z[3];
    if (s == NULL || q == NULL) return PS_ERR_NULL;
    code = fx_check(force, inv_scale);
    if (code != PS_OK) return code;
    f1 = force > 0 ? force : 0;
    r0 = s->r;
    r1 = fx_log_stage(q, f1, inv_scale);
    r_mid = fx_log_stage(q, (int32_t)(((int64_t)s->force + f1) >> 1), inv_scale);
    /* alpha = r0 + (2/3)(r_mid - (r0 + r1)/2) = r0 + (2 r_mid - r0 - r1) / 3 */
    alpha = r0 + mul_q30(2 * r_mid - r0 - r1, FX_THIRD_Q30);
    beta = r1 - r0;
    for (i = 0; i < 3; ++i) {
        fx_wide acc = {0, 0};
        int j;
        for (j = 0; j < 3; ++j) /* the low-pass's row has zeros: a product skipped is ~30 */
            if (q->phi[i][j] != 0) fx_mac(&acc, q->phi[i][j], s->z[j]);
        if (alpha != 0) fx_mac(&acc, q->g0[i], alpha); /* 0 while the force stays 0 */
        if (beta != 0) fx_mac(&acc, q->g1[i], beta);
        z[i] = fx_round(acc, 30);
    }
    for (i = 0; i < 3; ++i) s->z[i] = z[i];
    s->force = f1;
    s->r = r1;
    if (ib != NULL) *ib = ps_gto_rate_fx(s, q);
    return PS_OK;
}

int32_t ps_gto_rate_fx(const ps_gto_fx *s, const ps_gto_plan_fx *q)
{
    fx_wide acc = {0, 0};
    int32_t y;
    if (s == NULL || q == NULL) return 0;
    fx_mac(&acc, q->c[0], s->z[0]);
    fx_mac(&acc, q->c[1], s->z[1]);
    fx_mac(&acc, q->c[2], s->z[2]);
    if (acc.hi < 0) return 0; /* negative (the plan's bounds keep y within int32) */
    y = fx_round(acc, 30);
    return y > 0 ? y : 0;
}
