"""The C backend of the arm chain: :class:`CArmChain`, ``c/chain.c`` through ctypes.

``spindle.chain.make_chain(ChainConfig(backend="c"))`` returns a :class:`CArmChain`: the same
API, outputs and counters as the numpy :class:`~spindle.chain.arm.ArmChain` (the double build
agrees to round-off), with every push done in C and each block push in ONE C call. The library
is compiled on first use (:mod:`spindle.native.build`); without a C compiler the constructor
raises :class:`~spindle.native.build.CBackendError` saying so.

As in the numpy chain, a push that fails (a spindle step that does not converge) raises and
leaves the chain exactly as it was (see ``docs/c_chain.md``).
"""

from __future__ import annotations

import ctypes
import math
from dataclasses import fields, replace
from functools import cache

import numpy as np

from spindle import core, number_rule
from spindle.chain.conditioning import natural_rad_s
from spindle.chain.config import (
    COUNTERS,
    MUSCLES,
    ArmSample,
    ChainConfig,
    real_array,
    real_number,
)
from spindle.chain.force import MomentArmFits, load_moment_arm_fits
from spindle.chain.length_model import LengthFits, load_length_fits
from spindle.chain.samples import (
    BatchSample,
    block_inputs,
    check_loads,
    checked_angle,
    checked_lengths,
)
from spindle.methods import get_method
from spindle.native import build
from spindle.native.abi import Status, params_struct, real_type, status_name
from spindle.native.abi import structs as spindle_structs
from spindle.renamed import renamed_attribute
from spindle.tendon_organ import TendonOrganState

# Constants of proprio.h's chain section (checked against the header by the tests).
MEDIAN_MAX_WINDOW = 15
FIT_MAX_COEFFS = 16
PREDICTOR_MAX_SEGMENTS = 16
MAX_UPDATES = 1_000_000
MOMENT_ARM_MAX_POINTS = 320

PER_MUSCLE = ("length_L0", "velocity_L0_s", "acceleration_L0_s2", "template_L0",
              "gamma_static_pps", "gamma_dynamic_pps", "ia_pps", "ii_pps", "force_N", "ib_pps")
"""ArmSample's per-muscle fields, in the order ps_arm_sample stores them (contiguous)."""
SAMPLE_FIELDS = tuple(f.name for f in fields(ArmSample))
SCALARS = ("counts", "counts_filtered", "angle_deg", "torque_Nm")
"""ps_arm_sample's real scalars after t_s and accepted, in order."""
assert SAMPLE_FIELDS[2:6] == SCALARS and SAMPLE_FIELDS[6:] == PER_MUSCLE


@cache
def structs(variant: str = "double") -> dict[str, type]:
    """ctypes mirrors of the chain section's structs for ``variant``."""
    real = real_type(variant)
    PsParams, PsSpindle = spindle_structs(variant)
    pair = real * 2
    n_muscles = len(MUSCLES)

    class PsMedian(ctypes.Structure):
        _fields_ = [("values", real * MEDIAN_MAX_WINDOW), ("window", ctypes.c_int),
                    ("next", ctypes.c_int)]

    class PsPredictor(ctypes.Structure):
        _fields_ = [("t", ctypes.c_double * PREDICTOR_MAX_SEGMENTS),
                    ("p", pair * PREDICTOR_MAX_SEGMENTS), ("u", pair * PREDICTOR_MAX_SEGMENTS),
                    ("integral", pair), ("first", ctypes.c_int), ("count", ctypes.c_int)]

    class PsCounters(ctypes.Structure):
        _fields_ = [(name, ctypes.c_ulong) for name in COUNTERS]

    class PsArmSample(ctypes.Structure):
        _fields_ = [("t_s", ctypes.c_double), ("accepted", ctypes.c_int),
                    *[(name, real) for name in SCALARS], *[(name, pair) for name in PER_MUSCLE]]

    class PsGtoParams(ctypes.Structure):
        _fields_ = [("gain_pps", real), ("tau_lowpass_s", real), ("num", real * 3),
                    ("den", real * 2)]

    class PsGtoPlan(ctypes.Structure):
        _fields_ = [("phi", (real * 3) * 3), ("g0", real * 3), ("g1", real * 3),
                    ("c", real * 3), ("gain_pps", real), ("inv_a0", real), ("h", real)]

    class PsGto(ctypes.Structure):
        _fields_ = [("z", real * 3), ("force_N", real), ("r_pps", real)]

    class PsChainConfig(ctypes.Structure):
        _fields_ = [
            ("max_count", real), ("zero_count", real), ("count_sign", real),
            ("deg_per_count", real), ("median_window", ctypes.c_int),
            ("n_coefficients", ctypes.c_int * n_muscles),
            ("coefficients", (real * FIT_MAX_COEFFS) * n_muscles),
            ("fit_lo_rad", real), ("fit_hi_rad", real), ("lowpass_rad_s", real),
            ("gap_s", ctypes.c_double), ("max_bridge_s", ctypes.c_double),
            ("resync_after_samples", ctypes.c_long),
            ("max_speed_deg_s", real), ("max_speed_L0_s", real),
            ("gamma_static_min_pps", real), ("gamma_static_max_pps", real),
            ("gamma_dynamic_pps", real), ("delay_s", ctypes.c_double),
            ("shortening_threshold_L0", real), ("predictor_rate_hz", real),
            ("predictor_kp_1_s", real), ("predictor_ki_1_s2", real), ("params", PsParams),
            ("theta", real), ("step_s", ctypes.c_double),
            ("load_Nm_per_count", real), ("gto", PsGtoParams), ("force_scale_N", pair),
            ("n_moment_arm_points", ctypes.c_int), ("moment_arm_lo_rad", real),
            ("moment_arm_hi_rad", real),
            ("moment_arm_m", (real * MOMENT_ARM_MAX_POINTS) * n_muscles),
        ]

    class PsChainState(ctypes.Structure):
        _fields_ = [
            ("median", PsMedian), ("predictor", PsPredictor), ("spindle", PsSpindle * n_muscles),
            ("u", pair), ("x", pair), ("v", pair), ("a", pair), ("angle_deg", real),
            ("t_s", ctypes.c_double), ("behind", ctypes.c_long), ("has_intended", ctypes.c_int),
            ("intended_L0", pair), ("gto", PsGto * n_muscles), ("gto_plan", PsGtoPlan),
            ("torque_Nm", real), ("counters", PsCounters), ("last", PsArmSample),
        ]

    class PsArmChain(ctypes.Structure):
        _fields_ = [
            ("config", PsChainConfig), ("angle_min_deg", real), ("angle_max_deg", real),
            ("length_min_L0", pair), ("length_max_L0", pair), ("predictor_keep", ctypes.c_int),
            ("stage", ctypes.c_int), ("state", PsChainState),
        ]

    return {cls.__name__: cls for cls in (PsMedian, PsPredictor, PsCounters, PsArmSample,
                                          PsGtoParams, PsGtoPlan, PsGto, PsChainConfig,
                                          PsChainState, PsArmChain)}


@cache
def sample_dtype(variant: str = "double") -> np.dtype:
    """A numpy structured dtype laid out as ``ps_arm_sample`` (an array of them is a table)."""
    cls = structs(variant)["PsArmSample"]
    real = np.float32 if variant == "float" else np.float64
    kinds = {"t_s": (np.float64, ()), "accepted": (np.intc, ())}
    names, formats, offsets = [], [], []
    for name, _ in cls._fields_:
        base, shape = kinds.get(name, (real, (2,) if name in PER_MUSCLE else ()))
        names.append(name)
        formats.append((base, shape) if shape else base)
        offsets.append(getattr(cls, name).offset)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets,
                     "itemsize": ctypes.sizeof(cls)})


@cache
def library(variant: str = "double") -> ctypes.CDLL:
    """The built library with the chain's prototypes declared."""
    lib = build.load(variant)
    real = real_type(variant)
    s = structs(variant)
    chain_p = ctypes.POINTER(s["PsArmChain"])
    sample_p = ctypes.POINTER(s["PsArmSample"])
    real_p = ctypes.POINTER(real)
    long_p = ctypes.POINTER(ctypes.c_long)
    protos = {
        "ps_chain_init": [chain_p, ctypes.POINTER(s["PsChainConfig"])],
        "ps_chain_length_L0": [chain_p, real, real_p],
        "ps_chain_reset": [chain_p, real, ctypes.c_double, real_p, sample_p],
        "ps_chain_reset_load": [chain_p, real, ctypes.c_double, real_p, real_p, sample_p],
        "ps_chain_push_counts_load": [chain_p, ctypes.c_double, real, real_p, sample_p],
        "ps_chain_push_counts_load_block": [chain_p, ctypes.c_long, ctypes.c_void_p,
                                            ctypes.c_void_p, ctypes.c_void_p, sample_p, long_p],
        "ps_chain_run_counts_load": [chain_p, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p,
                                     ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, long_p],
        "ps_chain_batch_reset_load": [ctypes.c_void_p, ctypes.c_long, ctypes.c_void_p,
                                      ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p,
                                      ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                                      ctypes.c_void_p, long_p],
        "ps_chain_batch_push_counts_load_block": [
            ctypes.c_void_p, ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, long_p, long_p],
        "ps_chain_batch_push_counts_load": [
            ctypes.c_void_p, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, long_p],
        "ps_chain_set_intended_angle": [chain_p, real_p],
        "ps_chain_push_counts": [chain_p, ctypes.c_double, real, sample_p],
        "ps_chain_push_angle": [chain_p, ctypes.c_double, real, sample_p],
        "ps_chain_push_lengths": [chain_p, ctypes.c_double, real_p, real_p, sample_p],
        "ps_chain_push_counts_block": [chain_p, ctypes.c_long, ctypes.c_void_p,
                                        ctypes.c_void_p, sample_p, long_p],
        "ps_chain_push_angle_block": [chain_p, ctypes.c_long, ctypes.c_void_p,
                                        ctypes.c_void_p, sample_p, long_p],
        "ps_chain_push_lengths_block": [chain_p, ctypes.c_long, ctypes.c_void_p,
                                        ctypes.c_void_p, sample_p, long_p],
        **{f"ps_chain_run_{kind}": [chain_p, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p,
                                    ctypes.c_void_p, ctypes.c_void_p, long_p]
           for kind in ("counts", "angle", "lengths")},
        # The batch entry points take raw addresses (numpy buffers; .ctypes.data_as costs us).
        "ps_chain_batch_reset": [ctypes.c_void_p, ctypes.c_long, ctypes.c_void_p, ctypes.c_long,
                                 ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                                 ctypes.c_void_p, ctypes.c_void_p, long_p],
        "ps_chain_batch_set_intended_angle": [ctypes.c_void_p, ctypes.c_long, ctypes.c_void_p,
                                              long_p],
        **{f"ps_chain_batch_push_{kind}_block": [
            ctypes.c_void_p, ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, long_p, long_p]
           for kind in ("counts", "angle", "lengths")},
        **{f"ps_chain_batch_push_{kind}": [
            ctypes.c_void_p, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.c_void_p, ctypes.c_void_p, long_p]
           for kind in ("counts", "angle", "lengths")},
    }
    for name, argtypes in protos.items():
        fn = getattr(lib, name)
        fn.argtypes = argtypes
        fn.restype = ctypes.c_int
    return lib


def chain_config_struct(config: ChainConfig, fits: LengthFits, variant: str = "double",
                        moment_arms: MomentArmFits | None = None) -> ctypes.Structure:
    """``config``, ``fits`` and the moment arms (default: ``config.moment_arm_fits_path``'s)
    resolved into a filled ``ps_chain_config``."""
    if len(fits.fits) != len(MUSCLES):
        raise ValueError(f"length fits are for {fits.muscles}, the chain needs {MUSCLES}")
    if config.median_window > MEDIAN_MAX_WINDOW:
        raise ValueError(f"median_window={config.median_window} exceeds the C backend's "
                         f"PS_MEDIAN_MAX_WINDOW={MEDIAN_MAX_WINDOW}")
    out = structs(variant)["PsChainConfig"]()
    enc, cal, fm = config.encoder, config.calibration, config.fusimotor
    out.max_count = enc.max_count
    out.zero_count, out.count_sign, out.deg_per_count = (cal.zero_count, cal.sign,
                                                         cal.deg_per_count)
    out.median_window = config.median_window
    for k, fit in enumerate(fits.fits):
        if len(fit.coefficients) > FIT_MAX_COEFFS:
            raise ValueError(f"the {fit.muscle} fit has {len(fit.coefficients)} coefficients, "
                             f"above the C backend's PS_FIT_MAX_COEFFS={FIT_MAX_COEFFS}")
        out.n_coefficients[k] = len(fit.coefficients)
        out.coefficients[k][:len(fit.coefficients)] = fit.coefficients
    out.fit_lo_rad, out.fit_hi_rad = fits.valid_range_rad
    out.lowpass_rad_s = 0.0 if config.lowpass_hz is None else natural_rad_s(config.lowpass_hz)
    out.gap_s = config.gap_s
    out.max_bridge_s = config.max_bridge_s
    out.resync_after_samples = config.resync_after_samples
    out.max_speed_deg_s = config.max_speed_deg_s
    out.max_speed_L0_s = config.max_speed_L0_s
    out.gamma_static_min_pps = fm.gamma_static_min_pps
    out.gamma_static_max_pps = fm.gamma_static_max_pps
    out.gamma_dynamic_pps = fm.gamma_dynamic_pps
    out.delay_s = fm.delay_s
    out.shortening_threshold_L0 = fm.shortening_threshold_L0
    out.predictor_rate_hz = fm.predictor_rate_hz
    out.predictor_kp_1_s = fm.predictor_kp_1_s
    out.predictor_ki_1_s2 = fm.predictor_ki_1_s2
    if math.ceil(fm.delay_s * fm.predictor_rate_hz) + 2 > PREDICTOR_MAX_SEGMENTS:
        raise ValueError(
            f"delay_s={fm.delay_s!r} at predictor_rate_hz={fm.predictor_rate_hz!r} needs more "
            f"than the C backend's PS_PREDICTOR_MAX_SEGMENTS={PREDICTOR_MAX_SEGMENTS} segments")
    out.params = params_struct(config.params, variant)
    out.theta = get_method(config.method).theta
    out.step_s = config.spindle_step_s
    _fill_force_sense(out, config, moment_arms if moment_arms is not None
                      else load_moment_arm_fits(config.moment_arm_fits_path))
    return out


def _fill_force_sense(out: ctypes.Structure, config: ChainConfig,
                      moment_arms: MomentArmFits) -> None:
    """The force sense's fields of a ``ps_chain_config``: load resolution, tendon organ
    constants, force scales and the moment-arm tables."""
    if moment_arms.muscles != MUSCLES:
        raise ValueError(f"moment arms are for {moment_arms.muscles}, the chain needs {MUSCLES}")
    points = len(moment_arms.table_m[0])
    if points > MOMENT_ARM_MAX_POINTS:
        raise ValueError(f"the moment-arm tables have {points} points, above the C backend's "
                         f"PS_MOMENT_ARM_MAX_POINTS={MOMENT_ARM_MAX_POINTS}")
    gto = config.gto
    out.load_Nm_per_count = config.load.Nm_per_count
    out.gto.gain_pps, out.gto.tau_lowpass_s = gto.gain_pps, gto.tau_lowpass_s
    out.gto.num[:] = list(gto.num)
    out.gto.den[:] = list(gto.den)
    out.force_scale_N[:] = config.force_scale_N.tolist()
    out.n_moment_arm_points = points
    out.moment_arm_lo_rad, out.moment_arm_hi_rad = moment_arms.valid_range_rad
    for k, table in enumerate(moment_arms.table_m):
        out.moment_arm_m[k][:points] = table


_float = real_number  # NaN for anything that is not one real number: the C chain's bad-sample rules


_C_SNAPSHOTS = "_c_struct_snapshots"
"""The key of CArmChain's pickled state holding its structs' bytes."""


def _rebuilt_by_init(value: object) -> bool:
    """True for what ``CArmChain.__init__`` re-creates: the library, ctypes scalars, arrays,
    pointers and types (scratch buffers and handles), and numpy views of C memory."""
    if isinstance(value, ctypes.CDLL | ctypes._SimpleCData | ctypes.Array | ctypes._Pointer):
        return True
    if isinstance(value, type):
        return True
    if isinstance(value, dict) and value and all(isinstance(v, type) for v in value.values()):
        return True  # the struct classes of the variant
    if isinstance(value, np.ndarray):
        base = value
        while isinstance(base, np.ndarray):
            base = base.base
        return isinstance(base, ctypes.Structure | ctypes.Array)
    return False


@cache
def _layout(cls: type) -> tuple:
    """A ctypes struct's layout: (name, offset, size, nested layout) for every field."""
    fields_ = tuple((name, getattr(cls, name).offset, getattr(cls, name).size,
                     _layout(kind) if issubclass(kind, ctypes.Structure) else kind.__name__)
                    for name, kind, *_ in cls._fields_)
    return (ctypes.sizeof(cls), *fields_)


class CArmChain:
    """The one-arm chain computed by ``c/chain.c``: the API, outputs and counters of the numpy
    :class:`~spindle.chain.arm.ArmChain` (both implement :class:`~spindle.chain.config.Chain`;
    neither inherits from the other).

    Args:
        config, fits: as for :class:`~spindle.chain.arm.ArmChain` (``config.backend`` is not
            read: this class is the C backend).
        variant: ``"double"`` (agrees with numpy to round-off) or ``"float"`` (what a
            microcontroller without an FPU runs; see ``docs/c_chain.md`` for its accuracy).
    """

    backend = "c"

    def __init__(self, config: ChainConfig | None = None, fits: LengthFits | None = None,
                 variant: str = "double"):
        self.config = replace(ChainConfig() if config is None else config, backend="c")
        self.fits = fits if fits is not None else load_length_fits(self.config.fits_path)
        if self.fits.muscles != MUSCLES:
            raise ValueError(f"length fits are for {self.fits.muscles}, the chain needs {MUSCLES}")
        self.variant = variant
        self._lib = library(variant)
        self._structs = structs(variant)
        self._real = real_type(variant)
        self._np_real = np.float32 if variant == "float" else np.float64
        self._config_struct = chain_config_struct(self.config, self.fits, variant)
        self._chain = self._structs["PsArmChain"]()
        self._chain_p = ctypes.pointer(self._chain)
        self._sample = self._structs["PsArmSample"]()
        self._sample_p = ctypes.pointer(self._sample)
        self._n_done = ctypes.c_long()
        self._n_done_p = ctypes.pointer(self._n_done)
        self._pair = (self._real * 2)()
        self._pair_p = ctypes.cast(self._pair, ctypes.POINTER(self._real))
        self._scalar = self._real()
        self._scalar_p = ctypes.pointer(self._scalar)
        self._load = self._real()
        self._load_p = ctypes.pointer(self._load)
        status = self._lib.ps_chain_init(self._chain_p, ctypes.byref(self._config_struct))
        if status != Status.PS_OK:
            raise ValueError(f"the C chain refused the configuration ({status_name(status)})")
        c = self._chain
        self.angle_range_deg = (float(c.angle_min_deg), float(c.angle_max_deg))
        self.length_min_L0 = np.array(c.length_min_L0[:], dtype=float)
        self.length_max_L0 = np.array(c.length_max_L0[:], dtype=float)
        # A numpy view of the sample struct's per-muscle block (it lives as long as self).
        self._rows = np.frombuffer(self._sample, dtype=self._np_real, count=2 * len(PER_MUSCLE),
                                   offset=type(self._sample).length_L0.offset).reshape(-1, 2)
        self._last: ArmSample | None = None

    # -- pickling and deep copies: the C structs travel as their bytes ---------------------
    def __getstate__(self) -> dict[str, object]:
        """The Python-side settings plus a byte snapshot of every C struct the chain owns.

        The structs hold no pointers (caller-owned, fixed-size), so their bytes are the whole
        C state: config, median window, predictor, spindles, counters, last output. The
        library, the pointers to the structs and the numpy views of them are not pickled:
        :meth:`__setstate__` rebuilds them through the normal loader and constructor.
        """
        state: dict[str, object] = {}
        snapshots: dict[str, tuple[tuple, bytes]] = {}
        for name, value in self.__dict__.items():
            if isinstance(value, ctypes.Structure):
                snapshots[name] = (_layout(type(value)), bytes(value))
            elif not _rebuilt_by_init(value):
                state[name] = value
        state[_C_SNAPSHOTS] = snapshots
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        """Rebuild the ctypes objects for ``state``'s variant, then restore the structs' bytes
        (the copy continues bit-identically); the pointers are the new objects' own."""
        state = dict(state)
        snapshots = state.pop(_C_SNAPSHOTS)
        CArmChain.__init__(self, state["config"], state["fits"], state["variant"])
        for name, (layout, raw) in snapshots.items():
            target = getattr(self, name)
            if _layout(type(target)) != layout:
                raise ValueError(
                    f"cannot unpickle CArmChain: its {name} struct was pickled with a "
                    f"different C layout ({len(raw)} bytes) than this build's "
                    f"({ctypes.sizeof(target)} bytes); unpickle with the version that "
                    "pickled it")
            ctypes.memmove(ctypes.addressof(target), raw, len(raw))
        self.__dict__.update(state)

    # -- state ---------------------------------------------------------------------------
    def reset(self, angle_deg: float, t_s: float = 0.0,
              length_L0: np.ndarray | None = None, load: float | None = None) -> ArmSample:
        t = real_number(t_s)
        if not math.isfinite(t):
            raise ValueError(f"t_s={t_s!r} must be a finite real number")
        angle = checked_angle(angle_deg)
        lengths_p = None
        if length_L0 is not None:
            L = checked_lengths(length_L0)
            if L is None:
                raise ValueError(f"length_L0={length_L0!r} must be 2 finite lengths within "
                                 f"{core.LENGTH_RANGE_L0} L0")
            self._pair[:] = L
            lengths_p = self._pair_p
        status = self._lib.ps_chain_reset_load(self._chain_p, angle, t, lengths_p,
                                               self._load_pointer(load), self._sample_p)
        if status == Status.PS_ERR_ANGLE_RANGE:  # the fits' own error and message
            self.fits.length_L0(math.radians(angle))
        self._check(status, "reset")
        self._last = self._sample_out(True)
        return self._last

    def set_intended_angle(self, angle_deg: float | None) -> None:
        if angle_deg is None:
            self._check(self._lib.ps_chain_set_intended_angle(self._chain_p, None), "switch")
            return
        self._scalar.value = checked_angle(angle_deg)
        self._check(self._lib.ps_chain_set_intended_angle(self._chain_p, self._scalar_p),
                    "switch")

    @property
    def last(self) -> ArmSample:
        """The latest output."""
        if self._last is None:
            raise RuntimeError("call ArmChain.reset before using the chain")
        return self._last

    @property
    def counters(self) -> dict[str, int]:
        """Counts of each handling rule since the last reset (as ArmChain.counters)."""
        counted = self._chain.state.counters
        return {name: int(getattr(counted, name)) for name in COUNTERS}

    @property
    def spindle_state(self) -> core.SpindleState:
        """A copy of the spindles' state (2 spindles: BRA, TRImed)."""
        if self._last is None:
            raise RuntimeError("call ArmChain.reset before using the chain")
        sp = self._chain.state.spindle

        def fibres(name):
            return np.array([getattr(sp[k], name)[:] for k in range(len(MUSCLES))], dtype=float)

        def scalar(name):
            return np.array([getattr(sp[k], name) for k in range(len(MUSCLES))], dtype=float)

        return core.SpindleState(fibres("T"), fibres("v"), fibres("z"), fibres("f"),
                                 scalar("L"), scalar("gd"), scalar("gs"))

    @property
    def tendon_organ_state(self) -> TendonOrganState:
        """A copy of the tendon organs' state (2 organs: BRA, TRImed)."""
        if self._last is None:
            raise RuntimeError("call ArmChain.reset before using the chain")
        organs = self._chain.state.gto
        return TendonOrganState(
            np.array([organs[k].z[:] for k in range(len(MUSCLES))], dtype=float).T,
            np.array([organs[k].force_N for k in range(len(MUSCLES))], dtype=float),
            np.array([organs[k].r_pps for k in range(len(MUSCLES))], dtype=float))

    # -- pushes ----------------------------------------------------------------------------
    def push_counts(self, t_s: float, counts: float, load: float | None = None) -> ArmSample:
        status = self._lib.ps_chain_push_counts_load(self._chain_p, _float(t_s), _float(counts),
                                                     self._load_pointer(load), self._sample_p)
        return self._pushed(status, t_s)

    def push_angle(self, t_s: float, angle_deg: float) -> ArmSample:
        status = self._lib.ps_chain_push_angle(self._chain_p, _float(t_s), _float(angle_deg),
                                               self._sample_p)
        return self._pushed(status, t_s)

    def push_lengths(self, t_s: float, length_L0: np.ndarray,
                     angle_deg: float | None = None) -> ArmSample:
        L = real_array(length_L0)
        self._pair[:] = L.tolist() if L.shape == (2,) else [math.nan, math.nan]
        angle_p = None
        if angle_deg is not None:
            self._scalar.value = _float(angle_deg)
            angle_p = self._scalar_p
        status = self._lib.ps_chain_push_lengths(self._chain_p, _float(t_s), self._pair_p,
                                                 angle_p, self._sample_p)
        return self._pushed(status, t_s)

    def push_counts_block(self, t_s: np.ndarray, counts: np.ndarray,
                          load: np.ndarray | None = None) -> ArmSample:
        return self._block(self._lib.ps_chain_push_counts_load_block, "counts", t_s, counts, (),
                           load)

    def push_angle_block(self, t_s: np.ndarray, angle_deg: np.ndarray) -> ArmSample:
        return self._block(self._lib.ps_chain_push_angle_block, "angle_deg", t_s, angle_deg,
                           ())

    def push_lengths_block(self, t_s: np.ndarray, length_L0: np.ndarray) -> ArmSample:
        return self._block(self._lib.ps_chain_push_lengths_block, "length_L0", t_s, length_L0,
                           (2,))

    def run_trace(self, push: str, t_s: np.ndarray, signal: np.ndarray,
                  intended_angle_deg: np.ndarray | None = None,
                  load: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Push a whole trace in one C call; every output stacked (for :func:`run_chain`).

        ``push`` names the entry point (``"push_counts"``, ``"push_angle"``,
        ``"push_lengths"``); ``intended_angle_deg`` (k,) sets the switch before each sample
        (NaN: the measured motion), as :func:`run_chain` does; ``load`` (k,) the load words
        beside counts (``"push_counts"`` only; None: none). Returns the fields of
        :class:`ArmSample` stacked over the k samples (rejected ones included).
        """
        kind = push.removeprefix("push_")
        shape = (2,) if kind == "lengths" else ()
        t, x = block_inputs(kind, t_s, signal, shape)
        t = np.ascontiguousarray(t, dtype=np.float64)
        x = np.ascontiguousarray(x, dtype=self._np_real)
        words = check_loads(push, load, t.shape)
        if words is not None:
            words = np.ascontiguousarray(words, dtype=self._np_real)
        intended = None
        if intended_angle_deg is not None:
            intended = np.ascontiguousarray(
                number_rule.real_array("intended_angle_deg", intended_angle_deg),
                dtype=self._np_real)
            if intended.shape != t.shape:
                raise ValueError(f"intended_angle_deg has shape {intended.shape}, expected "
                                 f"{t.shape}")
        samples = (self._structs["PsArmSample"] * t.size)()
        intended_p = None if intended is None else intended.__array_interface__["data"][0]
        if words is None:
            status = getattr(self._lib, f"ps_chain_run_{kind}")(
                self._chain_p, t.size, _address(t), _address(x), intended_p,
                ctypes.addressof(samples), self._n_done_p)
        else:
            status = self._lib.ps_chain_run_counts_load(
                self._chain_p, t.size, _address(t), _address(x), _address(words), intended_p,
                ctypes.addressof(samples), self._n_done_p)
        done = self._n_done.value
        if self._last is not None:
            self._last = self._sample_from(self._chain.state.last)
        if status != Status.PS_OK:
            if intended is not None and status == Status.PS_ERR_NONFINITE:  # the switch's input
                raise ValueError(f"intended_angle_deg={float(intended[done])!r} must be "
                                 "finite (NaN selects the measured motion)")
            self._check(status, "push", float(t[done]))
        table = np.frombuffer(samples, dtype=sample_dtype(self.variant), count=t.size)
        out = {name: table[name].astype(float) for name in SAMPLE_FIELDS}
        out["accepted"] = table["accepted"] != 0
        return out

    # -- plumbing ----------------------------------------------------------------------------
    def _block(self, fn, name, t_s, signal, sample_shape, load=None) -> ArmSample:
        t, x = block_inputs(name, t_s, signal, sample_shape)
        t = np.ascontiguousarray(t, dtype=np.float64)
        x = np.ascontiguousarray(x, dtype=self._np_real)
        # Raw addresses: the arrays outlive the call, and .ctypes.data_as costs microseconds.
        if name == "counts":  # the load form (NULL: no load readings)
            words = check_loads("push_counts", load, t.shape)
            words = None if words is None else np.ascontiguousarray(words, dtype=self._np_real)
            status = fn(self._chain_p, t.size, _address(t), _address(x),
                        None if words is None else _address(words), self._sample_p,
                        self._n_done_p)
        else:
            status = fn(self._chain_p, t.size, _address(t), _address(x), self._sample_p,
                        self._n_done_p)
        if status != Status.PS_OK:
            i = self._n_done.value
            if self._n_done.value > 0:
                self._last = self._sample_out(True)
            self._check(status, "push", float(t[i]))
        if t.size:
            self._last = self._sample_out(True)
        return self.last

    def _load_pointer(self, load: float | None):
        """A pointer to the load word (NaN for anything not one real number: an invalid
        word), or None for no load reading."""
        if load is None:
            return None
        self._load.value = _float(load)
        return self._load_p

    def _pushed(self, status: int, t_s: object) -> ArmSample:
        self._check(status, "push", _float(t_s))
        if self._sample.accepted:
            self._last = self._sample_out(True)
            return self._last
        last = self.last
        out = object.__new__(ArmSample)
        out.__dict__.update(last.__dict__, accepted=False)
        return out

    def _check(self, status: int, what: str, t_s: float | None = None) -> None:
        if status == Status.PS_OK:
            return
        if status == Status.PS_ERR_NOT_RESET:
            raise RuntimeError(f"call ArmChain.reset before using the chain ({what})")
        if status == Status.PS_ERR_INTERVAL:
            raise ValueError(
                f"the sample at t_s={t_s!r} is too far after the last accepted one at "
                f"{float(self._chain.state.t_s)!r} s: the interval needs more than "
                f"{MAX_UPDATES} spindle sub-steps or predictor updates; chain left unchanged")
        if status == Status.PS_ERR_FORCE_RANGE:
            raise ValueError(
                f"the sample at t_s={t_s!r} stands for a tendon force above MAX_FORCE_N "
                f"(the load reading's torque over the moment arm); chain left unchanged")
        if what == "push":
            raise FloatingPointError(
                f"the C chain failed at t_s={t_s!r} ({status_name(status)}): a spindle "
                "step did not produce a valid state; chain left unchanged")
        raise ValueError(f"the C chain refused the {what} ({status_name(status)})")

    def _sample_out(self, accepted: bool) -> ArmSample:
        return self._sample_from(self._sample, accepted, self._rows)

    def _sample_from(self, s: ctypes.Structure, accepted: bool = True,
                     rows: np.ndarray | None = None) -> ArmSample:
        if rows is None:
            rows = np.frombuffer(s, dtype=self._np_real, count=2 * len(PER_MUSCLE),
                                 offset=type(s).length_L0.offset).reshape(-1, 2)
        out = object.__new__(ArmSample)
        # What ArmSample's frozen __init__ does, without its per-field object.__setattr__
        # (4 us, as much as the C work of a 10-sample block).
        out.__dict__.update(zip(SAMPLE_FIELDS, (
            float(s.t_s), accepted, float(s.counts), float(s.counts_filtered),
            float(s.angle_deg), float(s.torque_Nm), *rows.astype(float)), strict=True))
        return out


# -- many arms: the batched chain --------------------------------------------------------------
_C_LONG = np.dtype(f"i{ctypes.sizeof(ctypes.c_long)}")
_C_ULONG = np.dtype(f"u{ctypes.sizeof(ctypes.c_ulong)}")
_SPINDLE_FIELDS = (("T", "tension_FU"), ("v", "polar_velocity_L0_s"), ("z", "velocity_root"),
                   ("f", "activation"), ("L", "length_L0"), ("gd", "gamma_dyn_pps"),
                   ("gs", "gamma_stat_pps"))
"""ps_spindle's fields and the core.SpindleState attribute each one fills."""
_ENTRY = {"counts": "counts", "angle_deg": "angle", "length_L0": "lengths"}
"""A pushed signal's name -> the kind in the C entry point's name."""


@cache
def chain_dtype(variant: str = "double") -> np.dtype:
    """A numpy structured dtype over ``ps_arm_chain`` exposing what the batch reads (stage,
    spindles, counters, last output): an array of chains becomes a table, no per-arm loop."""
    s = structs(variant)
    chain_cls, state_cls = s["PsArmChain"], s["PsChainState"]
    spindle_cls = spindle_structs(variant)[1]
    real = np.float32 if variant == "float" else np.float64
    spindle = np.dtype({
        "names": [name for name, _ in _SPINDLE_FIELDS],
        "formats": [(real, (3,)) if name in "Tvzf" else real for name, _ in _SPINDLE_FIELDS],
        "offsets": [getattr(spindle_cls, name).offset for name, _ in _SPINDLE_FIELDS],
        "itemsize": ctypes.sizeof(spindle_cls)})
    state = chain_cls.state.offset
    return np.dtype({
        "names": ["stage", "spindle", "counters", "last"],
        "formats": [np.intc, (spindle, (len(MUSCLES),)), (_C_ULONG, (len(COUNTERS),)),
                    sample_dtype(variant)],
        "offsets": [chain_cls.stage.offset, state + state_cls.spindle.offset,
                    state + state_cls.counters.offset, state + state_cls.last.offset],
        "itemsize": ctypes.sizeof(chain_cls)})


@cache
def _sample_columns(variant: str) -> tuple[int, int] | None:
    """(columns, column of counts) of ``ps_arm_sample`` read as rows of doubles, if the double
    build lays it out as t_s, accepted (+ padding), then every real field in ArmSample's order
    (so one copy of those rows gives every field); None otherwise (the float build)."""
    if variant != "double":
        return None
    cls = structs(variant)["PsArmSample"]
    offsets = [getattr(cls, name).offset for name in SAMPLE_FIELDS[2:]]
    start = offsets[0]
    width = 8 * len(SCALARS)
    expected = [start + 8 * j for j in range(len(SCALARS))] + [start + width + 16 * j
                                                               for j in range(len(PER_MUSCLE))]
    if offsets != expected or ctypes.sizeof(cls) != start + width + 16 * len(PER_MUSCLE) \
            or cls.t_s.offset != 0 or start % 8:
        return None
    return ctypes.sizeof(cls) // 8, start // 8


_VIEWED_FIELDS = ("t_s", *SCALARS, *PER_MUSCLE)
assert len(SCALARS) == 4  # _batch_sample's columns


def _batch_sample(table: np.ndarray, rows: np.ndarray | None, accepted: np.ndarray):
    """A ``BatchSample`` (float copies) of ``ps_arm_sample`` rows: ``rows``, the rows read as
    doubles (see :func:`_sample_columns`), or else the structured ``table``."""
    if rows is None:
        values = {name: table[name].astype(float) for name in SAMPLE_FIELDS}
    else:
        # One copy of the rows, every field a view of it: a structured field costs ~1.5 us to
        # read, 13 of them most of a small batch's call. The views are taken along the first
        # axis of transposes (the same arrays as block[:, j], ~9k fewer instructions a call).
        block = rows.copy()
        c = rows.shape[1] - 2 * len(PER_MUSCLE) - len(SCALARS)
        column = block.T
        per_muscle = block[:, c + len(SCALARS):].reshape(-1, len(PER_MUSCLE), 2).transpose(
            1, 0, 2)
        values = dict(zip(_VIEWED_FIELDS, (column[0], column[c], column[c + 1], column[c + 2],
                                           column[c + 3], *per_muscle), strict=True))
    values["accepted"] = accepted
    out = object.__new__(BatchSample)
    # what the frozen dataclass's __init__ does, without a per-field object.__setattr__
    out.__dict__.update(values)
    return out


class CArmChainBatch:
    """``n_arms`` arm chains in C, each advanced by ONE C call for the whole batch.

    The API of :class:`spindle.chain.batch.ArmChainBatch` (``docs/c_chain.md``, Batches):
    arm k behaves exactly like a :class:`CArmChain` with the same config and fits fed the same
    samples (outputs, counters, handling rules). The chains are one contiguous ctypes array
    of ``ps_arm_chain``; outputs, counters and spindle states are read through numpy views of
    it, without a per-arm Python loop. A push that raises leaves every arm exactly as it was
    (the C call is atomic across arms). Pickling and ``copy.deepcopy`` carry the chains'
    bytes, as :class:`CArmChain` does.

    Args:
        n_arms: number of arms (>= 1).
        config, fits: as for :class:`CArmChain` (``config.backend`` is not read).
        variant: ``"double"`` or ``"float"``.
    """

    backend = "c"

    def __init__(self, n_arms: int, config: ChainConfig | None = None,
                 fits: LengthFits | None = None, variant: str = "double"):
        if (isinstance(n_arms, bool | np.bool_) or not isinstance(n_arms, int | np.integer)
                or n_arms < 1):
            raise ValueError(f"n_arms={n_arms!r} must be an integer >= 1")
        self.n_arms = int(n_arms)
        self.config = replace(ChainConfig() if config is None else config, backend="c")
        self.fits = fits if fits is not None else load_length_fits(self.config.fits_path)
        if self.fits.muscles != MUSCLES:
            raise ValueError(f"length fits are for {self.fits.muscles}, the chain needs {MUSCLES}")
        self.variant = variant
        self._lib = library(variant)
        s = structs(variant)
        self._np_real = np.float32 if variant == "float" else np.float64
        first = s["PsArmChain"]()
        status = self._lib.ps_chain_init(ctypes.byref(first),
                                         ctypes.byref(chain_config_struct(self.config, self.fits,
                                                                          variant)))
        if status != Status.PS_OK:
            raise ValueError(f"the C chain refused the configuration ({status_name(status)})")
        self.angle_range_deg = (float(first.angle_min_deg), float(first.angle_max_deg))
        self.length_min_L0 = np.array(first.length_min_L0[:], dtype=float)
        self.length_max_L0 = np.array(first.length_max_L0[:], dtype=float)
        n = self.n_arms
        self._chains = (s["PsArmChain"] * n)()
        # ps_chain_init once (its 1301-point length range), its bytes copied to every arm
        raw = np.frombuffer(self._chains, dtype=np.uint8).reshape(n, ctypes.sizeof(first))
        raw[:] = np.frombuffer(first, dtype=np.uint8)
        self._work = (s["PsChainState"] * n)()
        self._out = (s["PsArmSample"] * n)()
        self._table = np.frombuffer(self._chains, dtype=chain_dtype(variant))
        self._out_table = np.frombuffer(self._out, dtype=sample_dtype(variant))
        # a view kept: reading a structured field costs ~1.5 us a call
        self._out_accepted = self._out_table["accepted"]
        self._out_rows = self._last_rows = None
        layout = _sample_columns(variant)
        if layout is not None:
            width = layout[0]
            self._out_rows = np.frombuffer(self._out, dtype=np.float64).reshape(n, width)
            at = (s["PsArmChain"].state.offset + s["PsChainState"].last.offset) // 8
            self._last_rows = np.frombuffer(self._chains, dtype=np.float64).reshape(
                n, ctypes.sizeof(first) // 8)[:, at:at + width]
        self._addr = (ctypes.addressof(self._chains), ctypes.addressof(self._work),
                      ctypes.addressof(self._out))
        self._failed = (ctypes.c_long(), ctypes.c_long())
        self._failed_p = tuple(ctypes.pointer(f) for f in self._failed)
        self._block_fn = {name: getattr(self._lib, f"ps_chain_batch_push_{kind}_block")
                          for name, kind in _ENTRY.items() if name != "counts"}
        # (signal, k) -> the push's input buffers and their addresses, kept between calls:
        # building contiguous arrays and reading their addresses at each push cost the
        # single env ~40k of its ~1M instructions per step
        self._buffers: dict[tuple[str, int], tuple[np.ndarray, ...]] = {}

    def _push_buffers(self, name: str, k: int, sample_shape: tuple[int, ...]) -> tuple:
        """(times, signal, load, samples per arm, their four addresses) buffers of a (n, k)
        block push."""
        key = (name, k)
        buffers = self._buffers.get(key)
        if buffers is None:
            n = self.n_arms
            t = np.empty((n, k))
            x = np.empty((n, k, *sample_shape), dtype=self._np_real)
            words = np.empty((n, k), dtype=self._np_real)
            counts = np.empty(n, dtype=_C_LONG)
            buffers = self._buffers[key] = (t, x, words, counts, _address(t), _address(x),
                                            _address(words), _address(counts))
        return buffers

    # -- pickling and deep copies: the chains travel as their bytes ------------------------
    def __getstate__(self) -> dict[str, object]:
        """Settings plus the bytes of the ``ps_arm_chain`` array (no pointers in it: the
        whole C state); the library, buffers and views are rebuilt by :meth:`__setstate__`."""
        return {"n_arms": self.n_arms, "config": self.config, "fits": self.fits,
                "variant": self.variant,
                _C_SNAPSHOTS: (_layout(structs(self.variant)["PsArmChain"]),
                               bytes(self._chains))}

    def __setstate__(self, state: dict[str, object]) -> None:
        CArmChainBatch.__init__(self, state["n_arms"], state["config"], state["fits"],
                                  state["variant"])
        layout, raw = state[_C_SNAPSHOTS]
        if layout != _layout(structs(self.variant)["PsArmChain"]) or len(raw) != ctypes.sizeof(
                self._chains):
            raise ValueError(
                f"cannot unpickle CArmChainBatch: its chains were pickled with a different C "
                f"layout ({len(raw)} bytes) than this build's ({ctypes.sizeof(self._chains)} "
                "bytes); unpickle with the version that pickled it")
        ctypes.memmove(self._addr[0], raw, len(raw))

    # -- state ---------------------------------------------------------------------------
    def reset(self, angle_deg: np.ndarray, t_s: float | np.ndarray = 0.0,
              length_L0: np.ndarray | None = None, arms: np.ndarray | None = None,
              load: np.ndarray | None = None):
        """Arms at rest: every arm, or the arms of the index array ``arms`` (the others
        untouched); see :meth:`spindle.chain.batch.ArmChainBatch.reset`. The first reset
        covers every arm (``arms=None``; a partial one before it raises RuntimeError and
        changes nothing). Returns :attr:`last` (every arm's output)."""
        index = self._arms(arms)
        m = self.n_arms if index is None else index.size
        if index is not None:
            never = self._table["stage"] < 2
            never[index] = False
            if never.any():
                raise RuntimeError(f"arm {int(np.argmax(never))} was never reset: the first reset "
                                   "must cover every arm (arms=None)")
        angle = _batch_real("angle_deg", angle_deg, (m,))
        t = np.broadcast_to(real_number(t_s), (m,)) if np.ndim(t_s) == 0 else _batch_real(
            "t_s", t_s, (m,))
        t = np.ascontiguousarray(t, dtype=np.float64)
        which = np.arange(m) if index is None else index
        for name, values in (("t_s", t), ("angle_deg", angle)):
            bad = ~np.isfinite(values)
            if bad.any():
                j = int(np.argmax(bad))
                raise ValueError(f"{name}={values[j]!r} of arm {int(which[j])} must be a finite "
                                 "real number")
        lengths = None
        if length_L0 is not None:
            lengths = _batch_real("length_L0", length_L0, (m, 2))
            lo, hi = core.LENGTH_RANGE_L0
            bad = ~np.all(np.isfinite(lengths) & (lengths >= lo) & (lengths <= hi), axis=1)
            if bad.any():
                j = int(np.argmax(bad))
                raise ValueError(f"length_L0={lengths[j]!r} of arm {int(which[j])} must be 2 "
                                 f"finite lengths within {core.LENGTH_RANGE_L0} L0")
            lengths = np.ascontiguousarray(lengths, dtype=self._np_real)
        angle = np.ascontiguousarray(angle, dtype=self._np_real)
        words = None if load is None else np.ascontiguousarray(
            _batch_real("load", load, (m,)), dtype=self._np_real)
        status = self._lib.ps_chain_batch_reset_load(
            self._addr[0], self.n_arms, None if index is None else _address(index), m,
            _address(angle), _address(t), None if lengths is None else _address(lengths),
            None if words is None else _address(words), self._addr[1], None, self._failed_p[0])
        if status != Status.PS_OK:
            raise ValueError(f"the C chain refused the reset of arm {self._failed[0].value} "
                             f"({status_name(status)})")
        return self.last

    def set_intended_angle(self, angle_deg: np.ndarray | None) -> None:
        """The switch of every arm: None, or (n,) intended angles with NaN for the arms that
        follow their measured motion (see :meth:`ArmChain.set_intended_angle`)."""
        angle = None
        if angle_deg is not None:
            angle = np.ascontiguousarray(number_rule.real_array("angle_deg", angle_deg),
                                         dtype=self._np_real)
            _check_shape("angle_deg", angle, (self.n_arms,))
        status = self._lib.ps_chain_batch_set_intended_angle(
            self._addr[0], self.n_arms, None if angle is None else _address(angle),
            self._failed_p[0])
        if status == Status.PS_ERR_NONFINITE:
            i = self._failed[0].value
            raise ValueError(f"angle_deg={float(angle[i])!r} of arm {i} must be finite "
                             "(NaN selects the measured motion)")
        self._check(status)

    @property
    def counters(self) -> dict[str, np.ndarray]:
        """Counts of each handling rule since each arm's last reset: name -> (n,) int64."""
        counted = self._table["counters"].astype(np.int64)
        return {name: counted[:, j] for j, name in enumerate(COUNTERS)}

    @property
    def last(self):
        """Every arm's latest accepted output (a ``BatchSample``)."""
        self._require_reset()
        table = self._table["last"]
        return _batch_sample(table, self._last_rows, table["accepted"] != 0)

    @property
    def spindle_state(self) -> core.SpindleState:
        """A copy of the 2n spindles' state, arm-major (arm i: BRA 2i, TRImed 2i+1)."""
        self._require_reset()
        sp = self._table["spindle"]
        n = 2 * self.n_arms
        return core.SpindleState(**{
            attr: sp[name].astype(float).reshape(n, 3) if name in "Tvzf"
            else sp[name].astype(float).reshape(n) for name, attr in _SPINDLE_FIELDS})

    # -- pushes ----------------------------------------------------------------------------
    def push_counts(self, t_s: np.ndarray, counts: np.ndarray, active: np.ndarray | None = None,
                    load: np.ndarray | None = None):
        """One reading per arm (``active`` (n,) bool: only those arms get one), with its load
        word ``load`` (n,) (None: no load readings)."""
        return self._push("counts", t_s, counts, (), active, load)

    def push_angle(self, t_s: np.ndarray, angle_deg: np.ndarray,
                   active: np.ndarray | None = None):
        """One elbow angle (deg) per arm."""
        return self._push("angle_deg", t_s, angle_deg, (), active)

    def push_lengths(self, t_s: np.ndarray, length_L0: np.ndarray,
                     active: np.ndarray | None = None):
        """One pair of fibre lengths (L0) per arm: length_L0 (n, 2)."""
        return self._push("length_L0", t_s, length_L0, (2,), active)

    def push_counts_block(self, t_s: np.ndarray, counts: np.ndarray,
                          n_samples: np.ndarray | None = None, load: np.ndarray | None = None):
        """Arm i pushes its first ``n_samples[i]`` (default k) of (n, k) readings (with the
        (n, k) load words ``load``; None: no load readings)."""
        return self._block("counts", t_s, counts, (), n_samples, load)

    def push_angle_block(self, t_s: np.ndarray, angle_deg: np.ndarray,
                         n_samples: np.ndarray | None = None):
        """Arm i pushes its first ``n_samples[i]`` of (n, k) angles."""
        return self._block("angle_deg", t_s, angle_deg, (), n_samples)

    def push_lengths_block(self, t_s: np.ndarray, length_L0: np.ndarray,
                           n_samples: np.ndarray | None = None):
        """Arm i pushes its first ``n_samples[i]`` of (n, k, 2) lengths."""
        return self._block("length_L0", t_s, length_L0, (2,), n_samples)

    # -- plumbing ----------------------------------------------------------------------------
    def _push(self, name, t_s, signal, sample_shape, active, load=None):
        n = self.n_arms
        t = np.ascontiguousarray(_batch_real("t_s", t_s, (n,)), dtype=np.float64)
        x = np.ascontiguousarray(_batch_real(name, signal, (n, *sample_shape)),
                                 dtype=self._np_real)
        mask = None
        if active is not None:
            mask = np.asarray(active)
            if mask.dtype != np.bool_:
                raise ValueError(f"active has dtype {mask.dtype}, expected bool")
            _check_shape("active", mask, (n,))
            mask = np.ascontiguousarray(mask)
        mask_p = None if mask is None else _address(mask)
        if name == "counts":
            words = None if load is None else np.ascontiguousarray(
                _batch_real("load", load, (n,)), dtype=self._np_real)
            status = self._lib.ps_chain_batch_push_counts_load(
                self._addr[0], n, mask_p, _address(t), _address(x),
                None if words is None else _address(words), self._addr[1], self._addr[2],
                self._failed_p[0])
        else:
            status = getattr(self._lib, f"ps_chain_batch_push_{_ENTRY[name]}")(
                self._addr[0], n, mask_p, _address(t), _address(x), self._addr[1],
                self._addr[2], self._failed_p[0])
        if status != Status.PS_OK:
            self._check(status, t.reshape(n, 1), 0)
        return _batch_sample(self._out_table, self._out_rows, self._out_accepted != 0)

    def _block(self, name, t_s, signal, sample_shape, n_samples, load=None):
        n = self.n_arms
        t = real_array(t_s)
        if t.ndim != 2 or t.shape[0] != n:
            raise ValueError(f"t_s has shape {t.shape}, expected ({n}, k)")
        k = t.shape[1]
        x = _batch_real(name, signal, (n, k, *sample_shape))
        t_buf, x_buf, w_buf, c_buf, t_p, x_p, w_p, c_p = self._push_buffers(name, k,
                                                                            sample_shape)
        # assignments, not np.copyto (half the instructions); the float build rounds
        t_buf[...] = t
        x_buf[...] = x
        counts_p = None
        if n_samples is not None:
            given = np.asarray(n_samples)
            _check_shape("n_samples", given, (n,))
            if given.dtype.kind not in "iu":  # bools are kind "b"
                raise ValueError(f"n_samples has dtype {given.dtype}, expected integers")
            # the range in Python ints: 5k instructions, where the array comparisons and
            # .any() took 24k (an encoder env pushes n_samples at every step)
            values = given.tolist()
            if min(values) < 0 or max(values) > k:
                bad = (given < 0) | (given > k)
                i = int(np.argmax(bad))
                raise ValueError(f"n_samples[{i}]={int(given[i])} must lie in 0..{k} (k samples "
                                 "per arm in this block)")
            c_buf[...] = given  # checked: integers in 0..k
            counts_p = c_p
        if name == "counts":
            if load is not None:
                w_buf[...] = _batch_real("load", load, (n, k))
            status = self._lib.ps_chain_batch_push_counts_load_block(
                self._addr[0], n, k, counts_p, t_p, x_p, None if load is None else w_p,
                self._addr[1], self._addr[2], *self._failed_p)
        else:
            status = self._block_fn[name](self._addr[0], n, k, counts_p, t_p, x_p,
                                          self._addr[1], self._addr[2], *self._failed_p)
        if status != Status.PS_OK:
            self._check(status, t, self._failed[1].value)
        return _batch_sample(self._out_table, self._out_rows, self._out_accepted != 0)

    def _check(self, status: int, t: np.ndarray | None = None, sample: int = 0) -> None:
        if status == Status.PS_OK:
            return
        i = self._failed[0].value
        if status == Status.PS_ERR_NOT_RESET:
            raise RuntimeError(f"call reset before using the chain (arm {i} was never reset)")
        t_s = float(t[i, sample]) if t is not None and i >= 0 else math.nan
        if status == Status.PS_ERR_INTERVAL:
            raise ValueError(
                f"the sample of arm {i} at t_s={t_s!r} is too far after its last accepted one "
                f"at {float(self._chains[i].state.t_s)!r} s: the interval needs more than "
                f"{MAX_UPDATES} spindle sub-steps or predictor updates; no arm changed")
        if t is not None:
            raise FloatingPointError(
                f"the C chain of arm {i} failed at t_s={t_s!r} ({status_name(status)}): a "
                "spindle step did not produce a valid state; no arm changed")
        raise ValueError(f"the C chain refused the call for arm {i} ({status_name(status)})")

    def _require_reset(self) -> None:
        never = self._table["stage"] < 2
        if never.any():
            raise RuntimeError(f"call reset before using the chain (arm {int(np.argmax(never))} "
                               "was never reset)")

    def _arms(self, arms: np.ndarray | None) -> np.ndarray | None:
        if arms is None:
            return None
        index = np.asarray(arms)
        if index.ndim != 1 or index.dtype == np.bool_ or not (
                np.issubdtype(index.dtype, np.integer) or index.size == 0):
            raise ValueError(f"arms must be a 1-D integer index array, got shape {index.shape} "
                             f"dtype {index.dtype}")
        bad = (index < 0) | (index >= self.n_arms)
        if bad.any():
            raise ValueError(f"arms contains {int(index[np.argmax(bad)])}, outside "
                             f"0..{self.n_arms - 1}")
        if np.unique(index).size != index.size:
            raise ValueError(f"arms={index.tolist()!r} repeats an arm")
        return np.ascontiguousarray(index, dtype=_C_LONG)


def _address(array: np.ndarray) -> int:
    return array.__array_interface__["data"][0]


def _check_shape(name: str, array: np.ndarray, expected: tuple[int, ...]) -> None:
    if array.shape != expected:
        raise ValueError(f"{name} has shape {array.shape}, expected {expected}")


def _batch_real(name: str, value: object, expected: tuple[int, ...]) -> np.ndarray:
    """``value`` as a float array (NaN for non-real elements: the bad-sample rules) of shape
    ``expected`` (else ValueError naming the argument, its shape and the expected one)."""
    array = real_array(value)
    _check_shape(name, array, expected)
    return array


def config_c_source(config: ChainConfig | None = None, fits: LengthFits | None = None,
                    name: str = "proprio_chain_config") -> str:
    """C99 source defining ``const ps_chain_config <name>`` for ``config`` and ``fits``.

    What a microcontroller build compiles beside ``spindle/native/c/*.c`` (no Python, no JSON
    on the device). Values are C99 hexadecimal floating constants, so the double build gets
    exactly the numbers the Python binding passes. ``python -m spindle.native.chain >
    config.c`` writes it for the default chain.
    """
    config = ChainConfig() if config is None else config
    fits = fits if fits is not None else load_length_fits(config.fits_path)
    filled = chain_config_struct(config, fits, "double")

    def literal(value) -> str:
        if isinstance(value, int):
            return str(value)
        if isinstance(value, ctypes.Array):
            return "{" + ", ".join(literal(v) for v in value) + "}"
        if isinstance(value, ctypes.Structure):
            return "{" + ", ".join(f".{f} = {literal(getattr(value, f))}"
                                   for f, _ in value._fields_) + "}"
        return float(value).hex()

    body = ",\n".join(f"    .{f} = {literal(getattr(filled, f))}" for f, _ in filled._fields_)
    return (f"/* Generated by spindle.native.chain.config_c_source: {config.method}, "
            f"fits of {', '.join(fits.muscles)} (elbow.xml sha256 {fits.model_sha256[:12]}). */\n"
            f'#include "proprio.h"\n\nconst ps_chain_config {name} = {{\n{body}\n}};\n')


if __name__ == "__main__":
    print(config_c_source(), end="")

_RENAMED = {"CBatchedArmChain": "CArmChainBatch"}  # renamed-from: the old names (spindle.renamed)


def __getattr__(name: str) -> object:
    return renamed_attribute(__name__, name, _RENAMED, globals())
