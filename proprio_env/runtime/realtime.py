"""Scheduling the runtime's path through the kernel: the loop under ``SCHED_FIFO``, and the
kernel workers that carry a serial port's bytes.

Every byte a tty receives, a pseudo-terminal's (the virtual servo's) or a USB serial
adapter's (``ftdi_sio``, ``cdc_acm``), reaches its reader through a kernel worker:
``tty_flip_buffer_push`` queues the tty's flush on the kernel's unbound workqueue, and one of
its workers (``kworker/uN:M``) hands the bytes to the line discipline, which wakes the
reader. Those workers run under the normal scheduler (``SCHED_OTHER``, nice 0). On a busy
machine a woken worker waits for a CPU behind the other processes, up to the scheduler's
tick (4 ms at HZ = 250): measured against the virtual servo at load 2-3 on 2 cores, with the
runtime and the servo under ``SCHED_FIFO`` 50, the request's pty transit had p99 1.27 ms and
max 24 ms, the reply's p99.9 4.0 ms (182 deadline misses in 20 s). Under ``SCHED_FIFO`` the
worker runs as soon as a CPU has no higher real-time task (request transit p99 0.11 ms, 21
misses). :class:`TtyWorkers` does that, and puts them back as they were.

Real-time priority needs ``CAP_SYS_NICE`` (root). Refused: ``PermissionError`` naming what
was refused; nothing is left changed.
"""

from __future__ import annotations

import os
import time

KTHREADD_CHILDREN = "/proc/2/task/2/children"
"""Kernel threads are children of kthreadd (pid 2); this lists them in one read."""
UNBOUND_WORKER_PREFIX = "kworker/u"
"""The unbound workqueues' worker pools (``kworker/u<pool>:<id>``); ``kworker/R-...`` are
rescuers and ``kworker/<cpu>:...`` per-CPU workers, which tty flushes do not use."""
REFRESH_S = 1.0
"""How often :meth:`TtyWorkers.refresh` looks for workers the kernel started since."""


def check_priority(name: str, priority: int | None) -> None:
    """``ValueError`` unless ``priority`` is None or an integer in 1..99."""
    if priority is not None and not (isinstance(priority, int) and not isinstance(priority, bool)
                                     and 1 <= priority <= 99):
        raise ValueError(f"{name}={priority!r} must be an integer in 1..99 (or None)")


def set_realtime(priority: int | None) -> tuple | None:
    """Put this process under ``SCHED_FIFO`` at ``priority``; returns the previous
    (policy, param) to restore, or None when ``priority`` is None."""
    if priority is None:
        return None
    previous = (os.sched_getscheduler(0), os.sched_getparam(0))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except PermissionError as err:
        raise PermissionError(f"SCHED_FIFO priority {priority} refused for this process "
                              f"(needs root or CAP_SYS_NICE): {err}") from None
    return previous


def _is_unbound_worker(tid: str) -> bool:
    try:
        with open(f"/proc/{tid}/comm") as f:
            return f.read().startswith(UNBOUND_WORKER_PREFIX)
    except OSError:  # it exited meanwhile
        return False


class TtyWorkers:
    """The kernel's unbound workqueue workers (which carry every tty's received bytes) under
    ``SCHED_FIFO`` at ``priority`` while the runtime runs.

    :meth:`boost` changes the workers there now, :meth:`refresh` the ones the kernel started
    since (one read of a small proc file per :data:`REFRESH_S`, and the names of new kernel
    threads), :meth:`restore` puts every one back to the policy and priority it had. Other work on
    those workers (writeback, filesystem conversions) runs at that priority too meanwhile:
    keep ``priority`` below the loop's, and restore (the runtime does, in ``finally``).
    """

    def __init__(self, priority: int) -> None:
        check_priority("tty_worker_priority", priority)
        self.priority = priority
        self.previous: dict[int, tuple[int, os.sched_param]] = {}
        self._seen: set[str] = set()
        self._next_refresh = 0.0

    def boost(self) -> int:
        """Boost the workers there now; returns how many. ``PermissionError`` when refused
        (nothing is left boosted)."""
        try:
            self._boost_new(self._new_workers())
        except PermissionError as err:
            self.restore()
            raise PermissionError(f"SCHED_FIFO priority {self.priority} refused for the "
                                  f"kernel's tty workers (needs root or CAP_SYS_NICE): "
                                  f"{err}") from None
        self._next_refresh = time.monotonic() + REFRESH_S
        return len(self.previous)

    def refresh(self) -> None:
        """Boost workers the kernel started since the last look (at most once per
        :data:`REFRESH_S`; cheap when no thread came or went)."""
        now = time.monotonic()
        if now < self._next_refresh:
            return
        self._next_refresh = now + REFRESH_S
        try:
            self._boost_new(self._new_workers())
        except PermissionError:  # allowed at boost(), so not expected; the run goes on
            pass

    def _new_workers(self) -> list[int]:
        """Unbound workers among the kernel threads not looked at before."""
        try:
            with open(KTHREADD_CHILDREN) as f:
                children = set(f.read().split())
        except OSError:
            return []
        new, self._seen = children - self._seen, children
        return [int(tid) for tid in new if _is_unbound_worker(tid)]

    def _boost_new(self, tids: list[int]) -> None:
        for tid in tids:
            if tid in self.previous:
                continue
            try:
                before = (os.sched_getscheduler(tid), os.sched_getparam(tid))
                os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(self.priority))
            except ProcessLookupError:  # the worker exited meanwhile
                continue
            self.previous[tid] = before

    def restore(self) -> None:
        """Every boosted worker back to its policy and priority (those gone: skipped)."""
        for tid, (policy, param) in self.previous.items():
            if not _is_unbound_worker(str(tid)):  # gone (its id may be another's now)
                continue
            try:
                os.sched_setscheduler(tid, policy, param)
            except (ProcessLookupError, PermissionError):
                pass
        self.previous.clear()
