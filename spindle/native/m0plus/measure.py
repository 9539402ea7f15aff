"""Cost and accuracy of the C spindle on the Cortex-M0+: the lever table and the demo motion.

Every configuration runs the Mileusnic Fig. 3 protocol (ramps 0.95 -> 1.08 L0 at 0.11, 0.66,
1.55 L0/s, drive (0,0), (70,0), (0,70) pps, 3.3 s) sampled once per spindle step, in the
emulator and in the float32 host twin; the two agree to the bit, and the twin's rates give
the accuracy (worst-run RMS of Ia and II against the stiff reference, spindle.reference).

The demo motion measures the fixed-point step as the prosthesis runs it, with the drives the
numpy chain makes at every sample (the Fig. 3 protocol holds them constant within a run, so
the step reuses its activation targets there).
"""

from __future__ import annotations

import ctypes
import dataclasses
from pathlib import Path

import numpy as np

from spindle.chain.config import MUSCLES, ChainConfig
from spindle.chain.trace import ChainTrace, run_chain
from spindle.native import abi
from spindle.native import spindle as native_spindle
from spindle.native.fixed import fixed_rates
from spindle.native.m0plus.build import (
    PARAMS,
    Config,
    build_firmware,
    fixed_plan,
    host_library,
    sizes,
)
from spindle.native.m0plus.emulator import M0Plus
from spindle.native.m0plus.isa import objdump_violations

SPEEDS = (0.11, 0.66, 1.55)
DRIVES = ((0.0, 0.0), (70.0, 0.0), (0.0, 70.0))
ALL_RUNS = tuple((v, gd, gs) for v in SPEEDS for gd, gs in DRIVES)
DURATION_S = 3.3
REFERENCE_DT_S = 1e-3
QUICK_RUNS = ((1.55, 70.0, 0.0), (0.66, 0.0, 70.0))
"""The lever rows' runs: the fastest ramp with dynamic drive, the medium one with static."""
RMS_TARGET_PPS = 2.0

FAST = ("PS_FAST_CBRT", "PS_CBRT_REFINE=1")
LOOSE = ("PS_NEWTON_TOL_Z=1e-3",)
LEVERS = [
    Config("forward Euler, z = powf(|v|, 0.1) (orientation)", 1e-3, theta=0.0),
    Config("trapezoidal, z = sgn(v)|v|^0.1 (no powf), Newton to 2e-6", 1e-3),
    Config("+ plan: derived constants, reciprocals, bounded Newton start", 1e-3, plan=True),
    Config("+ cube root without libm (PS_FAST_CBRT)", 1e-3, plan=True, defines=FAST),
    Config("+ Newton tolerance 1e-3 in z (PS_NEWTON_TOL_Z)", 1e-3, plan=True,
           defines=(*FAST, *LOOSE)),
    Config("  fixed 2 Newton iterations instead (PS_NEWTON_ITER=2)", 1e-3, plan=True,
           defines=(*FAST, "PS_NEWTON_ITER=2")),
    Config("  tolerance 1e-3 at a 2 ms step", 2e-3, plan=True, defines=(*FAST, *LOOSE)),
    Config("  tolerance 1e-3 at a 3 ms step", 3e-3, plan=True, defines=(*FAST, *LOOSE)),
    Config("  tolerance 1e-3 at a 5 ms step", 5e-3, plan=True, defines=(*FAST, *LOOSE)),
    Config("+ plan const in flash (5 ms)", 5e-3, plan=True, plan_in_flash=True,
           defines=(*FAST, *LOOSE)),
    Config("  fixed point at a 3 ms step", 3e-3, fixed=True),
    Config("fixed point: int32 Q24 step (ps_spindle_step_fx), plan in flash (5 ms)", 5e-3,
           fixed=True),
]
FINAL = LEVERS[-1]

Run = tuple[float, float, float]  # (speed L0/s, gamma_dynamic pps, gamma_static pps)
Rates = tuple[np.ndarray, np.ndarray]  # (Ia, II) in pps


# ---- protocol, reference, accuracy ------------------------------------------------------

def protocol(speed: float, step_s: float) -> np.ndarray:
    """The Fig. 3 ramp-and-hold length (L0) at ``speed`` (L0/s), one sample per step."""
    t = np.arange(round(DURATION_S / step_s) + 1) * step_s
    end = 1.0 + (1.08 - 0.95) / speed
    return 0.95 + speed * np.clip(t - 1.0, 0.0, end - 1.0)


def references(runs) -> dict[Run, Rates]:
    """The stiff reference's rates of each run (scipy Radau), every REFERENCE_DT_S."""
    from spindle.reference import ramp_and_hold, solve_reference

    t = np.arange(round(DURATION_S / REFERENCE_DT_S) + 1) * REFERENCE_DT_S
    out = {}
    for run in runs:
        speed, gd, gs = run
        ref = solve_reference(ramp_and_hold(speed_L0_s=speed, gamma_dyn_pps=gd,
                                            gamma_stat_pps=gs), t, params=PARAMS)
        out[run] = (ref.ia, ref.ii)
    return out


def _host_fixed_rates(lib, cfg: Config, run: Run) -> Rates:
    speed, gd, gs = run
    L = protocol(speed, cfg.step_s)
    ia, ii, code = fixed_rates(lib, fixed_plan(lib, cfg), L, np.full(L.shape, gd),
                               np.full(L.shape, gs))
    if code != abi.Status.PS_OK:
        raise RuntimeError(f"host fixed-point step: {abi.status_name(code)}")
    return ia, ii


def _host_float_rates(lib, cfg: Config, run: Run) -> Rates:
    speed, gd, gs = run
    L = protocol(speed, cfg.step_s).astype(np.float32)
    _, PsSpindle = abi.structs("float")
    params = abi.params_struct(PARAMS, "float")
    s = PsSpindle()
    code = lib.ps_spindle_init(ctypes.byref(s), ctypes.byref(params), L[0], gd, gs)
    if code != abi.Status.PS_OK:
        raise RuntimeError("init failed")
    ia = np.empty(len(L))
    ii = np.empty(len(L))
    a, b = ctypes.c_float(), ctypes.c_float()
    lib.ps_spindle_afferents(ctypes.byref(s), ctypes.byref(params), ctypes.byref(a),
                             ctypes.byref(b))
    ia[0], ii[0] = a.value, b.value
    if cfg.plan:
        plan = abi.plan_struct("float")()
        lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(params), cfg.step_s, cfg.theta)
    for j in range(1, len(L)):
        if cfg.plan:
            code = lib.ps_spindle_step_plan(ctypes.byref(s), ctypes.byref(plan), L[j], gd, gs,
                                            ctypes.byref(a), ctypes.byref(b))
        else:
            code = lib.ps_spindle_step(ctypes.byref(s), ctypes.byref(params), L[j], gd, gs,
                                       cfg.step_s, cfg.theta, ctypes.byref(a), ctypes.byref(b))
        if code != abi.Status.PS_OK:
            raise RuntimeError(f"host step {j}: {abi.status_name(code)}")
        ia[j], ii[j] = a.value, b.value
    return ia, ii


def host_rates(lib, cfg: Config, run: Run) -> Rates:
    """The host twin's rates along one run, as the firmware of ``cfg`` computes them."""
    return _host_fixed_rates(lib, cfg, run) if cfg.fixed else _host_float_rates(lib, cfg, run)


def accuracy(lib, cfg: Config, refs: dict[Run, Rates]) -> float:
    """Worst-run RMS (pps) of Ia and II against the reference, over the runs of ``refs``."""
    every = round(cfg.step_s / REFERENCE_DT_S)
    worst = 0.0
    for run, (ref_ia, ref_ii) in refs.items():
        ia, ii = host_rates(lib, cfg, run)
        for got, ref in ((ia, ref_ia[::every]), (ii, ref_ii[::every])):
            worst = max(worst, float(np.sqrt(np.mean((got - ref) ** 2))))
    return worst


# ---- one configuration --------------------------------------------------------------------

@dataclasses.dataclass
class Measured:
    cfg: Config
    instr_mean: float
    instr_max: int
    mips: float
    rms_pps: float
    flash: int
    ram: int
    stack_used: int
    max_diff_host_pps: float
    steps: int
    violations: list[str]
    profile: list[tuple[str, int]]


def _check_firmware_params(emu: M0Plus, cfg: Config) -> None:
    # (the fixed-point firmware holds only the plan, made from PARAMS by plan_fx_header)
    if not cfg.fixed and emu.read_symbol("fw_params") != bytes(
            abi.params_struct(PARAMS, "float")):
        raise RuntimeError("fw_params in firmware.c differ from spindle.HUMAN")


def _emulate_pair(emu: M0Plus, lib, cfg: Config, pair: list[Run]) -> tuple[list[int], float]:
    """Muscle 0 and muscle 1 on two runs at once: (instructions per step call, max |emulator
    - host| in pps)."""
    lengths = [protocol(speed, cfg.step_s) for speed, _, _ in pair]
    gds = [gd for _, gd, _ in pair]
    gss = [gs for _, _, gs in pair]
    emu.write_io([x[0] for x in lengths], gds, gss, cfg.fixed)
    status, _ = emu.call("fw_init")
    if status != abi.Status.PS_OK:
        raise RuntimeError(f"fw_init: {abi.status_name(status)}")
    host = [host_rates(lib, cfg, run) for run in pair]
    counts, max_diff = [], 0.0
    for j in range(1, len(lengths[0])):
        emu.write_io([x[j] for x in lengths], gds, gss, cfg.fixed)
        for k in range(2):
            status, n = emu.call("fw_step_muscle", k)
            if status != abi.Status.PS_OK:
                raise RuntimeError(f"fw_step_muscle: {abi.status_name(status)}")
            counts.append(n)
        ia, ii, _ = emu.read_rates(cfg.fixed)
        for k in range(2):
            max_diff = max(max_diff, abs(ia[k] - host[k][0][j]), abs(ii[k] - host[k][1][j]))
    return counts, max_diff


def measure(cfg: Config, runs, refs: dict[Run, Rates], build_dir: Path) -> Measured:
    """Instructions per step (emulated on ``runs``), accuracy (host twin on ``refs``' runs),
    sizes and the ARMv6-M check of the firmware of ``cfg``."""
    lib = host_library(cfg, build_dir)
    rms = accuracy(lib, cfg, refs)
    emu = M0Plus(build_firmware(cfg, build_dir))
    _check_firmware_params(emu, cfg)
    counts, max_diff = [], 0.0
    for k in range(0, len(runs), 2):
        pair = list(runs[k:k + 2])
        pair += [pair[0]] * (2 - len(pair))
        pair_counts, pair_diff = _emulate_pair(emu, lib, cfg, pair)
        counts += pair_counts
        max_diff = max(max_diff, pair_diff)
    # RAM: re-link with the stack reservation cut to the measured high-water mark plus a
    # 64-byte margin (rounded to 64 B); arm-none-eabi-size then counts it in bss.
    stack = (emu.stack_used() + 64 + 63) // 64 * 64
    sized = build_firmware(cfg, build_dir, stack_bytes=stack)
    flash, ram = sizes(sized)
    seen, bad = objdump_violations(sized)
    if seen < 100:
        raise RuntimeError("objdump parsing found almost no instructions")
    counts = np.array(counts)
    return Measured(cfg, float(counts.mean()), int(counts.max()),
                    float(counts.mean()) / cfg.step_s / 1e6, rms, flash, ram, emu.stack_used(),
                    max_diff, len(counts), sorted(emu.violations) + bad,
                    [(name, n // len(counts)) for name, n in emu.profile.most_common(12)])


# ---- demo motion: drives that change every sample -----------------------------------------

@dataclasses.dataclass
class DemoMeasured:
    steps: int
    instr_mean: tuple[float, float]  # per muscle (BRA, TRImed)
    instr_max: int
    held_instr_mean: float  # the same lengths, the drives held at their first sample
    held_instr_max: int
    peak_t_s: float  # time of the costliest step
    rms_vs_double: dict[str, float]  # "BRA Ia" ... (pps): against double ps_spindle_step
    rms_vs_chain: dict[str, float]  # against the numpy chain's own rates (1 ms trapezoidal)
    max_diff_host_pps: float
    drive_changes: tuple[float, float]  # fraction of steps in which gs, gd change

    def mips(self, step_s: float) -> float:
        return float(np.mean(self.instr_mean)) / step_s / 1e6


def demo_trace(t_s: np.ndarray, angle_deg: np.ndarray) -> ChainTrace:
    """The numpy chain (ChainConfig with the firmware's constants) along an elbow motion
    sampled once per spindle step."""
    trace = run_chain(t_s, angle_deg=angle_deg, config=ChainConfig(params=PARAMS))
    if not trace.accepted.all():
        raise RuntimeError(f"the chain rejected demo samples: {trace.counters}")
    return trace


def emulate_demo(emu: M0Plus, L: np.ndarray, gd: np.ndarray, gs: np.ndarray):
    """Both muscles through the sequence in the firmware: (instructions (T-1, 2), Ia, II)."""
    emu.write_io(L[0], gd[0], gs[0], True)
    status, _ = emu.call("fw_init")
    if status != abi.Status.PS_OK:
        raise RuntimeError(f"fw_init: {abi.status_name(status)}")
    counts = np.empty((len(L) - 1, 2), dtype=np.int64)
    ia = np.empty((len(L) - 1, 2))
    ii = np.empty((len(L) - 1, 2))
    for j in range(1, len(L)):
        emu.write_io(L[j], gd[j], gs[j], True)
        for k in range(2):
            status, counts[j - 1, k] = emu.call("fw_step_muscle", k)
            if status != abi.Status.PS_OK:
                raise RuntimeError(f"fw_step_muscle({k}) at step {j}: "
                                   f"{abi.status_name(status)}")
        ia[j - 1], ii[j - 1], _ = emu.read_rates(True)
    return counts, ia, ii


def _demo_accuracy(lib, cfg: Config, trace: ChainTrace, emu_ia: np.ndarray,
                   emu_ii: np.ndarray) -> tuple[dict[str, float], dict[str, float], float]:
    """RMS of the host fixed-point rates against the double step and against the chain's own
    rates, per muscle and afferent; and the max |emulator - host| (pps)."""
    L, gd, gs = trace.length_L0, trace.gamma_dynamic_pps, trace.gamma_static_pps
    plan = fixed_plan(lib, cfg)
    rms_double, rms_chain, max_diff = {}, {}, 0.0
    for k, muscle in enumerate(MUSCLES):
        fx_ia, fx_ii, code = fixed_rates(lib, plan, L[:, k], gd[:, k], gs[:, k])
        if code != abi.Status.PS_OK:
            raise RuntimeError(f"host fixed-point step ({muscle}): {abi.status_name(code)}")
        max_diff = max(max_diff, float(np.max(np.abs(emu_ia[:, k] - fx_ia[1:]))),
                       float(np.max(np.abs(emu_ii[:, k] - fx_ii[1:]))))
        ref_ia, ref_ii = native_spindle.run_spindle(L[:, k], gd[:, k], gs[:, k], cfg.step_s,
                                                    cfg.theta, 1, PARAMS, "double")
        for name, got, ref, chain in (("Ia", fx_ia, ref_ia, trace.ia_pps[:, k]),
                                      ("II", fx_ii, ref_ii, trace.ii_pps[:, k])):
            rms_double[f"{muscle} {name}"] = float(np.sqrt(np.mean((got - ref) ** 2)))
            rms_chain[f"{muscle} {name}"] = float(np.sqrt(np.mean((got - chain) ** 2)))
    return rms_double, rms_chain, max_diff


def measure_demo(cfg: Config, build_dir: Path, t_s: np.ndarray,
                 angle_deg: np.ndarray) -> DemoMeasured:
    """The fixed-point firmware along an elbow motion (``angle_deg`` at ``t_s``, one sample
    per spindle step), drives changing as the numpy chain makes them."""
    if not cfg.fixed:
        raise ValueError("the demo motion is measured on the fixed-point configuration")
    trace = demo_trace(t_s, angle_deg)
    L, gd, gs = trace.length_L0, trace.gamma_dynamic_pps, trace.gamma_static_pps
    lib = host_library(cfg, build_dir)
    emu = M0Plus(build_firmware(cfg, build_dir))
    counts, emu_ia, emu_ii = emulate_demo(emu, L, gd, gs)
    held, _, _ = emulate_demo(emu, L, np.broadcast_to(gd[0], gd.shape),
                              np.broadcast_to(gs[0], gs.shape))
    rms_double, rms_chain, max_diff = _demo_accuracy(lib, cfg, trace, emu_ia, emu_ii)
    changes = (float(np.mean(np.diff(gs, axis=0) != 0)), float(np.mean(np.diff(gd, axis=0) != 0)))
    return DemoMeasured(len(counts), (float(counts[:, 0].mean()), float(counts[:, 1].mean())),
                        int(counts.max()), float(held.mean()), int(held.max()),
                        float(trace.t_s[1 + int(np.argmax(counts.max(axis=1)))]), rms_double,
                        rms_chain, max_diff, changes)
