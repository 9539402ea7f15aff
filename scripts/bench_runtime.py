"""Real-time figures of the runtime against the virtual AX-12 (docs/runtime.md).

For each setting, side by side in one run: a virtual servo (a child process on a pty), the
runtime reading it through dynamixel_sdk at 500 Hz with the LSL outlets (loopback-only
config) and the CSV log, for --duration seconds. Prints per setting the latency from a
reading's arrival to the outputs published (p50, p99, max), the read time, the deadline
misses and the machine's load average.

Beside each run a *witness* on each CPU (a child process pinned there, doing nothing but
wake every 1 ms, under SCHED_FIFO 99 when the run is real-time) records how late each of
its wakes was. A witness wake late by a millisecond or more is a stall of that CPU itself
(the kernel or the hypervisor did not run even the highest-priority task there); the table
counts the deadline misses whose sample's period overlapped such a stall (``with a
stall``). The miss count itself is unchanged: every sample published after its period is a
miss.

    PYTHONPATH=. python scripts/bench_runtime.py                     # 60 s, C backend
    PYTHONPATH=. python scripts/bench_runtime.py --duration 20 --backends c,numpy --rt both
"""

from __future__ import annotations

import argparse
import csv
import gc
import os
import subprocess
import sys
import tempfile
import time
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
    cpus = sorted(os.sched_getaffinity(0))
    witnesses = [subprocess.Popen([sys.executable, __file__, "--witness",
                                   str(tmp / f"witness-{tag}-{cpu}.npy"), "--witness-cpu",
                                   str(cpu), "--witness-priority", str(99 if rt_priority else 0),
                                   "--duration", str(args.duration + 2)]) for cpu in cpus]
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
        for witness in witnesses:
            witness.wait(args.duration + 30)
    with open(tmp / f"log-{tag}.csv", newline="") as f:
        log = list(csv.DictReader(f))
    summary["stalls"] = np.concatenate([np.load(tmp / f"witness-{tag}-{cpu}.npy")
                                        for cpu in cpus])
    summary["t0"] = runtime.t0
    summary["misses_in_stall"] = misses_in_stalls(log, runtime.t0, runtime.period_s,
                                                  summary["stalls"])
    read_s = np.array([float(r["read_s"]) for r in log])
    summary["read_ms"] = np.percentile(read_s * 1e3, [50, 99]).tolist()
    summary["read_s"] = read_s
    summary["latency_s"] = np.array([float(r["latency_s"]) for r in log if r["latency_s"]])
    summary["load_before"] = load_before
    summary["rt"] = rt_priority
    return summary


STALL_S = 1e-3
"""A witness wake this late is a stall of the machine (its p99.9 is ~0.5 ms otherwise)."""


def run_witness(out: Path, cpu: int, priority: int, duration_s: float) -> None:
    """Wake every 1 ms for ``duration_s`` on ``cpu``; save each wake's (due, lateness) in s."""
    gc.disable()
    os.sched_setaffinity(0, {cpu})
    if priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    n = int(duration_s * 1000)
    due = time.perf_counter() + (np.arange(n) + 1) * 1e-3
    late = np.empty(n)
    for k in range(n):
        left = due[k] - time.perf_counter()
        if left > 0:
            time.sleep(left)
        late[k] = time.perf_counter() - due[k]
    np.save(out, np.stack((due, late), axis=1))


def misses_in_stalls(log: list[dict], t0: float, period_s: float,
                     witness: np.ndarray) -> int:
    """Deadline misses (late samples and skipped ticks) during which the witness was held
    off by a stall of at least :data:`STALL_S`: a late sample and the ticks skipped after
    it count when the stall overlaps the time from its due time to the next sample's."""
    stalls = witness[witness[:, 1] >= STALL_S]
    begin, end = stalls[:, 0], stalls[:, 0] + stalls[:, 1]
    count = 0
    for row, nxt in zip(log, [*log[1:], None], strict=True):
        k = int(row["index"])
        skipped_after = int(nxt["skipped_before"]) if nxt is not None else 0
        misses = int(row["deadline_missed"] == "1") + skipped_after
        if misses == 0:
            continue
        a, b = t0 + k * period_s, t0 + (k + 1 + skipped_after) * period_s
        if np.any((begin < b) & (end > a)):
            count += misses
    return count


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
    ap.add_argument("--witness", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--witness-priority", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--witness-cpu", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.witness:
        run_witness(Path(args.witness), args.witness_cpu, args.witness_priority,
                    args.duration)
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="bench_runtime_"))
    from proprio_env.runtime.sinks import write_loopback_lsl_config

    os.environ["LSLAPICFG"] = str(write_loopback_lsl_config(tmp / "lsl_api.cfg"))
    rts = {"off": [None], "on": [50], "both": [None, 50]}[args.rt]
    rows = [run_one(b, rt, args, tmp) for b in args.backends.split(",") for rt in rts]
    print(f"bench_runtime: {args.duration:g} s per setting at {args.rate:g} Hz, virtual AX-12 "
          f"on a pty (return delay {2 * args.return_delay} us), LSL + CSV log, "
          f"{os.cpu_count()} CPUs")
    head = ("backend", "SCHED_FIFO", "tty workers", "ticks", "read", "p50 ms", "p99 ms", "max ms",
            "read p50/p99 ms", "misses", "with a stall", "skipped", "timeouts", "stale",
            "witness stalls", "load avg 1 min")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for s in rows:
        c, lat = s["counters"], s["latency"]
        cells = (s["backend"], "50" if s["rt"] else "off",
                 str(s["tty_worker_priority"] or "off"),
                 str(c["readings"] + c["skipped_ticks"]), str(c["readings"]),
                 f"{lat['p50_ms']:.3f}", f"{lat['p99_ms']:.3f}", f"{lat['max_ms']:.3f}",
                 f"{s['read_ms'][0]:.2f}/{s['read_ms'][1]:.2f}", str(c["deadline_misses"]),
                 str(s["misses_in_stall"]), str(c["skipped_ticks"]), str(c["timeout"]),
                 str(c["stale_replies"]), stall_cell(s["stalls"]),
                 f"{s['load_before'][0]:.2f} -> {s['load_average'][0]:.2f}")
        print("| " + " | ".join(cells) + " |")
    if args.figure:
        plot(rows, args, Path(args.figure))
    return 0


def stall_cell(witness: np.ndarray) -> str:
    """How many witness wakes (all CPUs) were a stall, and the longest (ms)."""
    late = witness[:, 1]
    return f"{int(np.sum(late >= STALL_S))} (max {late.max() * 1e3:.1f})"


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
