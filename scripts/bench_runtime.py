"""Real-time figures of the runtime against the virtual AX-12 (docs/runtime.md).

For each setting, side by side in one run: a virtual servo (a child process on a pty), the
runtime reading it through dynamixel_sdk at 500 Hz with the LSL outlets (loopback-only
config) and the CSV log, for --duration seconds. Prints per setting the latency from a
reading's arrival to the outputs published (p50, p99, max), the read time, the deadline
misses and the machine's load average.

    PYTHONPATH=. python scripts/bench_runtime.py                     # 60 s, C backend
    PYTHONPATH=. python scripts/bench_runtime.py --duration 20 --backends c,numpy --rt both
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import tempfile
from pathlib import Path

import numpy as np


def run_one(backend: str, rt_priority: int | None, args, tmp: Path) -> dict:
    from proprio_env.runtime.cli import start_virtual_servo
    from proprio_env.runtime.loop import Runtime
    from proprio_env.runtime.sinks import CsvLog, LslSink
    from proprio_env.runtime.sources import DynamixelSource

    tag = f"{backend}-{rt_priority}"
    tty_priority = args.tty_worker_priority or None
    link = str(tmp / f"ax12-{tag}")
    child = start_virtual_servo(link, args.track, [], rt_priority,
                                extra=("--return-delay", str(args.return_delay)))
    load_before = os.getloadavg()
    try:
        source = DynamixelSource(link, latency_timer_ms=args.latency_timer_ms)
        runtime = Runtime(source, rate_hz=args.rate, backend=backend,
                          sinks=[LslSink(f"bench-{os.getpid()}-{tag}")],
                          log=CsvLog(tmp / f"log-{tag}.csv"), duration_s=args.duration,
                          rt_priority=rt_priority,
                          tty_worker_priority=tty_priority if rt_priority else None)
        summary = runtime.run()
    finally:
        child.terminate()
        child.wait(10)
    with open(tmp / f"log-{tag}.csv", newline="") as f:
        log = list(csv.DictReader(f))
    read_s = np.array([float(r["read_s"]) for r in log])
    summary["read_ms"] = np.percentile(read_s * 1e3, [50, 99]).tolist()
    summary["read_s"] = read_s
    summary["latency_s"] = np.array([float(r["latency_s"]) for r in log if r["latency_s"]])
    summary["load_before"] = load_before
    summary["rt"] = rt_priority
    return summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds per setting")
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--backends", default="c", help="comma list of numpy, c")
    ap.add_argument("--rt", choices=("off", "on", "both"), default="both",
                    help="SCHED_FIFO priority 50 for the runtime and the servo (needs root)")
    ap.add_argument("--return-delay", type=int, default=0,
                    help="the virtual servo's return delay register (2 us units)")
    ap.add_argument("--tty-worker-priority", type=int, default=49,
                    help="with --rt on: the kernel's tty workers under SCHED_FIFO at this "
                         "priority (0: left alone)")
    ap.add_argument("--latency-timer-ms", type=float, default=1.0)
    ap.add_argument("--track", default="elbow", choices=("scripted", "elbow"))
    ap.add_argument("--figure", default=None, help="PNG of the latency and read-time tails")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_runtime_"))
    from proprio_env.runtime.sinks import write_loopback_lsl_config

    os.environ["LSLAPICFG"] = str(write_loopback_lsl_config(tmp / "lsl_api.cfg"))
    rts = {"off": [None], "on": [50], "both": [None, 50]}[args.rt]
    rows = [run_one(b, rt, args, tmp) for b in args.backends.split(",") for rt in rts]
    print(f"bench_runtime: {args.duration:g} s per setting at {args.rate:g} Hz, virtual AX-12 "
          f"on a pty (return delay {2 * args.return_delay} us), LSL + CSV log, "
          f"{os.cpu_count()} CPUs")
    head = ("backend", "SCHED_FIFO", "tty workers", "ticks", "read", "p50 ms", "p99 ms", "max ms",
            "read p50/p99 ms", "misses", "skipped", "timeouts", "stale", "load avg 1 min")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for s in rows:
        c, lat = s["counters"], s["latency"]
        cells = (s["backend"], "50" if s["rt"] else "off",
                 str(s["tty_worker_priority"] or "off"),
                 str(c["readings"] + c["skipped_ticks"]), str(c["readings"]),
                 f"{lat['p50_ms']:.3f}", f"{lat['p99_ms']:.3f}", f"{lat['max_ms']:.3f}",
                 f"{s['read_ms'][0]:.2f}/{s['read_ms'][1]:.2f}", str(c["deadline_misses"]),
                 str(c["skipped_ticks"]), str(c["timeout"]), str(c["stale_replies"]),
                 f"{s['load_before'][0]:.2f} -> {s['load_average'][0]:.2f}")
        print("| " + " | ".join(cells) + " |")
    if args.figure:
        plot(rows, args, Path(args.figure))
    return 0


def plot(rows: list[dict], args, path: Path) -> None:
    """Survival curves (fraction of samples above a time) of the latency and the read time,
    against the sample period."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, key, title in zip(axes, ("latency_s", "read_s"),
                              ("latency: reading's arrival -> outputs published",
                               "read: request sent -> reply arrived"), strict=True):
        for s in rows:
            x = np.sort(s[key]) * 1e3
            frac = 1.0 - np.arange(x.size) / x.size
            ax.step(x, frac, where="post",
                    label=f"{s['backend']}, SCHED_FIFO {'50' if s['rt'] else 'off'}")
        ax.axvline(1e3 / args.rate, color="k", lw=0.8, ls="--", label="sample period")
        ax.set(xscale="log", yscale="log", xlabel="ms", title=title)
        ax.grid(True, which="both", lw=0.3)
    axes[0].set_ylabel("fraction of samples above")
    axes[0].legend(fontsize=8)
    load = ", ".join(f"{s['load_average'][0]:.1f}" for s in rows)
    fig.suptitle(f"runtime vs virtual AX-12, {args.rate:g} Hz, {args.duration:g} s each; "
                 f"2-core machine, load average {load}", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    sys.exit(main())
