"""Keep the publisher's interpreter work in the control loop's idle time.

Python runs one thread at a time (the GIL).  A publisher thread that holds the
interpreter when the loop thread wakes up delays the loop by up to the switch interval
(``loop.switch_interval``, 0.5 ms), and one that asks for it in the middle of a long
cycle body cuts the body in two.  The loop's deadlines lie on a fixed grid
(``deadline = first + k * period``; overruns skip whole periods), so the idle part of
every period is known in advance::

      deadline            busy (wake latency + body, p99)         next wake - guard
    --|-----------------------|================ idle =================|---spin---|--


:meth:`LoopPacer.wait` returns at once when a step of ``step_ns`` fits in the idle part
of the current period and otherwise sleeps (no GIL held) until the next idle part
starts.  The publisher calls it between its steps (batching, encoding, each
``send_chunks``), so it never holds the interpreter across the loop's wake-up.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class LoopPacer:
    """Idle-time scheduling on the loop's deadline grid (all times perf_counter [ns]).

    period_ns: loop period; spin_margin_ns: the loop wakes this long before a deadline
    and spins; guard_ns: extra margin on both sides of the busy part; step_ns: the longest
    step the caller runs between two ``wait`` calls; clock/sleep: injectable for tests.
    Until :meth:`update` has seen the loop, ``wait`` returns at once.
    """

    def __init__(self, period_ns: int, spin_margin_ns: int, guard_ns: int = 150_000,
                 step_ns: int = 350_000, clock: Callable[[], int] = time.perf_counter_ns,
                 sleep: Callable[[float], None] = time.sleep):
        self.period = int(period_ns)
        self.spin = int(spin_margin_ns)
        self.guard = int(guard_ns)
        self.step = int(step_ns)
        self.clock = clock
        self.sleep = sleep
        self.anchor: int | None = None  #: a deadline on the loop's grid [ns]
        self.busy = self.period // 4  #: wake latency + body time after a deadline [ns]
        self.waits = 0  #: wait() calls that had to sleep

    def update(self, last_deadline_ns: int, busy_ns: int) -> None:
        """New grid anchor (the newest recorded deadline) and busy-time estimate [ns]."""
        self.anchor = int(last_deadline_ns)
        self.busy = max(0, int(busy_ns))

    def window(self) -> tuple[int, int]:
        """(start, end) of the idle part, as offsets after a deadline [ns]; start may be
        >= end when the loop leaves no room (then ``wait`` does not hold anything back)."""
        return self.busy + self.guard, self.period - self.spin - self.guard

    def wait(self) -> None:
        """Return when a step of ``step_ns`` fits before the loop's next wake-up."""
        if self.anchor is None:
            return
        start, end = self.window()
        if end - start < self.step:
            return  # no idle part long enough: pacing would only stall the publisher
        phase = (self.clock() - self.anchor) % self.period
        if start <= phase <= end - self.step:
            return
        delay = start - phase if phase < start else self.period - phase + start
        self.waits += 1
        self.sleep(delay * 1e-9)
