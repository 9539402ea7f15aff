/*
 * stimulation.c -- the stimulator stage (proprio.h section 4): afferent rates into
 * charge-balanced pulse events, the same operations in the same order as
 * spindle/stimulation/encoder.py and generator.py, channel by channel.
 */
#include "proprio.h"

#include <math.h>
#include <stddef.h>

#define LN2 0.6931471805599453
#define SQRT_HALF 0.7071067811865476
#define ATANH_TERMS 12
#define NO_RATE ((double)NAN) /* no previous rate (NAN is a float constant) */

/* ---- the counter-based generator (generator.py) ---- */

static uint64_t mix(uint64_t x)
{
    uint64_t z = x + 0x9E3779B97F4A7C15ULL;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

uint64_t ps_stim_bits(uint64_t seed, uint64_t channel, uint64_t index)
{
    return mix(mix(mix(seed) ^ channel) ^ index);
}

double ps_stim_uniform(uint64_t seed, uint64_t channel, uint64_t index)
{
    return ((double)(ps_stim_bits(seed, channel, index) >> 12) + 0.5) * (1.0 / 4503599627370496.0);
}

double ps_stim_log_unit(double u)
{
    int e = 0;
    double m = frexp(u, &e), f, s, s2, series, ed;
    int k;
    if (m < SQRT_HALF) {
        m = m * 2.0;
        e = e - 1;
    }
    ed = (double)e;
    f = m - 1.0;
    s = f / (2.0 + f);
    s2 = s * s;
    series = 1.0 / (double)(2 * ATANH_TERMS - 1);
    for (k = ATANH_TERMS - 2; k >= 0; --k)
        series = series * s2 + 1.0 / (double)(2 * k + 1);
    return ed * LN2 + 2.0 * s * series;
}

double ps_stim_gamma_threshold(uint64_t seed, uint64_t channel, uint64_t draw, int32_t shape)
{
    uint64_t first = draw * (uint64_t)shape;
    double total = 0.0;
    int32_t j;
    for (j = 0; j < shape; ++j)
        total = total - ps_stim_log_unit(ps_stim_uniform(seed, channel, first + (uint64_t)j));
    return total / (double)shape;
}

/* ---- configuration (safety.py, config.py) ---- */

static int finite_in(double x, double lo, double hi) { return isfinite(x) && x >= lo && x <= hi; }

static double min_interval_s(const ps_stim_config *c, int k)
{
    const ps_stim_channel *ch = &c->channel[k];
    return (double)(2 * ch->phase_us + ch->gap_us + c->min_interval_us) * 1e-6;
}

static int channel_check(const ps_stim_config *c, int k)
{
    const ps_stim_channel *ch = &c->channel[k];
    double q_uC, kk;
    if (ch->threshold_uA < 1 || ch->max_uA > PS_STIM_MAX_AMPLITUDE_UA
        || ch->threshold_uA > ch->max_uA || ch->phase_us < 1 || ch->phase_us > PS_STIM_MAX_PHASE_US
        || ch->gap_us < 0 || ch->gap_us > PS_STIM_MAX_PHASE_US || !(isfinite(ch->area_cm2)
        && ch->area_cm2 > 0.0))
        return PS_ERR_CONFIG;
    q_uC = (double)((int64_t)ch->max_uA * ch->phase_us) * 1e-6;
    kk = log10(q_uC) + log10(q_uC / ch->area_cm2);
    if (q_uC * 1e3 > c->max_charge_nC || kk > c->shannon_k)
        return PS_ERR_CHARGE;
    if (min_interval_s(c, k) * c->max_rate_pps > 1.0)
        return PS_ERR_CONFIG;
    return PS_OK;
}

int ps_stim_config_check(const ps_stim_config *c)
{
    int k, code;
    if (c == NULL)
        return PS_ERR_NULL;
    if (c->n_channels < 1 || c->n_channels > PS_STIM_MAX_CHANNELS || c->mode < 0
        || c->mode > PS_STIM_MODE_BIOMIMETIC || c->min_interval_us < 0
        || c->min_interval_us > 1000000 || !finite_in(c->max_rate_pps, 1e-300, PS_STIM_MAX_RATE_PPS)
        || !finite_in(c->max_total_rate_pps, 0.0, 1e6) || !isfinite(c->shannon_k)
        || !finite_in(c->max_charge_nC, 1e-300, 1e6) || !finite_in(c->full_scale_pps, 1e-300, 1e300)
        || !finite_in(c->full_scale_change_pps_s, 1e-300, 1e300)
        || !finite_in(c->carrier_pps, 1e-300, 1e300) || !finite_in(c->rate_level, 0.0, 1e3)
        || !finite_in(c->rate_change, 0.0, 1e3) || !finite_in(c->amp_level, 0.0, 1e3)
        || !finite_in(c->amp_change, 0.0, 1e3) || !finite_in(c->dead_time_s, 1e-300, 1.0)
        || c->gamma_shape < 1 || c->gamma_shape > PS_STIM_MAX_GAMMA_SHAPE)
        return PS_ERR_CONFIG;
    for (k = 0; k < c->n_channels; ++k) {
        code = channel_check(c, k);
        if (code != PS_OK)
            return code;
    }
    if (c->mode == PS_STIM_MODE_AMPLITUDE && c->carrier_pps > c->max_rate_pps)
        return PS_ERR_CONFIG;
    if (c->mode == PS_STIM_MODE_STOCHASTIC) {
        if (c->max_rate_pps * c->dead_time_s >= 1.0)
            return PS_ERR_CONFIG;
        for (k = 0; k < c->n_channels; ++k)
            if (c->dead_time_s < min_interval_s(c, k))
                return PS_ERR_CONFIG;
    }
    return PS_OK;
}

int ps_stim_init(ps_stim_state *s, const ps_stim_config *c, ps_time t0_s)
{
    int k, j, code;
    if (s == NULL || c == NULL)
        return PS_ERR_NULL;
    code = ps_stim_config_check(c);
    if (code != PS_OK)
        return code;
    if (!isfinite(t0_s))
        return PS_ERR_NONFINITE;
    s->t_s = t0_s;
    s->last_any_s = -(double)INFINITY;
    for (k = 0; k < PS_STIM_MAX_CHANNELS; ++k) {
        int stochastic = c->mode == PS_STIM_MODE_STOCHASTIC && k < c->n_channels;
        s->phase[k] = 0.0;
        s->threshold[k] = stochastic
            ? ps_stim_gamma_threshold(c->seed, (uint64_t)k, 0, c->gamma_shape) : 1.0;
        s->draws[k] = stochastic ? 1u : 0u;
        s->resume_s[k] = t0_s;
        s->last_pulse_s[k] = -(double)INFINITY;
        s->previous_pps[k] = NO_RATE;
        for (j = 0; j < PS_STIM_COUNTERS; ++j)
            s->counts[k][j] = 0;
    }
    s->ready = 1;
    return PS_OK;
}

/* ---- one step (encoder.py) ---- */

/* What one channel asks for this interval: the rate rules and the mode's mapping. */
typedef struct drive {
    double pulse_pps, previous_pps;
    int32_t amplitude_uA;
    int rule;          /* -1 none, else the counter of the rate rule applied */
    int amp_clipped;
} drive;

static drive channel_drive(const ps_stim_config *c, int k, double previous, double r,
                           double dt_s)
{
    drive d;
    const ps_stim_channel *ch = &c->channel[k];
    double thr = (double)ch->threshold_uA, top = (double)ch->max_uA, level, change, amp_drive;
    int stopped = 0;
    d.rule = -1;
    d.amp_clipped = 0;
    d.previous_pps = previous;
    if (!isfinite(r)) {
        d.rule = PS_STIM_COUNT_RATE_NONFINITE;
        r = 0.0;
        stopped = 1;
        previous = NO_RATE;
    } else if (r < 0.0) {
        d.rule = PS_STIM_COUNT_RATE_NEGATIVE;
        r = 0.0;
    } else if (r > c->max_rate_pps) {
        d.rule = PS_STIM_COUNT_RATE_CLIPPED;
        r = c->max_rate_pps;
    }
    if (c->mode == PS_STIM_MODE_FREQUENCY || c->mode == PS_STIM_MODE_STOCHASTIC) {
        d.previous_pps = stopped ? NO_RATE : d.previous_pps;
        d.pulse_pps = r;
        d.amplitude_uA = ch->max_uA;
        return d;
    }
    level = r / c->full_scale_pps;
    level = level < 1.0 ? level : 1.0;
    if (c->mode == PS_STIM_MODE_AMPLITUDE) {
        d.pulse_pps = r > 0.0 ? c->carrier_pps : 0.0;
        amp_drive = r / c->full_scale_pps;
    } else {
        change = isnan(previous) ? 0.0 : fabs(r - previous) / dt_s;
        change = change / c->full_scale_change_pps_s;
        change = change < 1.0 ? change : 1.0;
        d.pulse_pps = c->rate_level * level + c->rate_change * change;
        d.pulse_pps = c->max_rate_pps * (d.pulse_pps < 1.0 ? d.pulse_pps : 1.0);
        amp_drive = c->amp_level * level + c->amp_change * change;
    }
    d.previous_pps = stopped ? NO_RATE : r;
    if (stopped)
        d.pulse_pps = 0.0;
    d.amp_clipped = amp_drive > 1.0 && d.pulse_pps > 0.0;
    d.amplitude_uA = (int32_t)floor(thr + (top - thr) * (amp_drive < 1.0 ? amp_drive : 1.0) + 0.5);
    return d;
}

/* One channel's pulse-rate integration over [t0, t1): the crossings' times into
 * out[i].time_s (if out is not NULL, at most `room`); returns their number. Advances `cl`. */
typedef struct channel_clock {
    double phase, threshold;
    ps_time resume_s;
    uint64_t draws;
} channel_clock;

static long channel_crossings(const ps_stim_config *c, int k, channel_clock *cl,
                              double pulse_pps, ps_time t0, ps_time t1, ps_pulse *out,
                              long room)
{
    int stochastic = c->mode == PS_STIM_MODE_STOCHASTIC;
    double dead = stochastic ? c->dead_time_s : 0.0;
    double rate = stochastic ? pulse_pps / (1.0 - pulse_pps * dead) : pulse_pps;
    ps_time tau = t0 > cl->resume_s ? t0 : cl->resume_s, cross;
    long n = 0;
    if (!(rate > 0.0))
        return 0;
    while (tau < t1) {
        cross = tau + (cl->threshold - cl->phase) / rate;
        if (cross < tau)
            cross = tau;
        if (!(cross < t1)) {
            cl->phase += rate * (t1 - tau);
            break;
        }
        if (out != NULL && n < room)
            out[n].time_s = cross;
        ++n;
        cl->phase = 0.0;
        if (stochastic) {
            cl->threshold = ps_stim_gamma_threshold(c->seed, (uint64_t)k, cl->draws,
                                                    c->gamma_shape);
            cl->draws += 1;
        }
        tau = cross + dead;
        cl->resume_s = tau;
    }
    return n;
}

/* Crossings are at least 1/max_rate (deterministic) or the dead time (stochastic) apart. */
static long max_events(const ps_stim_config *c, ps_time dt_s)
{
    double per = c->mode == PS_STIM_MODE_STOCHASTIC ? 1.0 / c->dead_time_s : c->max_rate_pps;
    return (long)c->n_channels * ((long)(dt_s * per) + 2);
}

long ps_stim_max_events(const ps_stim_config *c, ps_time dt_s)
{
    if (ps_stim_config_check(c) != PS_OK || !finite_in(dt_s, 1e-300, PS_STIM_MAX_DT_S))
        return -1;
    return max_events(c, dt_s);
}

static int before(const ps_pulse *a, const ps_pulse *b)
{
    return a->time_s < b->time_s || (a->time_s == b->time_s && a->channel < b->channel);
}

/* The candidates in time order (ties: lower channel), then the admission rules. */
static long admit(ps_stim_state *s, const ps_stim_config *c, ps_pulse *ev, long n)
{
    double spacing = c->max_total_rate_pps > 0.0 ? 1.0 / c->max_total_rate_pps : 0.0;
    long i, j, kept = 0;
    for (i = 1; i < n; ++i) {
        ps_pulse x = ev[i];
        for (j = i; j > 0 && before(&x, &ev[j - 1]); --j)
            ev[j] = ev[j - 1];
        ev[j] = x;
    }
    for (i = 0; i < n; ++i) {
        int k = ev[i].channel;
        ps_time t = ev[i].time_s;
        if (t - s->last_pulse_s[k] < min_interval_s(c, k)) {
            s->counts[k][PS_STIM_COUNT_DROPPED_INTERVAL] += 1;
        } else if (t - s->last_any_s < spacing) {
            s->counts[k][PS_STIM_COUNT_DROPPED_TOTAL_RATE] += 1;
        } else {
            s->last_pulse_s[k] = t;
            s->last_any_s = t;
            s->counts[k][PS_STIM_COUNT_PULSES] += 1;
            ev[kept++] = ev[i];
        }
    }
    return kept;
}

static long count_candidates(const ps_stim_state *s, const ps_stim_config *c,
                             const double *rates_pps, ps_time dt_s)
{
    long total = 0;
    int k;
    for (k = 0; k < c->n_channels; ++k) {
        drive d = channel_drive(c, k, s->previous_pps[k], rates_pps[k], dt_s);
        channel_clock cl;
        cl.phase = s->phase[k];
        cl.threshold = s->threshold[k];
        cl.resume_s = s->resume_s[k];
        cl.draws = s->draws[k];
        total += channel_crossings(c, k, &cl, d.pulse_pps, s->t_s, s->t_s + dt_s, NULL, 0);
    }
    return total;
}

int ps_stim_step(ps_stim_state *s, const ps_stim_config *c, const double *rates_pps,
                 ps_time dt_s, ps_pulse *events, long capacity, long *n_events)
{
    ps_time t0, t1;
    long n = 0, m, i;
    int k;
    if (n_events != NULL)
        *n_events = 0;
    if (s == NULL || c == NULL || rates_pps == NULL || (events == NULL && capacity > 0))
        return PS_ERR_NULL;
    if (s->ready != 1)
        return PS_ERR_NOT_RESET;
    if (!finite_in(dt_s, 1e-300, PS_STIM_MAX_DT_S))
        return PS_ERR_STEP;
    if (capacity < max_events(c, dt_s) && count_candidates(s, c, rates_pps, dt_s) > capacity)
        return PS_ERR_BUFFER_FULL;
    t0 = s->t_s;
    t1 = t0 + dt_s;
    for (k = 0; k < c->n_channels; ++k) {
        drive d = channel_drive(c, k, s->previous_pps[k], rates_pps[k], dt_s);
        channel_clock cl;
        if (d.rule >= 0)
            s->counts[k][d.rule] += 1;
        s->counts[k][PS_STIM_COUNT_AMPLITUDE_CLIPPED] += (uint64_t)d.amp_clipped;
        s->previous_pps[k] = d.previous_pps;
        cl.phase = s->phase[k];
        cl.threshold = s->threshold[k];
        cl.resume_s = s->resume_s[k];
        cl.draws = s->draws[k];
        m = channel_crossings(c, k, &cl, d.pulse_pps, t0, t1, events + n, capacity - n);
        for (i = n; i < n + m; ++i) {
            events[i].channel = k;
            events[i].amplitude_uA = d.amplitude_uA;
            events[i].cathodic_us = c->channel[k].phase_us;
            events[i].anodic_us = c->channel[k].phase_us;
            events[i].gap_us = c->channel[k].gap_us;
        }
        n += m;
        s->phase[k] = cl.phase;
        s->threshold[k] = cl.threshold;
        s->resume_s[k] = cl.resume_s;
        s->draws[k] = cl.draws;
    }
    n = admit(s, c, events, n);
    s->t_s = t1;
    if (n_events != NULL)
        *n_events = n;
    return PS_OK;
}

int ps_stim_run(ps_stim_state *s, const ps_stim_config *c, long n, const double *rates_pps,
                const ps_time *dt_s, ps_pulse *events, long capacity, long *n_events,
                long *n_done)
{
    long i, total = 0, got = 0;
    int code = PS_OK;
    if (n_done != NULL)
        *n_done = 0;
    if (n_events != NULL)
        *n_events = 0;
    if (s == NULL || c == NULL || (n > 0 && (rates_pps == NULL || dt_s == NULL)))
        return PS_ERR_NULL;
    if (n < 0)
        return PS_ERR_ARGUMENT;
    for (i = 0; i < n; ++i) {
        code = ps_stim_step(s, c, rates_pps + i * c->n_channels, dt_s[i],
                            events == NULL ? NULL : events + total, capacity - total, &got);
        if (code != PS_OK)
            break;
        total += got;
        if (n_done != NULL)
            *n_done = i + 1;
    }
    if (n_events != NULL)
        *n_events = total;
    return code;
}

/* ---- fixed point (the device build): the same steps in integers ---- */

#define FX_ONE PS_STIM_FX_PULSE
#define FX_Q24 ((int64_t)1 << 24)
#define FX_LN2_Q30 744261118LL /* round(ln 2 * 2^30) */
#define FX_LOG_TERMS 12
#define FX_NO_PULSE (-((int64_t)1 << 60))

static int32_t round_q16(double x) { return (int32_t)floor(x * 65536.0 + 0.5); }

int ps_stim_fx_config_init(ps_stim_fx_config *q, const ps_stim_config *c)
{
    ps_stim_fx_config out;
    int k, code;
    if (q == NULL || c == NULL)
        return PS_ERR_NULL;
    code = ps_stim_config_check(c);
    if (code != PS_OK)
        return code;
    /* Q16 rates in int32 (<= 32767 pps), whole pps/s and µs in int32 */
    if (c->full_scale_pps > 32767.0 || c->full_scale_pps < 1.0 / 65536.0
        || c->full_scale_change_pps_s < 1.0 || c->full_scale_change_pps_s > 2e9
        || c->dead_time_s < 1e-6 || c->rate_level > 3e4 || c->rate_change > 3e4
        || c->amp_level > 3e4 || c->amp_change > 3e4
        || (c->max_total_rate_pps > 0.0 && c->max_total_rate_pps < 1e-3))
        return PS_ERR_CONFIG;
    out.n_channels = c->n_channels;
    out.mode = c->mode;
    out.gamma_shape = c->gamma_shape;
    for (k = 0; k < PS_STIM_MAX_CHANNELS; ++k) {
        const ps_stim_channel *ch = &c->channel[k];
        int used = k < c->n_channels;
        out.threshold_uA[k] = used ? ch->threshold_uA : 0;
        out.max_uA[k] = used ? ch->max_uA : 0;
        out.phase_us[k] = used ? ch->phase_us : 0;
        out.gap_us[k] = used ? ch->gap_us : 0;
        out.min_interval_us[k] = used ? 2 * ch->phase_us + ch->gap_us + c->min_interval_us : 0;
    }
    out.max_rate_q16 = round_q16(c->max_rate_pps);
    out.carrier_q16 = round_q16(c->carrier_pps);
    out.full_scale_q16 = round_q16(c->full_scale_pps);
    out.full_scale_change_pps_s = (int32_t)floor(c->full_scale_change_pps_s + 0.5);
    out.rate_level_q16 = round_q16(c->rate_level);
    out.rate_change_q16 = round_q16(c->rate_change);
    out.amp_level_q16 = round_q16(c->amp_level);
    out.amp_change_q16 = round_q16(c->amp_change);
    out.dead_us = (int32_t)floor(c->dead_time_s * 1e6 + 0.5);
    out.min_total_us = c->max_total_rate_pps > 0.0
        ? (int32_t)ceil(1e6 / c->max_total_rate_pps) : 0;
    out.seed = c->seed;
    /* r / (1 - r dead) at most 100 r: the phase's int64 arithmetic keeps its bounds */
    if (c->mode == PS_STIM_MODE_STOCHASTIC
        && 100 * (int64_t)out.max_rate_q16 * out.dead_us > 99 * FX_ONE)
        return PS_ERR_CONFIG;
    *q = out;
    return PS_OK;
}

int64_t ps_stim_fx_neg_log(uint64_t bits)
{
    /* u = m / 2^53 with m = 2 (bits >> 12) + 1 (the double form's uniform, exactly);
     * -ln u = (53 - p) ln 2 - ln y with y = m / 2^p in [1, 2), p the top bit of m */
    uint64_t m = 2u * (bits >> 12) + 1u, y, one = (uint64_t)1 << 32;
    int p = 0, k;
    int64_t s, s2, acc;
    while ((m >> (p + 1)) != 0)
        ++p;
    y = p >= 32 ? m >> (p - 32) : m << (32 - p);         /* y in Q32 */
    s = (int64_t)(((y - one) << 30) / (y + one));       /* (y-1)/(y+1) in Q30, <= 1/3 */
    s2 = (s * s) >> 30;
    acc = ((int64_t)1 << 30) / (2 * FX_LOG_TERMS - 1);
    for (k = FX_LOG_TERMS - 2; k >= 0; --k)
        acc = ((acc * s2) >> 30) + ((int64_t)1 << 30) / (2 * k + 1);
    return (int64_t)(53 - p) * FX_LN2_Q30 - ((2 * s * acc) >> 30);
}

static int64_t fx_threshold(const ps_stim_fx_config *q, int k, uint64_t draw)
{
    uint64_t first = draw * (uint64_t)q->gamma_shape;
    int64_t total = 0;
    int32_t j;
    for (j = 0; j < q->gamma_shape; ++j)
        total += ps_stim_fx_neg_log(ps_stim_bits(q->seed, (uint64_t)k, first + (uint64_t)j));
    /* Q30 -> pulses of FX_ONE = 2^22 * 15625: x * 15625 / 2^8, rounded */
    return (total * 15625 + 128 * q->gamma_shape) / (256 * q->gamma_shape);
}

int ps_stim_fx_init(ps_stim_fx_state *s, const ps_stim_fx_config *q, int64_t t0_us)
{
    int k, j;
    if (s == NULL || q == NULL)
        return PS_ERR_NULL;
    if (q->n_channels < 1 || q->n_channels > PS_STIM_MAX_CHANNELS || q->mode < 0
        || q->mode > PS_STIM_MODE_BIOMIMETIC || q->gamma_shape < 1
        || q->gamma_shape > PS_STIM_MAX_GAMMA_SHAPE)
        return PS_ERR_CONFIG;
    s->t_us = t0_us;
    s->last_any_us = FX_NO_PULSE;
    for (k = 0; k < PS_STIM_MAX_CHANNELS; ++k) {
        int stochastic = q->mode == PS_STIM_MODE_STOCHASTIC && k < q->n_channels;
        s->phase[k] = 0;
        s->threshold[k] = stochastic ? fx_threshold(q, k, 0) : FX_ONE;
        s->draws[k] = stochastic ? 1u : 0u;
        s->resume_us[k] = t0_us;
        s->last_pulse_us[k] = FX_NO_PULSE;
        s->previous_q16[k] = -1;
        for (j = 0; j < PS_STIM_COUNTERS; ++j)
            s->counts[k][j] = 0;
    }
    s->ready = 1;
    return PS_OK;
}

typedef struct drive_fx {
    int64_t pulse_q16;
    int32_t amplitude_uA, previous_q16;
    int rule, amp_clipped;
} drive_fx;

static int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }
/* a / b and a / 2^k rounded to nearest, for a >= 0, b > 0 */
static int64_t div_round(int64_t a, int64_t b) { return (a + b / 2) / b; }
static int64_t shift_round(int64_t a, int k) { return (a + ((int64_t)1 << (k - 1))) >> k; }

/* The amplitude and biomimetic drives of a rate r already within the rules (into *d, whose
 * rule and previous_q16 are set). */
static void graded_drive_fx(const ps_stim_fx_config *q, int k, int32_t previous, int32_t r,
                            int32_t dt_us, drive_fx *d)
{
    int64_t level, change, drive, x;
    int32_t thr = q->threshold_uA[k], top = q->max_uA[k];
    /* drives as fractions in Q24, every quotient and shift rounded to nearest: Q16 or
     * truncation would bias the biomimetic rate and let its pulses drift by tens of µs
     * over seconds against the double form */
    level = min64(div_round(((int64_t)r << 24), q->full_scale_q16), FX_Q24);
    if (q->mode == PS_STIM_MODE_AMPLITUDE) {
        d->pulse_q16 = r > 0 ? q->carrier_q16 : 0;
        drive = div_round(((int64_t)r << 24), q->full_scale_q16);
    } else {
        int64_t diff = previous < 0 ? 0 : (int64_t)(r > previous ? r - previous : previous - r);
        /* |dr| / dt / full scale: Q16 pps over µs, times 10^6 = 15625 * 2^6, into Q24 */
        change = min64(div_round(diff * 15625 << 14,
                                 (int64_t)dt_us * q->full_scale_change_pps_s), FX_Q24);
        x = min64(shift_round((int64_t)q->rate_level_q16 * level
                              + (int64_t)q->rate_change_q16 * change, 16), FX_Q24);
        d->pulse_q16 = shift_round((int64_t)q->max_rate_q16 * x, 24);
        drive = shift_round((int64_t)q->amp_level_q16 * level
                            + (int64_t)q->amp_change_q16 * change, 16);
    }
    d->amp_clipped = drive > FX_Q24 && d->pulse_q16 > 0;
    d->amplitude_uA = thr + (int32_t)(((int64_t)(top - thr) * min64(drive, FX_Q24)
                                       + (FX_Q24 >> 1)) >> 24);
}

/* The rate's rules (negative: 0, above max_rate: clipped) and the drive; inline for the
 * frequency and stochastic modes' few operations (the call cost ~30 instructions per channel
 * and sample on the Cortex-M0+). Into *out: a struct returned by value costs a copy. */
#if defined(__GNUC__)
__attribute__((always_inline))
#endif
static inline void channel_drive_fx(const ps_stim_fx_config *q, int k, int32_t previous,
                                    int32_t r, int32_t dt_us, drive_fx *out)
{
    out->rule = -1;
    out->amp_clipped = 0;
    if (r < 0) {
        out->rule = PS_STIM_COUNT_RATE_NEGATIVE;
        r = 0;
    } else if (r > q->max_rate_q16) {
        out->rule = PS_STIM_COUNT_RATE_CLIPPED;
        r = q->max_rate_q16;
    }
    out->previous_q16 = r;
    if (q->mode == PS_STIM_MODE_FREQUENCY || q->mode == PS_STIM_MODE_STOCHASTIC) {
        out->pulse_q16 = r;
        out->amplitude_uA = q->max_uA[k];
        return;
    }
    graded_drive_fx(q, k, previous, r, dt_us, out);
}

/* a b for int32 a, b (ps_fx_mul_wide: no 64 x 64 multiply helper on the device) */
static int64_t wide_product(int32_t a, int32_t b)
{
    ps_fx_wide p = ps_fx_mul_wide(a, b);
    return (int64_t)(((uint64_t)(uint32_t)p.hi << 32) | p.lo);
}

typedef struct clock_fx {
    int64_t phase, threshold, resume_us;
    uint64_t draws;
} clock_fx;

/* No crossing in [tau, t1) (ceil(need / rate) >= t1 - tau) is need > rate (t1 - tau - 1): the
 * common case of a sample's interval, decided without the 64-bit division (~200 instructions
 * on a core without a divider); then the phase advances to t1 and 1 is returned. rate > 0. */
static int no_crossing_fx(int64_t *phase, int64_t need, int64_t rate, int64_t tau, int64_t t1)
{
    const int64_t short_of_end = rate <= INT32_MAX
                                     ? wide_product((int32_t)rate, (int32_t)(t1 - tau - 1))
                                     : rate * (t1 - tau - 1);
    if (need <= short_of_end)
        return 0;
    *phase += short_of_end + rate;
    return 1;
}

/* A deterministic channel (no dead time) with no crossing in the step, its phase advanced in
 * place (1), without the clock's copies and the crossings' call: the usual sample of the
 * device (measured on the Cortex-M0+ system firmware, bench_embedded --system-only: the
 * pulse encoder's 1261 instructions per sample for four channels became 1003, 877 with the
 * drive inline); 0: the channel needs channel_crossings_fx. */
static int quiet_channel_fx(ps_stim_fx_state *s, const ps_stim_fx_config *q, int k,
                            int64_t rate, int64_t t0, int64_t t1)
{
    const int64_t tau = t0 > s->resume_us[k] ? t0 : s->resume_us[k];
    if (q->mode == PS_STIM_MODE_STOCHASTIC)
        return 0;
    if (rate <= 0 || tau >= t1)
        return 1; /* channel_crossings_fx would leave the clock as it is */
    return no_crossing_fx(&s->phase[k], s->threshold[k] - s->phase[k], rate, tau, t1);
}

static long channel_crossings_fx(const ps_stim_fx_config *q, int k, clock_fx *cl,
                                 int64_t pulse_q16, int64_t t0, int64_t t1, ps_pulse_fx *out,
                                 long room)
{
    int stochastic = q->mode == PS_STIM_MODE_STOCHASTIC;
    int64_t dead = stochastic ? q->dead_us : 0, rate = pulse_q16, tau, need, offset, cross;
    long n = 0;
    if (stochastic && pulse_q16 > 0)  /* r / (1 - r dead), in the phase's units per µs */
        rate = pulse_q16 * (FX_ONE >> 10) / ((FX_ONE - pulse_q16 * dead) >> 10);
    if (rate <= 0)
        return 0;
    tau = t0 > cl->resume_us ? t0 : cl->resume_us;
    while (tau < t1) {
        need = cl->threshold - cl->phase;
        if (no_crossing_fx(&cl->phase, need, rate, tau, t1))
            break;
        offset = need <= 0 ? 0 : (need + rate - 1) / rate;
        cross = tau + offset;
        if (out != NULL && n < room)
            out[n].time_us = cross;
        ++n;
        cl->phase = offset * rate - need; /* the overshoot: the integral stays exact */
        if (stochastic) {
            cl->threshold = fx_threshold(q, k, cl->draws);
            cl->draws += 1;
        }
        tau = cross + dead;
        cl->resume_us = tau;
    }
    return n;
}

static int before_fx(const ps_pulse_fx *a, const ps_pulse_fx *b)
{
    return a->time_us < b->time_us || (a->time_us == b->time_us && a->channel < b->channel);
}

static long admit_fx(ps_stim_fx_state *s, const ps_stim_fx_config *q, ps_pulse_fx *ev, long n)
{
    long i, j, kept = 0;
    for (i = 1; i < n; ++i) {
        ps_pulse_fx x = ev[i];
        for (j = i; j > 0 && before_fx(&x, &ev[j - 1]); --j)
            ev[j] = ev[j - 1];
        ev[j] = x;
    }
    for (i = 0; i < n; ++i) {
        int k = ev[i].channel;
        int64_t t = ev[i].time_us;
        if (t - s->last_pulse_us[k] < q->min_interval_us[k]) {
            s->counts[k][PS_STIM_COUNT_DROPPED_INTERVAL] += 1;
        } else if (t - s->last_any_us < q->min_total_us) {
            s->counts[k][PS_STIM_COUNT_DROPPED_TOTAL_RATE] += 1;
        } else {
            s->last_pulse_us[k] = t;
            s->last_any_us = t;
            s->counts[k][PS_STIM_COUNT_PULSES] += 1;
            ev[kept++] = ev[i];
        }
    }
    return kept;
}

static void clock_of(const ps_stim_fx_state *s, int k, clock_fx *cl)
{
    cl->phase = s->phase[k];
    cl->threshold = s->threshold[k];
    cl->resume_us = s->resume_us[k];
    cl->draws = s->draws[k];
}

/* A bound of one step's pulses (ps_stim_max_events in integers): crossings are at least
 * 1/max_rate apart (deterministic) or the dead time apart (stochastic). */
static long fx_max_events(const ps_stim_fx_config *q, int32_t dt_us)
{
    int64_t span = wide_product(dt_us, q->max_rate_q16), per;
    if (q->mode == PS_STIM_MODE_STOCHASTIC)
        per = (int64_t)dt_us / (q->dead_us > 0 ? q->dead_us : 1);
    else /* below one pulse's phase (a sample's interval): 0 without the 64-bit division */
        per = span < FX_ONE ? 0 : span / FX_ONE;
    return (long)q->n_channels * (long)(per + 2);
}

int ps_stim_fx_step(ps_stim_fx_state *s, const ps_stim_fx_config *q, const int32_t *rates_q16,
                    int32_t dt_us, ps_pulse_fx *events, long capacity, long *n_events)
{
    int64_t t0, t1;
    long n = 0, m, i;
    int k;
    if (n_events != NULL)
        *n_events = 0;
    if (s == NULL || q == NULL || rates_q16 == NULL || (events == NULL && capacity > 0))
        return PS_ERR_NULL;
    if (s->ready != 1)
        return PS_ERR_NOT_RESET;
    if (dt_us < 1 || dt_us > 1000000)
        return PS_ERR_STEP;
    t0 = s->t_us;
    t1 = t0 + dt_us;
    if (capacity < fx_max_events(q, dt_us)) {  /* dry run: the pulses must fit */
        for (k = 0; k < q->n_channels; ++k) {
            drive_fx d;
            clock_fx cl;
            channel_drive_fx(q, k, s->previous_q16[k], rates_q16[k], dt_us, &d);
            clock_of(s, k, &cl);
            n += channel_crossings_fx(q, k, &cl, d.pulse_q16, t0, t1, NULL, 0);
        }
        if (n > capacity)
            return PS_ERR_BUFFER_FULL;
        n = 0;
    }
    for (k = 0; k < q->n_channels; ++k) {
        drive_fx d;
        clock_fx cl;
        channel_drive_fx(q, k, s->previous_q16[k], rates_q16[k], dt_us, &d);
        if (d.rule >= 0)
            s->counts[k][d.rule] += 1;
        s->counts[k][PS_STIM_COUNT_AMPLITUDE_CLIPPED] += (uint32_t)d.amp_clipped;
        s->previous_q16[k] = d.previous_q16;
        if (quiet_channel_fx(s, q, k, d.pulse_q16, t0, t1))
            continue;
        clock_of(s, k, &cl);
        m = channel_crossings_fx(q, k, &cl, d.pulse_q16, t0, t1, events + n, capacity - n);
        for (i = n; i < n + m; ++i) {
            events[i].channel = k;
            events[i].amplitude_uA = d.amplitude_uA;
            events[i].cathodic_us = q->phase_us[k];
            events[i].anodic_us = q->phase_us[k];
            events[i].gap_us = q->gap_us[k];
        }
        n += m;
        s->phase[k] = cl.phase;
        s->threshold[k] = cl.threshold;
        s->resume_us[k] = cl.resume_us;
        s->draws[k] = cl.draws;
    }
    n = admit_fx(s, q, events, n);
    s->t_us = t1;
    if (n_events != NULL)
        *n_events = n;
    return PS_OK;
}
