"""``proprio-run``: the runtime from the command line (docs/runtime.md)."""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from spindle.backends import BACKEND_CHOICES

SOURCES = ("dynamixel", "virtual", "simulated", "replay")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="proprio-run",
        description="Read an AX-12 (or the virtual one, a simulated elbow, a replay), run the "
                    "chain in real time, stream rates and pulses on LSL, log every reading.")
    ap.add_argument("--source", choices=SOURCES, default="dynamixel")
    ap.add_argument("--port", default="/dev/ttyUSB0", help="serial port (dynamixel)")
    ap.add_argument("--baud", type=int, default=1_000_000, help="bus baud rate (AX-12: 1 Mbps)")
    ap.add_argument("--id", type=int, default=1, help="servo ID")
    ap.add_argument("--return-delay-us", type=float, default=None,
                    help="write the return delay time (register 5) on open, in us")
    ap.add_argument("--latency-timer-ms", type=float, default=16.0,
                    help="the USB adapter's latency timer (the SDK's reply timeout budgets it)")
    ap.add_argument("--replay", default=None, help="CSV of readings (replay)")
    ap.add_argument("--track", default="elbow", choices=("scripted", "elbow"),
                    help="motion of the virtual servo / simulated elbow")
    ap.add_argument("--servo-fault", action="append", default=[],
                    help="a fault of the virtual servo (see proprio-virtual-servo --help)")
    ap.add_argument("--rate", type=float, default=500.0, help="sample rate (Hz)")
    ap.add_argument("--backend", choices=BACKEND_CHOICES, default="auto")
    ap.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    ap.add_argument("--log", default="proprio_run.csv", help="CSV log ('' for none)")
    ap.add_argument("--no-lsl", action="store_true", help="no LSL outlets")
    ap.add_argument("--lsl-name", default="proprio", help="LSL stream name prefix")
    ap.add_argument("--lsl-loopback", action="store_true",
                    help="keep LSL on this machine (writes an lsl_api.cfg, sets LSLAPICFG)")
    ap.add_argument("--stage", action="append", default=[],
                    help="MODULE:FACTORY of an extra rate stage (called with no arguments)")
    ap.add_argument("--pulse-encoder", default="stimulation",
                    help="'stimulation' (the default: the stimulator stage, BRA and TRImed Ia, "
                         "II and Ib frequency-coded into pulse events), 'none', or "
                         "MODULE:FACTORY of a pulse encoder")
    ap.add_argument("--rt-priority", type=int, default=None,
                    help="run the loop (and a virtual servo) under SCHED_FIFO at this "
                         "priority, 1-99 (needs root or CAP_SYS_NICE)")
    ap.add_argument("--tty-worker-priority", type=int, default=None,
                    help="meanwhile run the kernel's workers that carry the serial port's "
                         "bytes under SCHED_FIFO at this priority, 1-99, below "
                         "--rt-priority (needs root; restored at the end)")
    ap.add_argument("--no-force-sense", action="store_true",
                    help="push the angle alone, not the servo's load word (Ib stays at 0)")
    ap.add_argument("--quiet", action="store_true", help="no live status line")
    return ap


def load_factory(spec: str):
    """``module:attribute`` called with no arguments."""
    module, _, attr = spec.partition(":")
    if not module or not attr:
        raise ValueError(f"{spec!r}: expected MODULE:FACTORY")
    return getattr(importlib.import_module(module), attr)()


def start_virtual_servo(link: str, track: str, faults: list[str],
                        rt_priority: int | None = None, extra: tuple[str, ...] = ()
                        ) -> subprocess.Popen:
    """``proprio-virtual-servo`` in a child process; returns once its link exists."""
    cmd = [sys.executable, "-m", "proprio_env.runtime.virtual_servo", "--link", link,
           "--track", track, *extra]
    for f in faults:
        cmd += ["--fault", f]
    if rt_priority is not None:
        cmd += ["--rt-priority", str(rt_priority)]
    child = subprocess.Popen(cmd, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 30
    while not os.path.exists(link):
        if child.poll() is not None or time.monotonic() > deadline:
            child.kill()
            raise RuntimeError("the virtual servo did not start")
        time.sleep(0.05)
    return child


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.lsl_loopback:
        from proprio_env.runtime.sinks import write_loopback_lsl_config

        cfg = Path(tempfile.gettempdir()) / f"proprio_lsl_{os.getpid()}.cfg"
        os.environ["LSLAPICFG"] = str(write_loopback_lsl_config(cfg))
    from proprio_env.runtime.loop import Runtime
    from proprio_env.runtime.sinks import CsvLog, LslSink
    from proprio_env.runtime.sources import DynamixelSource, ReplaySource, SimulatedElbowSource
    from proprio_env.runtime.stages import SpindleStage
    from proprio_env.runtime.status import StatusLine

    child = None
    if args.source == "virtual":
        args.port = str(Path(tempfile.gettempdir()) / f"proprio-ax12-{os.getpid()}")
        child = start_virtual_servo(args.port, args.track, args.servo_fault, args.rt_priority)
    try:
        if args.source in ("dynamixel", "virtual"):
            source = DynamixelSource(args.port, args.baud, args.id, args.return_delay_us,
                                     args.latency_timer_ms)
        elif args.source == "simulated":
            source = SimulatedElbowSource(args.track)
        else:
            if not args.replay:
                raise SystemExit("--source replay needs --replay FILE")
            source = ReplaySource(args.replay)
        stages = [SpindleStage()] + [load_factory(s) for s in args.stage]
        config = None  # a real AX-12: its own load scale (AX12_LOAD)
        if args.source in ("virtual", "simulated"):  # the model servo's torque range
            from proprio_env.body.servo_motion import servo_load_params
            from spindle.chain import ChainConfig

            config = ChainConfig(load=servo_load_params())
        if args.pulse_encoder == "stimulation":
            from proprio_env.runtime.stages import StimulationEncoder

            encoder = StimulationEncoder(backend=args.backend)
        elif args.pulse_encoder in ("", "none"):
            encoder = None
        else:
            encoder = load_factory(args.pulse_encoder)
        sinks = [] if args.no_lsl else [LslSink(args.lsl_name)]
        runtime = Runtime(source, rate_hz=args.rate, backend=args.backend, config=config,
                          stages=stages, pulse_encoder=encoder, sinks=sinks,
                          log=CsvLog(args.log) if args.log else None,
                          status=None if args.quiet else StatusLine(),
                          duration_s=args.duration, info={"port": args.port},
                          rt_priority=args.rt_priority,
                          tty_worker_priority=args.tty_worker_priority,
                          force_sense=not args.no_force_sense)
        summary = runtime.run()
    finally:
        if child is not None:
            child.terminate()
            child.wait(10)
    c, lat = summary["counters"], summary["latency"]
    print(f"backend {summary['backend']}  readings {c['readings']}  accepted {c['accepted']}  "
          f"rejected {c['rejected']}  timeouts {c['timeout']}  corrupt {c['corrupt']}  "
          f"unplugged {c['unplugged']}  reconnects {c['reconnects']}  "
          f"deadline misses {c['deadline_misses']}  latency p50 {lat['p50_ms']:.3f} "
          f"p99 {lat['p99_ms']:.3f} max {lat['max_ms']:.3f} ms", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
