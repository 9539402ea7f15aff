/*
 * chain.c -- the on-prosthesis chain of one arm: encoder counts in, Ia and II out.
 *
 *   counts -> median filter -> f(x) -> angle -> fitted BRA/TRImed lengths -> tracking
 *   low-pass (L, dL/dt) -> PI template -> gamma_s = h, gamma_d = g -> spindles -> Ia, II
 *   load word -> torque -> BRA/TRImed tendon forces (moment arms) -> tendon organs -> Ib
 *
 * A port of spindle/chain/ (arm.py with sensor.py, length_model.py, conditioning.py and
 * fusimotor.py), in their order of operations, so the double build agrees with the numpy
 * chain to round-off. Sections follow those modules.
 *
 * Both chains are atomic: a push either completes or leaves the chain exactly as it was
 * (here it works on a copy of the state). Intervals longer than max_bridge_s restart the
 * chain at rest, so every push costs bounded work; PS_ERR_INTERVAL remains as a guard that a
 * configuration ps_chain_init accepted never reaches.
 */
#include "proprio.h"

#include <float.h>
#include <math.h>
#include <stddef.h>

#define PS_PI 3.141592653589793238462643383279502884
/* The constants of CPython's math.degrees / math.radians, so the conversions round alike. */
#define RAD_TO_DEG (180.0 / PS_PI)
#define DEG_TO_RAD (PS_PI / 180.0)
#define FIT_RANGE_POINTS 1301 /* ArmChain's grid for each muscle's length range */

/* ======================================================================================
 * sensor.py
 * ====================================================================================== */

int ps_median_reset(ps_median *m, int window, ps_real value)
{
    int i;
    if (m == NULL) {
        return PS_ERR_NULL;
    }
    if (window < 1 || window > PS_MEDIAN_MAX_WINDOW || window % 2 != 1) {
        return PS_ERR_CONFIG;
    }
    m->window = window;
    m->next = 0;
    for (i = 0; i < window; ++i) {
        m->values[i] = value;
    }
    return PS_OK;
}

ps_real ps_median_push(ps_median *m, ps_real value)
{
    ps_real sorted[PS_MEDIAN_MAX_WINDOW];
    int i, j, n;
    if (m == NULL) {
        return value;
    }
    n = m->window;
    if (n < 1 || n > PS_MEDIAN_MAX_WINDOW || m->next < 0 || m->next >= n) {
        return value; /* a filter never reset: behave as a window of one */
    }
    m->values[m->next] = value;
    m->next = (m->next + 1) % n;
    /* Insertion sort: the window is tiny, and the result is the same element as numpy's
     * sorted(window)[n // 2]. */
    for (i = 0; i < n; ++i) {
        ps_real x = m->values[i];
        for (j = i; j > 0 && sorted[j - 1] > x; --j) {
            sorted[j] = sorted[j - 1];
        }
        sorted[j] = x;
    }
    return sorted[n / 2];
}

int ps_is_valid_reading(ps_real counts, ps_real max_count)
{
    return isfinite(counts) && counts == (ps_real)floor((double)counts)
           && counts >= 0 && counts <= max_count;
}

static ps_real calibration_angle_deg(const ps_chain_config *cfg, ps_real counts)
{
    return cfg->count_sign * (counts - cfg->zero_count) * cfg->deg_per_count;
}

/* ======================================================================================
 * length_model.py
 * ====================================================================================== */

ps_real ps_chebval(ps_real x, const ps_real *c, int n)
{
    ps_real c0, c1, x2, tmp;
    int i;
    if (c == NULL || n < 1) {
        return 0;
    }
    if (n == 1) {
        return c[0] + 0 * x;
    }
    if (n == 2) {
        return c[0] + c[1] * x;
    }
    x2 = 2 * x;
    c0 = c[n - 2];
    c1 = c[n - 1];
    for (i = 3; i <= n; ++i) {
        tmp = c0;
        c0 = c[n - i] - c1;
        c1 = tmp + c1 * x2;
    }
    return c0 + c1 * x;
}

static void fit_lengths(const ps_chain_config *cfg, ps_real angle_rad, ps_real *out)
{
    ps_real lo = cfg->fit_lo_rad, hi = cfg->fit_hi_rad;
    ps_real x = (2 * angle_rad - (lo + hi)) / (hi - lo);
    int k;
    for (k = 0; k < PS_MUSCLES; ++k) {
        out[k] = ps_chebval(x, cfg->coefficients[k], cfg->n_coefficients[k]);
    }
}

/* ======================================================================================
 * conditioning.py
 * ====================================================================================== */

void ps_tracking_step(ps_real x, ps_real v, ps_real u0, ps_real u1, ps_real dt_s,
                      ps_real omega, ps_real *x1, ps_real *v1, ps_real *a1)
{
    ps_real slope = (u1 - u0) / dt_s;
    ps_real offset = 2 * slope / omega;
    ps_real A = x - u0 + offset;
    ps_real B = v - slope + omega * A;
    ps_real decay = (ps_real)exp((double)(-omega * dt_s));
    ps_real xe = u1 - offset + (A + B * dt_s) * decay;
    ps_real ve = slope + (B - omega * (A + B * dt_s)) * decay;
    if (x1 != NULL) {
        *x1 = xe;
    }
    if (v1 != NULL) {
        *v1 = ve;
    }
    if (a1 != NULL) {
        *a1 = omega * omega * (u1 - xe) - 2 * omega * ve;
    }
}

/* ======================================================================================
 * fusimotor.py
 * ====================================================================================== */

static int predictor_index(const ps_predictor *pr, int i)
{
    return (pr->first + i) % PS_PREDICTOR_MAX_SEGMENTS;
}

static void predictor_reset(ps_predictor *pr, ps_time t, const ps_real *L)
{
    int k;
    pr->first = 0;
    pr->count = 1;
    pr->t[0] = t;
    for (k = 0; k < PS_MUSCLES; ++k) {
        pr->p[0][k] = L[k];
        pr->u[0][k] = 0;
        pr->integral[k] = 0;
    }
}

/* Append a segment, dropping the oldest beyond `keep` (the deque's maxlen). */
static void predictor_append(ps_predictor *pr, int keep, ps_time t, const ps_real *p,
                             const ps_real *u)
{
    int slot, k;
    if (pr->count == keep) {
        pr->first = (pr->first + 1) % PS_PREDICTOR_MAX_SEGMENTS;
        pr->count -= 1;
    }
    slot = predictor_index(pr, pr->count);
    pr->t[slot] = t;
    for (k = 0; k < PS_MUSCLES; ++k) {
        pr->p[slot][k] = p[k];
        pr->u[slot][k] = u[k];
    }
    pr->count += 1;
}

/* MotionPredictor.update: PS_ERR_INTERVAL if it would take more than PS_CHAIN_MAX_UPDATES
 * updates (including a clock so large that t + period == t). */
static int predictor_update(ps_predictor *pr, const ps_arm_chain *c, ps_time t,
                            const ps_real *L, ps_real *template_out)
{
    const ps_chain_config *cfg = &c->config;
    ps_time dt = 1.0 / cfg->predictor_rate_hz;
    ps_real kp = cfg->predictor_kp_1_s, ki = cfg->predictor_ki_1_s2;
    int newest = predictor_index(pr, pr->count - 1);
    ps_time tk = pr->t[newest];
    ps_real p[PS_MUSCLES], u[PS_MUSCLES];
    long n = 0;
    int k;
    if ((t - tk) / dt > (double)PS_CHAIN_MAX_UPDATES) {
        return PS_ERR_INTERVAL;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        p[k] = pr->p[newest][k];
        u[k] = pr->u[newest][k];
    }
    while (t >= tk + dt * (1.0 - 1e-9)) {
        ps_time next = tk + dt;
        if (++n > PS_CHAIN_MAX_UPDATES) {
            return PS_ERR_INTERVAL;
        }
        /* At a clock so large (beyond 2^48 s) that tk + dt rounds to tk, the next
         * representable time: every update moves on, so the loop ends. */
        tk = next > tk ? next : nextafter(tk, HUGE_VAL);
        for (k = 0; k < PS_MUSCLES; ++k) {
            ps_real error;
            p[k] = p[k] + (ps_real)dt * u[k];
            error = L[k] - p[k];
            pr->integral[k] = pr->integral[k] + (ki * (ps_real)dt) * error;
            u[k] = kp * error + pr->integral[k];
        }
        predictor_append(pr, c->predictor_keep, tk, p, u);
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        template_out[k] = p[k] + u[k] * (ps_real)(t - tk);
    }
    return PS_OK;
}

/* MotionPredictor.template_at: the template at an earlier time (clamped to the oldest). */
static void predictor_template_at(const ps_predictor *pr, ps_time t, ps_real *out)
{
    int i, k;
    for (i = pr->count - 1; i >= 0; --i) {
        int s = predictor_index(pr, i);
        if (pr->t[s] <= t) {
            for (k = 0; k < PS_MUSCLES; ++k) {
                out[k] = pr->p[s][k] + pr->u[s][k] * (ps_real)(t - pr->t[s]);
            }
            return;
        }
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        out[k] = pr->p[pr->first][k];
    }
}

/* Fusimotor._rates: h(x) and g(x) of the template at t. */
static void fusimotor_rates(const ps_arm_chain *c, const ps_predictor *pr, ps_time t,
                            const ps_real *template_L0, ps_real *gs, ps_real *gd)
{
    const ps_chain_config *cfg = &c->config;
    ps_real delayed[PS_MUSCLES];
    ps_real span = cfg->gamma_static_max_pps - cfg->gamma_static_min_pps;
    int k;
    predictor_template_at(pr, t - cfg->delay_s, delayed);
    for (k = 0; k < PS_MUSCLES; ++k) {
        ps_real lo = c->length_min_L0[k], hi = c->length_max_L0[k];
        ps_real g = cfg->gamma_static_min_pps + span * (hi - template_L0[k]) / (hi - lo);
        if (g < cfg->gamma_static_min_pps) {
            g = cfg->gamma_static_min_pps;
        }
        if (g > cfg->gamma_static_max_pps) {
            g = cfg->gamma_static_max_pps;
        }
        gs[k] = g;
        gd[k] = (delayed[k] - template_L0[k] > cfg->shortening_threshold_L0)
                    ? 0 : cfg->gamma_dynamic_pps;
    }
}

/* ======================================================================================
 * arm.py
 * ====================================================================================== */

/* The encoder, f(x) and the median filter (sensor.py's EncoderParams, Calibration,
 * MedianFilter). */
static int sensor_ok(const ps_chain_config *cfg)
{
    return cfg->max_count >= 1 && isfinite(cfg->max_count)
           && (cfg->count_sign == 1 || cfg->count_sign == -1)
           && cfg->deg_per_count > 0 && isfinite(cfg->deg_per_count)
           && isfinite(cfg->zero_count)
           && cfg->median_window >= 1 && cfg->median_window <= PS_MEDIAN_MAX_WINDOW
           && cfg->median_window % 2 == 1;
}

/* The fitted length model (length_model.py's LengthFits). */
static int fits_ok(const ps_chain_config *cfg)
{
    int k, i;
    for (k = 0; k < PS_MUSCLES; ++k) {
        if (cfg->n_coefficients[k] < 1 || cfg->n_coefficients[k] > PS_FIT_MAX_COEFFS) {
            return 0;
        }
        for (i = 0; i < cfg->n_coefficients[k]; ++i) {
            if (!isfinite(cfg->coefficients[k][i])) {
                return 0;
            }
        }
    }
    /* An elbow range in rad: bounded, so its conversion to degrees cannot overflow. */
    return cfg->fit_lo_rad >= -2 * PS_PI && cfg->fit_hi_rad <= 2 * PS_PI
           && cfg->fit_lo_rad < cfg->fit_hi_rad;
}

/* The conditioning filter and the handling rules (ChainConfig). */
static int handling_ok(const ps_chain_config *cfg)
{
    return cfg->lowpass_rad_s >= 0 && isfinite(cfg->lowpass_rad_s)
           && cfg->gap_s > 0 && isfinite(cfg->gap_s)
           && cfg->max_bridge_s > 0 && isfinite(cfg->max_bridge_s)
           && cfg->resync_after_samples >= 1
           && cfg->resync_after_samples <= PS_CHAIN_MAX_RESYNC
           && cfg->max_speed_deg_s > 0 && isfinite(cfg->max_speed_deg_s)
           && cfg->max_speed_L0_s > 0 && cfg->max_speed_L0_s <= PS_MAX_SPEED_L0_S;
}

/* FusimotorParams' own rules, its PI loop's stability (Jury's test of the discrete loop) and
 * a template history that fits the predictor. */
static int fusimotor_ok(const ps_chain_config *cfg)
{
    double dt, a, b;
    int keep = 0;
    if (!(cfg->gamma_static_min_pps >= 0 && isfinite(cfg->gamma_static_min_pps)
          && cfg->gamma_static_max_pps >= cfg->gamma_static_min_pps
          && isfinite(cfg->gamma_static_max_pps)
          && cfg->gamma_dynamic_pps >= 0 && isfinite(cfg->gamma_dynamic_pps)
          && cfg->delay_s >= 0 && isfinite(cfg->delay_s)
          && cfg->shortening_threshold_L0 >= 0 && isfinite(cfg->shortening_threshold_L0)
          && cfg->predictor_rate_hz >= 1e-3 && cfg->predictor_rate_hz <= 1e6)) {
        return 0;
    }
    dt = 1 / cfg->predictor_rate_hz;
    a = cfg->predictor_kp_1_s * dt;
    b = cfg->predictor_ki_1_s2 * dt * dt;
    if (!(a > 0 && b > 0 && a < 2 && 2 * a + b < 4)) {
        return 0;
    }
    if (cfg->delay_s * cfg->predictor_rate_hz < PS_PREDICTOR_MAX_SEGMENTS) {
        keep = (int)ceil(cfg->delay_s * (double)cfg->predictor_rate_hz) + 2;
    }
    return keep >= 2 && keep <= PS_PREDICTOR_MAX_SEGMENTS;
}

/* The spindle's sub-steps, and ChainConfig's bound on the work of one bridged interval. */
static int substeps_ok(const ps_chain_config *cfg)
{
    return cfg->theta >= 0 && cfg->theta <= 1 && cfg->step_s > 0 && cfg->step_s <= 1
           && cfg->max_bridge_s / cfg->step_s <= (double)PS_CHAIN_MAX_BRIDGE_UPDATES
           && cfg->max_bridge_s * (double)cfg->predictor_rate_hz
                  <= (double)PS_CHAIN_MAX_BRIDGE_UPDATES;
}

/* The force sense: a load resolution, tendon organ constants ps_gto_plan_init accepts (at the
 * longest interval, which one exact step must cover), force scales, and moment-arm tables
 * with the flexor's >= PS_MIN_MOMENT_ARM_M and the extensor's <= -PS_MIN_MOMENT_ARM_M. */
static int force_ok(const ps_chain_config *cfg)
{
    ps_gto_plan q;
    int k, i, n = cfg->n_moment_arm_points;
    if (!(cfg->load_Nm_per_count > 0 && isfinite(cfg->load_Nm_per_count)
          && cfg->max_bridge_s <= PS_GTO_MAX_STEP_S
          && ps_gto_plan_init(&q, &cfg->gto, (ps_real)cfg->max_bridge_s) == PS_OK
          && n >= 2 && n <= PS_MOMENT_ARM_MAX_POINTS && isfinite(cfg->moment_arm_lo_rad)
          && isfinite(cfg->moment_arm_hi_rad)
          && cfg->moment_arm_lo_rad < cfg->moment_arm_hi_rad)) {
        return 0;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        if (!(cfg->force_scale_N[k] >= (ps_real)PS_GTO_MIN_FORCE_SCALE_N
              && isfinite(cfg->force_scale_N[k]))) {
            return 0;
        }
        for (i = 0; i < n; ++i) {
            ps_real r = k == 0 ? cfg->moment_arm_m[k][i] : -cfg->moment_arm_m[k][i];
            if (!(r >= (ps_real)PS_MIN_MOMENT_ARM_M && isfinite(r))) {
                return 0;
            }
        }
    }
    return 1;
}

/* The spindle constants by the spindle's own check (spindle.c), then each stage's rules. */
static int config_ok(const ps_chain_config *cfg)
{
    return ps_params_check(&cfg->params) == PS_OK && sensor_ok(cfg) && fits_ok(cfg)
           && handling_ok(cfg) && fusimotor_ok(cfg) && substeps_ok(cfg) && force_ok(cfg);
}

int ps_chain_init(ps_arm_chain *c, const ps_chain_config *config)
{
    int i, k;
    ps_real lo, hi, step;
    if (c == NULL || config == NULL) {
        return PS_ERR_NULL;
    }
    c->stage = 0;
    if (!config_ok(config)) {
        return PS_ERR_CONFIG;
    }
    c->config = *config;
    lo = config->fit_lo_rad;
    hi = config->fit_hi_rad;
    c->angle_min_deg = (ps_real)((double)lo * RAD_TO_DEG);
    c->angle_max_deg = (ps_real)((double)hi * RAD_TO_DEG);
    c->predictor_keep =
        (int)ceil(config->delay_s * (double)config->predictor_rate_hz) + 2;
    /* numpy.linspace(lo, hi, 1301): i * step + lo, the last point exactly hi. */
    step = (hi - lo) / (FIT_RANGE_POINTS - 1);
    for (i = 0; i < FIT_RANGE_POINTS; ++i) {
        ps_real angle = (i == FIT_RANGE_POINTS - 1) ? hi : (ps_real)i * step + lo;
        ps_real L[PS_MUSCLES];
        fit_lengths(config, angle, L);
        for (k = 0; k < PS_MUSCLES; ++k) {
            if (i == 0 || L[k] < c->length_min_L0[k]) {
                c->length_min_L0[k] = L[k];
            }
            if (i == 0 || L[k] > c->length_max_L0[k]) {
                c->length_max_L0[k] = L[k];
            }
        }
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        if (!(c->length_max_L0[k] > c->length_min_L0[k])) {
            return PS_ERR_CONFIG; /* h(x) needs a range */
        }
    }
    c->stage = 1;
    return PS_OK;
}

int ps_chain_length_L0(const ps_arm_chain *c, ps_real angle_rad, ps_real length_L0[PS_MUSCLES])
{
    if (c == NULL || length_L0 == NULL) {
        return PS_ERR_NULL;
    }
    if (c->stage < 1) {
        return PS_ERR_NOT_RESET;
    }
    if (!isfinite(angle_rad)) {
        return PS_ERR_NONFINITE;
    }
    fit_lengths(&c->config, angle_rad, length_L0);
    return PS_OK;
}

static int lengths_ok(const ps_real *L)
{
    int k;
    for (k = 0; k < PS_MUSCLES; ++k) {
        if (!(isfinite(L[k]) && L[k] >= PS_LENGTH_MIN_L0 && L[k] <= PS_LENGTH_MAX_L0)) {
            return 0;
        }
    }
    return 1;
}

/* The reading the median window restarts on at an angle, clamped to the encoder's range: with
 * exact lengths the angle is only recorded and may lie anywhere, and a reading no encoder
 * can give (or an infinite one) must not reach the median's output. */
static ps_real rest_reading(const ps_chain_config *cfg, ps_real angle_deg)
{
    ps_real counts = cfg->zero_count + cfg->count_sign * angle_deg / cfg->deg_per_count;
    if (!(counts >= 0)) {
        counts = 0;
    }
    if (counts > cfg->max_count) {
        counts = cfg->max_count;
    }
    return counts;
}

static ps_real clamp_angle(const ps_arm_chain *c, ps_real angle)
{
    return angle < c->angle_min_deg ? c->angle_min_deg
                                    : (angle > c->angle_max_deg ? c->angle_max_deg : angle);
}

/* ======================================================================================
 * the force sense (sensor.py's load word, force.py, tendon_organ.py in the chain)
 * ====================================================================================== */

static int load_valid(ps_real word)
{
    return isfinite(word) && word == (ps_real)floor((double)word) && word >= 0
           && word <= PS_LOAD_MAX_WORD;
}

/* load_torque_Nm of a valid word: the magnitude's torque, negative for a clockwise load, times
 * the mounting's sign. */
static ps_real load_torque(const ps_chain_config *cfg, ps_real word)
{
    long w = (long)word;
    ps_real direction = (w & (PS_LOAD_MAGNITUDE_MAX + 1)) ? -1 : 1;
    return cfg->count_sign * direction * (ps_real)(w & PS_LOAD_MAGNITUDE_MAX)
           * cfg->load_Nm_per_count;
}

/* The torque of an accepted sample by the load rules (its counts into st): a valid word's,
 * the last one held over an invalid word, 0 without one. */
static ps_real sample_torque(const ps_chain_config *cfg, ps_chain_state *st, int is_counts,
                             const ps_real *load)
{
    if (load == NULL) {
        st->counters.missing_load += (unsigned long)is_counts;
        return 0;
    }
    if (!load_valid(*load)) {
        st->counters.invalid_load += 1;
        return st->torque_Nm;
    }
    return load_torque(cfg, *load);
}

/* MomentArmFits.moment_arms_m with clip: the table at the angle clamped to its range, linear
 * between the points of numpy.linspace(lo, hi, n) (as numpy.interp). */
static ps_real moment_arm(const ps_chain_config *cfg, int k, ps_real angle_rad)
{
    const int n = cfg->n_moment_arm_points;
    const ps_real lo = cfg->moment_arm_lo_rad, hi = cfg->moment_arm_hi_rad;
    const ps_real *table = cfg->moment_arm_m[k];
    ps_real step = (hi - lo) / (ps_real)(n - 1), x0, x1;
    long j;
    if (!(angle_rad > lo)) {
        return table[0];
    }
    if (angle_rad >= hi) {
        return table[n - 1];
    }
    j = (long)((angle_rad - lo) / step);
    j = j > n - 2 ? n - 2 : j;
    x0 = (ps_real)j * step + lo;
    if (angle_rad < x0 && j > 0) { /* the division rounded up past a grid point */
        j -= 1;
        x0 = (ps_real)j * step + lo;
    }
    x1 = j + 1 == n - 1 ? hi : (ps_real)(j + 1) * step + lo;
    if (angle_rad >= x1 && j + 1 < n - 1) {
        j += 1;
        x0 = x1;
        x1 = j + 1 == n - 1 ? hi : (ps_real)(j + 1) * step + lo;
    }
    return (table[j + 1] - table[j]) / (x1 - x0) * (angle_rad - x0) + table[j];
}

/* tendon_forces_N: flexion torque on BRA, extension torque on TRImed, never negative. */
static void tendon_forces(const ps_chain_config *cfg, ps_real torque, ps_real angle_deg,
                          ps_real force[PS_MUSCLES])
{
    ps_real angle = (ps_real)((double)angle_deg * DEG_TO_RAD);
    ps_real f;
    force[0] = 0;
    force[1] = 0;
    if (torque > 0) {
        f = torque / moment_arm(cfg, 0, angle);
        force[0] = f > 0 ? f : 0;
    } else {
        f = torque / moment_arm(cfg, 1, angle);
        force[1] = f > 0 ? f : 0;
    }
}

/* The tendon organs at rest at the force of `torque` at the angle; their rates to ib. */
static int rest_tendon_organs(const ps_chain_config *cfg, ps_chain_state *st, ps_real torque,
                              ps_real angle_deg, ps_real *force, ps_real *ib)
{
    int k, status;
    tendon_forces(cfg, torque, angle_deg, force);
    for (k = 0; k < PS_MUSCLES; ++k) {
        status = ps_gto_init(&st->gto[k], &st->gto_plan, force[k], cfg->force_scale_N[k]);
        if (status != PS_OK) {
            return status;
        }
        ib[k] = ps_gto_rate(&st->gto[k], &st->gto_plan);
    }
    return PS_OK;
}

/* The tendon organs over an interval dt in ONE exact step to the force of `torque` at the
 * angle (the force a line over the interval); the plan is remade when the interval changes. */
static int advance_tendon_organs(const ps_chain_config *cfg, ps_chain_state *st,
                                 ps_real torque, ps_real angle_deg, ps_time dt,
                                 ps_real *force, ps_real *ib)
{
    int k, status, resting = 1;
    tendon_forces(cfg, torque, angle_deg, force);
    for (k = 0; k < PS_MUSCLES; ++k) {
        resting = resting && force[k] == 0 && st->gto[k].r_pps == 0 && st->gto[k].z[0] == 0
                  && st->gto[k].z[1] == 0 && st->gto[k].z[2] == 0;
    }
    if (resting) { /* at rest at zero force and staying there: the step would give zeros */
        ib[0] = 0;
        ib[1] = 0;
        return PS_OK;
    }
    if (st->gto_plan.h != (ps_real)dt) {
        status = ps_gto_plan_init(&st->gto_plan, &cfg->gto, (ps_real)dt);
        if (status != PS_OK) {
            return status;
        }
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        status = ps_gto_step(&st->gto[k], &st->gto_plan, force[k], cfg->force_scale_N[k],
                             &ib[k]);
        if (status != PS_OK) {
            return status;
        }
    }
    return PS_OK;
}

/* ArmChain._rest: at rest at `angle_deg` and lengths L at t, the median window on `reading`,
 * the predictor on its input (the intended lengths when the switch is on); what reset and a
 * restart share. Counters and the switch are left alone. */
static int rest(const ps_arm_chain *c, ps_chain_state *st, ps_time t, ps_real angle_deg,
                const ps_real *L, ps_real reading, ps_real counts, ps_real filtered,
                ps_real torque)
{
    ps_real gs[PS_MUSCLES], gd[PS_MUSCLES], template_in[PS_MUSCLES];
    int k, status;
    status = rest_tendon_organs(&c->config, st, torque, angle_deg, st->last.force_N,
                                st->last.ib_pps);
    if (status != PS_OK) {
        return status;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        template_in[k] = st->has_intended ? st->intended_L0[k] : L[k];
    }
    predictor_reset(&st->predictor, t, template_in);
    fusimotor_rates(c, &st->predictor, t, template_in, gs, gd);
    for (k = 0; k < PS_MUSCLES; ++k) {
        status = ps_spindle_init(&st->spindle[k], &c->config.params, L[k], gd[k], gs[k]);
        if (status != PS_OK) {
            return status;
        }
    }
    status = ps_median_reset(&st->median, c->config.median_window, reading);
    if (status != PS_OK) {
        return status;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        st->u[k] = L[k];
        st->x[k] = L[k];
        st->v[k] = 0;
        st->a[k] = 0;
        st->last.length_L0[k] = L[k];
        st->last.velocity_L0_s[k] = 0;
        st->last.acceleration_L0_s2[k] = 0;
        st->last.template_L0[k] = template_in[k];
        st->last.gamma_static_pps[k] = gs[k];
        st->last.gamma_dynamic_pps[k] = gd[k];
        ps_spindle_afferents(&st->spindle[k], &c->config.params, &st->last.ia_pps[k],
                             &st->last.ii_pps[k]);
    }
    st->angle_deg = angle_deg;
    st->t_s = t;
    st->behind = 0;
    st->torque_Nm = torque;
    st->last.t_s = t;
    st->last.accepted = 1;
    st->last.counts = counts;
    st->last.counts_filtered = filtered;
    st->last.angle_deg = angle_deg;
    st->last.torque_Nm = torque;
    return PS_OK;
}

/* The lengths a reset starts at: length_L0 (checked) if given, else the fitted lengths at
 * the angle, clamped to the fits' range (*clamped = 1 then); *recorded is the angle used. */
static int reset_lengths(const ps_arm_chain *c, ps_real angle_deg, const ps_real *length_L0,
                         ps_real L[PS_MUSCLES], ps_real *recorded, int *clamped)
{
    int k;
    *recorded = angle_deg;
    *clamped = 0;
    if (length_L0 == NULL) {
        if (!(c->angle_min_deg <= angle_deg && angle_deg <= c->angle_max_deg)) {
            *clamped = 1;
            *recorded = clamp_angle(c, angle_deg);
        }
        fit_lengths(&c->config, (ps_real)((double)*recorded * DEG_TO_RAD), L);
        return PS_OK;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        if (!isfinite(length_L0[k])) {
            return PS_ERR_NONFINITE;
        }
    }
    if (!lengths_ok(length_L0)) {
        return PS_ERR_LENGTH_RANGE;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        L[k] = length_L0[k];
    }
    return PS_OK;
}

/* The state of `c` reset at rest (ps_chain_reset's work) into `st`; `c` is not written. */
static int reset_state(const ps_arm_chain *c, ps_real angle_deg, ps_time t_s,
                       const ps_real *length_L0, const ps_real *load, ps_chain_state *st)
{
    ps_real L[PS_MUSCLES], recorded, torque = 0;
    ps_chain_counters zero = {0}; /* the universal zero initializer: every counter */
    int k, status, clamped, bad_load = load != NULL && !load_valid(*load);
    if (c->stage < 1) {
        return PS_ERR_NOT_RESET;
    }
    if (!isfinite(t_s) || !isfinite(angle_deg)) {
        return PS_ERR_NONFINITE;
    }
    status = reset_lengths(c, angle_deg, length_L0, L, &recorded, &clamped);
    if (status != PS_OK) {
        return status;
    }
    st->has_intended = 0;
    for (k = 0; k < PS_MUSCLES; ++k) {
        st->intended_L0[k] = 0;
    }
    /* any valid step: the plan is remade for the first interval */
    status = ps_gto_plan_init(&st->gto_plan, &c->config.gto, (ps_real)c->config.max_bridge_s);
    if (status != PS_OK) {
        return status;
    }
    if (load != NULL && !bad_load) {
        torque = load_torque(&c->config, *load);
    }
    status = rest(c, st, t_s, recorded, L, rest_reading(&c->config, angle_deg), -1, -1,
                  torque);
    if (status != PS_OK) {
        return status;
    }
    st->counters = zero;
    st->counters.angle_clamped = (unsigned long)clamped;
    st->counters.invalid_load = (unsigned long)bad_load;
    return PS_OK;
}

int ps_chain_reset(ps_arm_chain *c, ps_real angle_deg, ps_time t_s, const ps_real *length_L0,
                   ps_arm_sample *out)
{
    return ps_chain_reset_load(c, angle_deg, t_s, length_L0, NULL, out);
}

int ps_chain_reset_load(ps_arm_chain *c, ps_real angle_deg, ps_time t_s,
                        const ps_real *length_L0, const ps_real *load, ps_arm_sample *out)
{
    ps_chain_state st;
    int status;
    if (c == NULL) {
        return PS_ERR_NULL;
    }
    status = reset_state(c, angle_deg, t_s, length_L0, load, &st);
    if (status != PS_OK) {
        return status;
    }
    c->state = st;
    c->stage = 2;
    if (out != NULL) {
        *out = st.last;
    }
    return PS_OK;
}

int ps_chain_set_intended_angle(ps_arm_chain *c, const ps_real *angle_deg)
{
    ps_real angle;
    if (c == NULL) {
        return PS_ERR_NULL;
    }
    if (c->stage < 2) {
        return PS_ERR_NOT_RESET;
    }
    if (angle_deg == NULL) {
        c->state.has_intended = 0;
        return PS_OK;
    }
    angle = *angle_deg;
    if (!isfinite(angle)) {
        return PS_ERR_NONFINITE;
    }
    if (angle < c->angle_min_deg) {
        angle = c->angle_min_deg;
    }
    if (angle > c->angle_max_deg) {
        angle = c->angle_max_deg;
    }
    fit_lengths(&c->config, (ps_real)((double)angle * DEG_TO_RAD), c->state.intended_L0);
    c->state.has_intended = 1;
    return PS_OK;
}

/* ArmChain._time: 1 if t may be pushed, else counts the reason and returns 0. An earlier
 * time passes as a clock resync when it is the resync_after_samples-th since the last
 * accepted sample. */
static int time_ok(const ps_chain_config *cfg, ps_chain_state *st, ps_time t)
{
    if (!isfinite(t)) {
        st->counters.bad_time += 1;
        return 0;
    }
    if (t == st->t_s) {
        st->counters.repeated_time += 1;
        return 0;
    }
    if (t < st->t_s) {
        st->behind += 1;
        if (st->behind < cfg->resync_after_samples) {
            st->counters.time_backwards += 1;
            return 0;
        }
        return 1;
    }
#ifdef PS_FLOAT
    /* An interval below float's normal range would become a zero or denormal step. */
    if (t - st->t_s < (double)FLT_MIN) {
        st->counters.repeated_time += 1;
        return 0;
    }
#endif
    return 1;
}

static void hermite_weights(ps_real s, ps_real *w)
{
    ps_real s2 = s * s, s3 = s * s * s;
    w[0] = 2 * s3 - 3 * s2 + 1;
    w[1] = -2 * s3 + 3 * s2;
    w[2] = s3 - 2 * s2 + s;
    w[3] = s3 - s2;
}

/* ArmChain._advance_spindles: equal sub-steps no longer than step_s, the length following
 * the cubic Hermite curve through (x0, v0) and (x1, v1), kept within the slew limit and the
 * spindle's range; the drive held at (gd, gs). */
static int advance_spindles(const ps_arm_chain *c, ps_chain_state *st, const ps_real *x0,
                            const ps_real *v0, const ps_real *x1, const ps_real *v1,
                            const ps_real *gd, const ps_real *gs, ps_time dt, ps_real *ia,
                            ps_real *ii)
{
    const ps_chain_config *cfg = &c->config;
    double steps = ceil(dt / cfg->step_s * (1 - 1e-12));
    long k, j;
    ps_real h, reach, previous[PS_MUSCLES];
    int m, status;
    if (!(steps <= (double)PS_CHAIN_MAX_UPDATES)) {
        return PS_ERR_INTERVAL;
    }
    k = steps < 1 ? 1 : (long)steps;
    h = (ps_real)(dt / (double)k);
    reach = cfg->max_speed_L0_s * h;
    for (m = 0; m < PS_MUSCLES; ++m) {
        previous[m] = x0[m];
    }
    for (j = 1; j < k; ++j) {
        ps_real w[4];
        ps_real left = reach * (ps_real)(k - j);
        hermite_weights((ps_real)((double)j / (double)k), w);
        for (m = 0; m < PS_MUSCLES; ++m) {
            ps_real Ls = w[0] * x0[m] + w[1] * x1[m]
                         + (ps_real)dt * (w[2] * v0[m] + w[3] * v1[m]);
            /* Within a slew-limited step of the previous sub-step, able to reach x1 at that
             * speed, and within the spindle's range (ArmChain._advance_spindles). */
            Ls = Ls < previous[m] - reach ? previous[m] - reach : Ls;
            Ls = Ls > previous[m] + reach ? previous[m] + reach : Ls;
            Ls = Ls < x1[m] - left ? x1[m] - left : Ls;
            Ls = Ls > x1[m] + left ? x1[m] + left : Ls;
            Ls = Ls < (ps_real)PS_LENGTH_MIN_L0 ? (ps_real)PS_LENGTH_MIN_L0 : Ls;
            Ls = Ls > (ps_real)PS_LENGTH_MAX_L0 ? (ps_real)PS_LENGTH_MAX_L0 : Ls;
            status = ps_spindle_step(&st->spindle[m], &cfg->params, Ls, gd[m], gs[m], h,
                                     cfg->theta, NULL, NULL);
            if (status != PS_OK) {
                return status;
            }
            previous[m] = Ls;
        }
    }
    for (m = 0; m < PS_MUSCLES; ++m) {
        status = ps_spindle_step(&st->spindle[m], &cfg->params, x1[m], gd[m], gs[m], h,
                                 cfg->theta, &ia[m], &ii[m]);
        if (status != PS_OK) {
            return status;
        }
    }
    return PS_OK;
}

/* 1 if the interval to t needs at most PS_CHAIN_MAX_UPDATES spindle sub-steps: checked
 * before any use of it, so a corrupt huge time never reaches a conversion or a loop. */
static int interval_ok(const ps_arm_chain *c, const ps_chain_state *st, ps_time t)
{
    return (t - st->t_s) / c->config.step_s <= (double)PS_CHAIN_MAX_UPDATES;
}

/* ArmChain._restarts: an interval too long to bridge, or a clock resync (an earlier time that
 * time_ok let through). */
static int restarts(const ps_arm_chain *c, const ps_chain_state *st, ps_time t)
{
    return t < st->t_s || t - st->t_s > c->config.max_bridge_s;
}

/* ArmChain's slew limit: L_in is L_given with every change since the last input u limited
 * to max_speed_L0_s * dt; 1 if any was limited. */
static int slew_limit(const ps_chain_config *cfg, const ps_chain_state *st,
                      const ps_real *L_given, ps_real dt, ps_real L_in[PS_MUSCLES])
{
    const ps_real limit = cfg->max_speed_L0_s * dt;
    ps_real change[PS_MUSCLES];
    int k, limited = 0;
    for (k = 0; k < PS_MUSCLES; ++k) {
        L_in[k] = L_given[k];
        change[k] = L_in[k] - st->u[k];
        if (fabs((double)change[k]) > (double)limit) {
            limited = 1;
        }
    }
    if (limited) {
        for (k = 0; k < PS_MUSCLES; ++k) {
            ps_real clipped = change[k] < -limit ? -limit : (change[k] > limit ? limit
                                                                                : change[k]);
            L_in[k] = L_in[k] - change[k] + clipped;
        }
    }
    return limited;
}

/* The conditioning stage: (L, dL/dt, d2L/dt2) after dt from the tracking low-pass, or from
 * differences when it is off (lowpass_rad_s = 0). */
static void condition(const ps_chain_config *cfg, const ps_chain_state *st,
                      const ps_real *L_in, ps_real dt, ps_real *x1, ps_real *v1, ps_real *a1)
{
    int k;
    for (k = 0; k < PS_MUSCLES; ++k) {
        if (cfg->lowpass_rad_s > 0) {
            ps_tracking_step(st->x[k], st->v[k], st->u[k], L_in[k], dt, cfg->lowpass_rad_s,
                             &x1[k], &v1[k], &a1[k]);
        } else {
            x1[k] = L_in[k];
            v1[k] = (x1[k] - st->x[k]) / dt;
            a1[k] = (v1[k] - st->v[k]) / dt;
        }
    }
}

/* ArmChain._length_stage on a working copy of the state. `given_angle` is the sample's angle
 * before the slew limit and clamp (the median's reading after a restart). */
static int length_stage(const ps_arm_chain *c, ps_chain_state *st, ps_time t,
                        const ps_real *L_given, ps_real angle, ps_real counts,
                        ps_real filtered, ps_real given_angle, ps_real torque)
{
    const ps_chain_config *cfg = &c->config;
    ps_time dt_time = t - st->t_s;
    ps_real dt;
    ps_real L_in[PS_MUSCLES], x1[PS_MUSCLES], v1[PS_MUSCLES], a1[PS_MUSCLES],
        tmpl[PS_MUSCLES], gs[PS_MUSCLES], gd[PS_MUSCLES], ia[PS_MUSCLES], ii[PS_MUSCLES];
    const ps_real *template_in;
    int k, status;
    if (dt_time > cfg->gap_s) {
        st->counters.gaps += 1;
    }
    if (restarts(c, st, t)) {
        st->counters.restarts += 1;
        st->counters.clock_resyncs += t < st->t_s;
        st->counters.accepted += 1;
        return rest(c, st, t, angle, L_given,
                    counts >= 0 ? counts : rest_reading(cfg, given_angle), counts, filtered,
                    torque);
    }
    if (!interval_ok(c, st, t)) {
        return PS_ERR_INTERVAL;
    }
    dt = (ps_real)dt_time;
    if (slew_limit(cfg, st, L_given, dt, L_in)) {
        st->counters.slew_limited += 1;
    }
    condition(cfg, st, L_in, dt, x1, v1, a1);
    template_in = st->has_intended ? st->intended_L0 : x1;
    status = predictor_update(&st->predictor, c, t, template_in, tmpl);
    if (status != PS_OK) {
        return status;
    }
    fusimotor_rates(c, &st->predictor, t, tmpl, gs, gd);
    status = advance_spindles(c, st, st->x, st->v, x1, v1, gd, gs, dt_time, ia, ii);
    if (status != PS_OK) {
        return status;
    }
    status = advance_tendon_organs(cfg, st, torque, angle, dt_time, st->last.force_N,
                                   st->last.ib_pps);
    if (status != PS_OK) {
        return status;
    }
    for (k = 0; k < PS_MUSCLES; ++k) {
        st->u[k] = L_in[k];
        st->x[k] = x1[k];
        st->v[k] = v1[k];
        st->a[k] = a1[k];
        st->last.length_L0[k] = x1[k];
        st->last.velocity_L0_s[k] = v1[k];
        st->last.acceleration_L0_s2[k] = a1[k];
        st->last.template_L0[k] = tmpl[k];
        st->last.gamma_static_pps[k] = gs[k];
        st->last.gamma_dynamic_pps[k] = gd[k];
        st->last.ia_pps[k] = ia[k];
        st->last.ii_pps[k] = ii[k];
    }
    st->angle_deg = angle;
    st->t_s = t;
    st->behind = 0;
    st->torque_Nm = torque;
    st->counters.accepted += 1;
    st->last.t_s = t;
    st->last.accepted = 1;
    st->last.counts = counts;
    st->last.counts_filtered = filtered;
    st->last.angle_deg = angle;
    st->last.torque_Nm = torque;
    return PS_OK;
}

/* ArmChain._angle_stage: slew limit, clamp to the fitted range, fitted lengths. */
static int angle_stage(const ps_arm_chain *c, ps_chain_state *st, ps_time t, ps_real angle,
                       ps_real counts, ps_real filtered, ps_real torque)
{
    ps_real limit, L[PS_MUSCLES], given = angle;
    if (!restarts(c, st, t)) { /* a restart starts afresh at the new angle */
        if (!interval_ok(c, st, t)) {
            return PS_ERR_INTERVAL;
        }
        limit = c->config.max_speed_deg_s * (ps_real)(t - st->t_s);
        if (fabs((double)(angle - st->angle_deg)) > (double)limit) {
            st->counters.slew_limited += 1;
            angle = st->angle_deg + (angle - st->angle_deg < 0 ? -limit : limit);
        }
    }
    if (!(c->angle_min_deg <= angle && angle <= c->angle_max_deg)) {
        st->counters.angle_clamped += 1;
        angle = clamp_angle(c, angle);
    }
    fit_lengths(&c->config, (ps_real)((double)angle * DEG_TO_RAD), L);
    return length_stage(c, st, t, L, angle, counts, filtered, given, torque);
}

enum push_kind { PUSH_COUNTS, PUSH_ANGLE, PUSH_LENGTHS };

/* One push on the state `st` of chain `c` (c's own state or a copy of it: only st is read and
 * written). On an error st is left part-way and must be discarded by the caller. *accepted
 * receives whether the sample was accepted (a rejected one only changes a counter). */
static int push_state(const ps_arm_chain *c, ps_chain_state *st, enum push_kind kind,
                      ps_time t, ps_real value, const ps_real *lengths,
                      const ps_real *angle_deg, const ps_real *load, int *accepted)
{
    int status = PS_OK;
    *accepted = 0;
    if (!time_ok(&c->config, st, t)) {
        return PS_OK;
    }
    if (kind == PUSH_COUNTS) {
        if (!ps_is_valid_reading(value, c->config.max_count)) {
            st->counters.invalid_reading += 1;
        } else {
            /* a restart refills the window with this reading instead */
            ps_real filtered = restarts(c, st, t) ? value : ps_median_push(&st->median, value);
            status = angle_stage(c, st, t, calibration_angle_deg(&c->config, filtered), value,
                                 filtered, sample_torque(&c->config, st, 1, load));
            *accepted = 1;
        }
    } else if (kind == PUSH_ANGLE) {
        if (!isfinite(value)) {
            st->counters.invalid_angle += 1;
        } else {
            status = angle_stage(c, st, t, value, -1, -1,
                                 sample_torque(&c->config, st, 0, load));
            *accepted = 1;
        }
    } else {
        if (!lengths_ok(lengths)) {
            st->counters.invalid_length += 1;
        } else {
            ps_real angle = (angle_deg == NULL || !isfinite(*angle_deg)) ? st->angle_deg
                                                                         : *angle_deg;
            status = length_stage(c, st, t, lengths, angle, -1, -1, angle,
                                  sample_torque(&c->config, st, 0, load));
            *accepted = 1;
        }
    }
    return status;
}

/* One push on a copy of the state, committed only if it completes. A rejected sample only
 * changes a counter, so it is committed too. */
static int push(ps_arm_chain *c, enum push_kind kind, ps_time t, ps_real value,
                const ps_real *lengths, const ps_real *angle_deg, const ps_real *load,
                ps_arm_sample *out)
{
    ps_chain_state st;
    int status, accepted;
    if (c == NULL || (kind == PUSH_LENGTHS && lengths == NULL)) {
        return PS_ERR_NULL;
    }
    if (c->stage < 2) {
        return PS_ERR_NOT_RESET;
    }
    st = c->state;
    status = push_state(c, &st, kind, t, value, lengths, angle_deg, load, &accepted);
    if (status != PS_OK) {
        return status;
    }
    c->state = st;
    if (out != NULL) {
        *out = st.last;
        out->accepted = accepted;
    }
    return PS_OK;
}

int ps_chain_push_counts(ps_arm_chain *c, ps_time t_s, ps_real counts, ps_arm_sample *out)
{
    return push(c, PUSH_COUNTS, t_s, counts, NULL, NULL, NULL, out);
}

int ps_chain_push_counts_load(ps_arm_chain *c, ps_time t_s, ps_real counts,
                              const ps_real *load, ps_arm_sample *out)
{
    return push(c, PUSH_COUNTS, t_s, counts, NULL, NULL, load, out);
}

int ps_chain_push_angle(ps_arm_chain *c, ps_time t_s, ps_real angle_deg, ps_arm_sample *out)
{
    return push(c, PUSH_ANGLE, t_s, angle_deg, NULL, NULL, NULL, out);
}

int ps_chain_push_lengths(ps_arm_chain *c, ps_time t_s, const ps_real length_L0[PS_MUSCLES],
                          const ps_real *angle_deg, ps_arm_sample *out)
{
    return push(c, PUSH_LENGTHS, t_s, 0, length_L0, angle_deg, NULL, out);
}

static int push_block(ps_arm_chain *c, enum push_kind kind, long n, const ps_time *t_s,
                      const ps_real *values, const ps_real *load, ps_arm_sample *out,
                      long *n_done)
{
    long i;
    int status = PS_OK;
    if (n_done != NULL) {
        *n_done = 0;
    }
    if (c == NULL || (n > 0 && (t_s == NULL || values == NULL))) {
        return PS_ERR_NULL;
    }
    if (c->stage < 2) {
        return PS_ERR_NOT_RESET;
    }
    for (i = 0; i < n; ++i) {
        if (kind == PUSH_LENGTHS) {
            status = push(c, kind, t_s[i], 0, values + PS_MUSCLES * i, NULL, NULL, NULL);
        } else {
            status = push(c, kind, t_s[i], values[i], NULL, NULL,
                          load == NULL ? NULL : &load[i], NULL);
        }
        if (status != PS_OK) {
            break;
        }
        if (n_done != NULL) {
            *n_done = i + 1;
        }
    }
    if (out != NULL) {
        *out = c->state.last; /* ArmChain's block pushes return ArmChain.last */
    }
    return status;
}

int ps_chain_push_counts_block(ps_arm_chain *c, long n, const ps_time *t_s,
                               const ps_real *counts, ps_arm_sample *out, long *n_done)
{
    return push_block(c, PUSH_COUNTS, n, t_s, counts, NULL, out, n_done);
}

int ps_chain_push_counts_load_block(ps_arm_chain *c, long n, const ps_time *t_s,
                                    const ps_real *counts, const ps_real *load,
                                    ps_arm_sample *out, long *n_done)
{
    return push_block(c, PUSH_COUNTS, n, t_s, counts, load, out, n_done);
}

int ps_chain_push_angle_block(ps_arm_chain *c, long n, const ps_time *t_s,
                              const ps_real *angle_deg, ps_arm_sample *out, long *n_done)
{
    return push_block(c, PUSH_ANGLE, n, t_s, angle_deg, NULL, out, n_done);
}

int ps_chain_push_lengths_block(ps_arm_chain *c, long n, const ps_time *t_s,
                                const ps_real *length_L0, ps_arm_sample *out, long *n_done)
{
    return push_block(c, PUSH_LENGTHS, n, t_s, length_L0, NULL, out, n_done);
}

static int run_trace(ps_arm_chain *c, enum push_kind kind, long n, const ps_time *t_s,
                     const ps_real *values, const ps_real *load, const ps_real *intended_deg,
                     ps_arm_sample *samples, long *n_done)
{
    long i;
    int status = PS_OK;
    if (n_done != NULL) {
        *n_done = 0;
    }
    if (c == NULL || (n > 0 && (t_s == NULL || values == NULL || samples == NULL))) {
        return PS_ERR_NULL;
    }
    if (c->stage < 2) {
        return PS_ERR_NOT_RESET;
    }
    for (i = 0; i < n; ++i) {
        if (intended_deg != NULL) {
            ps_real angle = intended_deg[i];
            status = ps_chain_set_intended_angle(c, angle != angle ? NULL : &angle);
            if (status != PS_OK) {
                break;
            }
        }
        if (kind == PUSH_LENGTHS) {
            status = push(c, kind, t_s[i], 0, values + PS_MUSCLES * i, NULL, NULL,
                          &samples[i]);
        } else {
            status = push(c, kind, t_s[i], values[i], NULL, NULL,
                          load == NULL ? NULL : &load[i], &samples[i]);
        }
        if (status != PS_OK) {
            break;
        }
        if (n_done != NULL) {
            *n_done = i + 1;
        }
    }
    return status;
}

int ps_chain_run_counts(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *counts,
                        const ps_real *intended_deg, ps_arm_sample *samples, long *n_done)
{
    return run_trace(c, PUSH_COUNTS, n, t_s, counts, NULL, intended_deg, samples, n_done);
}

int ps_chain_run_counts_load(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *counts,
                             const ps_real *load, const ps_real *intended_deg,
                             ps_arm_sample *samples, long *n_done)
{
    return run_trace(c, PUSH_COUNTS, n, t_s, counts, load, intended_deg, samples, n_done);
}

int ps_chain_run_angle(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *angle_deg,
                       const ps_real *intended_deg, ps_arm_sample *samples, long *n_done)
{
    return run_trace(c, PUSH_ANGLE, n, t_s, angle_deg, NULL, intended_deg, samples, n_done);
}

int ps_chain_run_lengths(ps_arm_chain *c, long n, const ps_time *t_s, const ps_real *length_L0,
                         const ps_real *intended_deg, ps_arm_sample *samples, long *n_done)
{
    return run_trace(c, PUSH_LENGTHS, n, t_s, length_L0, NULL, intended_deg, samples,
                     n_done);
}


/* ======================================================================================
 * Batches: many arms' chains in one array, one call for all of them (left out of a device
 * build with -DPS_NO_BATCH: 1.8 kB of Cortex-M0+ code the one-arm firmware does not need)
 * ====================================================================================== */
#ifndef PS_NO_BATCH

static void set_failed(long *failed_arm, long arm, long *failed_sample, long sample)
{
    if (failed_arm != NULL) {
        *failed_arm = arm;
    }
    if (failed_sample != NULL) {
        *failed_sample = sample;
    }
}

/* Every arm usable (initialised and reset) and every per-arm count within 0..k; on failure
 * *failed_arm names the first arm that is not. */
static int batch_ok(const ps_arm_chain *chains, long n_arms, long k, const long *n_samples,
                    long *failed_arm)
{
    long i;
    if (k < 0) {
        return PS_ERR_ARGUMENT;
    }
    for (i = 0; i < n_arms; ++i) {
        if (chains[i].stage < 2) {
            set_failed(failed_arm, i, NULL, 0);
            return PS_ERR_NOT_RESET;
        }
        if (n_samples != NULL && (n_samples[i] < 0 || n_samples[i] > k)) {
            set_failed(failed_arm, i, NULL, 0);
            return PS_ERR_ARGUMENT;
        }
    }
    return PS_OK;
}

/* Arm i pushes its first n_i samples (n_samples[i], or k; active[i] ? 1 : 0 for the
 * one-sample forms) in place, its state saved in backup[i] first; the first failure puts
 * back every arm pushed so far, so the call is atomic across arms at the cost of one state
 * copy per arm (a single push copies the state twice per sample). `per_sample` selects the
 * outputs of the one-sample forms (the push's own, accepted = 0 if rejected) over those of
 * the blocks (ArmChain.last). */
static int batch_push(ps_arm_chain *chains, enum push_kind kind, long n_arms, long k,
                      const long *n_samples, const unsigned char *active, const ps_time *t_s,
                      const ps_real *values, const ps_real *load, ps_chain_state *backup,
                      ps_arm_sample *out, long *failed_arm, long *failed_sample)
{
    const long width = kind == PUSH_LENGTHS ? PS_MUSCLES : 1;
    const int per_sample = active != NULL || k < 0;
    long i, j, n;
    int status = PS_OK, accepted = 0;
    set_failed(failed_arm, -1, failed_sample, -1);
    if (n_arms < 0) {
        return PS_ERR_ARGUMENT;
    }
    if (n_arms == 0) {
        return PS_OK;
    }
    if (chains == NULL || backup == NULL || t_s == NULL || values == NULL) {
        return PS_ERR_NULL;
    }
    if (per_sample) {
        k = 1;
    }
    status = batch_ok(chains, n_arms, k, n_samples, failed_arm);
    if (status != PS_OK) {
        return status;
    }
    for (i = 0; i < n_arms; ++i) {
        ps_arm_chain *c = &chains[i];
        n = active != NULL ? (active[i] != 0) : (n_samples != NULL ? n_samples[i] : k);
        backup[i] = c->state;
        accepted = 0;
        for (j = 0; j < n; ++j) {
            long at = i * k + j;
            status = push_state(c, &c->state, kind, t_s[at], width == 1 ? values[at] : 0,
                                values + width * at, NULL, load == NULL ? NULL : &load[at],
                                &accepted);
            if (status != PS_OK) {
                for (; i >= 0; --i) {
                    chains[i].state = backup[i];
                }
                set_failed(failed_arm, c - chains, failed_sample, j);
                return status;
            }
        }
        if (out != NULL) {
            out[i] = c->state.last;
            /* an arm given no sample repeats its last output as not accepted */
            out[i].accepted = per_sample ? accepted : n > 0;
        }
    }
    return PS_OK;
}

int ps_chain_batch_reset(ps_arm_chain *chains, long n_arms, const long *arms, long m,
                         const ps_real *angle_deg, const ps_time *t_s,
                         const ps_real *length_L0, ps_chain_state *scratch,
                         ps_arm_sample *out, long *failed_arm)
{
    return ps_chain_batch_reset_load(chains, n_arms, arms, m, angle_deg, t_s, length_L0, NULL,
                                     scratch, out, failed_arm);
}

int ps_chain_batch_reset_load(ps_arm_chain *chains, long n_arms, const long *arms, long m,
                              const ps_real *angle_deg, const ps_time *t_s,
                              const ps_real *length_L0, const ps_real *load,
                              ps_chain_state *scratch, ps_arm_sample *out, long *failed_arm)
{
    long j;
    int status;
    set_failed(failed_arm, -1, NULL, 0);
    if (n_arms < 0 || m < 0 || (arms == NULL && m != n_arms)) {
        return PS_ERR_ARGUMENT;
    }
    if (m == 0) {
        return PS_OK;
    }
    if (chains == NULL || angle_deg == NULL || t_s == NULL || scratch == NULL) {
        return PS_ERR_NULL;
    }
    /* Every new state is built in scratch first, so a refused arm leaves all untouched. */
    for (j = 0; j < m; ++j) {
        long i = arms == NULL ? j : arms[j];
        if (i < 0 || i >= n_arms) {
            set_failed(failed_arm, i, NULL, 0);
            return PS_ERR_ARGUMENT;
        }
        status = reset_state(&chains[i], angle_deg[j], t_s[j],
                             length_L0 == NULL ? NULL : length_L0 + PS_MUSCLES * j,
                             load == NULL ? NULL : &load[j], &scratch[j]);
        if (status != PS_OK) {
            set_failed(failed_arm, i, NULL, 0);
            return status;
        }
    }
    for (j = 0; j < m; ++j) {
        long i = arms == NULL ? j : arms[j];
        chains[i].state = scratch[j];
        chains[i].stage = 2;
        if (out != NULL) {
            out[j] = scratch[j].last;
        }
    }
    return PS_OK;
}

int ps_chain_batch_set_intended_angle(ps_arm_chain *chains, long n_arms,
                                      const ps_real *angle_deg, long *failed_arm)
{
    long i;
    int status;
    set_failed(failed_arm, -1, NULL, 0);
    if (n_arms < 0) {
        return PS_ERR_ARGUMENT;
    }
    if (n_arms > 0 && chains == NULL) {
        return PS_ERR_NULL;
    }
    for (i = 0; i < n_arms; ++i) { /* checked first: all arms or none */
        if (chains[i].stage < 2) {
            set_failed(failed_arm, i, NULL, 0);
            return PS_ERR_NOT_RESET;
        }
        if (angle_deg != NULL && isinf(angle_deg[i])) {
            set_failed(failed_arm, i, NULL, 0);
            return PS_ERR_NONFINITE;
        }
    }
    for (i = 0; i < n_arms; ++i) {
        int measured = angle_deg == NULL || isnan(angle_deg[i]);
        status = ps_chain_set_intended_angle(&chains[i], measured ? NULL : &angle_deg[i]);
        if (status != PS_OK) { /* not reached: its checks were made above */
            set_failed(failed_arm, i, NULL, 0);
            return status;
        }
    }
    return PS_OK;
}

int ps_chain_batch_push_counts_block(ps_arm_chain *chains, long n_arms, long k,
                                     const long *n_samples, const ps_time *t_s,
                                     const ps_real *counts, ps_chain_state *backup,
                                     ps_arm_sample *out, long *failed_arm, long *failed_sample)
{
    if (k < 0) {
        return PS_ERR_ARGUMENT;
    }
    return batch_push(chains, PUSH_COUNTS, n_arms, k, n_samples, NULL, t_s, counts, NULL,
                      backup, out, failed_arm, failed_sample);
}

int ps_chain_batch_push_angle_block(ps_arm_chain *chains, long n_arms, long k,
                                    const long *n_samples, const ps_time *t_s,
                                    const ps_real *angle_deg, ps_chain_state *backup,
                                    ps_arm_sample *out, long *failed_arm, long *failed_sample)
{
    if (k < 0) {
        return PS_ERR_ARGUMENT;
    }
    return batch_push(chains, PUSH_ANGLE, n_arms, k, n_samples, NULL, t_s, angle_deg, NULL,
                      backup, out, failed_arm, failed_sample);
}

int ps_chain_batch_push_lengths_block(ps_arm_chain *chains, long n_arms, long k,
                                      const long *n_samples, const ps_time *t_s,
                                      const ps_real *length_L0, ps_chain_state *backup,
                                      ps_arm_sample *out, long *failed_arm, long *failed_sample)
{
    if (k < 0) {
        return PS_ERR_ARGUMENT;
    }
    return batch_push(chains, PUSH_LENGTHS, n_arms, k, n_samples, NULL, t_s, length_L0,
                      NULL, backup, out, failed_arm, failed_sample);
}

/* The one-sample forms: k = -1 tells batch_push to use `active` (NULL: every arm). */
int ps_chain_batch_push_counts(ps_arm_chain *chains, long n_arms, const unsigned char *active,
                               const ps_time *t_s, const ps_real *counts,
                               ps_chain_state *backup, ps_arm_sample *out, long *failed_arm)
{
    return batch_push(chains, PUSH_COUNTS, n_arms, -1, NULL, active, t_s, counts, NULL, backup,
                      out, failed_arm, NULL);
}

int ps_chain_batch_push_angle(ps_arm_chain *chains, long n_arms, const unsigned char *active,
                              const ps_time *t_s, const ps_real *angle_deg,
                              ps_chain_state *backup, ps_arm_sample *out, long *failed_arm)
{
    return batch_push(chains, PUSH_ANGLE, n_arms, -1, NULL, active, t_s, angle_deg, NULL,
                      backup, out, failed_arm, NULL);
}

int ps_chain_batch_push_lengths(ps_arm_chain *chains, long n_arms, const unsigned char *active,
                                const ps_time *t_s, const ps_real *length_L0,
                                ps_chain_state *backup, ps_arm_sample *out, long *failed_arm)
{
    return batch_push(chains, PUSH_LENGTHS, n_arms, -1, NULL, active, t_s, length_L0, NULL,
                      backup, out, failed_arm, NULL);
}
int ps_chain_batch_push_counts_load_block(ps_arm_chain *chains, long n_arms, long k,
                                          const long *n_samples, const ps_time *t_s,
                                          const ps_real *counts, const ps_real *load,
                                          ps_chain_state *backup, ps_arm_sample *out,
                                          long *failed_arm, long *failed_sample)
{
    if (k < 0) {
        return PS_ERR_ARGUMENT;
    }
    return batch_push(chains, PUSH_COUNTS, n_arms, k, n_samples, NULL, t_s, counts, load,
                      backup, out, failed_arm, failed_sample);
}

int ps_chain_batch_push_counts_load(ps_arm_chain *chains, long n_arms,
                                    const unsigned char *active, const ps_time *t_s,
                                    const ps_real *counts, const ps_real *load,
                                    ps_chain_state *backup, ps_arm_sample *out,
                                    long *failed_arm)
{
    return batch_push(chains, PUSH_COUNTS, n_arms, -1, NULL, active, t_s, counts, load, backup,
                      out, failed_arm, NULL);
}
#endif /* PS_NO_BATCH */
