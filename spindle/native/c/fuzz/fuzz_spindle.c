/*
 * fuzz_spindle.c -- randomized robustness driver for spindle.c, built by
 * tests/test_c_sanitizers.py with AddressSanitizer and UndefinedBehaviorSanitizer.
 *
 * usage: fuzz_spindle SEED ITERATIONS
 *
 * Every iteration draws a state (a valid one, or one stepped from it, or random bytes),
 * constants (CAT, or perturbed, or garbage), inputs from a pool of extreme values (NaN, inf,
 * huge, negative, subnormal, out of range, NULL pointers) and calls every spindle function.
 * It checks the header's promises and exits 1 with a message on the first broken one:
 *   - the status is one of enum ps_status;
 *   - on failure the state and the outputs are exactly as before;
 *   - with valid constants and a valid state, the status is the documented one for the
 *     first invalid input, and a success leaves a finite state and finite rates >= 0.
 * The sanitizers abort on any memory error or undefined behaviour.
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

static ps_real extreme(rng *r)
{
    switch (pick(r, 12)) {
    case 0: return (ps_real)NAN;
    case 1: return (ps_real)INFINITY;
    case 2: return -(ps_real)INFINITY;
    case 3: return (ps_real)1e30;
    case 4: return (ps_real)-1e30;
    case 5: return (ps_real)0.0;
    case 6: return -(ps_real)0.0;
    case 7: return (ps_real)1e-40;
    case 8: return (ps_real)uniform(r, -1e6, 1e6);
    case 9: return (ps_real)uniform(r, -2.0, 2.0);
    case 10: return (ps_real)-1e-9;
    default: return (ps_real)uniform(r, 0.0, 1.0);
    }
}

static void cat_params(ps_params *p)
{
    static const double KSR = 10.4649, KPR = 0.15, M = 0.0002;
    const double beta0[3] = {0.0605, 0.0822, 0.0822}, bdrive[3] = {0.2592, -0.046, -0.069};
    const double Gdrive[3] = {0.0289, 0.0636, 0.0954}, X[3] = {0.0, 0.7, 0.7};
    const double Gp[3] = {20000.0, 10000.0, 10000.0}, Gs[3] = {0.0, 7250.0, 7250.0};
    const double freq[3] = {60.0, 60.0, 90.0}, tau[3] = {0.149, 0.205, 0.0};
    int i;
    for (i = 0; i < PS_NFIBRES; ++i) {
        p->KSR[i] = (ps_real)KSR; p->KPR[i] = (ps_real)KPR; p->M[i] = (ps_real)M;
        p->beta0[i] = (ps_real)beta0[i]; p->beta_drive[i] = (ps_real)bdrive[i];
        p->Gamma_drive[i] = (ps_real)Gdrive[i]; p->CL[i] = 1; p->CS[i] = (ps_real)0.42;
        p->R[i] = (ps_real)0.46; p->a[i] = (ps_real)0.3; p->LSR0[i] = (ps_real)0.04;
        p->LPR0[i] = (ps_real)0.76; p->LNSR[i] = (ps_real)0.0423; p->LNPR[i] = (ps_real)0.89;
        p->X[i] = (ps_real)X[i]; p->Lsec[i] = (ps_real)0.04; p->G_pri[i] = (ps_real)Gp[i];
        p->G_sec[i] = (ps_real)Gs[i]; p->freq[i] = (ps_real)freq[i]; p->p[i] = 2;
        p->tau[i] = (ps_real)tau[i];
    }
    p->S = (ps_real)0.156;
}

static int valid_status(int st) { return st >= PS_OK && st <= PS_ERR_CONFIG; }

static int finite_state(const ps_spindle *s)
{
    int i;
    for (i = 0; i < PS_NFIBRES; ++i) {
        if (!isfinite(s->T[i]) || !isfinite(s->v[i]) || !isfinite(s->z[i])
            || !isfinite(s->f[i])) {
            return 0;
        }
    }
    return isfinite(s->L) && isfinite(s->gd) && isfinite(s->gs);
}

#define FAIL(...) do { fprintf(stderr, "iteration %ld: ", it); fprintf(stderr, __VA_ARGS__); \
                       fputc('\n', stderr); return 1; } while (0)

/* The status the header documents for these inputs (valid constants and state). */
static int expected_status(const ps_spindle *s, ps_real L, ps_real gd, ps_real gs, ps_real h,
                           ps_real theta)
{
    if (!(theta >= 0 && theta <= 1)) return PS_ERR_METHOD;
    if (!(isfinite(h) && h > 0)) return PS_ERR_STEP;
    if (!isfinite(L) || !isfinite(gd) || !isfinite(gs)) return PS_ERR_NONFINITE;
    if (L < (ps_real)PS_LENGTH_MIN_L0 || L > (ps_real)PS_LENGTH_MAX_L0) {
        return PS_ERR_LENGTH_RANGE;
    }
    if (gd < 0 || gs < 0) return PS_ERR_NEGATIVE_DRIVE;
    if (fabs((double)(L - s->L)) / (double)h > PS_MAX_SPEED_L0_S * (1 + 1e-6)) {
        return PS_ERR_SPEED;
    }
    if (fabs((double)(L - s->L)) / (double)h < PS_MAX_SPEED_L0_S * (1 - 1e-6)) return PS_OK;
    return -1; /* at the speed limit: either */
}

int main(int argc, char **argv)
{
    rng r;
    long it, iterations, n_ok = 0, n_fail = 0, n_runtime = 0;
    ps_params cat, p;
    ps_spindle good;
    if (argc != 3) {
        fprintf(stderr, "usage: %s SEED ITERATIONS\n", argv[0]);
        return 2;
    }
    r.s = strtoull(argv[1], NULL, 10) * 2654435761ULL + 88172645463325252ULL;
    iterations = strtol(argv[2], NULL, 10);
    cat_params(&cat);
    if (ps_params_check(&cat) != PS_OK) { fprintf(stderr, "CAT refused\n"); return 1; }
    if (ps_spindle_init(&good, &cat, 1, 0, 0) != PS_OK) return 1;

    for (it = 0; it < iterations; ++it) {
        ps_spindle s, before;
        ps_real L, gd, gs, h, theta, ia = (ps_real)-7, ii = (ps_real)-7;
        int st, valid_state = 1, mode = pick(&r, 10);

        /* constants */
        p = cat;
        if (mode == 0) {
            ps_real *field = (ps_real *)&p;
            int k, n = (int)(sizeof p / sizeof(ps_real));
            for (k = 0; k < 1 + pick(&r, 4); ++k) field[pick(&r, n)] = extreme(&r);
            st = ps_params_check(&p);
            if (st != PS_OK && st != PS_ERR_CONFIG) FAIL("params check status %d", st);
        } else if (mode == 1) {
            int i;
            for (i = 0; i < PS_NFIBRES; ++i) p.beta0[i] *= (ps_real)uniform(&r, 0.5, 2.0);
            if (ps_params_check(&p) != PS_OK) FAIL("perturbed CAT refused");
        }
        /* state */
        if (mode == 2) {
            unsigned char *b = (unsigned char *)&s;
            size_t k;
            for (k = 0; k < sizeof s; ++k) b[k] = (unsigned char)next_u64(&r);
            valid_state = 0;
        } else if (mode == 3) {
            s = good;
            ((ps_real *)&s)[pick(&r, (int)(sizeof s / sizeof(ps_real)))] = extreme(&r);
            valid_state = 0;
        } else {
            ps_real L0 = (ps_real)uniform(&r, 0.5, 1.5);
            st = ps_spindle_init(&s, &p, L0, (ps_real)uniform(&r, 0, 200),
                                 (ps_real)uniform(&r, 0, 200));
            if (!valid_status(st)) FAIL("init status %d", st);
            if (st != PS_OK) {
                /* constants that pass ps_params_check can still be unusable (a subnormal
                 * KSR or freq): PS_ERR_CONFIG is their documented status */
                if (mode != 0 || st != PS_ERR_CONFIG) FAIL("init refused valid inputs: %d", st);
                s = good;
                valid_state = 0;
            }
        }
        /* inputs: mostly valid, each one extreme now and then */
        theta = pick(&r, 3) == 0 ? (ps_real)0.5 : (ps_real)(pick(&r, 3) * 0.5);
        h = (ps_real)uniform(&r, 1e-5, 5e-3);
        L = (ps_real)(isfinite(s.L) && s.L > 0.5 && s.L < 1.5 ? s.L : 1.0);
        L += (ps_real)uniform(&r, -9.0, 9.0) * h;
        if (L < (ps_real)0.5) L = (ps_real)0.5;
        if (L > (ps_real)1.5) L = (ps_real)1.5;
        gd = (ps_real)uniform(&r, 0, 300);
        gs = (ps_real)uniform(&r, 0, 300);
        if (pick(&r, 4) == 0) L = extreme(&r);
        if (pick(&r, 6) == 0) gd = extreme(&r);
        if (pick(&r, 6) == 0) gs = extreme(&r);
        if (pick(&r, 6) == 0) h = extreme(&r);
        if (pick(&r, 8) == 0) theta = extreme(&r);
        if (theta == 0 && h > (ps_real)1e-3) h = (ps_real)1e-3; /* keep forward Euler stable */

        before = s;
        st = ps_spindle_step(pick(&r, 50) ? &s : NULL, pick(&r, 50) ? &p : NULL, L, gd, gs, h,
                             theta, pick(&r, 10) ? &ia : NULL, pick(&r, 10) ? &ii : NULL);
        if (!valid_status(st)) FAIL("step status %d", st);
        if (st != PS_OK) {
            ++n_fail;
            if (memcmp(&s, &before, sizeof s) != 0) FAIL("state changed on status %d", st);
            if (ia != (ps_real)-7 || ii != (ps_real)-7) FAIL("outputs written on status %d", st);
        } else {
            ++n_ok;
        }
        if (mode != 0 && valid_state && st != PS_ERR_NULL) {
            int want = expected_status(&before, L, gd, gs, h, theta);
            /* a valid step may still fail at run time: no convergence, or forward Euler
             * beyond its stability limit */
            int runtime = want == PS_OK
                          && (st == PS_ERR_NO_CONVERGENCE || st == PS_ERR_NONFINITE);
            if (runtime) ++n_runtime;
            if (want >= 0 && st != want && !runtime) {
                FAIL("status %d, documented %d (L=%g gd=%g gs=%g h=%g theta=%g)", st, want,
                     (double)L, (double)gd, (double)gs, (double)h, (double)theta);
            }
            if (st == PS_OK) {
                if (!finite_state(&s)) {
                    FAIL("success left a non-finite state (L=%g gd=%g gs=%g h=%g theta=%g)",
                         (double)L, (double)gd, (double)gs, (double)h, (double)theta);
                }
                if (ia != (ps_real)-7 && !(isfinite(ia) && ia >= 0)) FAIL("Ia %g", (double)ia);
                if (ii != (ps_real)-7 && !(isfinite(ii) && ii >= 0)) FAIL("II %g", (double)ii);
            }
        }

        /* the embedded fast path with the same draws */
        {
            ps_plan plan, plan_before;
            memset(&plan, 0x5a, sizeof plan);
            plan_before = plan;
            st = ps_plan_init(pick(&r, 30) ? &plan : NULL, pick(&r, 30) ? &p : NULL, h, theta);
            if (!valid_status(st)) FAIL("plan init status %d", st);
            if (st != PS_OK && memcmp(&plan, &plan_before, sizeof plan) != 0) {
                FAIL("plan init changed the plan on status %d", st);
            }
            if (st == PS_OK) {
                ps_real pia = (ps_real)-7, pii = (ps_real)-7;
                ps_spindle s2 = before;
                st = ps_spindle_step_plan(pick(&r, 50) ? &s2 : NULL, &plan, L, gd, gs,
                                          pick(&r, 10) ? &pia : NULL, pick(&r, 10) ? &pii : NULL);
                if (!valid_status(st)) FAIL("plan step status %d", st);
                if (st != PS_OK) {
                    if (memcmp(&s2, &before, sizeof s2) != 0) FAIL("plan step changed the state");
                    if (pia != (ps_real)-7 || pii != (ps_real)-7) FAIL("plan step wrote outputs");
                } else if (mode != 0 && valid_state && !finite_state(&s2)) {
                    FAIL("plan step success left a non-finite state");
                }
            }
        }

        /* the other entry points, with the same draws */
        ps_spindle_afferents(pick(&r, 20) ? &s : NULL, pick(&r, 20) ? &p : NULL,
                             pick(&r, 5) ? &ia : NULL, pick(&r, 5) ? &ii : NULL);
        before = s;
        st = ps_spindle_init(pick(&r, 30) ? &s : NULL, &p, L, gd, gs);
        if (!valid_status(st)) FAIL("init status %d", st);
        if (st != PS_OK && memcmp(&s, &before, sizeof s) != 0) FAIL("init changed the state");
        {
            ps_real Ls[8], gds[8], gss[8], ias[8], iis[8];
            long done = -1, every = 1 + pick(&r, 3), k, n = pick(&r, 9);
            for (k = 0; k < 8; ++k) {
                Ls[k] = L + (ps_real)(0.001 * (double)k);
                gds[k] = gd;
                gss[k] = gs;
            }
            if (pick(&r, 4) == 0) Ls[pick(&r, 8)] = extreme(&r);
            st = ps_spindle_run(&s, &p, Ls, gds, gss, n, h, theta, every, ias, iis, &done);
            if (!valid_status(st)) FAIL("run status %d", st);
            if (done < 0 || done > n) FAIL("run done %ld of %ld", done, n);
        }
    }
    printf("iterations=%ld ok=%ld refused=%ld runtime_failures=%ld\n", iterations, n_ok, n_fail,
           n_runtime);
    return 0;
}
