/*
 * fuzz_stim.c -- randomized robustness driver for the stimulator stage (stimulation.c), built
 * by tests/test_c_stimulation.py with AddressSanitizer and UndefinedBehaviorSanitizer.
 *
 * usage: fuzz_stim SEED ITERATIONS
 *
 * Every iteration draws a configuration (valid, or with one field broken), a state set up by
 * ps_stim_init (or ps_stim_fx_init from ps_stim_fx_config_init), then a few steps with rates
 * that are valid, negative, huge, NaN or infinite (int32 extremes in the fixed form),
 * intervals valid or not and an event buffer of random capacity (0 .. enough). It checks the
 * header's promises and exits 1 with a message on the first broken one:
 *   - every status is one of enum ps_status;
 *   - a failing step leaves the state byte for byte as it was and reports 0 events;
 *   - a successful step writes at most `capacity` events, in time order, each inside the
 *     interval, on a valid channel, with its amplitude within the channel's range, its two
 *     phases equal, a channel's pulses at least its pulse duration apart, and any two pulses
 *     at least 1/max_total_rate_pps apart.
 */
#include "proprio.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define CAPACITY 256

/* The driver's draws come from the library's own counter-based hash (its SplitMix64
 * finaliser is checked against a reference in tests/test_stimulation.py). */
typedef struct rng { uint64_t seed, counter; } rng;

static uint64_t next_u64(rng *r) { return ps_stim_bits(r->seed, 0xF022u, r->counter++); }

static double uniform(rng *r, double lo, double hi)
{
    double u = (double)(next_u64(r) >> 11) / 9007199254740992.0; /* [0, 1) */
    return lo + (hi - lo) * u;
}

static int below(rng *r, int n) { return (int)(next_u64(r) % (unsigned long long)n); }

static void fail(const char *what, long iteration)
{
    printf("FAIL iteration %ld: %s\n", iteration, what);
    exit(1);
}

static ps_stim_config draw_config(rng *r)
{
    ps_stim_config c;
    int k;
    memset(&c, 0, sizeof c);
    c.n_channels = 1 + below(r, PS_STIM_MAX_CHANNELS);
    c.mode = below(r, 4);
    c.gamma_shape = 1 + below(r, 4);
    c.min_interval_us = below(r, 3) ? 0 : below(r, 500);
    for (k = 0; k < c.n_channels; ++k) {
        c.channel[k].threshold_uA = 1 + below(r, 100);
        c.channel[k].max_uA = c.channel[k].threshold_uA + below(r, 200);
        c.channel[k].phase_us = 20 + below(r, 300);
        c.channel[k].gap_us = below(r, 100);
        c.channel[k].area_cm2 = uniform(r, 1e-4, 1e-2);
    }
    c.max_rate_pps = uniform(r, 10.0, 1000.0);
    c.max_total_rate_pps = below(r, 2) ? 0.0 : uniform(r, 5.0, 5000.0);
    c.shannon_k = 1.85;
    c.max_charge_nC = 1e3;
    c.full_scale_pps = uniform(r, 1.0, 500.0);
    c.full_scale_change_pps_s = uniform(r, 10.0, 1e5);
    c.carrier_pps = uniform(r, 1.0, c.max_rate_pps);
    c.rate_level = uniform(r, 0.0, 2.0);
    c.rate_change = uniform(r, 0.0, 2.0);
    c.amp_level = uniform(r, 0.0, 2.0);
    c.amp_change = uniform(r, 0.0, 2.0);
    c.dead_time_s = uniform(r, 1e-3, 0.95 / c.max_rate_pps);
    c.seed = next_u64(r);
    switch (below(r, 8)) {  /* sometimes break one field */
    case 0: c.channel[0].area_cm2 = 1e-7; break;
    case 1: c.max_rate_pps = NAN; break;
    case 2: c.channel[0].threshold_uA = c.channel[0].max_uA + 1; break;
    case 3: c.dead_time_s = 1e-6; break;
    default: break;
    }
    return c;
}

static double draw_rate(rng *r)
{
    switch (below(r, 10)) {
    case 0: return NAN;
    case 1: return below(r, 2) ? INFINITY : -INFINITY;
    case 2: return -uniform(r, 0.0, 1e3);
    case 3: return uniform(r, 1e3, 1e308);
    default: return uniform(r, 0.0, 400.0);
    }
}

static int is_status(int code) { return code >= PS_OK && code <= PS_ERR_CHARGE; }

static void check_events(const ps_stim_config *c, const ps_pulse *ev, long n, double t0,
                         double t1, ps_time *last, ps_time *last_any, long it)
{
    long i;
    double spacing = c->max_total_rate_pps > 0 ? 1.0 / c->max_total_rate_pps : 0.0;
    for (i = 0; i < n; ++i) {
        int k = ev[i].channel;
        const ps_stim_channel *ch;
        if (k < 0 || k >= c->n_channels) fail("channel out of range", it);
        ch = &c->channel[k];
        if (!(ev[i].time_s >= t0 && ev[i].time_s < t1)) fail("event outside the interval", it);
        if (i > 0 && ev[i].time_s < ev[i - 1].time_s) fail("events out of order", it);
        if (ev[i].amplitude_uA < ch->threshold_uA || ev[i].amplitude_uA > ch->max_uA)
            fail("amplitude outside the channel's range", it);
        if (ev[i].cathodic_us != ev[i].anodic_us || ev[i].cathodic_us != ch->phase_us)
            fail("phases differ", it);
        if (ev[i].time_s - last[k] < (2 * ch->phase_us + ch->gap_us + c->min_interval_us) * 1e-6
            * (1 - 1e-12))
            fail("a channel's pulses overlap", it);
        if (ev[i].time_s - *last_any < spacing * (1 - 1e-12)) fail("total rate exceeded", it);
        last[k] = ev[i].time_s;
        *last_any = ev[i].time_s;
    }
}

static void fuzz_double(rng *r, const ps_stim_config *c, long it, long *ok, long *refused)
{
    ps_stim_state s, before;
    ps_pulse ev[CAPACITY];
    ps_time last[PS_STIM_MAX_CHANNELS], last_any = -INFINITY;
    double rates[PS_STIM_MAX_CHANNELS];
    int code = ps_stim_init(&s, c, uniform(r, -10.0, 10.0)), step, k;
    long n;
    if (!is_status(code)) fail("init status", it);
    if (code != PS_OK) { ++*refused; return; }
    for (k = 0; k < PS_STIM_MAX_CHANNELS; ++k) last[k] = -INFINITY;
    for (step = 0; step < 20; ++step) {
        double dt = below(r, 20) ? uniform(r, 1e-4, 0.05) : (below(r, 2) ? -1.0 : NAN);
        long capacity = below(r, 4) ? CAPACITY : below(r, 8);
        double t0 = s.t_s;
        for (k = 0; k < c->n_channels; ++k) rates[k] = draw_rate(r);
        memcpy(&before, &s, sizeof s);
        code = ps_stim_step(&s, c, rates, dt, ev, capacity, &n);
        if (!is_status(code)) fail("step status", it);
        if (code != PS_OK) {
            if (memcmp(&before, &s, sizeof s) != 0 || n != 0) fail("a failed step changed", it);
            ++*refused;
            continue;
        }
        if (n > capacity) fail("more events than capacity", it);
        check_events(c, ev, n, t0, s.t_s, last, &last_any, it);
        ++*ok;
    }
}

static void fuzz_fixed(rng *r, const ps_stim_config *c, long it, long *ok, long *refused)
{
    ps_stim_fx_config q;
    ps_stim_fx_state s, before;
    ps_pulse_fx ev[CAPACITY];
    int32_t rates[PS_STIM_MAX_CHANNELS];
    int code = ps_stim_fx_config_init(&q, c), step, k;
    long n, i;
    if (!is_status(code)) fail("fx config status", it);
    if (code != PS_OK || ps_stim_fx_init(&s, &q, (int64_t)below(r, 1000000)) != PS_OK) {
        ++*refused;
        return;
    }
    for (step = 0; step < 20; ++step) {
        int32_t dt = below(r, 20) ? 100 + below(r, 50000) : (below(r, 2) ? 0 : 2000000);
        long capacity = below(r, 4) ? CAPACITY : below(r, 8);
        for (k = 0; k < c->n_channels; ++k)
            rates[k] = below(r, 8) ? (int32_t)below(r, 400 << 16)
                                   : (below(r, 2) ? INT32_MAX : INT32_MIN);
        memcpy(&before, &s, sizeof s);
        code = ps_stim_fx_step(&s, &q, rates, dt, ev, capacity, &n);
        if (!is_status(code)) fail("fx step status", it);
        if (code != PS_OK) {
            if (memcmp(&before, &s, sizeof s) != 0 || n != 0) fail("a failed fx step changed", it);
            ++*refused;
            continue;
        }
        if (n > capacity) fail("more fx events than capacity", it);
        for (i = 0; i < n; ++i) {
            const ps_pulse_fx *p = &ev[i];
            if (p->channel < 0 || p->channel >= q.n_channels) fail("fx channel", it);
            if (p->amplitude_uA < q.threshold_uA[p->channel] || p->amplitude_uA > q.max_uA[p->channel])
                fail("fx amplitude", it);
            if (p->time_us < before.t_us || p->time_us >= s.t_us) fail("fx event time", it);
            if (i > 0 && p->time_us < ev[i - 1].time_us) fail("fx order", it);
        }
        ++*ok;
    }
}

int main(int argc, char **argv)
{
    rng r;
    long iterations, it, ok = 0, refused = 0;
    if (argc != 3) {
        fprintf(stderr, "usage: %s SEED ITERATIONS\n", argv[0]);
        return 2;
    }
    r.seed = strtoull(argv[1], NULL, 10);
    r.counter = 0;
    iterations = strtol(argv[2], NULL, 10);
    for (it = 0; it < iterations; ++it) {
        ps_stim_config c = draw_config(&r);
        if (below(&r, 2))
            fuzz_double(&r, &c, it, &ok, &refused);
        else
            fuzz_fixed(&r, &c, it, &ok, &refused);
    }
    if (ps_stim_step(NULL, NULL, NULL, 0.01, NULL, 0, NULL) != PS_ERR_NULL)
        fail("NULL step", -1);
    printf("iterations=%ld ok=%ld refused=%ld\n", iterations, ok, refused);
    return 0;
}
