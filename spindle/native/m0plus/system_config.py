"""The whole-system firmware's configuration as C source: a ChainConfig in fixed point.

``system.c`` (``spindle/native/c/m0plus/``) compiles ``fw_system_config.h``: ``const
fw_config fw_cfg`` (the chain's settings and fusimotor constants in the Q formats of
system.c), ``fw_length_Q24`` (the length fits at every encoder count of the fitted range)
and ``const ps_plan_fx fw_plan`` (the spindle plan at the firmware's spindle step, made on the
host by ``ps_plan_fx_init``); for the tendon organs (``FW_GTO``) ``fw_gto_cfg`` (the load's
sign, 1/G2, the fixed-point plans of ``ps_gto_plan_fx_init`` at the organs' step
(:data:`GTO_STEP_S`) and on a 1024 us table) and ``fw_arm_force`` (force per load count over
the moment-arm table). Every number comes from the same resolved ``ps_chain_config`` the
host C chain runs (``spindle.native.chain.chain_config_struct``) and from the ranges
``ps_chain_init`` derives (fitted angle range, each muscle's length range), so the firmware
and the host chain it is compared with share one configuration.

With a stimulator configuration (a ``spindle.stimulation.StimConfig``) it also holds the
channel map ``fw_stim_source[channel] = {muscle index, 0 for Ia / 1 for II / 2 for Ib}`` of the
firmware's ``FW_STIM`` stage; the encoder's constants are ``fw_stim_config.h``
(``spindle.native.m0plus.stim.stim_config_header``, from ``ps_stim_fx_config_init``).

``python -m spindle.native.m0plus.system_config > fw_system_config.h`` writes it for the
default device configuration (:data:`DEVICE_CONFIG`, :data:`SPINDLE_STEP_S`, the default
``StimConfig``: Ia and II of both muscles, frequency mode).
"""

from __future__ import annotations

import math
from dataclasses import replace

from spindle.chain.config import MUSCLES, ChainConfig
from spindle.chain.length_model import LengthFits, load_length_fits
from spindle.chain.sensor import LOAD_MAGNITUDE_MAX
from spindle.native.chain import CArmChain, chain_config_struct
from spindle.native.m0plus.build import _initializer
from spindle.params import HUMAN

AFFERENTS = ("ia", "ii", "ib")
"""The afferents of ``fw_stim_source``, by index (system.c's held rates)."""

SPINDLE_STEP_S = 8e-3
"""The firmware's spindle step: 0.5 steps per sample at 500 Hz for the two muscles (grids
offset by half a step, so a sample steps at most one of them), each grid point stepped up to
half a step before its time (``spindle_lead_us``: the length from the tracking filter's line
past the sample), so a muscle's rates stand within half a step of the sample. Measured
against the host double chain (bench_embedded --system-only, worst RMS of Ia and II on the
demo motion / the faulty servo trace): 5 ms without the lead 0.64 / 0.98 pps (9330
instructions a sample), with it 0.42 / 0.73; 6 ms 0.53 / 0.88; 8 ms 0.68 / 1.06 for 2369
instructions a sample where 5 ms took 3668. (At 4 ms, exactly one step per nominal sample, a
backlog after jitter never drains.)"""
DEVICE_CONFIG = ChainConfig(params=HUMAN, max_bridge_s=6e-3)
"""The chain on the device: the seed paper's chain with one change, intervals above 6 ms
(two lost samples) restart at rest instead of being bridged, which bounds a sample's work to
three spindle steps (the deadline; the host default bridges 50 ms, 25 sub-steps)."""


DECAY_COARSE = 128
"""``FW_DECAY_COARSE`` of system.c: the tracking filter's decay tables cover 128 x 64 us."""
GTO_PLANS = 30
"""``FW_GTO_PLANS`` of system.c: the tendon organs' plan table, h = 0, 1024 us, ... 29.7 ms."""
GTO_PLAN_STEP_US = 1024
"""``1 << FW_GTO_PLAN_SHIFT``: the table's step."""
NOMINAL_INTERVAL_US = 2000
"""The encoder's period (500 Hz, ``FW_SAMPLE_US``)."""
GTO_STEP_S = 8e-3
"""The tendon organs' step in the firmware (``fw_gto_config.step_us``, its own exact plan):
four samples, the two muscles' grids offset by half a step (one organ steps every second
sample); the host chain steps them every sample. Measured (worst Ib RMS against the host
double chain on the demo motion / the faulty trace; instructions a sample on the demo;
TRImed Ib on the 60 samples of test_time_and_load_rules_at_their_limits_as_the_host, whose
load word flips from flexion to extension at once): every sample 0.0004 / 0.0004 pps, 2176;
4 ms -, 0.24; 8 ms 0.20 / 0.26 pps, 606, 0.94; 16 ms 0.44 / 0.44 pps, 336, 2.32 (the held
output lags a sudden load by up to a step: 16 ms is too coarse)."""
FORCE_PER_COUNT_BITS = 12
"""``fw_arm_force``: force (Q8 N) per load count, in Q12 (stored >> ``arm_shift`` as uint16)."""


def _q(value: float, bits: int) -> int:
    out = round(value * 2.0**bits)
    if not -2**31 <= out < 2**31:
        raise ValueError(f"{value!r} does not fit Q{bits} in int32")
    return out


def fixed_config(config: ChainConfig, fits: LengthFits, spindle_step_s: float) -> dict:
    """The fields of ``fw_config`` (system.c), in order, as integers (and the two times)."""
    c = chain_config_struct(config, fits, "double")
    ranges = CArmChain(config, fits)
    if c.lowpass_rad_s <= 0:
        raise ValueError("the firmware needs the tracking low-pass (lowpass_hz not None)")
    if c.theta != 0.5:
        raise ValueError("the firmware's fixed-point spindles are trapezoidal")
    lo_deg, hi_deg = ranges.angle_range_deg
    step_us = round(spindle_step_s * 1e6)
    period_s = 1.0 / c.predictor_rate_hz
    span = c.gamma_static_max_pps - c.gamma_static_min_pps
    return {
        "gap_s": float(c.gap_s), "max_bridge_s": float(c.max_bridge_s),
        "gap_Q32": round(c.gap_s * 2.0**32), "max_bridge_Q32": round(c.max_bridge_s * 2.0**32),
        "resync_after_samples": int(c.resync_after_samples),
        "max_count": int(c.max_count), "median_window": int(c.median_window),
        "zero_Q16": _q(c.zero_count, 16),
        "deg_per_count_Q30": _q(c.count_sign * c.deg_per_count, 30),
        "angle_min_Q16": _q(lo_deg, 16), "angle_max_Q16": _q(hi_deg, 16),
        "length_scale_Q28": _q(1.0 / c.deg_per_count, 28),
        "max_speed_deg_Q32_us": _q(c.max_speed_deg_s * 1e-6, 32),
        "max_speed_L0_Q40_us": _q(c.max_speed_L0_s * 1e-6, 40),
        "omega_Q16": _q(c.lowpass_rad_s, 16),
        "two_over_omega_Q32": _q(2.0 / c.lowpass_rad_s, 32),
        "predictor_period_us": round(period_s * 1e6),
        "predictor_keep": math.ceil(c.delay_s * c.predictor_rate_hz) + 2,
        "predictor_period_Q30": _q(period_s, 30),
        "kp_Q16": _q(c.predictor_kp_1_s, 16),
        "ki_dt_Q16": _q(c.predictor_ki_1_s2 * period_s, 16),
        "delay_us": round(c.delay_s * 1e6),
        "threshold_Q24": _q(c.shortening_threshold_L0, 24),
        "gs_min_Q8": _q(c.gamma_static_min_pps, 8), "gs_max_Q8": _q(c.gamma_static_max_pps, 8),
        "gd_Q8": _q(c.gamma_dynamic_pps, 8),
        "length_max_Q24": [_q(x, 24) for x in ranges.length_max_L0],
        "gs_gain_Q8": [_q(span / (hi - lo), 8)
                        for lo, hi in zip(ranges.length_min_L0, ranges.length_max_L0,
                                          strict=True)],
        "spindle_step_us": step_us,
        "spindle_reach_Q24": _round_q_product(_q(c.max_speed_L0_s * 1e-6, 40), step_us, 16),
        "spindle_lead_us": step_us // 2,
        "decay_coarse_Q30": [_q(math.exp(-c.lowpass_rad_s * 64e-6 * i), 30)
                             for i in range(DECAY_COARSE)],
        "decay_fine_Q30": [_q(math.exp(-c.lowpass_rad_s * 1e-6 * j), 30) for j in range(64)],
    }


def length_table(config: ChainConfig, fits: LengthFits) -> list[list[int]]:
    """``fw_length_Q24``: the length fits (Q24 L0; the Chebyshev series in double, as
    ``ps_chain_config`` holds them) at every encoder count of the fitted range from its low
    end, one point past the high end (the last interval's upper point)."""
    import numpy as np
    from numpy.polynomial import chebyshev

    c = chain_config_struct(config, fits, "double")
    lo, hi = c.fit_lo_rad, c.fit_hi_rad
    step = math.radians(c.deg_per_count)
    angles = lo + step * np.arange(math.floor((hi - lo) / step) + 2)
    x = (2 * angles - (lo + hi)) / (hi - lo)
    lengths = [chebyshev.chebval(x, list(c.coefficients[m])[:c.n_coefficients[m]])
               for m in range(len(MUSCLES))]
    return [[_q(float(lengths[m][i]), 24) for m in range(len(MUSCLES))]
            for i in range(len(angles))]


def _plan_fields(plan) -> list[int]:
    """phi (row-major), g0, g1 of a ``PsGtoPlanFx``: what changes with h."""
    return [int(v) for row in plan.phi for v in row] + [int(v) for v in plan.g0] + \
        [int(v) for v in plan.g1]


def gto_config(config: ChainConfig, moment_arms=None,
               gto_step_s: float = GTO_STEP_S) -> tuple[dict, list[list[int]]]:
    """The fields of ``fw_gto_config`` (system.c) and ``fw_arm_force`` (per grid point, per
    muscle, Q12 >> ``arm_shift``), from the force-sense settings of ``config`` as
    ``ps_chain_config`` holds them (``_fill_force_sense``): the load's resolution and sign,
    the moment-arm table, G2 and the tendon organs' fixed-point plans
    (``ps_gto_plan_fx_init``) at their step ``gto_step_s`` and on the table (to the longest
    step: ``gto_step_s`` + max_bridge_s, a grid point just missed and the longest bridged
    interval after it)."""
    from spindle.chain.force import load_moment_arm_fits
    from spindle.native.tendon_organ import FX_FORCE, fixed_inv_scale, fixed_plan

    arms = moment_arms if moment_arms is not None else \
        load_moment_arm_fits(config.moment_arm_fits_path)
    step_us = round(gto_step_s * 1e6)
    longest_us = step_us + config.max_bridge_s * 1e6 + 2
    if step_us < NOMINAL_INTERVAL_US or longest_us > (GTO_PLANS - 1) * GTO_PLAN_STEP_US:
        raise ValueError(f"gto_step_s={gto_step_s!r} with max_bridge_s={config.max_bridge_s!r}"
                         f" leaves the firmware's tendon-organ plans "
                         f"({(GTO_PLANS - 1) * GTO_PLAN_STEP_US} us)")
    n_plans = min(GTO_PLANS, math.ceil(longest_us / GTO_PLAN_STEP_US) + 1)
    nominal = fixed_plan(config.gto, step_us * 1e-6)
    identity = [1 << 30 if i == j else 0 for i in range(3) for j in range(3)] + [0] * 6
    plans = [identity] + [_plan_fields(fixed_plan(config.gto, k * GTO_PLAN_STEP_US * 1e-6))
                          for k in range(1, n_plans)]
    plans += [[0] * 15] * (GTO_PLANS - n_plans)
    lo, hi = (math.degrees(a) for a in arms.valid_range_rad)
    points = len(arms.table_m[0])
    per_count = config.load.Nm_per_count * FX_FORCE * 2.0**FORCE_PER_COUNT_BITS
    table = [[round(per_count / abs(arms.table_m[m][i])) for m in range(len(MUSCLES))]
             for i in range(points)]
    largest = max(max(row) for row in table)
    if largest * LOAD_MAGNITUDE_MAX >= 2**31:
        raise ValueError("a moment arm this short overflows the firmware's force product")
    shift = max(0, largest.bit_length() - 16)  # into uint16
    table = [[round(v / 2**shift) for v in row] for row in table]
    fields = {
        "load_sign": int(config.calibration.sign),
        "arm_lo_Q16": _q(lo, 16), "arm_scale_Q28": _q((points - 1) / (hi - lo), 28),
        "arm_last": points - 1, "arm_shift": shift,
        "inv_scale_Q24": [fixed_inv_scale(g2) for g2 in config.force_scale_N],
        "step_us": step_us,
        "plan_nominal": _struct_literal(nominal),
        "n_plans": n_plans,
        "plan_Q30": plans,
    }
    return fields, table


class _Raw(str):
    """A C initializer written as is."""


def _struct_literal(plan) -> _Raw:
    """A ``PsGtoPlanFx`` as a C initializer."""
    phi = [[int(v) for v in row] for row in plan.phi]
    rest = [[int(v) for v in getattr(plan, name)] for name in ("g0", "g1", "c")]
    return _Raw(_literal([phi, *rest, int(plan.gain), int(plan.inv_a0)]))


def _round_q_product(a: int, b: int, shift: int) -> int:
    """system.c's mul_q: round(a b / 2^shift), half up (the firmware's own rounding)."""
    return (a * b + (1 << (shift - 1))) >> shift


def _literal(value) -> str:
    if isinstance(value, _Raw):
        return str(value)
    if isinstance(value, float):
        return value.hex()
    if isinstance(value, list):
        return "{" + ", ".join(_literal(v) for v in value) + "}"
    return f"{value}L" if abs(value) > 32767 else str(value)


def stim_channel_source(stim) -> str:
    """``fw_stim_source``, the channel map of a ``StimConfig`` for the FW_STIM stage: per
    channel {muscle index, 0 for Ia / 1 for II / 2 for Ib} (Ib needs the FW_GTO stage). The
    encoder's own constants are ``fw_stim_config.h`` (``spindle.native.m0plus.stim``)."""
    sources = []
    for ch in stim.channels.channels:
        if ch.muscle not in MUSCLES or ch.afferent not in AFFERENTS:
            raise ValueError(f"channel {ch.label}: the firmware drives {AFFERENTS} of "
                             f"{MUSCLES} only")
        sources.append((MUSCLES.index(ch.muscle), AFFERENTS.index(ch.afferent)))
    rows = ", ".join(f"{{{m}, {a}}}" for m, a in sources)
    return f"const int32_t fw_stim_source[PS_STIM_MAX_CHANNELS][2] = {{{rows}}};\n"


def system_config_source(config: ChainConfig = DEVICE_CONFIG, fits: LengthFits | None = None,
                         spindle_step_s: float = SPINDLE_STEP_S, stim=None,
                         tendon_organs: bool = True, gto_step_s: float = GTO_STEP_S) -> str:
    """fw_system_config.h for ``config``, ``fits``, the spindle step, (if not None) the
    stimulator's ``StimConfig`` and (``tendon_organs``) the FW_GTO stage's constants, its
    organs stepping every ``gto_step_s``."""
    from spindle.native import fixed
    from spindle.native.spindle import library

    fits = fits if fits is not None else load_length_fits(config.fits_path)
    fields = fixed_config(config, fits, spindle_step_s)
    lib = library("double")
    fixed.declare_fixed(lib, "double")
    plan = fixed.make_plan(lib, config.params, round(spindle_step_s * 1e6) * 1e-6, 0.5, "double")
    plan_body = _initializer(plan, lambda _ctype, value: _literal(int(value)))
    body = ",\n    ".join(f".{k} = {_literal(v)}" for k, v in fields.items())
    return ("/* Generated by spindle.native.m0plus.system_config: the chain's configuration in\n"
            f" * the firmware's fixed point, fits of {', '.join(fits.muscles)} (elbow.xml sha256 "
            f"{fits.model_sha256[:12]}),\n * spindle plan at {spindle_step_s * 1e3:g} ms "
            "(ps_plan_fx_init). */\n"
            f"const fw_config fw_cfg = {{\n    {body}\n}};\n\n"
            f"const ps_plan_fx fw_plan = {{\n    {plan_body}\n}};\n"
            + _table_source("fw_length_Q24", length_table(config, fits))
            + ("" if stim is None else "\n" + stim_channel_source(stim))
            + ("" if not tendon_organs else "\n#ifdef FW_GTO\n" + _gto_source(config, gto_step_s)
               + "#endif\n"))


def _gto_source(config: ChainConfig, gto_step_s: float) -> str:
    fields, table = gto_config(config, gto_step_s=gto_step_s)
    body = ",\n    ".join(f".{k} = {_literal(v)}" for k, v in fields.items())
    return (f"const fw_gto_config fw_gto_cfg = {{\n    {body}\n}};\n"
            + _table_source("fw_arm_force", table, "uint16_t"))


def _table_source(name: str, table: list[list[int]], ctype: str = "int32_t") -> str:
    """A per-point, per-muscle table as a C definition."""
    rows = ",\n    ".join(_literal(row) for row in table)
    return f"const {ctype} {name}[{len(table)}][PS_MUSCLES] = {{\n    {rows}\n}};\n"


def device_config(**changes) -> ChainConfig:
    """DEVICE_CONFIG with ``changes`` (e.g. another ``max_bridge_s``)."""
    return replace(DEVICE_CONFIG, **changes)


if __name__ == "__main__":
    import tempfile
    from pathlib import Path

    from spindle.native.m0plus.stim import stim_config_header
    from spindle.stimulation.config import StimConfig

    print(system_config_source(stim=StimConfig()), end="")
    with tempfile.TemporaryDirectory() as tmp:  # and the encoder's fw_stim_config.h
        print("\n" + (stim_config_header(StimConfig(), Path(tmp)) / "fw_stim_config.h")
              .read_text(), end="")
