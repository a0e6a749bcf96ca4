"""Trial bracketing and the paper's metrics (eq. 14-16) for one bracketed execution.

``mmctl trial start`` / ``stop`` run :meth:`TrialTracker.start` / :meth:`TrialTracker.stop`
on the loop thread (the daemon's command queue), so a trial covers whole cycles:
from the first cycle after ``start`` to the last cycle before ``stop``, both included.
While a trial is active :meth:`TrialTracker.observe_row` appends three floats per cycle
(E_K, ‖f_h‖, ‖v‖; ~2 us); the means are computed off the loop thread by
:meth:`TrialTracker.finish`, with :func:`mmctl.control.metrics.trial_metrics`, the same
function ``mmctl metrics`` applies to a recording, on bit-identical inputs
(:func:`mmctl.telemetry.batch.norm3`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import structlog

from mmctl.control.metrics import TrialMetrics, trial_metrics
from mmctl.errors import MmctlError
from mmctl.telemetry import layout, ring
from mmctl.telemetry.batch import base_frame, norm3
from mmctl.telemetry.events import Event
from mmctl.telemetry.sample import TelemetrySample

log = structlog.get_logger("mmctl.trial")

BRACKET = f"{layout.TRIAL}/bracket"


class TrialError(MmctlError):
    """A trial command that does not fit the current state (already running, none active)."""


class TrialResult(NamedTuple):
    """One execution's metrics and where it lies in the cycle index.

    trial: 1, 2, ... since the daemon started; start_cycle/stop_cycle: first and last
    cycle included; samples: N; metrics: Ē [J], F̄_h [N], v̄ [m/s], x_f [m], T_f = N T [s];
    finished: False when the recording ended before ``trial stop``.
    """

    trial: int
    start_cycle: int
    stop_cycle: int
    samples: int
    metrics: TrialMetrics
    finished: bool = True

    def as_dict(self) -> dict[str, Any]:
        """The JSON form: keys ``E``, ``F_h``, ``v``, ``x_f``, ``T_f`` (SI) and the bracket."""
        m = self.metrics
        return {"trial": self.trial, "E": m.E_mean, "F_h": m.F_mean, "v": m.v_mean,
                "x_f": m.x_f, "T_f": m.T_f, "start_cycle": self.start_cycle,
                "stop_cycle": self.stop_cycle, "samples": self.samples,
                "finished": self.finished}


def compute(period: float, e_k: Any, f_norm: Any, v_norm: Any, p_final: Any,
            p_des: Any) -> TrialMetrics:
    """The paper's metrics from per-cycle E_K [J], ‖f_h‖ [N], ‖v‖ [m/s] and the final
    and preferred positions (3,) [m]; ``period`` T [s]."""
    return trial_metrics(period, e_k, f_norm, v_norm, p_final, p_des)


class TrialRows:
    """What a trial collected: per-cycle lists and the last row (loop thread)."""

    __slots__ = ("e", "f", "last", "start_cycle", "stop_cycle", "stop_t", "trial", "v")

    def __init__(self, trial: int):
        self.trial = trial
        self.start_cycle = -1
        self.stop_cycle = -1
        self.stop_t = 0.0
        self.e: list[float] = []
        self.f: list[float] = []
        self.v: list[float] = []
        #: the newest row, copied in place each cycle (its positions give x_f)
        self.last = np.full(ring.WIDTH, np.nan)


class TrialTracker:
    """Brackets trials; start/stop/observe run on the loop thread, finish anywhere.

    period: the control period T [s]; on_event: where start/stop events go (the
    publisher's ``post_event``), or None.
    """

    def __init__(self, period: float, on_event: Callable[[Event], Any] | None = None):
        self.period = period
        self.on_event = on_event
        self.count = 0
        self._rows: TrialRows | None = None
        self.results: list[TrialResult] = []

    @property
    def active(self) -> bool:
        return self._rows is not None

    def start(self) -> int:
        """Begin a trial at the next observed cycle; returns its number."""
        if self._rows is not None:
            raise TrialError(f"trial {self._rows.trial} is already running; "
                             "`mmctl trial stop` first")
        self.count += 1
        self._rows = TrialRows(self.count)
        return self.count

    def observe(self, s: TelemetrySample) -> None:
        """:meth:`observe_row` for a sample (tests and tools; the loop writes rows)."""
        if self._rows is not None:
            row = np.full(ring.WIDTH, np.nan)
            ring.encode(s, row)
            self.observe_row(row)

    def observe_row(self, row: Any) -> None:
        """Append one cycle from its telemetry row (:mod:`mmctl.telemetry.ring`; loop
        thread, ~2 us); a no-op when no trial is active.  The recording holds the same
        row, so metrics recomputed from it see the same floats."""
        rows = self._rows
        if rows is None:
            return
        cycle, t = int(row[ring.CYCLE]), float(row[ring.T])
        if rows.start_cycle < 0:
            rows.start_cycle = cycle
            if self.on_event is not None:
                self.on_event(Event(cycle, t, f"trial {rows.trial} start", entity=BRACKET,
                                    values={"trial": rows.trial, "start_cycle": cycle}))
        rows.e.append(float(row[ring.E_TOTAL]))
        rows.f.append(norm3(row[ring.F_H]))
        rows.v.append(norm3(row[ring.V]))
        rows.last[:] = row
        rows.stop_cycle = cycle
        rows.stop_t = t

    def stop(self) -> TrialRows:
        """End the active trial (loop thread, O(1)); pass the result to :meth:`finish`."""
        rows = self._rows
        if rows is None:
            raise TrialError("no trial is running; `mmctl trial start` first")
        self._rows = None
        return rows

    def finish(self, rows: TrialRows) -> TrialResult:
        """Compute the metrics (any thread), log them as one event, send them to the
        recording; raises :class:`TrialError` if the trial saw no cycle."""
        if not rows.e:
            raise TrialError(f"trial {rows.trial} saw no control cycle (is the loop running "
                             "and the robot connected?)")
        # the base frame, as the recording's positions (the same function: same bits)
        last = rows.last[None]
        m = compute(self.period, np.array(rows.e), np.array(rows.f), np.array(rows.v),
                    base_frame(last, ring.P)[0], base_frame(last, ring.P_DES)[0])
        result = TrialResult(rows.trial, rows.start_cycle, rows.stop_cycle, len(rows.e), m)
        self.results.append(result)
        d = result.as_dict()
        log.info("trial_metrics", **{k: v for k, v in d.items() if k != "finished"})
        if self.on_event is not None:
            text = (f"trial {rows.trial}: E={m.E_mean:.4g} J  F_h={m.F_mean:.4g} N  "
                    f"v={m.v_mean:.4g} m/s  x_f={m.x_f:.4g} m  T_f={m.T_f:.4g} s")
            values = {k: d[k] for k in (*layout.TRIAL_FIELDS, *layout.METRIC_KEYS)}
            self.on_event(Event(rows.stop_cycle, rows.stop_t, text, entity=layout.TRIAL_METRICS,
                                values=values))
        return result
