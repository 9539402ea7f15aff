"""The C stimulator (``stimulation.c``) through ctypes: :class:`CStimulator`, the same
interface, events and counters as :class:`spindle.stimulation.stimulator.NumpyStimulator`,
and the fixed-point form (``ps_stim_fx_*``) for tests and the device build.

The struct mirrors below follow section (4) of ``proprio.h`` field by field; the tests
compare their sizes and offsets with a compiled probe.
"""

from __future__ import annotations

import ctypes
import math
from functools import cache

import numpy as np

from spindle.native import abi, build
from spindle.stimulation.config import MAX_CHANNELS, StimConfig
from spindle.stimulation.encoder import COUNTERS, checked_step_input
from spindle.stimulation.events import empty_events
from spindle.stimulation.trace import checked_trace

FX_RATE_ONE = 1 << 16
"""``PS_STIM_FX_RATE_ONE``: 1 pps in the fixed form's Q16."""
FX_PULSE = 1_000_000 * FX_RATE_ONE
"""``PS_STIM_FX_PULSE``: one pulse of the fixed form's phase."""

i32, i64, u32, u64, dbl = (ctypes.c_int32, ctypes.c_int64, ctypes.c_uint32, ctypes.c_uint64,
                           ctypes.c_double)
M = MAX_CHANNELS
K = len(COUNTERS)


class PsStimChannel(ctypes.Structure):
    _fields_ = [("threshold_uA", i32), ("max_uA", i32), ("phase_us", i32), ("gap_us", i32),
                ("area_cm2", dbl)]


class PsStimConfig(ctypes.Structure):
    _fields_ = [("n_channels", i32), ("mode", i32), ("gamma_shape", i32),
                ("min_interval_us", i32), ("channel", PsStimChannel * M),
                *((name, dbl) for name in (
                    "max_rate_pps", "max_total_rate_pps", "shannon_k", "max_charge_nC",
                    "full_scale_pps", "full_scale_change_pps_s", "carrier_pps", "rate_level",
                    "rate_change", "amp_level", "amp_change", "dead_time_s")),
                ("seed", u64)]


class PsPulse(ctypes.Structure):
    _fields_ = [("time_s", dbl), ("channel", i32), ("amplitude_uA", i32), ("cathodic_us", i32),
                ("gap_us", i32), ("anodic_us", i32)]


class PsStimState(ctypes.Structure):
    _fields_ = [("t_s", dbl), ("last_any_s", dbl), ("phase", dbl * M), ("threshold", dbl * M),
                ("resume_s", dbl * M), ("last_pulse_s", dbl * M), ("previous_pps", dbl * M),
                ("draws", u64 * M), ("counts", (u64 * K) * M), ("ready", i32)]


class PsStimFxConfig(ctypes.Structure):
    _fields_ = [("n_channels", i32), ("mode", i32), ("gamma_shape", i32),
                *((name, i32 * M) for name in ("threshold_uA", "max_uA", "phase_us", "gap_us",
                                               "min_interval_us")),
                *((name, i32) for name in (
                    "max_rate_q16", "carrier_q16", "full_scale_q16", "full_scale_change_pps_s",
                    "rate_level_q16", "rate_change_q16", "amp_level_q16", "amp_change_q16",
                    "dead_us", "min_total_us")),
                ("seed", u64)]


class PsStimFxState(ctypes.Structure):
    _fields_ = [("t_us", i64), ("last_any_us", i64), ("phase", i64 * M), ("threshold", i64 * M),
                ("resume_us", i64 * M), ("last_pulse_us", i64 * M), ("previous_q16", i32 * M),
                ("draws", u64 * M), ("counts", (u32 * K) * M), ("ready", i32)]


class PsPulseFx(ctypes.Structure):
    _fields_ = [("time_us", i64), ("channel", i32), ("amplitude_uA", i32), ("cathodic_us", i32),
                ("gap_us", i32), ("anodic_us", i32)]


PULSE_FX_DTYPE = np.dtype([("time_us", "<i8"), ("channel", "<i4"), ("amplitude_uA", "<i4"),
                           ("cathodic_us", "<i4"), ("gap_us", "<i4"), ("anodic_us", "<i4")],
                          align=True)
"""``ps_pulse_fx`` as a numpy dtype."""


@cache
def library() -> ctypes.CDLL:
    """The double build with the stimulation prototypes declared."""
    lib = build.load("double")
    P = ctypes.POINTER
    lib.ps_stim_bits.restype = u64
    lib.ps_stim_bits.argtypes = [u64, u64, u64]
    lib.ps_stim_uniform.restype = dbl
    lib.ps_stim_uniform.argtypes = [u64, u64, u64]
    lib.ps_stim_log_unit.restype = dbl
    lib.ps_stim_log_unit.argtypes = [dbl]
    lib.ps_stim_gamma_threshold.restype = dbl
    lib.ps_stim_gamma_threshold.argtypes = [u64, u64, u64, i32]
    lib.ps_stim_config_check.argtypes = [P(PsStimConfig)]
    lib.ps_stim_init.argtypes = [P(PsStimState), P(PsStimConfig), dbl]
    lib.ps_stim_max_events.restype = ctypes.c_long
    lib.ps_stim_max_events.argtypes = [P(PsStimConfig), dbl]
    lib.ps_stim_step.argtypes = [P(PsStimState), P(PsStimConfig), P(dbl), dbl, P(PsPulse),
                                 ctypes.c_long, P(ctypes.c_long)]
    lib.ps_stim_run.argtypes = [P(PsStimState), P(PsStimConfig), ctypes.c_long, P(dbl), P(dbl),
                                P(PsPulse), ctypes.c_long, P(ctypes.c_long), P(ctypes.c_long)]
    return lib


@cache
def fixed_library() -> ctypes.CDLL:
    """:func:`library` with the fixed-point prototypes declared too."""
    lib = library()
    P = ctypes.POINTER
    lib.ps_stim_fx_config_init.argtypes = [P(PsStimFxConfig), P(PsStimConfig)]
    lib.ps_stim_fx_neg_log.restype = i64
    lib.ps_stim_fx_neg_log.argtypes = [u64]
    lib.ps_stim_fx_init.argtypes = [P(PsStimFxState), P(PsStimFxConfig), i64]
    lib.ps_stim_fx_step.argtypes = [P(PsStimFxState), P(PsStimFxConfig), P(i32), i32,
                                    P(PsPulseFx), ctypes.c_long, P(ctypes.c_long)]
    return lib


def config_struct(config: StimConfig) -> PsStimConfig:
    """``config`` as a filled ``ps_stim_config``."""
    out = PsStimConfig()
    p, lim = config.params, config.limits
    out.n_channels = config.n_channels
    out.mode = p.code
    out.gamma_shape = p.gamma_shape
    out.min_interval_us = lim.min_interval_us
    for k, c in enumerate(config.channels.channels):
        out.channel[k] = PsStimChannel(c.threshold_uA, c.max_uA, c.phase_us, c.gap_us,
                                       c.area_cm2)
    out.max_rate_pps = lim.max_rate_pps
    out.max_total_rate_pps = lim.max_total_rate_pps or 0.0
    out.shannon_k, out.max_charge_nC = lim.shannon_k, lim.max_charge_nC
    for name in ("full_scale_pps", "full_scale_change_pps_s", "carrier_pps", "rate_level",
                 "rate_change", "amp_level", "amp_change", "dead_time_s", "seed"):
        setattr(out, name, getattr(p, name))
    return out


def _check(code: int, what: str) -> None:
    if code != abi.Status.PS_OK:
        raise RuntimeError(f"{what}: {abi.status_name(code)}")


def _doubles(a: np.ndarray):
    return a.ctypes.data_as(ctypes.POINTER(dbl))


class CStimulator:
    """The C encoder of ``config`` (``backend="c"``)."""

    backend = "c"

    def __init__(self, config: StimConfig, t0_s: float = 0.0) -> None:
        self.config = config
        self._lib = library()
        self._config = config_struct(config)
        self.reset(t0_s)

    def reset(self, t0_s: float = 0.0) -> None:
        if not (isinstance(t0_s, int | float) and math.isfinite(t0_s)):
            raise ValueError(f"t0_s={t0_s!r} must be a finite number")
        state = PsStimState()
        _check(self._lib.ps_stim_init(ctypes.byref(state), ctypes.byref(self._config),
                                      float(t0_s)), "ps_stim_init")
        self.state = state

    def step(self, rates_pps: object, dt_s: float) -> np.ndarray:
        """The pulses of one interval (the numpy step's checks and errors)."""
        rates = checked_step_input(self.config, rates_pps, dt_s)
        return self.run(rates[None, :], float(dt_s))

    def run(self, rates_pps: object, dt_s: object) -> np.ndarray:
        rates, dt = checked_trace(self.config, rates_pps, dt_s)
        capacity = self._max_events(dt)
        out = empty_events(capacity)
        rates = np.ascontiguousarray(rates)
        n_events, n_done = ctypes.c_long(), ctypes.c_long()
        code = self._lib.ps_stim_run(
            ctypes.byref(self.state), ctypes.byref(self._config), rates.shape[0], _doubles(rates),
            _doubles(dt), out.ctypes.data_as(ctypes.POINTER(PsPulse)), capacity,
            ctypes.byref(n_events), ctypes.byref(n_done))
        _check(code, f"ps_stim_run (sample {n_done.value})")
        return out[: n_events.value].copy()

    def _max_events(self, dt: np.ndarray) -> int:
        """The sum of ``ps_stim_max_events`` over the intervals (a buffer that never fills)."""
        per = (1.0 / self.config.params.dead_time_s if self.config.params.mode == "stochastic"
               else self.config.limits.max_rate_pps)
        return int(np.sum(np.floor(dt * per) + 2)) * self.config.n_channels

    @property
    def t_s(self) -> float:
        return self.state.t_s

    @property
    def channel_counters(self) -> np.ndarray:
        n = self.config.n_channels
        return np.array([[self.state.counts[k][j] for j in range(K)] for k in range(n)],
                        dtype=np.int64)

    @property
    def counters(self) -> dict[str, int]:
        return dict(zip(COUNTERS, (int(v) for v in self.channel_counters.sum(axis=0)),
                        strict=True))


def to_q16(rates_pps: object) -> np.ndarray:
    """Rates (pps) as the fixed form's Q16 int32, rounded to nearest (finite rates only; the
    fixed form's negative and clipped rules apply to the integers)."""
    r = np.asarray(rates_pps, dtype=np.float64)
    if not np.all(np.isfinite(r)):
        raise ValueError("the fixed form takes finite rates (apply the non-finite rule first)")
    q = np.floor(np.clip(r, -32767.0, 32767.0) * FX_RATE_ONE + 0.5)
    return q.astype(np.int32)


def fixed_run(config: StimConfig, rates_q16: np.ndarray, dt_us: np.ndarray,
              t0_us: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The fixed-point encoder of ``config`` over a trace: row i of ``rates_q16`` (T,
    channels) held for ``dt_us[i]`` µs, from rest at ``t0_us``. Returns (events as
    :data:`PULSE_FX_DTYPE`, (channels, len(COUNTERS)) counters)."""
    lib = fixed_library()
    q = PsStimFxConfig()
    _check(lib.ps_stim_fx_config_init(ctypes.byref(q), ctypes.byref(config_struct(config))),
           "ps_stim_fx_config_init")
    s = PsStimFxState()
    _check(lib.ps_stim_fx_init(ctypes.byref(s), ctypes.byref(q), int(t0_us)), "ps_stim_fx_init")
    rates = np.ascontiguousarray(abi.checked_int32(rates_q16, "rates_q16"), dtype=np.int32)
    dt = abi.checked_int32(dt_us, "dt_us")
    per = 1.0 / config.params.dead_time_s if config.params.mode == "stochastic" else \
        config.limits.max_rate_pps
    room = int(np.floor(dt.max(initial=1) * 1e-6 * per) + 4) * config.n_channels
    chunk = np.zeros(room, dtype=PULSE_FX_DTYPE)
    got = ctypes.c_long()
    out = []
    for i in range(rates.shape[0]):
        code = lib.ps_stim_fx_step(ctypes.byref(s), ctypes.byref(q),
                                   rates[i].ctypes.data_as(ctypes.POINTER(i32)), int(dt[i]),
                                   chunk.ctypes.data_as(ctypes.POINTER(PsPulseFx)), room,
                                   ctypes.byref(got))
        _check(code, f"ps_stim_fx_step (sample {i})")
        out.append(chunk[: got.value].copy())
    counts = np.array([[s.counts[k][j] for j in range(K)] for k in range(config.n_channels)],
                      dtype=np.int64)
    return (np.concatenate(out) if out else np.zeros(0, PULSE_FX_DTYPE)), counts
