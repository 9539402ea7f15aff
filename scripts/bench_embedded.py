"""Cost of the C spindle on a Cortex-M0+: instructions per step, MIPS, flash and RAM.

A thin command line over spindle.native.m0plus (build, isa, emulator, measure). It
cross-compiles spindle/native/c/spindle.c with the firmware spindle/native/c/m0plus/firmware.c
(two muscles, HUMAN constants in flash) for -mcpu=cortex-m0plus -mthumb, soft float, newlib-nano,
and runs the step in an instruction-set emulator (unicorn >= 2.1) on the Mileusnic Fig. 3
protocol (ramps 0.95 -> 1.08 L0 at 0.11, 0.66, 1.55 L0/s, drive (0,0), (70,0), (0,70) pps,
3.3 s), sampled once per spindle step. For every configuration of the lever table it prints
the executed instructions per step, MIPS per muscle (instructions per step / step), flash and
RAM of the firmware (arm-none-eabi-size: flash = text + data, RAM = data + bss including the
reserved stack, whose high-water mark is measured in the emulator) and the accuracy: the
worst-run RMS of Ia and II against the stiff reference (spindle.reference, scipy Radau).

Instruction-set check: unicorn opened in M-class mode silently models a Cortex-M33 (its CPU
model cannot be changed there, and sdiv runs). The emulator is therefore opened in Thumb
mode with the Cortex-M0 model (ARMv6-M), and the script checks that sdiv and a Thumb-2
32-bit data-processing instruction do fault. That model still executes cbz/cbnz and it
(ARMv7-M only), so every executed instruction is also decoded with the ARMv6-M encoding
rules, and the whole binary is disassembled with arm-none-eabi-objdump and checked the same
way; any ARMv7-M-only instruction is an error.

The emulated rates are compared with a host build of the same sources and options (all
float32, no libm call on the measured path when PS_FAST_CBRT is set, so they agree to the
bit); the accuracy of each configuration is measured on the host build over all 9 runs.

The last rows are the fixed-point step (ps_spindle_step_fx, int32 Q24, firmware option
FW_FIXED): its plan is made on the host by ps_plan_fx_init from spindle.HUMAN and compiled
into the firmware as a const; lengths go to the firmware in Q24 and drives in Q8, rates come
back in Q16 (the host build gets the same rounded inputs, and the two agree to the bit).

A second input, the demo motion, measures the fixed-point step as the prosthesis runs it:
the Fig. 3 protocol holds the fusimotor drive constant within a run, so the step reuses its
activation targets there. The demo motion is the seed paper's repeated rapid elbow
flexion-extension (triangle 20-110 deg at 130 deg/s, proprio_env.body.servo_motion.triangle_deg)
through the numpy chain (spindle.chain.run_chain, ChainConfig()) sampled once per spindle step
(5 ms); the BRA and TRImed lengths and the chain's own gamma_s, gamma_d of every step are fed
to the two-muscle firmware. It prints the instructions per step per muscle, MIPS per muscle,
the costliest step, the same lengths with the drives held (the cost of the activation-target
divides), and the RMS of the fixed-point rates against the double ps_spindle_step at the same
step and inputs, and against the chain's own rates (numpy, trapezoidal 1 ms). Its summary
line `demo_mips_per_muscle=... demo_peak_mips=... demo_rms_vs_double_pps=...` precedes the
last line, which stays the Fig. 3 figure.

The whole system (spindle/native/c/m0plus/system.c, spindle.native.m0plus.system): one
fw_sample call per encoder sample, as the 500 Hz timer interrupt would make it, running the
whole chain (time and reading rules, median, f(x), fitted lengths, tracking low-pass,
predictor and fusimotor drive, the fixed-point BRA and TRImed spindles on an 8 ms grid stepped
up to half a step ahead of the sample, the tendon organs from the servo's load word on their own
8 ms grid, the stimulation encoder) in integer arithmetic, the
configuration generated on the host (system_config). Measured on the
demo motion (the triangle above, read by an ideal encoder at 500 Hz) and on a recorded servo
trace with the encoder's jitter, noise and invalid readings and injected faults
(proprio_env.experiments.fault_injection, counts entries): instructions and Cortex-M0+ cycles
per sample
(spindle.native.m0plus.cycles: ARM DDI 0484C instruction timings, flash wait states of the
EFM32ZG), mean and worst, per stage; flash, RAM, stack; the lowest EFM32ZG clock meeting every
sample's 2 ms deadline with a 25 % margin and its power (EFM32ZG datasheet, 114 uA/MHz at
3 V); Ia, II and Ib against the host double chain (CArmChain) on the same samples and load
words, RMS, the bad-sample counters of both (the load reading's included) and the pulse
counts against the host double encoder. Its line is the last:
    system_mips=... system_peak_cycles_per_sample=... clock_mhz=... power_mw=...
    flash_bytes=... ram_bytes=... rms_vs_host_pps=... ib_rms_vs_host_pps=...
    max_pulse_count_diff=...

Usage:
    PYTHONPATH=. python scripts/bench_embedded.py            # all levers, 9 runs (10-16 min)
    PYTHONPATH=. python scripts/bench_embedded.py --quick    # final configuration, 2 runs
    PYTHONPATH=. python scripts/bench_embedded.py --system-only --figure docs/img/m0plus_system.png
Needs: gcc-arm-none-eabi, libnewlib-arm-none-eabi, a host C compiler, unicorn, scipy.
The last line reads
    m0plus_mips_per_muscle=<float> rms_pps=<float> flash_bytes=<int> ram_bytes=<int>
for the cheapest measured configuration within RMS_TARGET_PPS (2 pps; --quick measures only
the final one, the fixed-point step at 5 ms).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from proprio_env.body.servo_motion import triangle_deg
from spindle.native.m0plus.build import Config
from spindle.native.m0plus.isa import isa_probe
from spindle.native.m0plus.measure import (
    ALL_RUNS,
    FINAL,
    LEVERS,
    QUICK_RUNS,
    RMS_TARGET_PPS,
    DemoMeasured,
    measure,
    measure_demo,
    references,
)

DEMO_LOW_DEG, DEMO_HIGH_DEG, DEMO_SPEED_DEG_S = 20.0, 110.0, 130.0
DEMO_CYCLES = 4


def demo_motion(step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The seed paper's repeated rapid flexion-extension, one sample per spindle step:
    (t_s, angle_deg)."""
    period_s = 2 * (DEMO_HIGH_DEG - DEMO_LOW_DEG) / DEMO_SPEED_DEG_S
    t = np.arange(round(DEMO_CYCLES * period_s / step_s) + 1) * step_s
    return t, triangle_deg(t, DEMO_LOW_DEG, DEMO_HIGH_DEG, DEMO_SPEED_DEG_S)


def print_demo(d: DemoMeasured, cfg: Config) -> None:
    step_s = cfg.step_s

    def worst(rms: dict[str, float]) -> str:
        return ", ".join(f"{k} {v:.2g}" for k, v in rms.items())

    print(f"\ndemo motion ({cfg.label}): triangle {DEMO_LOW_DEG:g}-{DEMO_HIGH_DEG:g} deg at "
          f"{DEMO_SPEED_DEG_S:g} deg/s, {DEMO_CYCLES} cycles, numpy chain (ChainConfig()) "
          f"sampled every {step_s * 1e3:g} ms, BRA and TRImed lengths and the chain's own "
          f"gamma_s, gamma_d per step (gamma_s changes in {d.drive_changes[0]:.0%} of the "
          f"steps, gamma_d in {d.drive_changes[1]:.0%}); {d.steps} steps x 2 muscles emulated")
    print("| input | instr/step BRA | instr/step TRImed | MIPS/muscle | peak instr/step "
          "| peak MIPS |")
    print("|---|---:|---:|---:|---:|---:|")
    print(f"| demo motion, drives from the chain | {d.instr_mean[0]:.0f} | {d.instr_mean[1]:.0f} "
          f"| {d.mips(step_s):.3f} | {d.instr_max} | {d.instr_max / step_s / 1e6:.3f} |")
    print(f"| same lengths, drives held at the first sample | | | "
          f"{d.held_instr_mean / step_s / 1e6:.3f} | {d.held_instr_max} "
          f"| {d.held_instr_max / step_s / 1e6:.3f} |")
    print(f"  costliest step at t = {d.peak_t_s:.3f} s")
    print(f"  fixed point vs double ps_spindle_step ({step_s * 1e3:g} ms, same inputs), RMS pps: "
          f"{worst(d.rms_vs_double)}")
    print(f"  fixed point vs the numpy chain's own rates (trapezoidal 1 ms), RMS pps: "
          f"{worst(d.rms_vs_chain)}")
    print(f"  emulator vs host fixed-point build: max {d.max_diff_host_pps:.2g} pps")
    print(f"demo_mips_per_muscle={d.mips(step_s):.4f} "
          f"demo_peak_mips={d.instr_max / step_s / 1e6:.4f} "
          f"demo_rms_vs_double_pps={max(d.rms_vs_double.values()):.4f}")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="only the final configuration, emulated on 2 of the 9 runs")
    ap.add_argument("--build-dir", type=Path, default=None)
    ap.add_argument("--profile", action="store_true",
                    help="print the instructions per step spent in each function")
    ap.add_argument("--only", type=int, nargs="*", default=None,
                    help="indices of the lever rows to measure")
    ap.add_argument("--no-demo", action="store_true",
                    help="skip the demo motion (the fixed-point step with moving drives)")
    ap.add_argument("--system-only", action="store_true",
                    help="only the whole-system firmware")
    ap.add_argument("--figure", type=Path, default=None,
                    help="save the whole system's per-stage cycles as a PNG here")
    args = ap.parse_args(argv)
    try:
        import unicorn
    except ImportError:
        sys.exit("needs unicorn >= 2.1: pip install 'unicorn>=2.1'")
    t0 = time.perf_counter()
    all_runs = list(ALL_RUNS)
    build_dir = args.build_dir or Path(tempfile.mkdtemp(prefix="bench_embedded_"))
    build_dir.mkdir(parents=True, exist_ok=True)
    print(f"unicorn {unicorn.__version__}; instruction-set probe:")
    for what, outcome in isa_probe().items():
        print(f"  {what}: {outcome}")
    if args.system_only:
        return run_system(args.quick, build_dir, args.figure)
    refs = references(all_runs)
    print(f"reference (scipy Radau, HUMAN, 9 runs): {time.perf_counter() - t0:.0f} s")
    configs = [FINAL] if args.quick else LEVERS
    if args.only is not None:
        configs = [LEVERS[k] for k in args.only]
    rows = []
    for cfg in configs:
        # lever rows: instructions over 2 runs (the fastest ramp with dynamic drive, the
        # medium one with static drive); the final row in full mode: all 9 runs
        emulated = all_runs if (cfg is FINAL and not args.quick) else list(QUICK_RUNS)
        m = measure(cfg, emulated, refs, build_dir)
        rows.append(m)
        print(f"{cfg.label}: {m.instr_mean:.0f} instr/step (max {m.instr_max}), "
              f"{m.mips:.3f} MIPS/muscle, rms {m.rms_pps:.3f} pps, flash {m.flash} B, "
              f"RAM {m.ram} B (stack high-water {m.stack_used} B), emulator vs host "
              f"{m.max_diff_host_pps:.2g} pps over {m.steps} steps", flush=True)
        if args.profile:
            print("  instructions per step by function:",
                  ", ".join(f"{name} {n}" for name, n in m.profile))
        if m.violations:
            print("  ARMv7-M-only instructions:", *m.violations[:10], sep="\n    ")
            return 1
    print("\n| configuration | step (ms) | instr/step | MIPS/muscle | RMS (pps) | flash (B) "
          "| RAM (B) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for m in rows:
        print(f"| {m.cfg.label} | {m.cfg.step_s * 1e3:g} | {m.instr_mean:.0f} | {m.mips:.3f} | "
              f"{m.rms_pps:.3f} | {m.flash} | {m.ram} |")
    # the last line: the cheapest measured configuration within the accuracy target
    within = [m for m in rows if m.rms_pps <= RMS_TARGET_PPS]
    final = min(within, key=lambda m: m.mips) if within else rows[-1]
    if not args.no_demo:
        demo = measure_demo(FINAL, build_dir, *demo_motion(FINAL.step_s))
        print_demo(demo, FINAL)
        if demo.max_diff_host_pps != 0.0:
            print("  the emulated fixed-point rates differ from the host build's")
            return 1
    print(f"best within {RMS_TARGET_PPS} pps RMS: {final.cfg.label}")
    print(f"ARMv6-M check: every executed instruction decoded, objdump of the whole firmware: "
          f"no ARMv7-M-only instruction; total {time.perf_counter() - t0:.0f} s")
    print(f"m0plus_mips_per_muscle={final.mips:.4f} rms_pps={final.rms_pps:.4f} "
          f"flash_bytes={final.flash} ram_bytes={final.ram}")
    return run_system(args.quick, build_dir, args.figure)


def _stage_figure(results, path: Path, clock_mhz: float, period: float) -> None:
    """Per stage: mean cycles per sample (0 WS) on each input, and the costliest sample's
    cycles at the clock's wait states stacked by stage beside the 2 ms budget at the clock."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from spindle.native.m0plus import cycles as cyc

    stages = list(dict.fromkeys(k for c in results.values() for k in c.run.by_stage
                                if k != "entry"))
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 4.2), width_ratios=(2.2, 1))
    y = np.arange(len(stages))
    for k, (name, c) in enumerate(results.items()):
        n = len(c.run.instructions)
        ax0.barh(y + 0.38 * k, [c.run.by_stage.get(s, [0, 0])[1] / n for s in stages], 0.38,
                 label=name)
    ax0.set_yticks(y + 0.19, stages)
    ax0.invert_yaxis()
    ax0.set_xlabel("cycles per sample, mean (0 wait states)")
    ax0.legend(loc="lower right", fontsize=8)
    ax0.set_title("Cortex-M0+ whole system: cost per stage")
    ws = cyc.wait_states(clock_mhz)  # the sample costliest at 1 WS, at the clock's WS
    worst = max(results.values(), key=lambda c: c.run.cycles_at(1).max())
    bottom = 0
    for s in stages:
        _, cycles, fetches, flash_reads = worst.run.peak_by_stage.get(s, [0, 0, 0, 0])
        v = cycles + ws * (fetches + flash_reads)
        ax1.bar(0, v, bottom=bottom, label=s)
        bottom += v
    ax1.axhline(clock_mhz * 1e6 * period, color="k", ls="--", lw=1)
    ax1.text(0.45, clock_mhz * 1e6 * period, f" {period * 1e3:g} ms at {clock_mhz:g} MHz",
             va="bottom", ha="right", fontsize=8)
    ax1.set_xticks([])
    ax1.set_ylabel(f"cycles ({ws} wait state{'' if ws == 1 else 's'} at {clock_mhz:g} MHz)")
    ax1.set_title("costliest sample", fontsize=10)
    handles, labels = ax1.get_legend_handles_labels()
    ax1.legend(handles[::-1], labels[::-1], fontsize=7, loc="center left",
               bbox_to_anchor=(1.02, 0.5))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _stage_table(results) -> None:
    stages = list(dict.fromkeys(k for c in results.values() for k in c.run.by_stage))
    print("\n| stage | " + " | ".join(f"{name}: instr/sample | cycles/sample (0 WS) | "
                                     "in its costliest sample: cycles (1 WS)"
                                     for name in results) + " |")
    print("|---|" + "---:|---:|---:|" * len(results))
    for stage in stages:
        cells = []
        for c in results.values():
            n = len(c.run.instructions)
            row = c.run.by_stage.get(stage, [0, 0, 0, 0])
            peak = c.run.peak_by_stage.get(stage, [0, 0, 0, 0])
            cells += [f"{row[0] / n:.0f}", f"{row[1] / n:.0f}", f"{peak[1] + peak[2] + peak[3]}"]
        print(f"| {stage} | " + " | ".join(cells) + " |")


def _input_table(results, period: float) -> None:
    print("| input | samples | instr/sample mean | max | MIPS | cycles/sample mean (0 WS) | "
          "max (0 WS) | max (1 WS) | RMS vs host (pps) | max abs (pps) | counters equal | "
          "pulses fw / host | max count diff per channel-second |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|")
    for name, c in results.items():
        r = c.run
        print(f"| {name} | {len(r.instructions)} | {r.instructions.mean():.0f} | "
              f"{r.instructions.max()} | {r.instructions.mean() / period / 1e6:.3f} | "
              f"{r.cycles.mean():.0f} | {r.cycles.max()} | {r.cycles_at(1).max()} | "
              f"{c.worst_rms_pps:.3f} | {c.max_abs_pps:.3f} | {c.counters_equal} | "
              f"{len(r.pulses)} / {len(c.host_pulses)} | {c.pulse_count_diff} |")
        print("  RMS per afferent: " + ", ".join(f"{k} {v:.3f}" for k, v in c.rms_pps.items()))
        print(f"  counters firmware: {r.counters}")
        if not c.counters_equal:
            print(f"  counters host:     {c.host_counters}")
        print(f"  spindle steps per sample: {np.bincount(r.steps).tolist()}; statuses "
              f"{sorted(set(r.status.tolist()))}; queue overruns {r.overruns}; pulse samples "
              f"lost {r.pulses_lost}")


def _clock(results, period: float) -> tuple[float, int]:
    """The clock the costliest sample allows (printed with its margin) and that sample's
    cycles at the clock's wait states."""
    from spindle.native.m0plus import cycles as cyc

    peak0 = max(int(c.run.cycles.max()) for c in results.values())
    peak1 = max(int(c.run.cycles_at(1).max()) for c in results.values())

    def peak(f: float) -> int:
        return peak0 if cyc.wait_states(f) == 0 else peak1

    def margin(f: float) -> float:
        return 1 - peak(f) / (f * 1e6 * period)

    keep = f"{cyc.DEADLINE_MARGIN:.0%} margin"
    clock = cyc.lowest_clock_mhz(peak0, peak1, period)
    if clock is not None:
        head = f"lowest EFM32ZG HFRCO band meeting every sample's deadline with a {keep}"
    else:
        clock = max(cyc.HFRCO_BANDS_MHZ, key=margin)
        head = (f"no EFM32ZG band keeps the {keep} "
                f"({cyc.needed_clock_mhz(peak1, period):.1f} MHz would); the best band")
    if margin(clock) < 0:
        need = cyc.needed_clock_mhz(peak1, period)
        print(f"deadline: the costliest sample ({peak1} cycles at 1 WS) needs {need:.1f} MHz "
              f"with a {keep}, above the EFM32ZG's {cyc.MAX_CLOCK_MHZ:g} MHz")
        return need, peak1
    print(f"deadline ({period * 1e3:g} ms): {head}: {clock:g} MHz ({cyc.wait_states(clock)} "
          f"wait states; costliest sample {peak(clock)} cycles = {peak(clock) / clock:.0f} us, "
          f"margin {margin(clock):.1%})")
    return clock, peak(clock)


def _measure_build(build_dir: Path, defines: tuple[str, ...], inputs):
    from spindle.native.m0plus import system as sysfw
    from spindle.native.m0plus.isa import objdump_violations

    elf = sysfw.build_system(build_dir, defines=defines)
    fw = sysfw.SystemFirmware(elf)
    results = {name: sysfw.compare(fw, samples) for name, samples in inputs.items()}
    seen, bad = objdump_violations(elf)
    flash, ram = sysfw.firmware_sizes(elf, fw.emu.stack_used(), build_dir, defines=defines)
    return results, sorted(fw.emu.violations) + bad, seen, flash, ram, fw.emu.stack_used()


def run_system(quick: bool, build_dir: Path, figure: Path | None = None) -> int:
    """The whole-system firmware on the demo motion and the faulty trace (and, for the
    breakdown, the build without the pulse encoder); prints the system's last line."""
    from spindle.native.m0plus import cycles as cyc
    from spindle.native.m0plus import system as sysfw
    from spindle.native.m0plus.system_config import DEVICE_CONFIG, GTO_STEP_S, SPINDLE_STEP_S

    t0 = time.perf_counter()
    demo_s, fault_n = (1.5, 1500) if quick else (DEMO_CYCLES * 2 * 90 / 130, 10000)
    faulty, faults = sysfw.fault_samples(fault_n, seed=1)
    inputs = {"demo motion": sysfw.demo_samples(demo_s), "servo trace, jitter + faults": faulty}
    period = sysfw.SAMPLE_PERIOD_S
    print(f"\nwhole system (system.c, chain config max_bridge_s={DEVICE_CONFIG.max_bridge_s:g} s, "
          f"spindles fixed point on a {SPINDLE_STEP_S * 1e3:g} ms grid, tendon organs on a "
          f"{GTO_STEP_S * 1e3:g} ms grid) vs the host double "
          f"chain (CArmChain, trapezoidal {DEVICE_CONFIG.spindle_step_s * 1e3:g} ms) and the "
          f"host double stimulation encoder (CStimulator, StimConfig()); faults injected: "
          f"{len(faults)} ({', '.join(sorted(set(faults)))})")
    chain_only = tuple(d for d in sysfw.DEFINES if d != "FW_STIM")
    base, *_, base_flash, base_ram, _ = _measure_build(
        build_dir, chain_only, {"demo motion": inputs["demo motion"]})
    print(f"without the pulse encoder (demo motion): "
          f"{base['demo motion'].run.instructions.mean():.0f} instr/sample "
          f"({base['demo motion'].run.instructions.mean() / period / 1e6:.3f} MIPS), "
          f"costliest {base['demo motion'].run.cycles_at(1).max()} cycles (1 WS), flash "
          f"{base_flash} B, RAM {base_ram} B")
    results, violations, seen, flash, ram, stack = _measure_build(build_dir, sysfw.DEFINES,
                                                                  inputs)
    print("with the pulse encoder (FW_STIM):")
    _input_table(results, period)
    _stage_table(results)
    clock, peak = _clock(results, period)
    if figure is not None:
        _stage_figure(results, figure, clock, period)
        print(f"figure: {figure}")
    mips = results["demo motion"].run.instructions.mean() / period / 1e6
    rms = max(c.worst_rms_pps for c in results.values())
    power = cyc.active_power_mw(clock)
    busy = results["demo motion"].run.cycles_at(cyc.wait_states(clock)).mean() / (
        clock * 1e6 * period)
    print(f"power: {cyc.SUPPLY_V:g} V x {cyc.ACTIVE_UA_PER_MHZ:g} uA/MHz x {clock:.1f} MHz "
          f"= {power:.2f} mW running continuously (the paper: under 10 mW); busy {busy:.0%} of "
          f"each period on the demo motion (sleeping in between would lower the average)")
    print(f"flash {flash} B, RAM {ram} B (stack high-water {stack} B); ARMv6-M: {seen} "
          f"instructions disassembled, {len(violations)} ARMv7-M-only; "
          f"{time.perf_counter() - t0:.0f} s")
    if violations:
        print("  ARMv7-M-only instructions:", *violations[:10], sep="\n    ")
        return 1
    ib_rms = max((v for c in results.values() for k, v in c.rms_pps.items()
                  if k.endswith(" Ib")), default=float("nan"))
    pulse_diff = max(c.pulse_count_diff for c in results.values())
    print(f"system_mips={mips:.4f} system_peak_cycles_per_sample={peak} "
          f"clock_mhz={clock:.1f} power_mw={power:.3f} flash_bytes={flash} "
          f"ram_bytes={ram} rms_vs_host_pps={rms:.4f} ib_rms_vs_host_pps={ib_rms:.4f} "
          f"max_pulse_count_diff={pulse_diff}")
    ok = all(c.counters_equal and c.pulse_count_diff <= 1 for c in results.values())
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
