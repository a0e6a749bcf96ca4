"""The fixed-period loop thread.

Deadlines are absolute (``deadline += period`` on ``time.perf_counter_ns``), never reset
from "now".  Each wait sleeps until ``spin_margin`` before the deadline and then spins,
which trades a little CPU for a wake-up latency well below the OS sleep granularity.

Overrun policy: when a cycle body ends after the next deadline, the deadlines that
already passed are *skipped* (not run late back to back), the skip is counted, and
once ``max_consecutive_misses`` cycles in a row or ``max_total_misses`` deadlines in
all have been missed, the next :class:`Tick` carries ``overrun=True`` so the body can
fault.  Timings of every cycle go to a :class:`~mmctl.runtime.timing.TimingRing`.

An exception escaping the body stops the loop; it is stored in :attr:`CycleLoop.error`
and re-raised by :meth:`CycleLoop.join`.

The wait is a strategy given once at construction (:class:`Wait`; default
:class:`SpinWait`): the loop calls it and nothing else per cycle.  ``mmctl bench loop``
gives its own, which alternates between this wait and a plain ``time.sleep``
(:class:`PlainSleep`) to interleave windows of both on one running loop.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple, Protocol

import structlog

from mmctl.errors import again
from mmctl.runtime.timing import TimingRing

log = structlog.get_logger("mmctl.loop")


class Tick(NamedTuple):
    """What the loop tells the body at the start of a cycle.

    index: cycle counter (0, 1, ...); deadline_ns: the absolute deadline this cycle
    was due at [ns, perf_counter]; wake_ns: when it actually started [ns];
    period_ns: the nominal period [ns]; consecutive_misses: cycles in a row that
    overran; total_misses: deadlines skipped since the last :meth:`CycleLoop.reset_misses`;
    overrun: the miss budget is exhausted (the body should fault).
    """

    index: int  # type: ignore[assignment]  # shadows tuple.index; kept: callers use it
    deadline_ns: int
    wake_ns: int
    period_ns: int
    consecutive_misses: int
    total_misses: int
    overrun: bool

    @property
    def period(self) -> float:
        """The nominal period [s]."""
        return self.period_ns * 1e-9


Body = Callable[[Tick], None]


_PR_SET_TIMERSLACK = 29
DEFAULT_TIMER_SLACK_NS = 50_000
"""Linux's timer slack for a normal thread [ns] (what a plain sleep loop gets)."""
LOOP_TIMER_SLACK_NS = 1_000
"""The loop thread's timer slack [ns]."""


def set_timer_slack(ns: int) -> bool:
    """Linux: let the calling thread's sleeps overshoot by at most ``ns`` [ns] (the
    default slack of 50 us is added to every wake-up of a non-real-time thread)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(_PR_SET_TIMERSLACK, ctypes.c_ulong(ns), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def apply_realtime(rt_priority: int, cpu_affinity: Sequence[int],
                   timer_slack: bool = True) -> list[str]:
    """Best effort: SCHED_FIFO priority, CPU affinity and (``timer_slack``) a 1 us timer
    slack for the *calling* thread.

    Returns the list of what could not be applied (each also logged as a warning).
    """
    problems: list[str] = []
    if timer_slack:
        set_timer_slack(LOOP_TIMER_SLACK_NS)
    if cpu_affinity:
        try:
            os.sched_setaffinity(0, set(cpu_affinity))
        except (OSError, AttributeError, ValueError) as exc:
            problems.append("cpu_affinity")
            log.warning("loop_affinity_not_applied", cpus=list(cpu_affinity), error=str(exc))
    if rt_priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
        except (OSError, AttributeError) as exc:
            problems.append("rt_priority")
            log.warning("loop_rt_priority_not_applied", priority=rt_priority, error=str(exc),
                        hint="grant CAP_SYS_NICE / LimitRTPRIO (see systemd/mmctl.service)")
    return problems


class Wait(Protocol):
    """Waits until ``deadline`` (``perf_counter_ns``) on the loop thread; returns the
    wake time [ns]."""

    def __call__(self, deadline: int) -> int: ...


class SpinWait:
    """Sleep until ``spin_margin_ns`` before the deadline, then spin (1 us timer slack,
    set by :func:`apply_realtime` on the loop thread)."""

    def __init__(self, spin_margin_ns: int):
        self.spin_margin_ns = spin_margin_ns

    def __call__(self, deadline: int) -> int:
        clock = time.perf_counter_ns
        remaining = deadline - clock() - self.spin_margin_ns
        if remaining > 0:
            time.sleep(remaining * 1e-9)
        now = clock()
        while now < deadline:
            now = clock()
        return now


class PlainSleep:
    """One ``time.sleep`` to the deadline, no spin (what a plain Python loop does; the
    caller sets the timer slack it wants)."""

    def __call__(self, deadline: int) -> int:
        clock = time.perf_counter_ns
        remaining = deadline - clock()
        if remaining > 0:
            time.sleep(remaining * 1e-9)
        return clock()


class GcInSlack:
    """Python's garbage collector run in the loop's slack instead of in whichever
    allocation crosses a threshold (the cycle's among them).

    While the loop runs, automatic collection is off; after a cycle, when ``every``
    cycles have passed and at least ``margin_ns`` are left before the next deadline,
    the young generation is collected (every second: the middle one too; every minute:
    all three).  Anything a collection would take from the next cycle waits for a
    cycle with slack.  ``collections`` counts them per generation, ``worst_ns`` is the
    longest.  :meth:`stop` turns automatic collection back on.
    """

    def __init__(self, every: int, margin_ns: int, rate_hz: float):
        self.every = max(1, int(every))
        self.margin_ns = int(margin_ns)
        self.per_second = max(1, round(rate_hz / self.every))
        self.per_minute = 60 * self.per_second
        self.collections = [0, 0, 0]
        self.worst_ns = 0
        self._since = 0
        self._n = 0
        self._was_enabled = True

    def start(self) -> None:
        import gc

        self._was_enabled = gc.isenabled()
        gc.disable()

    def stop(self) -> None:
        import gc

        if self._was_enabled:
            gc.enable()

    def after_cycle(self, next_deadline_ns: int) -> None:
        self._since += 1
        if self._since < self.every:
            return
        t0 = time.perf_counter_ns()
        if next_deadline_ns - t0 < self.margin_ns:
            return  # no slack this cycle: the next one
        import gc

        self._n += 1
        gen = 2 if self._n % self.per_minute == 0 else 1 if self._n % self.per_second == 0 else 0
        gc.collect(gen)
        self.collections[gen] += 1
        self.worst_ns = max(self.worst_ns, time.perf_counter_ns() - t0)
        self._since = 0


class CycleLoop:
    """Runs ``body(tick)`` every period on its own thread.

    rate_hz: cycle rate [Hz]; spin_margin: busy-wait window before each deadline [s];
    max_consecutive_misses / max_total_misses: overrun budget (see module doc);
    ring: where per-cycle timings go (a new one if None); rt_priority: SCHED_FIFO
    priority, 0 = leave the scheduler alone; cpu_affinity: CPUs for the thread; wait:
    how to wait for each deadline (default :class:`SpinWait` of ``spin_margin``).
    """

    def __init__(
        self,
        body: Body,
        rate_hz: float = 500.0,
        spin_margin: float = 0.0001,
        max_consecutive_misses: int = 5,
        max_total_misses: int = 1000,
        ring: TimingRing | None = None,
        rt_priority: int = 0,
        cpu_affinity: Sequence[int] = (),
        name: str = "mmctl-loop",
        wait: Wait | None = None,
        gc_slack: GcInSlack | None = None,
    ):
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz}")
        self._body = body
        self.period_ns = round(1e9 / rate_hz)
        self.spin_margin_ns = int(spin_margin * 1e9)
        self.max_consecutive = max_consecutive_misses
        self.max_total = max_total_misses
        self.ring = ring if ring is not None else TimingRing()
        self.rt_priority = rt_priority
        self.cpu_affinity = tuple(cpu_affinity)
        self.name = name
        self.error: BaseException | None = None
        #: the garbage collector's schedule in the cycles' slack (None: Python's own)
        self.gc_slack = gc_slack
        self._stop = threading.Event()
        self._done = threading.Event()
        self._thread: threading.Thread | None = None
        self._reset_requested = False
        self.wait_for_deadline: Wait = wait if wait is not None else SpinWait(
            self.spin_margin_ns)
        self.consecutive_misses = 0
        self.total_misses = 0
        #: deadlines missed since the loop started (never reset: the figure status
        #: shows; ``total_misses`` is the overrun budget's, reset on enable)
        self.missed_since_start = 0
        self.cycles = 0

    # -- lifecycle -----------------------------------------------------------------
    def start(self) -> None:
        """Start the loop thread (once)."""
        if self._thread is not None:
            raise RuntimeError("loop already started")
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Ask the loop to end after the current cycle (safe from any thread, twice)."""
        self._stop.set()

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the loop thread has ended (True; also when it never started)."""
        if self._thread is None:
            return True
        return self._done.wait(timeout)

    def join(self, timeout: float | None = None) -> None:
        """Stop, wait for the thread, and re-raise an exception the body raised."""
        self.stop()
        if self._thread is not None:
            self._thread.join(timeout)
        if self.error is not None:
            raise again(self.error)

    def reset_misses(self) -> None:
        """Zero the miss counters at the start of the next cycle (e.g. on enable)."""
        self._reset_requested = True

    # -- the thread ----------------------------------------------------------------
    def _run(self) -> None:
        apply_realtime(self.rt_priority, self.cpu_affinity)
        clock = time.perf_counter_ns
        period = self.period_ns
        ring = self.ring
        body = self._body
        wait = self.wait_for_deadline
        gc_slack = self.gc_slack
        if gc_slack is not None:
            gc_slack.start()
        deadline = clock() + period
        try:
            while not self._stop.is_set():
                wake = wait(deadline)
                if self._reset_requested:
                    self._reset_requested = False
                    self.consecutive_misses = 0
                    self.total_misses = 0
                overrun = (self.consecutive_misses >= self.max_consecutive
                           or self.total_misses >= self.max_total)
                body(Tick(self.cycles, deadline, wake, period, self.consecutive_misses,
                          self.total_misses, overrun))
                end = clock()
                this_deadline = deadline
                deadline += period
                missed = 0
                if end > deadline:
                    missed = (end - deadline) // period + 1
                    deadline += missed * period
                    self.consecutive_misses += 1
                    self.total_misses += missed
                    self.missed_since_start += missed
                else:
                    self.consecutive_misses = 0
                ring.record(this_deadline, wake - this_deadline, end - wake,
                            deadline - missed * period - end, missed)
                self.cycles += 1
                if gc_slack is not None:
                    gc_slack.after_cycle(deadline)
        except BaseException as exc:  # noqa: BLE001 -- stored, re-raised by join()
            self.error = exc
            log.error("loop_crashed", error=repr(exc), cycle=self.cycles)
        finally:
            if gc_slack is not None:
                gc_slack.stop()
            self._done.set()
