"""The telemetry publisher: drains the sample ring into a sink.

The loop thread calls :meth:`Publisher.put` (a bound :meth:`SampleRing.put
<mmctl.telemetry.ring.SampleRing.put>`: one row written into a preallocated ring;
never blocks, counts drops).  The publisher wakes ``scene_rate`` times a second, takes
every queued row and hands the sink

* the full-rate columns of every sample (trial-metric inputs),
* the loop timing each row carries for the cycle before it,
* the plot-rate columns (every ``plot_stride``-th cycle) and the drop counter,
* one 3-D scene frame (the newest sample) and the queued events,

in one batch.  It runs as a thread of the daemon (:meth:`Publisher.start`), paced into
the loop's idle time, or in a child process that maps the ring from a file
(:mod:`mmctl.telemetry.process_publisher`).  An exception in the
thread is logged, stored in :attr:`Publisher.error` and re-raised by
:meth:`Publisher.close`; the loop is never affected (the ring just fills up and counts
drops).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
import structlog

from mmctl.config.base import MecanumConfig
from mmctl.control.mecanum import wheel_matrix
from mmctl.errors import again
from mmctl.telemetry import layout
from mmctl.telemetry import ring as tr
from mmctl.telemetry.batch import Columns, full_rate, loop_timing, plot_rate, plot_stride
from mmctl.telemetry.events import Event
from mmctl.telemetry.pacer import LoopPacer
from mmctl.telemetry.queue import DropQueue
from mmctl.telemetry.ring import SampleRing
from mmctl.telemetry.sample import TelemetrySample
from mmctl.telemetry.scene import SceneFrame

log = structlog.get_logger("mmctl.telemetry")

#: events are rare (trial brackets, state changes); this bounds them anyway
EVENT_QUEUE_SIZE = 1024


#: rows a new binding limit must hold for before an event names it (50 ms at 500 Hz)
LIMIT_HOLD = 25


class Sink(Protocol):
    """Where batches go (:class:`~mmctl.telemetry.rerun_sink.RerunSink`, or a test fake)."""

    def open(self) -> None: ...
    def write(self, columns: list[Columns], scene: tuple[int, float, SceneFrame] | None = None,
              pace: Callable[[], None] | None = None) -> None: ...
    def write_event(self, event: Event) -> None: ...
    def close(self) -> None: ...


class Scene(Protocol):
    """Turns a sample into a 3-D frame (:class:`~mmctl.telemetry.scene.SceneBuilder`)."""

    def frame(self, s: TelemetrySample) -> SceneFrame: ...


class Publisher:
    """Sample ring + publisher (see the module docstring).

    sink: where batches go; loop_rate_hz: the control rate [Hz]; plot_rate_hz: rate of
    the plot-rate series [Hz]; scene_rate_hz: wake-ups per second, one 3-D frame each
    [Hz]; queue_size: rows the ring holds (when ``ring`` is None); ring: an existing
    ring (e.g. mapped from another process); timing: the loop's TimingRing (the rows'
    previous-cycle timing, and the pacer's clock), or None; scene: builds 3-D frames
    (None: no 3-D view); spin_margin_s: the loop's spin margin [s]; pace: keep the work
    in the loop's idle time (:mod:`~mmctl.telemetry.pacer`; needs ``timing``).
    """

    def __init__(self, sink: Sink, *, loop_rate_hz: float = 500.0, plot_rate_hz: float = 100.0,
                 scene_rate_hz: float = 15.0, queue_size: int = 4096,
                 ring: SampleRing | None = None, timing: Any = None,
                 scene: Scene | None = None, spin_margin_s: float = 0.0001, pace: bool = True,
                 mecanum: MecanumConfig | None = None):
        if scene_rate_hz <= 0 or plot_rate_hz <= 0 or loop_rate_hz <= 0:
            raise ValueError("rates must be > 0")
        self.sink = sink
        self.ring = ring if ring is not None else SampleRing(queue_size, timing=timing)
        self.events: DropQueue[Event] = DropQueue(EVENT_QUEUE_SIZE)
        self.put = self.ring.put  #: the loop's hot path: put(sample) -> bool, never blocks
        self.stride = plot_stride(loop_rate_hz, plot_rate_hz)
        self.wheels = wheel_matrix(mecanum if mecanum is not None else MecanumConfig())
        self.wake_period = 1.0 / scene_rate_hz
        self.period_ns = round(1e9 / loop_rate_hz)
        self.scene = scene
        self.error: BaseException | None = None
        self.published = 0  #: samples handed to the sink
        self.batches = 0
        self.flush_ns_max = 0  #: longest flush so far [ns]
        self.busy = BusyRing()
        """When this publisher ran its steps (between pacing points) [perf_counter ns]."""
        self.pacer = (LoopPacer(timing, self.period_ns, int(spin_margin_s * 1e9))
                      if pace and timing is not None else None)
        self._busy = np.zeros(0)
        self._state: tuple[float, float] | None = None
        self._limit = 0.0  # the limit code last reported (0: none)
        #: the current run of one limit code: code, rows, its first row's cycle and time
        self._limit_run: tuple[float, int, int, float] = (0.0, 0, 0, 0.0)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._progress = threading.Condition()
        self._closed = False

    # -- lifecycle ------------------------------------------------------------------
    def start(self) -> None:
        """Open the sink (in the caller: errors surface here) and start the thread."""
        if self._thread is not None:
            raise RuntimeError("publisher already started")
        self.sink.open()
        self._thread = threading.Thread(target=self._run, name="mmctl-telemetry", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 30.0) -> None:
        """Stop the thread after a last flush, close the sink, re-raise a thread error.

        Idempotent.
        """
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        try:
            self.sink.close()
        finally:
            if self.error is not None:
                raise again(self.error)

    def __enter__(self) -> Publisher:  # noqa: PYI034
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- producer side (any thread, never blocks) ------------------------------------------
    def post_event(self, event: Event) -> bool:
        """Queue an event for the next flush; False if the event queue was full."""
        return self.events.put(event)

    def stats(self) -> dict[str, Any]:
        """Counters for ``status``: accepted, dropped, published, batches, longest flush."""
        return {
            "accepted": self.ring.accepted,
            "dropped": self.ring.dropped,
            "queued": len(self.ring),
            "published": self.published,
            "batches": self.batches,
            "flush_max_us": round(self.flush_ns_max / 1e3, 1),
            "events_dropped": self.events.dropped,
            "error": repr(self.error) if self.error is not None else None,
        }

    def wait_published(self, count: int, timeout: float) -> bool:
        """Block until at least ``count`` samples reached the sink (or the thread died)."""
        deadline = time.monotonic() + timeout
        with self._progress:
            while self.published < count and self.error is None:
                left = deadline - time.monotonic()
                if left <= 0 or (self._thread is not None and not self._thread.is_alive()):
                    return self.published >= count
                self._progress.wait(min(left, 0.5))
        return self.published >= count

    # -- the thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self.run()
        except BaseException as exc:  # noqa: BLE001 -- stored, logged, re-raised by close()
            self.error = exc
            log.error("telemetry_publisher_failed", error=repr(exc))
        finally:
            with self._progress:
                self._progress.notify_all()

    def run(self) -> None:
        """Flush ``scene_rate`` times a second until :meth:`close`; a last flush then."""
        next_wake = time.monotonic()
        while True:
            next_wake += self.wake_period
            stopping = self._stop.wait(max(0.0, next_wake - time.monotonic()))
            self.flush()
            if stopping:
                break
            if time.monotonic() > next_wake + self.wake_period:
                next_wake = time.monotonic()  # fell behind: do not burst to catch up

    def flush(self) -> None:
        """Drain the queues into the sink once (the thread's body; tests may call it)."""
        wait = self.pacer.wait if self.pacer is not None else _no_pace
        busy = self.busy

        def pace() -> None:  # a pacing point: the step before it ends, the next begins after
            busy.end()
            wait()
            busy.begin()

        wait()
        busy.begin()
        t0 = time.perf_counter_ns()
        rows = self.ring.take()
        n = len(rows)
        columns: list[Columns] = []
        scene = None
        if n:
            columns.append(full_rate(rows))
            pace()
            columns.append(plot_rate(rows, self.stride, self.wheels))
            pace()
            timing = loop_timing(rows, self.period_ns)
            if len(timing):
                columns.append(timing)
                self._update_pacer(rows)
            columns.append(Columns(columns[0].cycle[-1:].copy(), columns[0].time_ns[-1:].copy(),
                                   {layout.DROPPED.path: np.array([[float(self.ring.dropped)]])}))
            if self.scene is not None:
                pace()
                last = tr.sample_of(rows[-1])
                scene = (last.cycle, last.t, self.scene.frame(last))
        self.sink.write(columns, scene, pace)
        for event in self._state_changes(rows):
            self.sink.write_event(event)
        limit = self._limit_change(rows)
        if limit is not None:
            self.sink.write_event(limit)
        for event in self.events.drain():
            self.sink.write_event(event)
        self.batches += 1
        self.ring.mark_published(n)
        with self._progress:
            self.published += n
            self._progress.notify_all()
        self.flush_ns_max = max(self.flush_ns_max, time.perf_counter_ns() - t0)
        busy.end()

    def _update_pacer(self, rows: np.ndarray) -> None:
        """The pacer's expected wake latency + body time: p75 of the recent cycles."""
        if self.pacer is None:
            return
        body = rows[:, tr.PREV_LATENCY] + rows[:, tr.PREV_COMPUTE]
        busy = np.concatenate((self._busy, body[np.isfinite(body)]))[-1024:]
        self._busy = busy
        self.pacer.update(int(np.percentile(busy, 75)))

    def _state_changes(self, rows: np.ndarray) -> list[Event]:
        """Text events where the mode or the safety state changed."""
        n = len(rows)
        if n == 0:
            return []
        mode, safety = rows[:, tr.MODE], rows[:, tr.SAFETY]
        change = np.ones(n, bool)
        change[1:] = (mode[1:] != mode[:-1]) | (safety[1:] != safety[:-1])
        if self._state is not None:
            change[0] = (float(mode[0]), float(safety[0])) != self._state
        self._state = (float(mode[-1]), float(safety[-1]))
        out = []
        for i in np.flatnonzero(change):
            m, st = tr.label(tr.MODES, mode[i]), tr.label(tr.SAFETY_STATES, safety[i])
            out.append(Event(int(rows[i, tr.CYCLE]), float(rows[i, tr.T]),
                             f"mode={m} safety={st}", "ERROR" if st == "fault" else "INFO"))
        return out


    def _limit_change(self, rows: np.ndarray) -> Event | None:
        """A text event when the limit that binds the command changed and has held for
        :data:`LIMIT_HOLD` rows, across batches (the acceleration limit may bind every
        other cycle: no event per cycle); at most one per batch, at the run's first row."""
        codes = rows[:, tr.LIMIT]
        n = len(codes)
        if n == 0:
            return None
        last = float(codes[-1])
        differs = np.flatnonzero(codes != last)
        if len(differs) == 0 and last == self._limit_run[0]:
            self._limit_run = (last, self._limit_run[1] + n, self._limit_run[2], self._limit_run[3])
        else:
            first = int(differs[-1]) + 1 if len(differs) else 0
            self._limit_run = (last, n - first, int(rows[first, tr.CYCLE]), float(rows[first, tr.T]))
        code, length, cycle, t = self._limit_run
        if length < LIMIT_HOLD or code == self._limit:
            return None
        self._limit = code
        return Event(cycle, t, f"limit={tr.label(tr.LIMITS, code) or 'none'}")


class BusyRing:
    """The publisher thread's recent work intervals [perf_counter ns], preallocated; one
    writer (the publisher thread), readers copy (:meth:`intervals`)."""

    def __init__(self, size: int = 16384):
        self.size = size
        self._start = np.zeros(size, np.int64)
        self._end = np.zeros(size, np.int64)
        self._open = 0
        self.count = 0

    def begin(self) -> None:
        self._open = time.perf_counter_ns()

    def end(self) -> None:
        if self._open:
            i = self.count % self.size
            self._start[i] = self._open
            self._end[i] = time.perf_counter_ns()
            self._open = 0
            self.count += 1

    def intervals(self) -> tuple[np.ndarray, np.ndarray]:
        """(starts, ends) of the intervals the ring still holds, oldest first."""
        n = self.count
        k = min(n, self.size - 1)
        idx = np.arange(n - k, n) % self.size
        return self._start[idx].copy(), self._end[idx].copy()


def _no_pace() -> None:
    """Pacing off: run every step at once."""
