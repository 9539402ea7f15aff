"""The whole-system firmware (``c/m0plus/system.c``) on the emulator, beside the host chain.

:func:`build_system` cross-compiles ``system.c`` with the fixed-point spindle of
``spindle.c`` and the configuration :mod:`.system_config` generates; :class:`SystemFirmware`
feeds it one encoder sample per ``fw_sample`` call (as the 500 Hz timer interrupt would) and
reads back its output record, its bad-sample counters and the instructions, Cortex-M0+
cycles (:mod:`.cycles`) and flash accesses of every call, per stage. :func:`host_chain` runs
the host's double C chain (``spindle.native.chain.CArmChain``, the numpy chain's twin) with
the same configuration on the same samples; :func:`measure_system` compares the two.

Inputs: :func:`demo_samples` (the seed paper's rapid flexion-extension read by an ideal
encoder at exactly 500 Hz) and :func:`fault_samples` (a recorded servo trace with the
encoder's jitter, noise and invalid readings and the faults of
``proprio_env.experiments.fault_injection``, its counts entries only: what the encoder port
delivers).
"""

from __future__ import annotations

import dataclasses
import math
import struct
import subprocess
from pathlib import Path

import numpy as np

from spindle.chain.config import COUNTERS, MUSCLES, ChainConfig
from spindle.chain.length_model import load_length_fits
from spindle.native.chain import CArmChain
from spindle.native.fixed import FX_DRIVE, FX_RATE
from spindle.native.m0plus.build import ARM_FLAGS, C_DIR, FW_DIR, LINK_FLAGS, key, sizes, tool
from spindle.native.m0plus.emulator import M0Plus
from spindle.native.m0plus.system_config import (
    DEVICE_CONFIG,
    GTO_STEP_S,
    SPINDLE_STEP_S,
    system_config_source,
)

FIRMWARE_COUNTERS = COUNTERS
"""The firmware's counters (``fw_counters`` in ``system.c``): the chain's, in order."""
LOAD_COUNTERS = ("invalid_load", "missing_load")
"""The load reading's counters: only a build with the tendon organs (``FW_GTO``) reads it."""

STAGES = {"stage_reading": "reading and time rules", "stage_median": "median filter",
          "stage_angle": "f(x), angle slew and clamp", "stage_lengths": "fitted lengths",
          "stage_tracking": "length slew, tracking low-pass",
          "stage_fusimotor": "predictor, fusimotor drive", "stage_spindles": "spindles",
          "rest_spindles": "spindles", "stage_tendon": "tendon organs (FW_GTO)",
          "stage_stim": "pulse encoder (FW_STIM)", "stage_output": "commit, output record"}
"""system.c's stage functions and the names the breakdown gives them."""
SAMPLE_PERIOD_S = 2e-3
STACK_BYTES = 0x800  # reserved while measuring; re-linked to the high-water mark
RECORD = struct.Struct("<3i8ii2i")  # fw_record: t_us, accepted, status, ia, ii, gs, gd, steps, ib
INPUT = struct.Struct("<dffi4x")  # fw_input: t_s, counts, load, has_load
RING = 4  # FW_RING
PULSE = struct.Struct("<q5i4x")  # ps_pulse_fx: time_us, channel, amplitude, phases
PULSE_RING = 16
DEFINES = ("PS_FX_INLINE_MUL", "FW_GTO", "FW_STIM")
"""The system build's options: fx_mul inlined into the fixed-point step (same results), the
tendon organs' stage (the load word), the stimulation encoder's stage."""


def default_stim():
    """The stimulator the firmware drives: ``StimConfig()`` (Ia and II of BRA and TRImed,
    frequency mode, at most 300 pps per channel)."""
    from spindle.stimulation.config import StimConfig

    return StimConfig()


def build_system(build_dir: Path, config: ChainConfig = DEVICE_CONFIG,
                 spindle_step_s: float = SPINDLE_STEP_S, stack_bytes: int = STACK_BYTES,
                 defines: tuple[str, ...] = DEFINES, opt: str = "-Os",
                 gto_step_s: float = GTO_STEP_S) -> Path:
    """The system firmware's ELF for ``config``, the spindles at ``spindle_step_s``, the
    tendon organs at ``gto_step_s``."""
    stim = default_stim() if "FW_STIM" in defines else None
    gto = "FW_GTO" in defines
    source = system_config_source(config, spindle_step_s=spindle_step_s, stim=stim,
                                  tendon_organs=gto, gto_step_s=gto_step_s)
    tag = key(source, stack_bytes, defines, opt, (FW_DIR / "system.c").read_bytes(),
              (C_DIR / "tendon_organ.c").read_bytes())
    header_dir = build_dir / f"system_{tag}"
    header_dir.mkdir(parents=True, exist_ok=True)
    (header_dir / "fw_system_config.h").write_text(source)
    elf = build_dir / f"system_{tag}.elf"
    if not elf.exists():
        names = ["fw_sample", "fw_in", "fw_count", "fw_out", "fw_overruns", "fw_out_head"]
        if stim is not None:
            names += ["fw_pulses", "fw_pulse_head", "fw_pulse_lost"]
        roots = [f"-Wl,-u,{name}" for name in names]
        extra = []
        if stim is not None:
            from spindle.native.m0plus.stim import stim_config_header

            extra = ["-I", str(stim_config_header(stim, build_dir)), str(C_DIR / "stimulation.c")]
        if gto:
            extra.append(str(C_DIR / "tendon_organ.c"))
        cmd = [tool("gcc"), *ARM_FLAGS, opt, *(f"-D{d}" for d in defines), "-I", str(C_DIR),
               "-I", str(header_dir), str(C_DIR / "spindle.c"), *extra, str(FW_DIR / "system.c"),
               str(FW_DIR / "startup.c"),
               "-T", str(FW_DIR / "m0plus.ld"), f"-Wl,--defsym=FW_STACK_SIZE={stack_bytes}",
               *roots, *LINK_FLAGS, "-o", str(elf)]
        subprocess.run(cmd, check=True)
    return elf


@dataclasses.dataclass
class Run:
    """The firmware along one input: per sample (T,) or (T, 2)."""

    ia_pps: np.ndarray
    ii_pps: np.ndarray
    ib_pps: np.ndarray    # 0 without the tendon organs (FW_GTO)
    gs_pps: np.ndarray
    gd_pps: np.ndarray
    accepted: np.ndarray  # 0 rejected, 1 accepted, 2 restarted at rest
    status: np.ndarray
    steps: np.ndarray     # spindle steps in the sample
    instructions: np.ndarray
    cycles: np.ndarray    # at zero wait states
    fetches: np.ndarray   # 32-bit words fetched from flash
    flash_reads: np.ndarray
    counters: dict[str, int]
    by_stage: dict[str, list[int]]  # stage -> [instructions, cycles, fetches, flash reads]
    peak_by_stage: dict[str, list[int]]  # the same in the costliest sample (cycles at 1 WS)
    overruns: int  # samples whose queue of spindle grid points was full (fw_overruns)
    pulses: np.ndarray  # (time_us, channel) of every pulse event, in order (FW_STIM)
    pulses_lost: int    # samples whose pulses did not fit the stage's buffer

    def cycles_at(self, wait_states: int) -> np.ndarray:
        return self.cycles + wait_states * (self.fetches + self.flash_reads)


class SystemFirmware:
    """The system firmware in the emulator."""

    def __init__(self, elf: Path):
        self.emu = M0Plus(elf, cycles=True, stages=STAGES)
        self.elf = elf

    @property
    def tendon_organs(self) -> bool:
        """Whether the build has the tendon organs' stage (FW_GTO: it reads the load word)."""
        return "stage_tendon" in self.emu.sym

    def run(self, samples: Samples) -> Run:
        """fw_init, then one fw_sample per sample."""
        emu, uc, sym = self.emu, self.emu.uc, self.emu.sym
        status, _ = emu.call("fw_init")
        if status != 0:
            raise RuntimeError(f"fw_init: status {status}")
        emu.by_stage.clear()
        t_s, counts = samples.t_s, samples.counts
        n = len(t_s)
        out = {name: np.zeros(n, dtype=np.int64) for name in
               ("accepted", "status", "steps", "instructions", "cycles", "fetches",
                "flash_reads")}
        rates = np.zeros((5, n, 2))
        head_addr, ring_addr, in_addr = sym["fw_out_head"][0], sym["fw_out"][0], sym["fw_in"][0]
        last, peak, peak_stages = None, -1, {}
        stim = "fw_pulse_head" in sym
        pulses, seen = [], 0
        for j in range(n):
            stages_before = {k: list(v) for k, v in emu.by_stage.items()}
            uc.mem_write(in_addr, INPUT.pack(float(t_s[j]), float(counts[j]),
                                             float(samples.load[j]), int(samples.has_load[j])))
            before = (emu.cycles, emu.fetches, emu.flash_reads)
            status, instructions = emu.call("fw_sample")
            out["instructions"][j] = instructions
            out["cycles"][j] = emu.cycles - before[0]
            out["fetches"][j] = emu.fetches - before[1]
            out["flash_reads"][j] = emu.flash_reads - before[2]
            ws1 = out["cycles"][j] + out["fetches"][j] + out["flash_reads"][j]
            if ws1 > peak:
                peak = ws1
                peak_stages = {k: [a - b for a, b in zip(v, stages_before.get(k, [0] * 4),
                                                         strict=True)]
                               for k, v in emu.by_stage.items()}
            out["status"][j] = status if status < 2**31 else status - 2**32
            head, = struct.unpack("<I", bytes(uc.mem_read(head_addr, 4)))
            if head and (last is None or head != last[0]):
                raw = bytes(uc.mem_read(ring_addr + RECORD.size * ((head - 1) % RING),
                                        RECORD.size))
                last = (head, RECORD.unpack(raw))
                out["accepted"][j] = last[1][1]
                out["steps"][j] = last[1][11]
            if stim:
                head, = struct.unpack("<I", bytes(uc.mem_read(sym["fw_pulse_head"][0], 4)))
                if head - seen > PULSE_RING:
                    raise RuntimeError(f"sample {j}: {head - seen} pulses overran the ring")
                for k in range(seen, head):
                    raw = bytes(uc.mem_read(sym["fw_pulses"][0] + PULSE.size * (k % PULSE_RING),
                                            PULSE.size))
                    pulses.append(PULSE.unpack(raw)[:2])
                seen = head
            if last is not None:
                fields = last[1]
                rates[:, j] = np.array(fields[3:11] + fields[12:14]).reshape(5, 2) / (
                    np.array([FX_RATE, FX_RATE, FX_DRIVE, FX_DRIVE, FX_RATE])[:, None])
        raw = bytes(uc.mem_read(sym["fw_count"][0], 4 * len(FIRMWARE_COUNTERS)))
        counters = dict(zip(FIRMWARE_COUNTERS, struct.unpack(f"<{len(FIRMWARE_COUNTERS)}I", raw),
                            strict=True))
        overruns, = struct.unpack("<I", bytes(uc.mem_read(sym["fw_overruns"][0], 4)))
        lost = struct.unpack("<I", bytes(uc.mem_read(sym["fw_pulse_lost"][0], 4)))[0] if stim \
            else 0
        return Run(rates[0], rates[1], rates[4], rates[2], rates[3], counters=counters,
                   overruns=overruns,
                   pulses=np.array(pulses, dtype=np.int64).reshape(-1, 2), pulses_lost=lost,
                   by_stage={k: list(v) for k, v in emu.by_stage.items()},
                   peak_by_stage=peak_stages, **out)


def host_chain(samples: Samples, config: ChainConfig = DEVICE_CONFIG,
               with_load: bool = True) -> tuple[dict[str, np.ndarray], dict]:
    """The host's double C chain on the same samples: reset at rest at the first sample (as
    the firmware's first sample, with its load word), then every other pushed, with its load
    word if one came (``with_load``: else none at all, as a build without the tendon organs
    reads). (outputs (T, ...), counters)."""
    chain = CArmChain(config, load_length_fits(config.fits_path))
    t, counts = np.asarray(samples.t_s, dtype=float), np.asarray(samples.counts, dtype=float)
    has_load = np.asarray(samples.has_load, dtype=bool) & with_load
    first_load = float(samples.load[0]) if has_load[0] else None
    rest = chain.reset(float(config.calibration.angle_deg(float(counts[0]))), float(t[0]),
                       load=first_load)
    pieces = [{name: np.asarray(getattr(rest, name))[None] for name in HOST_FIELDS}]
    start = 1
    while start < len(t):  # runs of samples with and without load words
        stop = start + 1
        while stop < len(t) and has_load[stop] == has_load[start]:
            stop += 1
        out = chain.run_trace("push_counts", t[start:stop], counts[start:stop],
                              load=samples.load[start:stop] if has_load[start] else None)
        pieces.append({name: out[name] for name in HOST_FIELDS})
        start = stop
    stacked = {name: np.concatenate([p[name] for p in pieces]) for name in HOST_FIELDS}
    names = FIRMWARE_COUNTERS if with_load else tuple(
        k for k in FIRMWARE_COUNTERS if k not in LOAD_COUNTERS)
    return stacked, {name: chain.counters[name] for name in names}


HOST_FIELDS = ("ia_pps", "ii_pps", "ib_pps", "gamma_static_pps", "gamma_dynamic_pps",
               "accepted")


def host_pulses(t_s: np.ndarray, host: dict[str, np.ndarray], stim,
                config: ChainConfig = DEVICE_CONFIG) -> np.ndarray:
    """The host's double stimulation encoder (CStimulator) on the host chain's rates, as the
    firmware's stage runs it: each accepted sample's interval since the last accepted one,
    unless the chain restarted there (an interval beyond max_bridge_s, or an earlier time),
    encoded with the rates output at the start of the interval; intervals below 0.5 us (a
    whole-us clock sees none) are skipped. Returns (time_us, channel) of every pulse."""
    from spindle.native.stimulation import CStimulator
    from spindle.stimulation.channels import afferent_rates

    rates = stim.channels.gather(afferent_rates(MUSCLES, ia=host["ia_pps"],
                                                ii=host["ii_pps"], ib=host["ib_pps"]))
    rows, dts, prev = [], [], 0
    for j in np.flatnonzero(host["accepted"])[1:]:
        dt = float(t_s[j]) - float(t_s[prev])
        if 0.5e-6 <= dt <= config.max_bridge_s:
            rows.append(rates[prev])
            dts.append(dt)
        prev = j
    if not rows:
        return np.zeros((0, 2), dtype=np.int64)
    events = CStimulator(stim).run(np.array(rows), np.array(dts))
    return np.stack((np.round(events["time_s"] * 1e6).astype(np.int64),
                     events["channel"].astype(np.int64)), axis=1)


def pulse_count_difference(fw: np.ndarray, host: np.ndarray, n_channels: int,
                           window_s: float = 1.0) -> int:
    """The largest |firmware - host| pulse count of one channel in one window (1 s)."""
    if len(fw) + len(host) == 0:
        return 0
    end = int(max(fw[:, 0].max(initial=0), host[:, 0].max(initial=0)) // (window_s * 1e6)) + 1

    def counts(events: np.ndarray) -> np.ndarray:
        out = np.zeros((n_channels, end), dtype=np.int64)
        np.add.at(out, (events[:, 1], (events[:, 0] // (window_s * 1e6)).astype(int)), 1)
        return out

    return int(np.max(np.abs(counts(fw) - counts(host))))


@dataclasses.dataclass(frozen=True)
class Samples:
    """What the encoder port delivers, per sample (T,): the time, the counts, the servo's load
    word (any value: the chain's rules judge it) and whether a load word came at all."""

    t_s: np.ndarray
    counts: np.ndarray
    load: np.ndarray
    has_load: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


def demo_samples(duration_s: float, low_deg: float = 20.0, high_deg: float = 110.0,
                 speed_deg_s: float = 130.0) -> Samples:
    """The seed paper's repeated rapid flexion-extension (a triangle at ``speed_deg_s``) read
    by the encoder without noise, jitter or glitches at exactly 500 Hz, with the load words of
    the fault trace's smooth servo torque (``fault_injection.servo_torque_Nm``, flexion and
    extension within 1.1 N m) read without noise or invalid words."""
    from proprio_env.body.encoder import LoadSensor
    from proprio_env.body.servo_motion import triangle_deg
    from proprio_env.experiments.fault_injection import servo_torque_Nm
    from spindle.chain.sensor import AX12, AX12_LOAD, Calibration

    t = np.arange(round(duration_s / SAMPLE_PERIOD_S) + 1) * SAMPLE_PERIOD_S
    angle = triangle_deg(t, low_deg, high_deg, speed_deg_s)
    cal = Calibration(deg_per_count=AX12.deg_per_count)
    counts = np.clip(np.round(cal.zero_count + cal.sign * angle / cal.deg_per_count), 0,
                     AX12.max_count)
    sensor = LoadSensor(dataclasses.replace(AX12_LOAD, noise_counts=0.0, invalid_rate=0.0),
                        sign=cal.sign, rng=0)
    load = sensor.read_block(np.array([servo_torque_Nm(float(x)) for x in t]))
    return Samples(t, counts, load, np.ones(len(t), dtype=bool))


def _as_float(x: object) -> float:
    try:
        return float(x)
    except OverflowError:  # the Python int 10**400
        return math.inf if x > 0 else -math.inf
    except TypeError:
        return math.nan


def fault_samples(n_samples: int, seed: int = 0,
                  fault_probability: float = 0.2) -> tuple[Samples, list[str]]:
    """A recorded servo trace with jitter, noise, invalid readings and injected faults
    (proprio_env.experiments.fault_injection.fault_stream, its counts entries with their load
    words, a segment pushed without load having none), starting at its first valid sample;
    counts and load words as float32 (what the firmware's input holds): (samples, the faults
    injected)."""
    from proprio_env.experiments.fault_injection import fault_stream
    from spindle.chain.sensor import AX12, is_valid_reading

    fits = load_length_fits(None)
    t, x, load, has_load, faults = [], [], [], [], []
    for seg in fault_stream(np.random.default_rng(seed), n_samples, fits, fault_probability):
        if seg.entry != "counts":
            continue
        t += [_as_float(v) for v in seg.t_s]
        x += [_as_float(v) for v in seg.values]
        words = seg.loads if seg.loads is not None else [0.0] * len(seg.t_s)
        load += [_as_float(v) for v in words]
        has_load += [seg.loads is not None] * len(seg.t_s)
        if seg.fault:
            faults.append(seg.fault)
    t_arr = np.array(t)
    x_arr = np.array(x, dtype=np.float32).astype(float)
    first = next(i for i in range(len(t)) if math.isfinite(t_arr[i])
                 and is_valid_reading(x_arr[i], AX12.max_count))
    return Samples(t_arr[first:], x_arr[first:],
                   np.array(load, dtype=np.float32).astype(float)[first:],
                   np.array(has_load[first:], dtype=bool)), faults


@dataclasses.dataclass
class Compared:
    run: Run
    host_counters: dict[str, int]
    rms_pps: dict[str, float]  # "BRA Ia" ...: firmware vs host double chain
    max_abs_pps: float
    host_pulses: np.ndarray      # (time_us, channel): the host's double encoder
    pulse_count_diff: int        # largest |fw - host| count per channel per second

    @property
    def counters_equal(self) -> bool:
        return self.run.counters == self.host_counters

    @property
    def worst_rms_pps(self) -> float:
        return max(self.rms_pps.values())


def compare(fw: SystemFirmware, samples: Samples,
            config: ChainConfig = DEVICE_CONFIG) -> Compared:
    """The firmware and the host double chain on the same samples (Ia, II and, with the
    tendon organs, Ib)."""
    run = fw.run(samples)
    host, host_counters = host_chain(samples, config, with_load=fw.tendon_organs)
    counters = {k: v for k, v in run.counters.items() if k in host_counters}
    run = dataclasses.replace(run, counters=counters)
    afferents = [("Ia", run.ia_pps, host["ia_pps"]), ("II", run.ii_pps, host["ii_pps"])]
    if fw.tendon_organs:
        afferents.append(("Ib", run.ib_pps, host["ib_pps"]))
    rms, worst = {}, 0.0
    for k, muscle in enumerate(MUSCLES):
        for name, got, ref in afferents:
            d = got[:, k] - ref[:, k]
            rms[f"{muscle} {name}"] = float(np.sqrt(np.mean(d**2)))
            worst = max(worst, float(np.max(np.abs(d))))
    host_events = np.zeros((0, 2), dtype=np.int64)
    diff = 0
    if "fw_pulse_head" in fw.emu.sym:
        stim = default_stim()
        host_events = host_pulses(samples.t_s, host, stim, config)
        diff = pulse_count_difference(run.pulses, host_events, stim.n_channels)
    return Compared(run, host_counters, rms, worst, host_events, diff)


def firmware_sizes(elf: Path, stack_used: int, build_dir: Path,
                   config: ChainConfig = DEVICE_CONFIG, spindle_step_s: float = SPINDLE_STEP_S,
                   defines: tuple[str, ...] = DEFINES,
                   gto_step_s: float = GTO_STEP_S) -> tuple[int, int]:
    """(flash, RAM) bytes, the stack re-linked to the high-water mark + 64 B (64 B units)."""
    stack = (stack_used + 64 + 63) // 64 * 64
    return sizes(build_system(build_dir, config, spindle_step_s, stack_bytes=stack,
                              defines=defines, gto_step_s=gto_step_s))
