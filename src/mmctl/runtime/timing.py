"""Per-cycle timing kept in a lock-free ring (one writer: the loop thread).

The ring holds preallocated int64 arrays (nanoseconds) and a single monotonically
increasing write counter.  The writer fills slot ``count % size`` and only then
increments ``count``; readers copy the arrays and drop the slots the writer may have
overwritten while they copied, so no lock is ever taken on the hot path.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

I64 = NDArray[np.int64]


class TimingSnapshot(NamedTuple):
    """A consistent copy of the newest samples, oldest first.

    deadline_ns: the absolute deadline each cycle was due at (perf_counter_ns) [ns];
    latency_ns: wake-up time minus deadline (>= 0 unless woken early) [ns];
    compute_ns: time spent in the cycle body [ns];
    slack_ns: next deadline minus end of the cycle body (< 0 on an overrun) [ns];
    missed: number of deadlines skipped after this cycle (0 = on time);
    first_index: cycle index of the first row.
    """

    deadline_ns: I64
    latency_ns: I64
    compute_ns: I64
    slack_ns: I64
    missed: I64
    first_index: int

    def __len__(self) -> int:
        return int(self.latency_ns.shape[0])


class TimingStats(NamedTuple):
    """Summary of a snapshot; times in microseconds [us]."""

    cycles: int
    compute_p50_us: float
    compute_p99_us: float
    compute_max_us: float
    latency_p50_us: float
    latency_p99_us: float
    latency_p999_us: float
    latency_max_us: float
    slack_min_us: float
    missed: int
    miss_rate: float

    def as_dict(self) -> dict[str, float | int]:
        """Plain-JSON form (for `status` and `bench loop`)."""
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in self._asdict().items()}


class TimingRing:
    """Preallocated ring of per-cycle timings; ``record`` is the single-writer hot path."""

    def __init__(self, size: int = 8192):
        if size <= 0:
            raise ValueError(f"size must be > 0, got {size}")
        self.size = size
        self._deadline = np.zeros(size, np.int64)
        self._latency = np.zeros(size, np.int64)
        self._compute = np.zeros(size, np.int64)
        self._slack = np.zeros(size, np.int64)
        self._missed = np.zeros(size, np.int64)
        self._count = 0
        #: the newest cycle's (latency, compute, slack, missed) [ns] as Python numbers,
        #: for the telemetry row of the cycle after it (NaN before the first)
        self.newest: tuple[float, ...] = (math.nan,) * 4

    @property
    def count(self) -> int:
        """Cycles recorded since creation."""
        return self._count

    def record(self, deadline_ns: int, latency_ns: int, compute_ns: int, slack_ns: int,
               missed: int) -> None:
        """Store one cycle's timing [ns]; call from the loop thread only."""
        i = self._count % self.size
        self._deadline[i] = deadline_ns
        self._latency[i] = latency_ns
        self._compute[i] = compute_ns
        self._slack[i] = slack_ns
        self._missed[i] = missed
        self.newest = (latency_ns, compute_ns, slack_ns, missed)
        self._count += 1  # publish: readers only trust slots below this count

    def last(self) -> tuple[int, int, int, int, int] | None:
        """The newest row (deadline, latency, compute, slack, missed) [ns], or None."""
        n = self._count
        if n == 0:
            return None
        i = (n - 1) % self.size
        return (int(self._deadline[i]), int(self._latency[i]), int(self._compute[i]),
                int(self._slack[i]), int(self._missed[i]))

    def snapshot(self, last: int | None = None) -> TimingSnapshot:
        """Copy the newest ``last`` samples (default: all the ring holds), oldest first."""
        end = self._count
        cols = [a.copy() for a in (self._deadline, self._latency, self._compute,
                                   self._slack, self._missed)]
        after = self._count
        # Slots written while we copied (indices end .. after-1), and the one the writer
        # may be filling now, overwrote the oldest entries; keep only stable rows.
        n = min(end, self.size - (after - end) - 1)
        if last is not None:
            n = min(n, max(last, 0))
        n = max(n, 0)
        idx = (np.arange(end - n, end) % self.size) if n else np.zeros(0, np.int64)
        deadline, latency, compute, slack, missed = (c[idx] for c in cols)
        return TimingSnapshot(deadline, latency, compute, slack, missed, end - n)

    def stats(self, last: int | None = None) -> TimingStats:
        """Percentiles of the newest ``last`` samples."""
        return summarize(self.snapshot(last))


def cycle_rows(per_cycle: NDArray[np.generic], snap: TimingSnapshot) -> NDArray[np.generic]:
    """The entries of a per-cycle array indexed by ``cycle % its size`` (the daemon's
    ``step_ns``, ``hook_ns``) for the snapshot's cycles, in the snapshot's order."""
    idx = np.arange(snap.first_index, snap.first_index + len(snap)) % per_cycle.shape[0]
    rows: NDArray[np.generic] = per_cycle[idx]
    return rows


def concat(snaps: list[TimingSnapshot]) -> TimingSnapshot:
    """Several snapshots as one (rows in the given order; ``first_index`` of the first)."""
    if not snaps:
        empty = np.zeros(0, np.int64)
        return TimingSnapshot(empty, empty, empty, empty, empty, 0)
    def col(k: int) -> I64:
        return np.concatenate([s[k] for s in snaps])

    return TimingSnapshot(col(0), col(1), col(2), col(3), col(4), snaps[0].first_index)


def summarize(s: TimingSnapshot) -> TimingStats:
    """Percentiles of compute time and wake latency, miss count and rate [us]."""
    n = len(s)
    if n == 0:
        return TimingStats(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0.0)
    comp = s.compute_ns / 1e3
    lat = s.latency_ns / 1e3
    missed = int(s.missed.sum())
    cp50, cp99 = np.percentile(comp, [50, 99])
    lp50, lp99, lp999 = np.percentile(lat, [50, 99, 99.9])
    return TimingStats(
        cycles=n,
        compute_p50_us=float(cp50),
        compute_p99_us=float(cp99),
        compute_max_us=float(comp.max()),
        latency_p50_us=float(lp50),
        latency_p99_us=float(lp99),
        latency_p999_us=float(lp999),
        latency_max_us=float(lat.max()),
        slack_min_us=float(s.slack_ns.min() / 1e3),
        missed=missed,
        miss_rate=missed / (n + missed),
    )
