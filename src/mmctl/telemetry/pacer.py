"""Keep the publisher's interpreter work in the control loop's idle time.

Python runs one thread at a time (the GIL).  A publisher thread that holds the
interpreter when the loop thread wakes up delays the loop by up to the switch interval
(``loop.switch_interval``), and one that asks for it in the middle of a cycle body cuts
the body in two.  The loop records every finished cycle in its
:class:`~mmctl.runtime.timing.TimingRing` (deadline, wake latency, compute time, slack),
so the newest record says when the last body ended and when the next deadline is::

      deadline      wake   body ends (recorded)            next wake - guard
    --|-------------|========|------------ idle -------------|---spin---|-- next deadline

:meth:`LoopPacer.wait` returns at once when the newest recorded cycle is the current
period's and a step of ``step_ns`` still fits before the loop's next wake-up; otherwise
it sleeps (no GIL held) until the next body is expected to end, then polls the ring
until that cycle is recorded.  The publisher calls it between its steps (batching,
encoding, each ``send_chunks``), so its work follows the loop's real progress instead
of a statistical guess: a long cycle simply makes it wait longer.  It never waits for
more than ``max_wait_ns`` in one call (a stopped loop does not stall the publisher).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol


class _Ring(Protocol):
    """What the pacer reads of :class:`~mmctl.runtime.timing.TimingRing`."""

    @property
    def count(self) -> int: ...

    def last(self) -> tuple[int, int, int, int, int] | None: ...


class LoopPacer:
    """Idle-time scheduling from the loop's timing ring (all times perf_counter [ns]).

    ring: the loop's timing ring; period_ns: the loop period; spin_margin_ns: the loop wakes this long before a
    deadline and spins; guard_ns: extra margin before that wake-up; step_ns: the longest
    step the caller runs between two ``wait`` calls; poll_ns: re-check interval while a
    body runs; max_wait_ns: the most one ``wait`` holds back; clock/sleep: injectable.
    """

    def __init__(self, ring: _Ring, period_ns: int, spin_margin_ns: int, guard_ns: int = 150_000,
                 step_ns: int = 350_000, poll_ns: int = 100_000, max_wait_ns: int = 20_000_000,
                 clock: Callable[[], int] = time.perf_counter_ns,
                 sleep: Callable[[float], None] = time.sleep):
        self.ring = ring
        self.period = int(period_ns)
        self.spin = int(spin_margin_ns)
        self.guard = int(guard_ns)
        self.step = int(step_ns)
        self.poll = int(poll_ns)
        self.max_wait = int(max_wait_ns)
        self.clock = clock
        self.sleep = sleep
        self.body_ns = 0  #: expected wake latency + body time (set by :meth:`update`) [ns]
        self.waits = 0  #: wait() calls that had to sleep
        self.gave_up = 0  #: wait() calls that hit max_wait_ns

    def update(self, body_ns: int) -> None:
        """A typical wake latency + body time [ns] (e.g. the recent median)."""
        self.body_ns = max(0, int(body_ns))

    def wait(self) -> None:
        """Return when a step of ``step_ns`` fits into the loop's current idle time."""
        start = self.clock()
        slept = False
        while True:
            last = self.ring.last()
            if last is None:
                return  # the loop has not run a cycle yet
            deadline, _latency, _compute, _slack, missed = last
            next_deadline = deadline + self.period * (1 + missed)
            now = self.clock()
            if now - start >= self.max_wait or now > next_deadline + 2 * self.period:
                if now - start >= self.max_wait:
                    self.gave_up += 1
                return  # a stopped or stalled loop: do not hold the publisher back
            wake = next_deadline - self.spin
            if now < wake - self.guard - self.step:
                if slept:
                    self.waits += 1
                return  # the newest record is this period's: idle, and the step fits
            slept = True
            if now < next_deadline + self.body_ns:
                delay = next_deadline + self.body_ns - now  # until the next body should end
            else:
                delay = self.poll  # it runs late: look again soon
            self.sleep(max(delay, self.poll // 4) * 1e-9)
