/*
 * system.c -- the whole prosthesis on a Cortex-M0+: one call per encoder sample.
 *
 *   reading -> median -> f(x) -> fitted lengths -> tracking low-pass -> predictor and
 *   fusimotor drive -> BRA/TRImed spindles (fixed point) [-> tendon organs] [-> pulses]
 *   -> output record
 *
 * fw_sample() is what a 500 Hz timer interrupt would run: it reads the sample in fw_in (time,
 * counts and, for the tendon organs, the servo's load word) and runs the stages of fw_stages[]
 * in order, each a function of the sample context (the table is what the bench's per-stage
 * breakdown follows: a stage is everything from its entry to the next stage's). The tendon
 * organs and the stimulation encoder are two more rows (FW_GTO, FW_STIM sections below).
 *
 * Everything after the time rules is integer arithmetic (no FPU on the part; soft float costs
 * 30-100 instructions per operation): angles Q16 deg, lengths Q24 L0, velocities Q20 L0/s,
 * drives Q8 pps, rates Q16 pps, intervals in whole microseconds. Only the time rules compare
 * the sample's time as a double, as the host chain does (ps_time), so the bad-sample rules and
 * counters are those of spindle/chain/arm.py and chain.c (see fw_counters).
 *
 * The spindles run on a fixed grid of the plan's h (fw_cfg.spindle_step_us, 8 ms; generated on
 * the host by ps_plan_fx_init), the two muscles' grids offset by half a step, so that a sample
 * at the nominal rate steps at most one spindle (every second sample one). A grid point steps
 * at the first sample at most spindle_lead_us (half a step) before it: its length is the
 * tracking filter's line x1 + v1 (tau - t) past the sample, or for a point the sample came
 * late for the cubic Hermite curve through the interval's ends (as chain.c's sub-steps); a
 * muscle's output holds its last step's rates, which then stand for a time within half a step
 * of the sample. A sample runs at most FW_MAX_STEPS (1) spindle steps, the oldest queued grid
 * point first (jitter and bridged intervals queue the others for the next samples).
 *
 * The tendon organs step on their own grid (fw_gto_cfg.step_us, 8 ms), likewise offset by
 * half a step between the muscles (FW_GTO section).
 *
 * The configuration (fw_system_config.h: const fw_config fw_cfg, const ps_plan_fx fw_plan) is
 * generated on the host by spindle.native.m0plus.system_config from a ChainConfig.
 */
#include "proprio.h"

#include <stdint.h>

/* ---- configuration (generated) -------------------------------------------------------- */

#define FW_DECAY_COARSE 128 /* the decay tables cover intervals below 128 * 64 us = 8.2 ms */

typedef struct fw_config {
    double gap_s, max_bridge_s;  /* the chain's interval rules (s) */
    int64_t gap_Q32, max_bridge_Q32; /* the same in Q32 s, rounded */
    int32_t resync_after_samples;
    int32_t max_count;           /* valid readings: integers 0..max_count */
    int32_t median_window;
    int32_t zero_Q16;            /* zero_count (counts, Q16) */
    int32_t deg_per_count_Q30;   /* count_sign * deg_per_count (deg, Q30) */
    int32_t angle_min_Q16, angle_max_Q16;       /* the fitted range (deg, Q16) */
    int32_t length_scale_Q28;                   /* fw_length_Q24's points per degree */
    int32_t max_speed_deg_Q32_us;               /* max_speed_deg_s: deg per us, Q32 */
    int32_t max_speed_L0_Q40_us;                /* max_speed_L0_s: L0 per us, Q40 */
    int32_t omega_Q16;                          /* tracking low-pass (rad/s) */
    int32_t two_over_omega_Q32;                 /* 2 / omega (s) */
    int32_t predictor_period_us, predictor_keep;
    int32_t predictor_period_Q30;               /* 1 / predictor_rate_hz (s) */
    int32_t kp_Q16, ki_dt_Q16;                  /* 1/s; ki * period (1/s) */
    int32_t delay_us, threshold_Q24;
    int32_t gs_min_Q8, gs_max_Q8, gd_Q8;
    int32_t length_max_Q24[PS_MUSCLES];         /* h(x): gs = min + gain (Lmax - template) */
    int32_t gs_gain_Q8[PS_MUSCLES];             /* span / (Lmax - Lmin) (pps/L0) */
    int32_t spindle_step_us;                    /* the plan's h */
    int32_t spindle_reach_Q24;                  /* the length's slew limit over one step */
    int32_t spindle_lead_us;                    /* grid points this far ahead step now */
    /* e^(-omega dt) of the tracking filter for dt = 64 i + j us (Q30): coarse i, fine j */
    int32_t decay_coarse_Q30[FW_DECAY_COARSE], decay_fine_Q30[64];
} fw_config;

#ifdef FW_GTO
/* The force sense's constants (generated with fw_cfg, from the same ps_chain_config): the load
 * word's sign, the moment-arm grid (the host's table points) as force per load count of each
 * muscle, 1/G2, and the tendon organs' fixed-point plans: one at the organs' nominal step
 * (step_us) and a table at h = k 1024 us (k = 0: no time passes), linear between its points.
 *
 * The organs step on their own grid of step_us (8 ms, four samples; the two muscles' grids
 * offset by half a step, so a sample at the nominal rate steps at most one organ): a 3-state
 * filter whose fastest pole is its 10 ms low-pass's (Lin & Crago 2002) needs no 2 ms step, and
 * the force is a line over the step as it is over a sample on the host. Between its steps a
 * muscle's Ib holds (measured against the host's organs stepped every sample: 0.26 pps RMS on
 * the bench's servo trace, 0.94 right after a load that appears at once; 2.3 at 16 ms). */
#define FW_GTO_PLANS 30          /* intervals up to (FW_GTO_PLANS - 1) * 1024 us = 29.7 ms */
#define FW_GTO_PLAN_SHIFT 10     /* the table's step, 1024 us: its index is a shift */
typedef struct fw_gto_config {
    int32_t load_sign;           /* the torque's sign of a counter-clockwise load word */
    int32_t arm_lo_Q16;          /* the moment-arm grid's first angle (deg, Q16) */
    int32_t arm_scale_Q28;       /* grid points per degree */
    int32_t arm_last;            /* the last grid point's index */
    int32_t arm_shift;           /* fw_arm_force's values are the Q12 ones >> arm_shift */
    int32_t inv_scale_Q24[PS_MUSCLES]; /* 1 / G2 (1/N) */
    int32_t step_us;             /* the organs' step, the interval of plan_nominal */
    ps_gto_plan_fx plan_nominal;
    int32_t n_plans;
    int32_t plan_Q30[FW_GTO_PLANS][15]; /* phi (row-major), g0, g1 at h = k 1024 us */
} fw_gto_config;
#endif

#include "fw_system_config.h" /* const fw_config fw_cfg; const ps_plan_fx fw_plan; with
                                * FW_STIM the channel map fw_stim_source[channel] =
                                * {muscle, 0: Ia / 1: II / 2: Ib}; with FW_GTO fw_gto_cfg and
                                * fw_arm_force[point][muscle], the force (N, Q8) per load
                                * count at the grid's angles, Nm_per_count / |moment arm|, in
                                * Q(12 - arm_shift), uint16 (half the flash of int32);
                                * fw_length_Q24[point][muscle], the length fits at every count
                                * of the fitted range (Q24 L0) */

#ifdef FW_STIM
/* const ps_stim_fx_config fw_stim_config (spindle.native.m0plus.stim) */
#include "fw_stim_config.h"
#endif

/* ---- state ----------------------------------------------------------------------------- */

/* chain.COUNTERS, in that order (only the rules a counts-only entry can reach increment
 * invalid_angle and invalid_length: never; invalid_load and missing_load only with FW_GTO,
 * which reads the load word). */
typedef struct fw_counters {
    uint32_t accepted, invalid_reading, invalid_angle, invalid_length, repeated_time,
        time_backwards, bad_time, gaps, slew_limited, angle_clamped, restarts, clock_resyncs,
        invalid_load, missing_load;
} fw_counters;

/* What the stages derive from an interval, kept while it repeats (the nominal one does). */
typedef struct fw_interval {
    int32_t us;                   /* -1: none yet */
    int32_t Q30, inv_Q11;         /* in s (Q30); 1 / interval (1/s, Q11: 0 for 0 us; Q12
                                   * overflowed int32 at 1 us, 4.096e9) */
    int32_t inv_us_Q30;           /* 1 / us (Q30; 0 for 0 us) */
    int32_t decay_Q30;            /* the tracking low-pass's e^(-omega dt) */
    /* the slew limits over it, max_speed_deg_s dt in Q32 deg and max_speed_L0_s dt in Q40 L0,
     * each as its Q16 (Q24) part, floored, and the 16 bits below: rounded to Q16 the angle's
     * was 66 units for 65.536 at 1 us (0.7%; the lengths' 134 for 134.2), so a slew over
     * few-us intervals took another number of limited samples than the host's */
    int32_t angle_limit_Q16, angle_limit_frac;
    int32_t length_limit_Q24, length_limit_frac;
} fw_interval;

#define FW_SAMPLE_US 2000 /* the encoder's nominal period (500 Hz) */
#define FW_SEGMENTS 8 /* >= predictor_keep (4 for the seed paper's 40 ms at 50 Hz); a power
                        * of 2 (the ring's index is a mask) */
#define FW_PENDING 8  /* queued spindle grid points per muscle */

typedef struct fw_state {
    int32_t median[PS_MEDIAN_MAX_WINDOW];  /* the window in arrival order (a ring) */
    int32_t sorted[PS_MEDIAN_MAX_WINDOW];  /* the same values in order */
    int32_t median_next;
    double t_s, epoch_s;          /* last accepted time; times below count from the epoch */
    int64_t t_key;                /* order_key(t_s) */
    int64_t t_Q32, epoch_Q32;     /* t_s and epoch_s by to_Q32 (-1: out of its range) */
    fw_interval interval;         /* the last interval's constants */
    uint32_t t_us;                /* last accepted time since the epoch */
    int32_t behind;
    int32_t angle_Q16;
    int32_t u_Q24[PS_MUSCLES], x_Q24[PS_MUSCLES], v_Q20[PS_MUSCLES];
    /* predictor: the last segments (t, p, u), oldest first from seg_first */
    uint32_t seg_t_us[FW_SEGMENTS];
    int32_t seg_p_Q24[FW_SEGMENTS][PS_MUSCLES], seg_u_Q20[FW_SEGMENTS][PS_MUSCLES];
    int32_t integral_Q20[PS_MUSCLES];
    int32_t seg_first, seg_count;
    /* spindles */
    ps_spindle_fx spindle[PS_MUSCLES];
    uint32_t next_step_us[PS_MUSCLES];
    int32_t last_L_Q24[PS_MUSCLES]; /* the last grid point's length */
    int32_t pending_L_Q24[PS_MUSCLES][FW_PENDING], pending_n[PS_MUSCLES]; /* queued grid points */
    uint32_t pending_t_us[PS_MUSCLES][FW_PENDING];
    int32_t ia_Q16[PS_MUSCLES], ii_Q16[PS_MUSCLES];
    int32_t gs_Q8[PS_MUSCLES], gd_Q8[PS_MUSCLES];
#ifdef FW_GTO
    ps_gto_fx gto[PS_MUSCLES];
    uint32_t gto_t_us[PS_MUSCLES];   /* each organ's last step (or rest) */
    uint32_t gto_due_us[PS_MUSCLES]; /* and its next grid point */
    int32_t torque_counts;          /* the last accepted sample's signed load (counts) */
#endif
    int32_t ib_Q16[PS_MUSCLES];
#ifdef FW_STIM
    int32_t held_Q16[PS_STIM_MAX_CHANNELS]; /* each channel's rate since the last sample */
#endif
    int32_t started;
    /* the bits below angle_Q16 and u_Q24 (0..65535) of an angle or lengths the slew limit set
     * (it moves them by the host's max_speed dt, the interval's limits in 16 more bits), and
     * the fw_count.accepted of that sample: they hold for the next sample only, so a sample
     * within the limits stores nothing (zeroing them cost ~20 instructions a sample); last:
     * the fields before them keep their short offsets */
    int32_t angle_frac, u_frac[PS_MUSCLES];
    uint32_t angle_tag, u_tag;
} fw_state;

/* One sample as the interrupt gets it. */
typedef struct fw_input {
    double t_s;
    float counts;
    float load;          /* the servo's load word, for the tendon organs (FW_GTO) */
    int32_t has_load;    /* 0: no load word came with the sample (missing_load) */
} fw_input;

/* What a sample leaves in the output ring. */
typedef struct fw_record {
    uint32_t t_us;
    int32_t accepted; /* 0: rejected (counted), 1: accepted, 2: restarted at rest */
    int32_t status;   /* PS_OK or a spindle step's failure */
    int32_t ia_Q16[PS_MUSCLES], ii_Q16[PS_MUSCLES];
    int32_t gs_Q8[PS_MUSCLES], gd_Q8[PS_MUSCLES];
    int32_t steps;    /* spindle steps taken in this sample */
    int32_t ib_Q16[PS_MUSCLES]; /* the tendon organs (0 without FW_GTO) */
} fw_record;

#define FW_RING 4 /* records: read out after every sample */

fw_input fw_in;
fw_counters fw_count;
fw_record fw_out[FW_RING];
uint32_t fw_out_head; /* records written so far; the newest is fw_out[(head - 1) % FW_RING] */
uint32_t fw_overruns;  /* samples that ran more than FW_MAX_STEPS spindle steps */
static fw_state st;

/* The working values of one sample, passed from stage to stage. */
typedef struct fw_ctx {
    int64_t t_key, t_Q32;
    int32_t counts, filtered, angle_Q16, restart;
    int32_t torque_counts; /* the sample's signed load by the load rules (FW_GTO) */
    uint32_t t_us;
    int32_t dt_us;
    const fw_interval *dt; /* its constants */
    int32_t L_Q24[PS_MUSCLES], x1_Q24[PS_MUSCLES], v1_Q20[PS_MUSCLES], tmpl_Q24[PS_MUSCLES];
    int32_t status, steps;
} fw_ctx;

enum { FW_NEXT = 0, FW_DONE = 1 }; /* a stage's return: go on, or the sample is finished */

/* ---- arithmetic ------------------------------------------------------------------------ */

/* round(a b / 2^shift) for 0 < shift < 32 and a result within int32: the 64-bit product
 * from 16-bit halves (ps_fx_mul_wide: the M0+ multiplies 32x32->32; libgcc's __muldi3 took
 * ~40 instructions and a call per product), floored after adding 2^(shift-1), exactly as
 * (a b + 2^(shift-1)) >> shift in int64. */
__attribute__((always_inline)) static inline int32_t mul_q(int32_t a, int32_t b, int shift)
{
    ps_fx_wide p = ps_fx_mul_wide(a, b);
    uint32_t rounded = p.lo + (1u << (shift - 1));
    p.hi += rounded < p.lo; /* the carry */
    return (int32_t)(((uint32_t)p.hi << (32 - shift)) | (rounded >> shift));
}

static int32_t clamp_i32(int32_t x, int32_t lo, int32_t hi)
{
    return x < lo ? lo : x > hi ? hi : x;
}

/* An interval in us (0 <= us < 2^21) as seconds in Q30: round(us 1099512 / 2^10) (2^40 / 1e6)
 * in 32-bit products, 1099512 = 1073 2^10 + 760, exactly (mul_q's 64-bit product took ~20
 * instructions more, three times a sample). */
static int32_t us_to_Q30(int32_t us)
{
    const uint32_t u = (uint32_t)us;
    return (int32_t)(u * 1073u + ((u * 760u + 512u) >> 10));
}

/* exp(-y) in Q30 for 0 <= y (Q26) < 32: Taylor series of exp(-y/32) to z^8 (the first term
 * left out, z^9 / 9!, is below 2.8e-6 of it for z < 1), then five squarings: within 22 Q30
 * units of exp at 20 Hz over 8.2-100 ms (three squarings from Q28 were within 20 up to y = 8,
 * and overflowed beyond: a 64 ms interval at the default 20 Hz, which a max_bridge_s up to
 * ChainConfig's 0.1 s bridges, decayed by a wrapped exponent). */
static int32_t exp_neg_Q30(int32_t y_Q26)
{
    static const int32_t inv_k_Q30[9] = {0, 1073741824, 536870912, 357913941, 268435456,
                                         214748365, 178956971, 153391689, 134217728};
    int32_t z = y_Q26 >> 1; /* y / 32 in Q30 */
    int32_t term = 1 << 30, sum = 1 << 30;
    int k;
    for (k = 1; k <= 8 && term != 0; ++k) { /* a term that rounds to 0 ends the series */
        term = -mul_q(mul_q(term, z, 30), inv_k_Q30[k], 30);
        sum += term;
    }
    for (k = 0; k < 5; ++k) {
        sum = mul_q(sum, sum, 30);
    }
    return sum;
}

/* ---- stages ---------------------------------------------------------------------------- */

static int rest_spindles(fw_ctx *c);

/* A double's order as an int64 (IEEE sign-magnitude to two's complement; -0 and +0 alike):
 * the time rules compare times exactly as doubles without a soft-float call. NaN excluded. */
static int64_t order_key(double x)
{
    union { double d; uint64_t u; } v;
    v.d = x;
    return (v.u >> 63) ? -(int64_t)(v.u & 0x7FFFFFFFFFFFFFFFull) : (int64_t)v.u;
}

static int is_finite_time(double x)
{
    union { double d; uint64_t u; } v;
    v.d = x;
    return ((uint32_t)(v.u >> 52) & 0x7FFu) != 0x7FFu;
}

/* x * 2^32 floored, for 0 <= x < 2^31 (s), from the double's bits; -1 outside (the time
 * rules then take the double path). */
static int64_t to_Q32(double x)
{
    union { double d; uint64_t u; } v;
    int32_t e;
    uint64_t mantissa;
    v.d = x;
    if (v.u == 0) {
        return 0;
    }
    e = (int32_t)(v.u >> 52) - 1023; /* the sign bit makes e large: refused */
    if (e >= 31) {
        return -1;
    }
    mantissa = (v.u & 0xFFFFFFFFFFFFFull) | (1ull << 52); /* x = mantissa 2^(e - 52) */
    if (e >= 20) {
        return (int64_t)(mantissa << (e - 20));
    }
    return e > -44 ? (int64_t)(mantissa >> (20 - e)) : 0;
}

/* The host's rule fl(t - t_s) > limit_s for a later t: decided on the Q32 times (interval_Q32
 * is exact to +-1, so 2 units from the limit on either side decide it: the double difference
 * of times this close to a limit is exact to ~1e-18 s), else by the double subtraction (times
 * within 0.5 ns of the limit, or outside to_Q32's range: interval_Q32 < 0). */
static int interval_exceeds(int64_t interval_Q32, int64_t limit_Q32, double t, double limit_s)
{
    if (interval_Q32 >= 0) {
        if (interval_Q32 > limit_Q32 + 2) {
            return 1;
        }
        if (interval_Q32 < limit_Q32 - 2) {
            return 0;
        }
    }
    return order_key(t - st.t_s) > order_key(limit_s);
}

/* is_valid_reading on the float's bits: an integer in 0..max_count (-0 reads 0), else -1. */
static int32_t valid_reading(float x, int32_t max_count)
{
    union { float f; uint32_t u; } v;
    uint32_t mantissa;
    int32_t e;
    v.f = x;
    if ((v.u & 0x7FFFFFFFu) == 0) {
        return 0;
    }
    e = (int32_t)((v.u >> 23) & 0xFFu) - 127;
    if ((v.u >> 31) || e < 0 || e > 23) { /* negative, NaN, inf, below 1 or above 2^24 */
        return -1;
    }
    mantissa = (v.u & 0x7FFFFFu) | 0x800000u;
    if (mantissa & ((1u << (23 - e)) - 1u)) {
        return -1; /* a fraction */
    }
    return (int32_t)(mantissa >> (23 - e)) <= max_count ? (int32_t)(mantissa >> (23 - e)) : -1;
}

/* Move the epoch to the last accepted sample's time and every time kept since the old one
 * back by as much (times are uint32 us since the epoch, kept below 2^31: every use is a
 * difference of nearby times). Called once the epoch is FW_EPOCH_S old; no double addition
 * (it would link libgcc's __aeabi_dadd, 1.7 KB). */
#ifndef FW_EPOCH_S
#define FW_EPOCH_S 1000 /* s */
#endif
static void rebase_epoch(void)
{
    const uint32_t shift = st.t_us;
    int m, k;
    st.epoch_s = st.t_s;
    st.epoch_Q32 = st.t_Q32;
    st.t_us = 0;
    for (k = 0; k < FW_SEGMENTS; ++k) {
        st.seg_t_us[k] -= shift;
    }
    for (m = 0; m < PS_MUSCLES; ++m) {
        st.next_step_us[m] -= shift;
#ifdef FW_GTO
        st.gto_t_us[m] -= shift;
        st.gto_due_us[m] -= shift;
#endif
        for (k = 0; k < FW_PENDING; ++k) {
            st.pending_t_us[m][k] -= shift;
        }
    }
}

#ifdef FW_GTO
/* The load rules of an accepted encoder sample (chain.c's sample_torque): a valid word's signed
 * magnitude (bit 10: clockwise), the last accepted sample's held over an invalid word
 * (invalid_load), 0 without a word (missing_load; not counted at the first sample, as the
 * host's reset). */
static void read_load(fw_ctx *c)
{
    int32_t word;
    if (!fw_in.has_load) {
        fw_count.missing_load += st.started ? 1u : 0u;
        c->torque_counts = 0;
        return;
    }
    word = valid_reading(fw_in.load, PS_LOAD_MAX_WORD);
    if (word < 0) {
        fw_count.invalid_load += 1;
        c->torque_counts = st.started ? st.torque_counts : 0;
        return;
    }
    c->torque_counts = (word & (PS_LOAD_MAGNITUDE_MAX + 1)) ? -(word & PS_LOAD_MAGNITUDE_MAX)
                                                             : word;
    c->torque_counts *= fw_gto_cfg.load_sign;
}
#endif

/* The constants of an interval of dt_us. The decay from the tables (one product) within
 * them, else the series (a longer max_bridge_s). */
static void interval_constants(fw_interval *out, int32_t dt_us)
{
    out->us = dt_us;
    out->Q30 = us_to_Q30(dt_us);
    out->inv_Q11 = dt_us > 0 ? (int32_t)(2048000000u / (uint32_t)dt_us) : 0;
    out->inv_us_Q30 = dt_us > 0 ? (int32_t)((1u << 30) / (uint32_t)dt_us) : 0;
    if (dt_us < 64 * FW_DECAY_COARSE) {
        out->decay_Q30 = mul_q(fw_cfg.decay_coarse_Q30[dt_us >> 6],
                               fw_cfg.decay_fine_Q30[dt_us & 63], 30);
    } else { /* omega dt in Q46; from 32 on exp(-omega dt) is below 2^-46: 0 in Q30 */
        ps_fx_wide y = ps_fx_mul_wide(fw_cfg.omega_Q16, out->Q30);
        out->decay_Q30 = y.hi >= (1 << 19) ? 0
                         : exp_neg_Q30((int32_t)(((uint32_t)y.hi << 12) | (y.lo >> 20)));
    }
    {
        ps_fx_wide limit = ps_fx_mul_wide(fw_cfg.max_speed_deg_Q32_us, dt_us); /* Q32 deg */
        const int far = limit.hi >= (1 << 14); /* 2^14 deg and more: no change reaches it */
        out->angle_limit_Q16 = far ? (1 << 30) : (int32_t)(((uint32_t)limit.hi << 16)
                                                           | (limit.lo >> 16));
        out->angle_limit_frac = far ? 0 : (int32_t)(limit.lo & 0xFFFFu);
    }
    {
        ps_fx_wide limit = ps_fx_mul_wide(fw_cfg.max_speed_L0_Q40_us, dt_us); /* Q40 L0 */
        out->length_limit_Q24 = (int32_t)(((uint32_t)limit.hi << 16) | (limit.lo >> 16));
        out->length_limit_frac = (int32_t)(limit.lo & 0xFFFFu);
    }
}

/* round(since 10^6 / 2^32) for 0 <= since < FW_EPOCH_S 2^32 (Q32 s to us; FW_EPOCH_S below
 * 4295 keeps the result in uint32) in 32-bit
 * products, exactly: 10^6 = 15625 2^6, the low word in 16-bit halves (the int64 product
 * called libgcc's __muldi3, ~45 instructions a sample). */
static uint32_t us_of_Q32(int64_t since)
{
    const uint32_t hi = (uint32_t)(since >> 32), lo = (uint32_t)since;
    const uint32_t a = (lo >> 16) * 15625u, x = (lo & 0xFFFFu) * 15625u + (1u << 25);
    return hi * 1000000u + ((a + (x >> 16)) >> 10);
}

/* The time t of a sample within max_bridge_s of the last accepted one, in us since the epoch
 * (rounded, below 2^31): from the Q32 times, else (a time outside to_Q32's range) the
 * doubles'. The epoch moves on once it is FW_EPOCH_S old. */
static uint32_t time_us(const fw_ctx *c, double t)
{
    double half_us;
    if (c->t_Q32 >= 0 && st.epoch_Q32 >= 0) {
        int64_t since = c->t_Q32 - st.epoch_Q32;
        if (since >= ((int64_t)FW_EPOCH_S << 32)) {
            rebase_epoch();
            since = c->t_Q32 - st.epoch_Q32;
        }
        return us_of_Q32(since);
    }
    half_us = (t - st.epoch_s) * 2e6;
    if (order_key(half_us) >= order_key(2e6 * FW_EPOCH_S)) {
        rebase_epoch();
        half_us = (t - st.epoch_s) * 2e6;
    }
    return ((uint32_t)half_us + 1u) >> 1;
}

/* ArmChain._time and the reading check: the bad-sample rules that reject a sample. */
static int stage_reading(fw_ctx *c)
{
    const double t = fw_in.t_s;
    int64_t t_key;
    if (!is_finite_time(t)) {
        fw_count.bad_time += 1;
        return FW_DONE;
    }
    t_key = order_key(t);
    if (st.started && t_key == st.t_key) {
        fw_count.repeated_time += 1;
        return FW_DONE;
    }
    if (st.started && t_key < st.t_key) {
        st.behind += 1;
        if (st.behind < fw_cfg.resync_after_samples) {
            fw_count.time_backwards += 1;
            return FW_DONE;
        }
    }
    c->counts = valid_reading(fw_in.counts, fw_cfg.max_count);
    if (c->counts < 0) {
        fw_count.invalid_reading += 1;
        return FW_DONE;
    }
    if (!st.started) { /* the host's reset: counters from zero */
        fw_counters zero = {0};
        fw_count = zero;
    }
#ifdef FW_GTO
    read_load(c);
#endif
    c->t_key = t_key;
    c->t_Q32 = to_Q32(t);
    /* before the first valid sample there is no interval: it starts the arm at rest, as the
     * host's reset does (no gap, restart or accepted sample counted) */
    c->restart = !st.started || t_key < st.t_key;
    if (!c->restart && t_key > st.t_key) {
        int64_t interval_Q32 = c->t_Q32 >= 0 && st.t_Q32 >= 0 ? c->t_Q32 - st.t_Q32 : -1;
        if (interval_exceeds(interval_Q32, fw_cfg.gap_Q32, t, fw_cfg.gap_s)) {
            fw_count.gaps += 1;
        }
        c->restart = interval_exceeds(interval_Q32, fw_cfg.max_bridge_Q32, t,
                                      fw_cfg.max_bridge_s);
    }
    if (c->restart) {
        c->t_us = 0;
        c->dt_us = 0;
    } else {
        c->t_us = time_us(c, t);
        c->dt_us = (int32_t)(c->t_us - st.t_us);
    }
    if (c->dt_us != st.interval.us) { /* the nominal interval repeats: no division */
        interval_constants(&st.interval, c->dt_us);
    }
    c->dt = &st.interval;
    return FW_NEXT;
}

/* MedianFilter: the window's middle value (a restart refills the window instead). The window
 * is also kept sorted: the oldest value's place goes to the new one, moved into order (a few
 * compares where sorting the window took ~250 instructions). */
static int stage_median(fw_ctx *c)
{
    const int n = fw_cfg.median_window;
    const int32_t v = c->counts;
    int32_t old;
    int i;
    if (c->restart) {
        for (i = 0; i < n; ++i) {
            st.median[i] = v;
            st.sorted[i] = v;
        }
        st.median_next = 0;
        c->filtered = v;
        return FW_NEXT;
    }
    old = st.median[st.median_next];
    st.median[st.median_next] = v;
    st.median_next = st.median_next + 1 == n ? 0 : st.median_next + 1;
    for (i = 0; st.sorted[i] != old; ++i) {
    }
    for (; i > 0 && st.sorted[i - 1] > v; --i) {
        st.sorted[i] = st.sorted[i - 1];
    }
    for (; i < n - 1 && st.sorted[i + 1] < v; ++i) {
        st.sorted[i] = st.sorted[i + 1];
    }
    st.sorted[i] = v;
    c->filtered = st.sorted[n / 2];
    return FW_NEXT;
}

/* The host's slew rule |x - previous| > limit on values with 16 more bits (the previous
 * value has `below` in them, 0..65535; x, a new reading's, none; the limit is hi and lo in
 * them), for change = x - previous in their last place: 0 (x stands), or 1 with *moved and
 * *frac the previous value moved by the limit towards x. */
__attribute__((noinline)) static int slew_limit(int32_t previous, int32_t below,
                                                int32_t change, int32_t hi, int32_t lo,
                                                int32_t *moved, int32_t *frac)
{
    int32_t sum;
    if (change > 0) { /* the change is change - below / 2^16 */
        if (change - hi <= 0 || (change - hi == 1 && 65536 - below <= lo)) {
            return 0;
        }
        sum = below + lo;
        *moved = previous + hi + (sum >> 16);
    } else { /* -change + below / 2^16 against the limit */
        if (-change - hi < 0 || (-change - hi == 0 && below <= lo)) {
            return 0;
        }
        sum = below - lo;
        *moved = previous - hi + (sum >> 16); /* sum >> 16: the borrow, -1 or 0 */
    }
    *frac = sum & 0xFFFF;
    return 1;
}

/* The bits below a value the previous accepted sample's slew limit set (0 if it set none). */
static int32_t slewed_below(uint32_t tag, int32_t frac)
{
    return tag + 1u == fw_count.accepted ? frac : 0;
}

/* f(x), the angle's slew limit and the clamp to the fitted range. */
static int stage_angle(fw_ctx *c)
{
    int32_t angle = mul_q(c->filtered * 65536 - fw_cfg.zero_Q16, fw_cfg.deg_per_count_Q30, 30);
    if (c->restart) {
        st.angle_frac = 0;
    } else {
        const int32_t limit = c->dt->angle_limit_Q16, change = angle - st.angle_Q16;
        int32_t moved, frac; /* not angle's address: it stays in a register */
        if ((change >= limit || change <= -limit)
            && slew_limit(st.angle_Q16, slewed_below(st.angle_tag, st.angle_frac), change,
                          limit, c->dt->angle_limit_frac, &moved, &frac)) {
            fw_count.slew_limited += 1;
            st.angle_frac = frac; /* no stage after the reading's rejects a sample */
            st.angle_tag = fw_count.accepted;
            angle = moved + (moved == fw_cfg.angle_max_Q16 && frac != 0); /* above: clamped */
        }
    }
    if (angle < fw_cfg.angle_min_Q16 || angle > fw_cfg.angle_max_Q16) {
        fw_count.angle_clamped += 1;
        angle = clamp_i32(angle, fw_cfg.angle_min_Q16, fw_cfg.angle_max_Q16);
        st.angle_frac = 0;
    }
    c->angle_Q16 = angle;
    return FW_NEXT;
}

/* The length fits at the angle: linear between the points of fw_length_Q24, the fits (double,
 * on the host) at every encoder count of the fitted range from its low end (a sample that is
 * not slew-limited lies on a point; between points the error is below 4e-7 L0, the fits'
 * curvature times step^2 / 8). */
static int stage_lengths(fw_ctx *c)
{
    int32_t position = mul_q(c->angle_Q16 - fw_cfg.angle_min_Q16, fw_cfg.length_scale_Q28, 28);
    int32_t j = position >> 16, fraction = position & 0xFFFF;
    int m;
    for (m = 0; m < PS_MUSCLES; ++m) {
        int32_t lo = fw_length_Q24[j][m];
        c->L_Q24[m] = fraction == 0 ? lo : lo + mul_q(fw_length_Q24[j + 1][m] - lo, fraction, 16);
    }
    return FW_NEXT;
}

/* The lengths' slew rule (the host's: a sample is limited if a muscle's length moved more
 * than the limit since the last one; each such length moves by the limit, the others stand),
 * on the Q40 lengths (u_frac below st.u_Q24). */
__attribute__((noinline)) static void slew_lengths(fw_ctx *c)
{
    int32_t moved[PS_MUSCLES], frac[PS_MUSCLES], hit[PS_MUSCLES], m;
    for (m = 0; m < PS_MUSCLES; ++m) {
        hit[m] = slew_limit(st.u_Q24[m], slewed_below(st.u_tag, st.u_frac[m]),
                            c->L_Q24[m] - st.u_Q24[m],
                            c->dt->length_limit_Q24, c->dt->length_limit_frac, &moved[m],
                            &frac[m]);
    }
    fw_count.slew_limited += (uint32_t)(hit[0] | hit[1]);
    st.u_tag = fw_count.accepted;
    for (m = 0; m < PS_MUSCLES; ++m) {
        c->L_Q24[m] = hit[m] ? moved[m] : c->L_Q24[m];
        st.u_frac[m] = hit[m] ? frac[m] : 0;
    }
}

/* The lengths' slew limit and the tracking low-pass (conditioning.tracking_step's closed
 * form: the input linear over the interval). */
static int stage_tracking(fw_ctx *c)
{
    const fw_interval *dt = c->dt;
    int32_t limit = dt->length_limit_Q24, m, limited = 0;
    if (c->restart) {
        st.u_frac[0] = st.u_frac[1] = 0;
        return FW_NEXT;
    }
    for (m = 0; m < PS_MUSCLES; ++m) {
        int32_t change = c->L_Q24[m] - st.u_Q24[m];
        limited |= change >= limit || change <= -limit;
    }
    if (limited) {
        slew_lengths(c);
    }
    for (m = 0; m < PS_MUSCLES; ++m) {
        int32_t u0 = st.u_Q24[m], u1 = c->L_Q24[m], slope, offset, A, B, AB;
        if (dt->us == 0) { /* an interval below 1 us: nothing moves */
            c->x1_Q24[m] = st.x_Q24[m];
            c->v1_Q20[m] = st.v_Q20[m];
            continue;
        }
        /* |slope| <= max_speed_L0_s (<= 10 L0/s: the slew limit above), in Q20 at any
         * interval of 1 us or more */
        slope = mul_q(u1 - u0, dt->inv_Q11, 15);                     /* Q20 */
        offset = mul_q(slope, fw_cfg.two_over_omega_Q32, 28);        /* Q24 */
        A = st.x_Q24[m] - u0 + offset;                               /* Q24 */
        B = st.v_Q20[m] - slope + mul_q(fw_cfg.omega_Q16, A, 20);    /* Q20 */
        AB = A + mul_q(B, dt->Q30, 26);                              /* Q24 */
        c->x1_Q24[m] = u1 - offset + mul_q(AB, dt->decay_Q30, 30);
        c->v1_Q20[m] = slope + mul_q(B - mul_q(fw_cfg.omega_Q16, AB, 20), dt->decay_Q30, 30);
    }
    return FW_NEXT;
}

static int seg_index(int i) { return (st.seg_first + i) & (FW_SEGMENTS - 1); }

/* The templates of segment s at time t (us), both muscles (one interval conversion). */
static void seg_templates(int s, uint32_t t_us, int32_t out_Q24[PS_MUSCLES])
{
    int32_t elapsed_Q30 = us_to_Q30((int32_t)(t_us - st.seg_t_us[s]));
    int m;
    for (m = 0; m < PS_MUSCLES; ++m) {
        out_Q24[m] = st.seg_p_Q24[s][m] + mul_q(st.seg_u_Q20[s][m], elapsed_Q30, 26);
    }
}

/* MotionPredictor (the down-sampled PI template) and Fusimotor: gamma_s = h(x), gamma_d =
 * g(x) from the template now and delay_s ago. */
static int stage_fusimotor(fw_ctx *c)
{
    const int32_t *in = c->restart ? c->L_Q24 : c->x1_Q24;
    int32_t delayed[PS_MUSCLES];
    uint32_t t_d = c->t_us - (uint32_t)fw_cfg.delay_us;
    int m, i;
    if (c->restart) {
        st.seg_first = 0;
        st.seg_count = 1;
        st.seg_t_us[0] = c->t_us;
        for (m = 0; m < PS_MUSCLES; ++m) {
            st.seg_p_Q24[0][m] = in[m];
            st.seg_u_Q20[0][m] = 0;
            st.integral_Q20[m] = 0;
        }
    }
    for (;;) {
        int newest = seg_index(st.seg_count - 1), slot;
        if ((int32_t)(c->t_us - st.seg_t_us[newest]) < fw_cfg.predictor_period_us) {
            break;
        }
        if (st.seg_count == fw_cfg.predictor_keep) {
            st.seg_first = seg_index(1);
            st.seg_count -= 1;
            newest = seg_index(st.seg_count - 1);
        }
        slot = seg_index(st.seg_count);
        st.seg_t_us[slot] = st.seg_t_us[newest] + (uint32_t)fw_cfg.predictor_period_us;
        for (m = 0; m < PS_MUSCLES; ++m) {
            int32_t p = st.seg_p_Q24[newest][m]
                        + mul_q(st.seg_u_Q20[newest][m], fw_cfg.predictor_period_Q30, 26);
            int32_t error = in[m] - p;
            st.integral_Q20[m] += mul_q(fw_cfg.ki_dt_Q16, error, 20);
            st.seg_p_Q24[slot][m] = p;
            st.seg_u_Q20[slot][m] = mul_q(fw_cfg.kp_Q16, error, 20) + st.integral_Q20[m];
        }
        st.seg_count += 1;
    }
    seg_templates(seg_index(st.seg_count - 1), c->t_us, c->tmpl_Q24);
    for (m = 0; m < PS_MUSCLES; ++m) {
        delayed[m] = st.seg_p_Q24[st.seg_first][m];
    }
    for (i = st.seg_count - 1; i >= 0; --i) {
        int s = seg_index(i);
        if ((int32_t)(st.seg_t_us[s] - t_d) <= 0) {
            seg_templates(s, t_d, delayed);
            break;
        }
    }
    for (m = 0; m < PS_MUSCLES; ++m) {
        int32_t gs = fw_cfg.gs_min_Q8 + mul_q(fw_cfg.length_max_Q24[m] - c->tmpl_Q24[m],
                                              fw_cfg.gs_gain_Q8[m], 24);
        st.gs_Q8[m] = clamp_i32(gs, fw_cfg.gs_min_Q8, fw_cfg.gs_max_Q8);
        st.gd_Q8[m] = delayed[m] - c->tmpl_Q24[m] > fw_cfg.threshold_Q24 ? 0 : fw_cfg.gd_Q8;
    }
    return FW_NEXT;
}

/* The length at grid time tau of the Hermite curve through the interval's ends. */
static int32_t hermite_Q24(const fw_ctx *c, int m, uint32_t tau_us)
{
    int32_t s = mul_q((int32_t)(tau_us - st.t_us), c->dt->inv_us_Q30, 6); /* Q24, no division */
    int32_t s2 = mul_q(s, s, 24), s3 = mul_q(s2, s, 24);
    int32_t w1 = 3 * s2 - 2 * s3, w2 = s3 - 2 * s2 + s, w3 = s3 - s2;
    int32_t x0 = st.x_Q24[m], x1 = c->x1_Q24[m];
    int32_t slopes = mul_q(w2, st.v_Q20[m], 24) + mul_q(w3, c->v1_Q20[m], 24); /* Q20 */
    return x0 + mul_q(w1, x1 - x0, 24) + mul_q(slopes, c->dt->Q30, 26);
}

#ifndef FW_MAX_STEPS
#define FW_MAX_STEPS 1 /* spindle steps per sample: what bounds a sample's worst case */
#endif
/* Step the muscle whose oldest queued grid point is the earliest. */
static int step_oldest(fw_ctx *c)
{
    int m = 0, k, status;
    int32_t L;
    if (st.pending_n[1] > 0 && (st.pending_n[0] == 0 || (int32_t)(st.pending_t_us[1][0]
                                                        - st.pending_t_us[0][0]) < 0)) {
        m = 1;
    }
    L = st.pending_L_Q24[m][0];
    status = ps_spindle_step_fx(&st.spindle[m], &fw_plan, L, st.gd_Q8[m], st.gs_Q8[m],
                                &st.ia_Q16[m], &st.ii_Q16[m]);
    if (status != PS_OK) {
        c->status = status;
    }
    st.pending_n[m] -= 1;
    for (k = 0; k < st.pending_n[m]; ++k) {
        st.pending_L_Q24[m][k] = st.pending_L_Q24[m][k + 1];
        st.pending_t_us[m][k] = st.pending_t_us[m][k + 1];
    }
    c->steps += 1;
    return status;
}

/* The spindles: every grid point up to spindle_lead_us after the sample queues its length (in
 * the interval the Hermite curve, after the sample the tracking filter's line x1 + v1 (tau - t),
 * within the slew limit of the previous grid point and the spindle's range): a muscle's rates
 * then stand for a grid point within half a step of the sample, not up to a step before it
 * (the output's lag was the larger part of the RMS against the host); at most FW_MAX_STEPS of
 * the queued steps run in this sample, oldest first (a queue that fills runs its oldest at
 * once, counted in fw_overruns). */
static int stage_spindles(fw_ctx *c)
{
    const int32_t reach = fw_cfg.spindle_reach_Q24;
    int m, k;
    if (c->restart) {
        return rest_spindles(c);
    }
    for (m = 0; m < PS_MUSCLES; ++m) {
        while ((int32_t)(c->t_us + (uint32_t)fw_cfg.spindle_lead_us - st.next_step_us[m]) >= 0) {
            int32_t ahead = (int32_t)(st.next_step_us[m] - c->t_us);
            int32_t L = ahead == 0 ? c->x1_Q24[m]
                        : ahead < 0 ? hermite_Q24(c, m, st.next_step_us[m])
                                    : c->x1_Q24[m] + mul_q(c->v1_Q20[m], us_to_Q30(ahead), 26);
            L = clamp_i32(L, st.last_L_Q24[m] - reach, st.last_L_Q24[m] + reach);
            L = clamp_i32(L, PS_FX_ONE / 2, PS_FX_ONE + PS_FX_ONE / 2);
            if (st.pending_n[m] == FW_PENDING) {
                fw_overruns += 1;
                (void)step_oldest(c);
            }
            st.pending_L_Q24[m][st.pending_n[m]] = L;
            st.pending_t_us[m][st.pending_n[m]] = st.next_step_us[m];
            st.pending_n[m] += 1;
            st.last_L_Q24[m] = L;
            st.next_step_us[m] += (uint32_t)fw_cfg.spindle_step_us;
        }
    }
    for (k = 0; k < FW_MAX_STEPS && st.pending_n[0] + st.pending_n[1] > 0; ++k) {
        if (step_oldest(c) != PS_OK) {
            break;
        }
    }
    return FW_NEXT;
}

/* At rest at the sample: the spindles' equilibrium, their grids restarting from now. */
static int rest_spindles(fw_ctx *c)
{
    int m;
    for (m = 0; m < PS_MUSCLES; ++m) {
        int status = ps_spindle_fx_init(&st.spindle[m], &fw_plan, c->L_Q24[m], st.gd_Q8[m],
                                        st.gs_Q8[m]);
        if (status != PS_OK) {
            c->status = status;
            return FW_NEXT;
        }
        ps_spindle_fx_afferents(&st.spindle[m], &fw_plan, &st.ia_Q16[m], &st.ii_Q16[m]);
        st.last_L_Q24[m] = c->L_Q24[m];
        st.pending_n[m] = 0;
        st.next_step_us[m] = c->t_us + (uint32_t)(fw_cfg.spindle_step_us * (m + 1) / 2);
        c->x1_Q24[m] = c->L_Q24[m];
        c->v1_Q20[m] = 0;
    }
    return FW_NEXT;
}

#ifdef FW_GTO
/* tendon_forces_N of muscle m: the torque over the moment arm at the angle (the host's
 * table, linear between its points, clamped to its ends), flexion torque to BRA (m = 0),
 * extension to TRImed. The table holds Nm_per_count / |r| (Q8 N per count), so a force is one
 * product. */
static int32_t tendon_force(const fw_ctx *c, int m)
{
    int32_t position, j, per_count, magnitude;
    if (m == 0 ? c->torque_counts <= 0 : c->torque_counts > 0) {
        return 0;
    }
    position = mul_q(c->angle_Q16 - fw_gto_cfg.arm_lo_Q16, fw_gto_cfg.arm_scale_Q28, 28);
    j = position >> 16;
    magnitude = c->torque_counts < 0 ? -c->torque_counts : c->torque_counts;
    if (position <= 0) {
        per_count = fw_arm_force[0][m] << fw_gto_cfg.arm_shift;
    } else if (j >= fw_gto_cfg.arm_last) {
        per_count = fw_arm_force[fw_gto_cfg.arm_last][m] << fw_gto_cfg.arm_shift;
    } else {
        int32_t lo = fw_arm_force[j][m] << fw_gto_cfg.arm_shift;
        int32_t hi = fw_arm_force[j + 1][m] << fw_gto_cfg.arm_shift;
        per_count = lo + mul_q(hi - lo, position & 0xFFFF, 16); /* Q12 */
    }
    return (magnitude * per_count + 2048) >> 12;
}

/* The plan for a step of h_us: the nominal one, else the table's, linear in h. */
static const ps_gto_plan_fx *gto_plan(int32_t h_us, ps_gto_plan_fx *scratch)
{
    int32_t k = h_us >> FW_GTO_PLAN_SHIFT, w_Q30, i;
    int32_t *out = &scratch->phi[0][0];
    const int32_t *a, *b;
    if (h_us == fw_gto_cfg.step_us) {
        return &fw_gto_cfg.plan_nominal;
    }
    if (k > fw_gto_cfg.n_plans - 2) {
        k = fw_gto_cfg.n_plans - 2;
    }
    a = fw_gto_cfg.plan_Q30[k];
    b = fw_gto_cfg.plan_Q30[k + 1];
    w_Q30 = (h_us - (k << FW_GTO_PLAN_SHIFT)) << (30 - FW_GTO_PLAN_SHIFT);
    *scratch = fw_gto_cfg.plan_nominal; /* c, gain and 1/a0 do not depend on h */
    for (i = 0; i < 15; ++i) { /* phi, g0, g1 are contiguous in ps_gto_plan_fx */
        out[i] = a[i] + mul_q(b[i] - a[i], w_Q30, 30);
    }
    return scratch;
}

/* An organ steps at the first sample within half a sample of its grid point: from its last
 * step to this sample, the force a line over the step (as chain.c's advance_tendon_organs
 * over a sample). Grid points a long interval skipped are dropped (the step covers them). */
static int gto_advance(const fw_ctx *c, int m)
{
    ps_gto_fx *g = &st.gto[m];
    ps_gto_plan_fx scratch;
    int32_t force_Q8;
    if ((int32_t)(c->t_us - st.gto_due_us[m]) < -(FW_SAMPLE_US / 2)) {
        return PS_OK;
    }
    do {
        st.gto_due_us[m] += (uint32_t)fw_gto_cfg.step_us;
    } while ((int32_t)(c->t_us - st.gto_due_us[m]) >= -(FW_SAMPLE_US / 2));
    force_Q8 = tendon_force(c, m);
    if (force_Q8 == 0 && g->r == 0 && g->z[0] == 0 && g->z[1] == 0 && g->z[2] == 0) {
        st.gto_t_us[m] = c->t_us; /* at rest at zero force it stays there */
        st.ib_Q16[m] = 0;
        return PS_OK;
    }
    {
        int32_t h_us = (int32_t)(c->t_us - st.gto_t_us[m]);
        st.gto_t_us[m] = c->t_us;
        return ps_gto_step_fx(g, gto_plan(h_us, &scratch), force_Q8,
                              fw_gto_cfg.inv_scale_Q24[m], &st.ib_Q16[m]);
    }
}

/* The tendon organs (Ib): at rest at a restart's force (their grids restarting from now,
 * offset by half a step), else each on its grid (gto_advance). */
static int stage_tendon(fw_ctx *c)
{
    int m, status = PS_OK;
    for (m = 0; m < PS_MUSCLES; ++m) {
        if (c->restart) {
            const ps_gto_plan_fx *plan = &fw_gto_cfg.plan_nominal;
            status = ps_gto_fx_init(&st.gto[m], plan, tendon_force(c, m),
                                    fw_gto_cfg.inv_scale_Q24[m]);
            st.ib_Q16[m] = ps_gto_rate_fx(&st.gto[m], plan);
            st.gto_t_us[m] = c->t_us;
            st.gto_due_us[m] = c->t_us + (uint32_t)(fw_gto_cfg.step_us * (m + 1) / 2);
        } else {
            status = gto_advance(c, m);
        }
        if (status != PS_OK) {
            c->status = status;
        }
    }
    return FW_NEXT;
}
#endif

#ifdef FW_STIM
/* The stimulation encoder (stimulation.c's fixed-point form, ps_stim_fx_step): the interval
 * that just ended, [previous sample, this sample), carried the rates the previous sample
 * output (held until this one), so it is encoded with those; its pulse events go to the ring
 * fw_pulses. Nothing is delivered across a restart (the interval is not bridged). */
#define FW_PULSE_RING 16 /* read out (by the stimulator's driver) after every sample */
#define FW_MAX_PULSES 8  /* per sample: 4 channels at <= 300 pps over <= 6 ms need <= 8 */
ps_pulse_fx fw_pulses[FW_PULSE_RING];
uint32_t fw_pulse_head; /* events written so far */
uint32_t fw_pulse_lost; /* samples whose pulses did not fit FW_MAX_PULSES (not delivered) */
static ps_stim_fx_state stim;
static ps_pulse_fx events[FW_MAX_PULSES]; /* one sample's pulses (static: not on the stack) */

static int stage_stim(fw_ctx *c)
{
    long n = 0, k;
    int status;
    if (c->restart || c->dt_us <= 0) {
        return FW_NEXT;
    }
    status = ps_stim_fx_step(&stim, &fw_stim_config, st.held_Q16, c->dt_us, events,
                             FW_MAX_PULSES, &n);
    if (status == PS_ERR_BUFFER_FULL) {
        fw_pulse_lost += 1;
        return FW_NEXT;
    }
    if (status != PS_OK) {
        c->status = status;
        return FW_NEXT;
    }
    for (k = 0; k < n; ++k) {
        fw_pulses[fw_pulse_head % FW_PULSE_RING] = events[k];
        fw_pulse_head += 1;
    }
    return FW_NEXT;
}
#endif

/* Commit the sample and write its record. */
static int stage_output(fw_ctx *c)
{
    fw_record *r = &fw_out[fw_out_head % FW_RING];
    int m;
    for (m = 0; m < PS_MUSCLES; ++m) {
        st.u_Q24[m] = c->L_Q24[m];
        st.x_Q24[m] = c->x1_Q24[m];
        st.v_Q20[m] = c->v1_Q20[m];
        r->ia_Q16[m] = st.ia_Q16[m];
        r->ii_Q16[m] = st.ii_Q16[m];
        r->gs_Q8[m] = st.gs_Q8[m];
        r->gd_Q8[m] = st.gd_Q8[m];
        r->ib_Q16[m] = st.ib_Q16[m];
    }
#ifdef FW_STIM
    /* the channels' rates until the next sample */
    for (m = 0; m < fw_stim_config.n_channels; ++m) {
        int32_t muscle = fw_stim_source[m][0], afferent = fw_stim_source[m][1];
        st.held_Q16[m] = afferent == 0 ? st.ia_Q16[muscle]
                         : afferent == 1 ? st.ii_Q16[muscle] : st.ib_Q16[muscle];
    }
#endif
    if (st.started) {
        fw_count.accepted += 1;
        if (c->restart) {
            fw_count.restarts += 1;
            fw_count.clock_resyncs += c->t_key < st.t_key ? 1u : 0u;
        }
    }
    st.started = 1;
    st.angle_Q16 = c->angle_Q16;
#ifdef FW_GTO
    st.torque_counts = c->torque_counts;
#endif
    if (c->restart) {
        st.epoch_s = fw_in.t_s;
        st.epoch_Q32 = c->t_Q32;
    }
    st.t_s = fw_in.t_s;
    st.t_key = c->t_key;
    st.t_Q32 = c->t_Q32;
    st.t_us = c->t_us;
    st.behind = 0;
    r->t_us = c->t_us;
    r->accepted = c->restart ? 2 : 1;
    r->status = c->status;
    r->steps = c->steps;
    fw_out_head += 1;
    return FW_DONE;
}

typedef int (*fw_stage_fn)(fw_ctx *c);

/* The per-sample pipeline, in order (the bench attributes instructions to these). */
static const fw_stage_fn fw_stages[] = {
    stage_reading, stage_median, stage_angle, stage_lengths, stage_tracking, stage_fusimotor,
    stage_spindles,
#ifdef FW_GTO
    stage_tendon,
#endif
#ifdef FW_STIM
    stage_stim,
#endif
    stage_output,
};

/* One encoder sample (fw_in): the timer interrupt's work. Returns PS_OK, or the status of a
 * failed spindle step (the sample is then still committed, its record says so). */
int fw_sample(void)
{
    fw_ctx c;
    unsigned k;
    c.status = PS_OK;
    c.steps = 0;
    for (k = 0; k < sizeof fw_stages / sizeof fw_stages[0]; ++k) {
        if (fw_stages[k](&c) == FW_DONE) {
            break;
        }
    }
    return c.status;
}

/* Before the first sample: the first sample restarts the chain at rest (the host's
 * run_chain resets at the first valid sample: the same outputs and counters). */
int fw_init(void)
{
    st.started = 0;
    st.t_s = 0.0;
    st.behind = 0;
    st.interval.us = -1; /* no interval's constants yet */
    st.ib_Q16[0] = 0;
    st.ib_Q16[1] = 0;
#ifdef FW_GTO
    st.torque_counts = 0;
#endif
    fw_out_head = 0;
    fw_overruns = 0;
#ifdef FW_STIM
    fw_pulse_head = 0;
    fw_pulse_lost = 0;
    return ps_stim_fx_init(&stim, &fw_stim_config, 0);
#else
    return PS_OK;
#endif
}

/* Start-up (vectors, Reset_Handler, fw_halt): startup.c. */

int main(void) { return fw_init(); }
