/*
 * tendon_organ.c -- the Lin & Crago (2002) Golgi tendon organ (proprio.h section 4).
 *
 * The C twin of spindle/tendon_organ.py: the same plan (a matrix exponential of the
 * augmented 5 x 5 system by the same Taylor scaling and squaring), the same step, the same
 * input rules. A fixed-point form of the step for cores without an FPU follows.
 *
 * No heap, no globals, no input is modified; on failure nothing is written.
 */
#include "proprio.h"

#include <math.h>
#include <stddef.h>

/* the step's pieces inlined where speed is the aim, the compiler's choice under -Os */
#if defined(__GNUC__) && !defined(__OPTIMIZE_SIZE__)
#define GTO_INLINE static inline __attribute__((always_inline))
#else
#define GTO_INLINE static
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
    if (!(finite_d((double)force_scale_N) && force_scale_N > 0)) return PS_ERR_CONFIG;
    return PS_OK;
}

GTO_INLINE ps_real rectified(ps_real force_N) { return force_N > 0 ? force_N : (ps_real)0; }

GTO_INLINE ps_real log_stage(const ps_gto_plan *q, ps_real force_N, ps_real force_scale_N)
{
#ifdef PS_FLOAT
    return q->gain_pps * log1pf(force_N / force_scale_N);
#else
    return q->gain_pps * log1p(force_N / force_scale_N);
#endif
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

ps_real ps_gto_rate(const ps_gto *s, const ps_gto_plan *q)
{
    ps_real y;
    if (s == NULL || q == NULL) return 0;
    y = q->c[0] * s->z[0] + q->c[1] * s->z[1] + q->c[2] * s->z[2];
    return y > 0 ? y : (ps_real)0;
}

/* ln cosh d: three terms of the series below |d| = 0.03 (spindle.tendon_organ.SERIES_D),
 * else |d| + ln(1 + e^{-2|d|}) - ln 2 */
GTO_INLINE ps_real gto_ln_cosh(ps_real d)
{
    const ps_real d2 = d * d;
    ps_real a;
    if (d < (ps_real)0.03 && d > (ps_real)-0.03)
        return d2 * ((ps_real)0.5 - d2 * ((ps_real)(1.0 / 12.0) - d2 * (ps_real)(1.0 / 45.0)));
    a = d < 0 ? -d : d;
#ifdef PS_FLOAT
    return a + log1pf(expf(-2.0f * a)) - logf(2.0f);
#else
    return a + log1p(exp(-2.0 * a)) - log(2.0);
#endif
}

/* the step on checked inputs */
GTO_INLINE void gto_advance(ps_gto *s, const ps_gto_plan *q, ps_real force_N, ps_real scale)
{
    const ps_real f1 = rectified(force_N);
    const ps_real r0 = s->r_pps, r1 = log_stage(q, f1, scale);
    const ps_real alpha = r0 + (ps_real)2 * q->gain_pps / (ps_real)3
                                   * gto_ln_cosh((r1 - r0) * ((ps_real)0.5 / q->gain_pps));
    const ps_real beta = r1 - r0;
    ps_real z[3];
    int i;
    for (i = 0; i < 3; ++i) {
        z[i] = q->phi[i][0] * s->z[0] + q->phi[i][1] * s->z[1] + q->phi[i][2] * s->z[2];
        z[i] += q->g0[i] * alpha;
        z[i] += q->g1[i] * beta;
    }
    for (i = 0; i < 3; ++i) s->z[i] = z[i];
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

int ps_gto_batch_run(ps_gto *s, long n, const ps_gto_plan *q, long steps,
                     const ps_real *force_N, const ps_real *force_scale_N, ps_real *ib,
                     long *failed)
{
    long i, k;
    if (n < 0 || steps < 0) return PS_ERR_ARGUMENT;
    if (n == 0 || steps == 0) return PS_OK;
    if (s == NULL || q == NULL || force_N == NULL || force_scale_N == NULL) return PS_ERR_NULL;
    for (k = 0; k < steps; ++k) {
        for (i = 0; i < n; ++i) {
            int code = check_force(force_N[k * n + i], force_scale_N[i]);
            if (code != PS_OK) {
                if (failed != NULL) *failed = k * n + i;
                return code;
            }
        }
    }
    for (k = 0; k < steps; ++k) {
        for (i = 0; i < n; ++i) {
            gto_advance(&s[i], q, force_N[k * n + i], force_scale_N[i]);
            if (ib != NULL) ib[k * n + i] = ps_gto_rate(&s[i], q);
        }
    }
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
