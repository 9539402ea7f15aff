/*
 * fuzz_fixed.c -- randomized robustness driver for the fixed-point step of spindle.c
 * (ps_plan_fx_init, ps_spindle_fx_init, ps_spindle_step_fx, ps_spindle_fx_afferents), built
 * by tests/test_c_fixed.py with AddressSanitizer and UndefinedBehaviorSanitizer (which
 * aborts on any signed int32 overflow: the test of the plan's bound analysis).
 *
 * usage: fuzz_fixed SEED ITERATIONS
 *
 * Every iteration draws constants (HUMAN, CAT, or CAT with random fields scaled by up to
 * 100x or replaced by extreme values: whatever ps_plan_fx_init accepts must step without
 * overflow), a step and theta (valid or not), a state (at rest, stepped from rest, random
 * fields inside the documented ranges, random bytes, one corrupted field) and inputs (valid
 * moves up to the speed limit, out-of-range lengths, negative and huge drives, too fast
 * moves, INT32_MIN/MAX, NULL pointers). It checks the header's promises and exits 1 with a
 * message on the first broken one:
 *   - every status is one of enum ps_status, and plan init leaves q untouched on failure;
 *   - on failure the state and the outputs are exactly as before;
 *   - with an accepted plan and a state in range, the status is the documented one for the
 *     first invalid input (NULL, length range, negative drive, state out of range, speed),
 *     and a success leaves a state in range (and rates >= 0 with HUMAN or CAT constants).
 */
#include "proprio.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct rng { unsigned long long s; } rng;

static unsigned long long next_u64(rng *r)
{
    r->s ^= r->s << 13;
    r->s ^= r->s >> 7;
    r->s ^= r->s << 17;
    return r->s;
}

static double uniform(rng *r, double lo, double hi)
{
    return lo + (hi - lo) * ((double)(next_u64(r) >> 11) / 9007199254740992.0);
}

static int pick(rng *r, int n) { return (int)(next_u64(r) % (unsigned long long)n); }

static int32_t uniform_i32(rng *r, double lo, double hi)
{
    return (int32_t)floor(uniform(r, lo, hi));
}

static int32_t extreme_i32(rng *r)
{
    switch (pick(r, 8)) {
    case 0: return INT32_MIN;
    case 1: return INT32_MAX;
    case 2: return 0;
    case 3: return -1;
    case 4: return (int32_t)(next_u64(r) >> 32);
    case 5: return PS_FX_ONE / 2 - 1;
    case 6: return PS_FX_ONE * 3 / 2 + 1;
    default: return uniform_i32(r, -4.0 * PS_FX_ONE, 4.0 * PS_FX_ONE);
    }
}

static ps_real extreme_real(rng *r)
{
    switch (pick(r, 8)) {
    case 0: return (ps_real)NAN;
    case 1: return (ps_real)INFINITY;
    case 2: return (ps_real)1e30;
    case 3: return (ps_real)-1.0;
    case 4: return (ps_real)0.0;
    case 5: return (ps_real)1e-30;
    case 6: return (ps_real)uniform(r, -1e3, 1e3);
    default: return (ps_real)uniform(r, 0.0, 2.0);
    }
}

static void cat_params(ps_params *p, double gain_scale)
{
    const double beta0[3] = {0.0605, 0.0822, 0.0822}, bdrive[3] = {0.2592, -0.046, -0.069};
    const double Gdrive[3] = {0.0289, 0.0636, 0.0954}, X[3] = {0.0, 0.7, 0.7};
    const double Gp[3] = {20000.0, 10000.0, 10000.0}, Gs[3] = {0.0, 7250.0, 7250.0};
    const double freq[3] = {60.0, 60.0, 90.0}, tau[3] = {0.149, 0.205, 0.0};
    int i;
    for (i = 0; i < PS_NFIBRES; ++i) {
        p->KSR[i] = (ps_real)10.4649; p->KPR[i] = (ps_real)0.15; p->M[i] = (ps_real)0.0002;
        p->beta0[i] = (ps_real)beta0[i]; p->beta_drive[i] = (ps_real)bdrive[i];
        p->Gamma_drive[i] = (ps_real)Gdrive[i]; p->CL[i] = 1; p->CS[i] = (ps_real)0.42;
        p->R[i] = (ps_real)0.46; p->a[i] = (ps_real)0.3; p->LSR0[i] = (ps_real)0.04;
        p->LPR0[i] = (ps_real)0.76; p->LNSR[i] = (ps_real)0.0423; p->LNPR[i] = (ps_real)0.89;
        p->X[i] = (ps_real)X[i]; p->Lsec[i] = (ps_real)0.04;
        p->G_pri[i] = (ps_real)(Gp[i] * gain_scale);
        p->G_sec[i] = (ps_real)(Gs[i] * gain_scale); p->freq[i] = (ps_real)freq[i]; p->p[i] = 2;
        p->tau[i] = (ps_real)tau[i];
    }
    p->S = (ps_real)0.156;
}

static int valid_status(int st) { return st >= PS_OK && st <= PS_ERR_CONFIG; }

/* The ranges of proprio.h, for a plan q. */
static int state_in_range(const ps_spindle_fx *s, const ps_plan_fx *q)
{
    const int32_t t_max = PS_FX_T_MAX * PS_FX_ONE;
    int i;
    if (s->L < PS_FX_ONE / 2 || s->L > PS_FX_ONE * 3 / 2 || s->gd < 0 || s->gs < 0) return 0;
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (s->T[i] < -t_max || s->T[i] > t_max || s->z[i] < -q->y_max || s->z[i] > q->y_max
            || s->v[i] < -q->v_max || s->v[i] > q->v_max || s->f[i] < 0 || s->f[i] > PS_FX_ONE
            || s->target[i] < 0 || s->target[i] > PS_FX_ONE) {
            return 0;
        }
    }
    return 1;
}

#define FAIL(...) do { fprintf(stderr, "iteration %ld: ", it); fprintf(stderr, __VA_ARGS__); \
                       fputc('\n', stderr); return 1; } while (0)

int main(int argc, char **argv)
{
    rng r;
    long it, iterations, n_ok = 0, n_fail = 0, n_runtime = 0, n_plans = 0, n_consistent = 0;
    long n_runtime_consistent = 0;
    ps_params human, cat;
    if (argc != 3) {
        fprintf(stderr, "usage: %s SEED ITERATIONS\n", argv[0]);
        return 2;
    }
    r.s = strtoull(argv[1], NULL, 10) * 2654435761ULL + 88172645463325252ULL;
    iterations = strtol(argv[2], NULL, 10);
    cat_params(&cat, 1.0);
    cat_params(&human, 0.2);

    for (it = 0; it < iterations; ++it) {
        ps_params p;
        ps_plan_fx q, q_before;
        ps_spindle_fx s, before;
        ps_real h, theta;
        int32_t L, gd, gs, ia = -7, ii = -7;
        int st, want, k, mode = pick(&r, 10), in_range, kind;

        /* constants, step, theta */
        p = pick(&r, 2) ? human : cat;
        if (mode == 0) { /* scaled or extreme fields */
            ps_real *field = (ps_real *)&p;
            int n = (int)(sizeof p / sizeof(ps_real));
            for (k = 0; k < 1 + pick(&r, 4); ++k) {
                int f = pick(&r, n);
                field[f] = pick(&r, 4) ? field[f] * (ps_real)exp(uniform(&r, -4.6, 4.6))
                                       : extreme_real(&r);
            }
        }
        h = (ps_real)(pick(&r, 10) ? uniform(&r, 5e-4, 2e-2) : (double)extreme_real(&r));
        theta = (ps_real)(pick(&r, 10) ? (pick(&r, 3) ? 0.5 : uniform(&r, 0.0, 1.0))
                                       : (double)extreme_real(&r));
        memset(&q, 0x5a, sizeof q);
        q_before = q;
        st = ps_plan_fx_init(pick(&r, 40) ? &q : NULL, pick(&r, 40) ? &p : NULL, h, theta);
        if (!valid_status(st)) FAIL("plan status %d", st);
        if (st != PS_OK) {
            if (memcmp(&q, &q_before, sizeof q) != 0) FAIL("plan changed on status %d", st);
            continue;
        }
        ++n_plans;

        /* state */
        gd = uniform_i32(&r, 0, 300.0 * PS_FX_DRIVE_ONE);
        gs = uniform_i32(&r, 0, 300.0 * PS_FX_DRIVE_ONE);
        L = uniform_i32(&r, 0.5 * PS_FX_ONE, 1.5 * PS_FX_ONE);
        st = ps_spindle_fx_init(&s, &q, L, gd, gs);
        if (st != PS_OK) FAIL("init refused valid inputs: %d", st);
        if (!state_in_range(&s, &q)) FAIL("init left a state out of range");
        kind = pick(&r, 6);
        switch (kind) {
        case 0: { /* random fields within the ranges */
            const double t = PS_FX_T_MAX * (double)PS_FX_ONE;
            for (k = 0; k < PS_NFIBRES; ++k) {
                s.T[k] = uniform_i32(&r, -t, t);
                s.z[k] = uniform_i32(&r, -(double)q.y_max, (double)q.y_max);
                s.v[k] = uniform_i32(&r, -(double)q.v_max, (double)q.v_max);
                s.f[k] = uniform_i32(&r, 0, PS_FX_ONE);
                s.target[k] = uniform_i32(&r, 0, PS_FX_ONE);
            }
            s.gd = pick(&r, 2) ? gd : INT32_MAX;
            break;
        }
        case 1: { /* random bytes */
            unsigned char *b = (unsigned char *)&s;
            size_t j;
            for (j = 0; j < sizeof s; ++j) b[j] = (unsigned char)next_u64(&r);
            break;
        }
        case 2: /* one corrupted field */
            ((int32_t *)&s)[pick(&r, (int)(sizeof s / sizeof(int32_t)))] = extreme_i32(&r);
            break;
        case 3: /* stepped from rest along a random move */
            for (k = 0; k < 1 + pick(&r, 40); ++k) {
                int32_t L1 = s.L + uniform_i32(&r, -(double)q.max_dL, (double)q.max_dL);
                if (L1 < PS_FX_ONE / 2) L1 = PS_FX_ONE / 2;
                if (L1 > PS_FX_ONE * 3 / 2) L1 = PS_FX_ONE * 3 / 2;
                if (ps_spindle_step_fx(&s, &q, L1, gd, gs, NULL, NULL) != PS_OK) break;
            }
            break;
        default:
            break;
        }
        in_range = state_in_range(&s, &q);

        /* inputs: a move within the speed limit, now and then an invalid one */
        L = (in_range ? s.L : PS_FX_ONE)
            + uniform_i32(&r, -(double)q.max_dL, (double)q.max_dL);
        if (L < PS_FX_ONE / 2) L = PS_FX_ONE / 2;
        if (L > PS_FX_ONE * 3 / 2) L = PS_FX_ONE * 3 / 2;
        gd = pick(&r, 3) ? gd : uniform_i32(&r, 0, 300.0 * PS_FX_DRIVE_ONE);
        if (pick(&r, 5) == 0) L = extreme_i32(&r);
        if (pick(&r, 8) == 0) gd = extreme_i32(&r);
        if (pick(&r, 8) == 0) gs = extreme_i32(&r);

        before = s;
        {
            const int null_s = pick(&r, 50) == 0, null_q = pick(&r, 50) == 0;
            st = ps_spindle_step_fx(null_s ? NULL : &s, null_q ? NULL : &q, L, gd, gs,
                                    pick(&r, 10) ? &ia : NULL, pick(&r, 10) ? &ii : NULL);
            if (!valid_status(st)) FAIL("step status %d", st);
            if (st != PS_OK) {
                ++n_fail;
                if (memcmp(&s, &before, sizeof s) != 0) FAIL("state changed on status %d", st);
                if (ia != -7 || ii != -7) FAIL("outputs written on status %d", st);
            } else {
                ++n_ok;
            }
            /* the documented status, in the documented order */
            if (null_s || null_q) {
                want = PS_ERR_NULL;
            } else if (L < PS_FX_ONE / 2 || L > PS_FX_ONE * 3 / 2) {
                want = PS_ERR_LENGTH_RANGE;
            } else if (gd < 0 || gs < 0) {
                want = PS_ERR_NEGATIVE_DRIVE;
            } else if (!in_range) {
                want = PS_ERR_NONFINITE;
            } else if ((L > before.L ? L - before.L : before.L - L) > q.max_dL) {
                want = PS_ERR_SPEED;
            } else {
                want = PS_OK;
                if (kind >= 3) ++n_consistent;
            }
            if (want == PS_OK && (st == PS_ERR_NO_CONVERGENCE || st == PS_ERR_NONFINITE)) {
                ++n_runtime; /* a valid step may fail at run time (documented) */
                if (kind >= 3) ++n_runtime_consistent;
            } else if (st != want) {
                FAIL("status %d, documented %d (mode %d, L=%ld gd=%ld gs=%ld)", st, want, mode,
                     (long)L, (long)gd, (long)gs);
            }
            if (st == PS_OK) {
                if (!state_in_range(&s, &q)) FAIL("success left a state out of range");
                /* rates >= 0 with the model's constants (a negative S or gain can make
                 * them negative: the model's arithmetic, not an overflow) */
                if (mode != 0 && ia != -7 && ia < 0) FAIL("Ia %ld", (long)ia);
                if (mode != 0 && ii != -7 && ii < 0) FAIL("II %ld", (long)ii);
            }
        }

        /* the other entry points with the same draws */
        ia = -7;
        ii = -7;
        ps_spindle_fx_afferents(pick(&r, 20) ? &s : NULL, pick(&r, 20) ? &q : NULL,
                                pick(&r, 5) ? &ia : NULL, pick(&r, 5) ? &ii : NULL);
        if (mode != 0 && ia < 0 && ia != -7) FAIL("afferents Ia %ld", (long)ia);
        before = s;
        st = ps_spindle_fx_init(pick(&r, 30) ? &s : NULL, &q, L, gd, gs);
        if (!valid_status(st)) FAIL("init status %d", st);
        if (st != PS_OK && memcmp(&s, &before, sizeof s) != 0) FAIL("init changed the state");
    }
    printf("iterations=%ld plans=%ld ok=%ld refused=%ld runtime_failures=%ld "
           "valid_steps_from_consistent_states=%ld of_which_failed=%ld\n", iterations, n_plans,
           n_ok, n_fail, n_runtime, n_consistent, n_runtime_consistent);
    return 0;
}
