/*
 * fuzz_chain.c -- randomized, extreme and invalid inputs through every chain entry point.
 *
 * Built with -fsanitize=address,undefined (tests/test_c_chain_fuzz.py): any memory error
 * or undefined behaviour aborts it. It also checks the contract itself and exits non-zero
 * when it is broken: every call returns a documented status; an accepted output is finite
 * with lengths in the spindle's range; a failing call changes nothing; no call returns
 * PS_ERR_ANGLE_RANGE or PS_ERR_INTERVAL (angles are clamped, long intervals restart).
 *
 * Usage: fuzz_chain CONFIG_FILE ITERATIONS SEED
 * CONFIG_FILE holds the bytes of a valid ps_chain_config (written by the test from
 * spindle.native.chain.chain_config_struct for the same build); each iteration also tries a
 * corrupted copy of it on ps_chain_init.
 */
#include "proprio.h"

#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef unsigned long long u64;

static u64 rng_state = 88172645463325252ULL;

static u64 next_u64(void)
{
    rng_state ^= rng_state << 13;
    rng_state ^= rng_state >> 7;
    rng_state ^= rng_state << 17;
    return rng_state;
}

static double uniform(void) { return (double)(next_u64() >> 11) * (1.0 / 9007199254740992.0); }
static int below(int n) { return (int)(next_u64() % (u64)n); }

/* An extreme or invalid real, representable in ps_real. */
static ps_real extreme(void)
{
    const double table[] = {0.0, -0.0, 1.0, -1.0, 0.5, 1.5, 0.49999999, 1.50000001, 1023.0,
                            1024.0, 65535.0, 1e-300, -1e-300, 1e30, -1e30, 1e300, -1e300,
                            DBL_MIN, 511.5, 130.0, 130.0000001, -1e-9};
    int i = below(24);
    if (i == 22) {
        return (ps_real)nan("");
    }
    if (i == 23) {
        return (ps_real)(below(2) ? HUGE_VAL : -HUGE_VAL);
    }
#ifdef PS_FLOAT
    if (fabs(table[i]) > FLT_MAX) {
        return table[i] > 0 ? FLT_MAX : -FLT_MAX;
    }
#endif
    return (ps_real)table[i];
}

static int failures = 0;

static void fail(const char *what, long it)
{
    fprintf(stderr, "contract broken at iteration %ld: %s\n", it, what);
    failures += 1;
}

static int finite_real(ps_real x) { return x == x && (x - x) == (x - x); }

static int sample_finite(const ps_arm_sample *s)
{
    int k, ok = finite_real(s->counts) && finite_real(s->counts_filtered)
                && finite_real(s->angle_deg) && s->t_s == s->t_s;
    for (k = 0; k < PS_MUSCLES; ++k) {
        ok = ok && finite_real(s->length_L0[k]) && finite_real(s->velocity_L0_s[k])
             && finite_real(s->acceleration_L0_s2[k]) && finite_real(s->template_L0[k])
             && finite_real(s->gamma_static_pps[k]) && finite_real(s->gamma_dynamic_pps[k])
             && finite_real(s->ia_pps[k]) && finite_real(s->ii_pps[k])
             && s->ia_pps[k] >= 0 && s->ii_pps[k] >= 0
             && s->length_L0[k] >= (ps_real)PS_LENGTH_MIN_L0
             && s->length_L0[k] <= (ps_real)PS_LENGTH_MAX_L0;
    }
    return ok;
}

static int documented(int status) { return status >= PS_OK && status <= PS_ERR_INTERVAL; }

/* A next time: mostly a sensor interval, sometimes equal, earlier, a gap, or garbage. */
static ps_time next_time(ps_time t)
{
    switch (below(16)) {
    case 0: return t;
    case 1: return t - uniform() * 0.01;
    case 2: return t + 0.01 + uniform() * 0.2; /* a gap */
    case 3: return nan("");
    case 4: return below(2) ? HUGE_VAL : -HUGE_VAL;
    case 5: /* corrupt clocks: a jump restarts the chain there; true times after it are
             * earlier and resync the clock after resync_after_samples of them */
        return below(8) ? t + 1e4 * uniform() : 1e300;
    case 6: return t + 1e-12;
    default: return t + 0.002 * (0.6 + 0.8 * uniform());
    }
}

static ps_real next_counts(ps_real counts)
{
    switch (below(10)) {
    case 0: return extreme();
    case 1: return (ps_real)below(1024) + (below(2) ? (ps_real)0.5 : 0);
    case 2: return (ps_real)below(65536);
    default: {
        ps_real c = counts + (ps_real)(below(7) - 3);
        return c < 0 ? 0 : (c > 1023 ? 1023 : c);
    }
    }
}

static ps_real random_angle(void)
{
    return below(6) == 0 ? extreme() : (ps_real)(-20.0 + 170.0 * uniform());
}

static void random_lengths(ps_real *L)
{
    int k;
    for (k = 0; k < PS_MUSCLES; ++k) {
        L[k] = below(8) == 0 ? extreme() : (ps_real)(0.45 + 1.1 * uniform());
    }
}

/* Corrupt one field of a config at random; init must refuse it or accept it cleanly. */
static void corrupt(ps_chain_config *cfg)
{
    ps_real *reals[] = {&cfg->max_count, &cfg->zero_count, &cfg->count_sign,
                        &cfg->deg_per_count, &cfg->fit_lo_rad, &cfg->fit_hi_rad,
                        &cfg->lowpass_rad_s, &cfg->max_speed_deg_s, &cfg->max_speed_L0_s,
                        &cfg->gamma_static_min_pps, &cfg->gamma_static_max_pps,
                        &cfg->gamma_dynamic_pps, &cfg->shortening_threshold_L0,
                        &cfg->predictor_rate_hz, &cfg->predictor_kp_1_s,
                        &cfg->predictor_ki_1_s2, &cfg->theta, &cfg->params.S,
                        &cfg->params.KSR[0], &cfg->params.M[2], &cfg->params.a[1],
                        &cfg->params.tau[0], &cfg->coefficients[0][0],
                        &cfg->coefficients[1][3]};
    int n = (int)(sizeof(reals) / sizeof(reals[0]));
    switch (below(6)) {
    case 0:
        if (below(2)) {
            cfg->median_window = below(40) - 5;
        } else {
            cfg->resync_after_samples = below(2) ? (long)below(40) - 5 : LONG_MAX - below(4);
        }
        break;
    case 1: cfg->n_coefficients[below(2)] = below(40) - 5; break;
    case 2:
        if (below(2)) {
            cfg->gap_s = (ps_time)extreme();
        } else {
            cfg->max_bridge_s = below(2) ? (ps_time)extreme() : uniform() * 1e3;
        }
        break;
    case 3: cfg->delay_s = below(2) ? (ps_time)extreme() : uniform(); break;
    case 4: cfg->step_s = below(2) ? (ps_time)extreme() : uniform() * 0.02; break;
    default: *reals[below(n)] = extreme(); break;
    }
}

int main(int argc, char **argv)
{
    ps_chain_config good, bad;
    ps_arm_chain chain, scratch, before;
    ps_arm_sample out;
    ps_time t = 0, times[24];
    ps_real counts = 512, values[48], intended[24], L[PS_MUSCLES], angle;
    ps_arm_sample table[24];
    long it, iterations, n_done, statuses[PS_ERR_INTERVAL + 1] = {0};
    unsigned long accepted_total = 0, restarts_total = 0;
    int status, i, n;
    FILE *f;

    if (argc != 4) {
        fprintf(stderr, "usage: %s CONFIG_FILE ITERATIONS SEED\n", argv[0]);
        return 2;
    }
    f = fopen(argv[1], "rb");
    if (f == NULL || fread(&good, sizeof good, 1, f) != 1) {
        fprintf(stderr, "cannot read a ps_chain_config (%lu bytes) from %s\n",
                (unsigned long)sizeof good, argv[1]);
        return 2;
    }
    fclose(f);
    iterations = strtol(argv[2], NULL, 10);
    rng_state ^= (u64)strtoull(argv[3], NULL, 10) * 0x9E3779B97F4A7C15ULL;
    if (rng_state == 0) {
        rng_state = 1;
    }

    /* NULL pointers and unusable chains are refused everywhere. */
    memset(&scratch, 0, sizeof scratch);
    if (ps_chain_init(NULL, &good) != PS_ERR_NULL || ps_chain_init(&scratch, NULL) != PS_ERR_NULL
        || ps_chain_reset(NULL, 0, 0, NULL, NULL) != PS_ERR_NULL
        || ps_chain_reset(&scratch, 30, 0, NULL, NULL) != PS_ERR_NOT_RESET
        || ps_chain_push_counts(&scratch, 1, 500, &out) != PS_ERR_NOT_RESET
        || ps_chain_push_angle(NULL, 1, 30, &out) != PS_ERR_NULL
        || ps_chain_push_lengths(&scratch, 1, NULL, NULL, &out) != PS_ERR_NULL
        || ps_chain_push_angle_block(&scratch, 3, NULL, NULL, &out, &n_done) != PS_ERR_NULL
        || ps_chain_run_angle(&scratch, 3, times, values, NULL, NULL, &n_done) != PS_ERR_NULL
        || ps_chain_set_intended_angle(NULL, NULL) != PS_ERR_NULL
        || ps_chain_length_L0(&scratch, 0, L) != PS_ERR_NOT_RESET) {
        fail("NULL / unusable chain not refused", -1);
    }
    if (ps_chain_init(&chain, &good) != PS_OK
        || ps_chain_reset(&chain, 40, 0, NULL, &out) != PS_OK || !sample_finite(&out)) {
        fprintf(stderr, "the valid configuration was refused\n");
        return 2;
    }

    for (it = 0; it < iterations; ++it) {
        int op = below(100);
        memcpy(&before, &chain, sizeof chain);
        if (op < 1) { /* the stages on their own */
            ps_median m;
            ps_real coef[PS_FIT_MAX_COEFFS], x1, v1, a1;
            memset(&m, 0, sizeof m);
            (void)ps_median_push(&m, extreme()); /* never reset */
            (void)ps_median_push(NULL, extreme());
            status = ps_median_reset(&m, below(20) - 2, extreme());
            for (i = 0; i < 20; ++i) {
                (void)ps_median_push(&m, extreme());
            }
            for (i = 0; i < PS_FIT_MAX_COEFFS; ++i) {
                coef[i] = below(4) ? (ps_real)uniform() : extreme();
            }
            (void)ps_chebval(extreme(), below(8) ? coef : NULL, below(PS_FIT_MAX_COEFFS + 3) - 2);
            (void)ps_is_valid_reading(extreme(), extreme());
            ps_tracking_step(extreme(), extreme(), extreme(), extreme(), extreme(), extreme(),
                             below(2) ? &x1 : NULL, &v1, below(2) ? &a1 : NULL);
            (void)ps_chain_length_L0(&chain, extreme(), L);
            (void)ps_chain_length_L0(&chain, 1, NULL);
        } else if (op < 2) { /* a corrupted configuration */
            bad = good;
            corrupt(&bad);
            status = ps_chain_init(&scratch, &bad);
            if (status == PS_OK) {
                status = ps_chain_reset(&scratch, random_angle(), next_time(0), NULL, &out);
                if (status == PS_OK) {
                    status = ps_chain_push_counts(&scratch, 0.5, next_counts(500), &out);
                }
            }
        } else if (op < 5) { /* reset, at an angle or at lengths */
            angle = random_angle();
            random_lengths(L);
            status = ps_chain_reset(&chain, angle,
                                    below(4) ? (fabs(t) < 1e6 ? t + 0.002 : 0.0) : next_time(t),
                                    below(2) ? L : NULL, &out);
            if (status == PS_OK) {
                t = chain.state.t_s;
                if (!sample_finite(&out)) {
                    fail("reset output not finite", it);
                }
            }
        } else if (op < 9) { /* the switch */
            angle = random_angle();
            status = ps_chain_set_intended_angle(&chain, below(3) ? &angle : NULL);
        } else if (op < 85) { /* single pushes */
            ps_time tn = next_time(t);
            int kind = below(3);
            if (kind == 0) {
                counts = next_counts(counts);
                status = ps_chain_push_counts(&chain, tn, counts, below(10) ? &out : NULL);
            } else if (kind == 1) {
                status = ps_chain_push_angle(&chain, tn, random_angle(), &out);
            } else {
                random_lengths(L);
                angle = random_angle();
                status = ps_chain_push_lengths(&chain, tn, L, below(2) ? &angle : NULL, &out);
            }
        } else { /* blocks, including empty and negative sizes */
            int kind = below(3);
            n = below(25) - 1;
            for (i = 0; i < n && i < 24; ++i) {
                times[i] = next_time(i ? times[i - 1] : t);
                counts = next_counts(counts);
                if (kind == 2) {
                    random_lengths(&values[2 * i]);
                } else {
                    values[i] = kind == 0 ? counts : random_angle();
                }
            }
            for (i = 0; i < 24; ++i) {
                intended[i] = below(3) ? (ps_real)nan("") : random_angle();
            }
            if (below(2)) {
                if (kind == 0) {
                    status = ps_chain_push_counts_block(&chain, n, times, values, &out, &n_done);
                } else if (kind == 1) {
                    status = ps_chain_push_angle_block(&chain, n, times, values, &out, &n_done);
                } else {
                    status = ps_chain_push_lengths_block(&chain, n, times, values, &out,
                                                         &n_done);
                }
            } else {
                const ps_real *sw = below(2) ? intended : NULL;
                if (kind == 0) {
                    status = ps_chain_run_counts(&chain, n, times, values, sw, table, &n_done);
                } else if (kind == 1) {
                    status = ps_chain_run_angle(&chain, n, times, values, sw, table, &n_done);
                } else {
                    status = ps_chain_run_lengths(&chain, n, times, values, sw, table, &n_done);
                }
                for (i = 0; i < n_done; ++i) {
                    if (!sample_finite(&table[i])) {
                        fail("a run output is not finite", it);
                    }
                }
            }
            if (n_done < 0 || n_done > (n > 0 ? n : 0)) {
                fail("n_done out of range", it);
            }
        }
        if (!documented(status)) {
            fail("undocumented status", it);
            status = 0;
        }
        if (status == PS_ERR_ANGLE_RANGE || status == PS_ERR_INTERVAL) {
            fail("an angle refused or an interval too long (they are clamped / restart)", it);
        }
        statuses[status] += 1;
        if (status != PS_OK && op >= 9 && op < 85
            && memcmp(&before.state, &chain.state, sizeof chain.state) != 0) {
            fail("a failing push changed the chain", it);
        }
        if (op >= 9 && chain.stage == 2 && before.stage == 2) {
            accepted_total += chain.state.counters.accepted - before.state.counters.accepted;
            restarts_total += chain.state.counters.restarts - before.state.counters.restarts;
        }
        if (chain.stage == 2) {
            t = chain.state.t_s;
            if (!sample_finite(&chain.state.last)) {
                fail("the chain's output is not finite", it);
            }
        }
    }
    printf("fuzz_chain: %ld iterations, %d contract failures, statuses:", iterations, failures);
    for (i = 0; i <= PS_ERR_INTERVAL; ++i) {
        printf(" %d:%ld", i, statuses[i]);
    }
    printf(", accepted samples %lu, restarts %lu\n", accepted_total, restarts_total);
    return failures == 0 ? 0 : 1;
}
