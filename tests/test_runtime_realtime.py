"""The runtime's real-time levers, checked against the kernel's own account: the tty workers
it boosts are the threads that carry a pty's bytes (their run counts in /proc), they run
under SCHED_FIFO meanwhile and get their policy back; a refused boost is a clear error that
leaves nothing changed; the log's writer thread reports a failed write; the virtual servo
serves without the garbage collector; the bench's stall attribution on a made-up run."""

from __future__ import annotations

import gc
import importlib.util
import os
import resource
import select
import subprocess
import sys
import threading
import tty
from pathlib import Path

import numpy as np
import pytest

from proprio_env.runtime.realtime import TtyWorkers, _is_unbound_worker

ROOT = Path(__file__).resolve().parents[1]
needs_root = pytest.mark.skipif(os.geteuid() != 0, reason="changing kernel threads needs root")


def _run_counts(tids) -> int:
    """Times these threads were scheduled in (the third field of /proc/<tid>/schedstat)."""
    total = 0
    for tid in tids:
        try:
            with open(f"/proc/{tid}/schedstat") as f:
                total += int(f.read().split()[2])
        except OSError:
            pass
    return total


@needs_root
def test_the_boosted_workers_carry_pty_bytes_under_fifo_and_get_their_policy_back():
    workers = TtyWorkers(3)
    assert workers.boost() >= 1
    tids = list(workers.previous)
    before = dict(workers.previous)
    try:
        for tid in tids:
            if _is_unbound_worker(str(tid)):
                assert os.sched_getscheduler(tid) == os.SCHED_FIFO
                assert os.sched_getparam(tid).sched_priority == 3
        master, slave = os.openpty()
        tty.setraw(slave)
        runs = _run_counts(tids)
        n = 200
        for _ in range(n):  # each byte written to a pty is flushed to its reader by a worker
            os.write(master, b"x")
            select.select([slave], [], [], 1.0)
            os.read(slave, 16)
        # every transfer took a worker of this set (other work on them only adds runs;
        # measured: ~1.1 runs per transfer)
        assert _run_counts(tids) - runs >= n
        os.close(master)
        os.close(slave)
    finally:
        workers.restore()
    for tid, (policy, param) in before.items():
        if _is_unbound_worker(str(tid)):
            assert os.sched_getscheduler(tid) == policy
            assert os.sched_getparam(tid).sched_priority == param.sched_priority
    assert workers.previous == {}


@needs_root
def test_a_refused_boost_is_a_clear_error_and_changes_nothing():
    if resource.getrlimit(resource.RLIMIT_RTPRIO)[0] != 0:
        pytest.skip("RLIMIT_RTPRIO lets an ordinary user use SCHED_FIFO here")
    code = (
        "import os, sys\n"
        "from proprio_env.runtime.realtime import TtyWorkers, set_realtime\n"
        "os.setgid(65534); os.setuid(65534)  # imported first: root's packages\n"
        "w = TtyWorkers(3)\n"
        "try:\n    w.boost()\nexcept PermissionError as e:\n    print('tty:', e)\n"
        "print('left boosted:', len(w.previous))\n"
        "try:\n    set_realtime(50)\nexcept PermissionError as e:\n    print('loop:', e)\n"
        "print('policy:', os.sched_getscheduler(0))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "tty: SCHED_FIFO priority 3 refused for the kernel's tty workers" in out.stdout
    assert "left boosted: 0" in out.stdout
    assert "loop: SCHED_FIFO priority 50 refused for this process" in out.stdout
    assert f"policy: {os.SCHED_OTHER}" in out.stdout


def test_priorities_outside_1_to_99_are_refused():
    from proprio_env.runtime.loop import Runtime
    from proprio_env.runtime.sources import ReplaySource

    with pytest.raises(ValueError, match="tty_worker_priority=0"):
        TtyWorkers(0)
    with pytest.raises(ValueError, match="tty_worker_priority=True"):
        TtyWorkers(True)

    class Nothing(ReplaySource):
        def __init__(self):
            pass

    with pytest.raises(ValueError, match="tty_worker_priority=100"):
        Runtime(Nothing(), tty_worker_priority=100)


def test_a_log_write_that_fails_stops_the_run_with_the_error(tmp_path):
    """/dev/full refuses every write (ENOSPC): the writer thread's error reaches the loop."""
    from proprio_env.runtime.loop import Runtime
    from proprio_env.runtime.sinks import CsvLog
    from proprio_env.runtime.sources import ReplaySource

    replay = tmp_path / "in.csv"
    t = np.arange(300) * 2e-3
    replay.write_text("t_s,counts\n" + "".join(f"{float(x)!r},{500 + i % 7}\n"
                                               for i, x in enumerate(t)))
    runtime = Runtime(ReplaySource(replay), backend="numpy", rate_hz=5000,
                      log=CsvLog(Path("/dev/full"), flush_every=50))
    with pytest.raises(OSError, match="No space left"):
        runtime.run()


def test_the_virtual_servo_serves_without_the_garbage_collector(tmp_path):
    from proprio_env.runtime.motion import ServoTrack
    from proprio_env.runtime.virtual_servo import VirtualServo

    t = np.linspace(0.0, 1.0, 11)
    servo = VirtualServo(tmp_path / "ax12", ServoTrack(t, np.full(11, 60.0), np.zeros(11),
                                                        20.0, 1.0))
    assert gc.isenabled()
    th = threading.Thread(target=servo.serve, args=(0.3,), daemon=True)
    th.start()
    # Wait for serving to begin: the collection before it can take long on a loaded process
    # (CI once saw it not begin within 0.15 s), and the duration counts from then.
    assert servo.serving.wait(30)
    serving = gc.isenabled(), gc.get_freeze_count()
    th.join(30)
    assert not th.is_alive()
    assert serving[0] is False and serving[1] > 0
    assert gc.isenabled() and gc.get_freeze_count() == 0


def _bench():
    spec = importlib.util.spec_from_file_location("bench_runtime",
                                                  ROOT / "scripts" / "bench_runtime.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_misses_are_attributed_to_a_stall_only_when_it_overlaps_their_period():
    bench = _bench()
    period, t0 = 2e-3, 100.0
    log = [{"index": "0", "deadline_missed": "0", "skipped_before": "0"},
           {"index": "1", "deadline_missed": "1", "skipped_before": "0"},   # 1 miss + 2 skipped
           {"index": "4", "deadline_missed": "0", "skipped_before": "2"},
           {"index": "5", "deadline_missed": "1", "skipped_before": "0"},   # 1 miss, no stall
           {"index": "6", "deadline_missed": "0", "skipped_before": "0"}]
    # a 3 ms stall from t0 + 5 ms (inside ticks 1..3: 2-8 ms); a 0.9 ms one (not a stall)
    # inside tick 5 (10-12 ms)
    witness = np.array([[t0 + 5e-3, 3e-3], [t0 + 10.5e-3, 0.9e-3], [t0 + 1e-3, 1e-5]])
    assert bench.misses_in_stalls(log, t0, period, witness) == 3
    assert bench.misses_in_stalls(log, t0, period, witness[1:]) == 0
