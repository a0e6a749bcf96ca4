"""Which late cycles overlap the telemetry publisher's work: synthetic timings with
known answers, and the publisher's record of its own work intervals."""

from __future__ import annotations

import numpy as np

from mmctl.bench.telemetry_overhead import overlapping_misses
from mmctl.runtime.timing import TimingSnapshot
from mmctl.telemetry.publisher import BusyRing

P = 2_000_000  # period [ns]


def snap(rows: list[tuple[int, int, int, int]]) -> TimingSnapshot:
    """rows of (deadline, latency, compute, missed) [ns]."""
    a = np.array(rows, dtype=np.int64)
    slack = np.zeros(len(rows), np.int64)
    return TimingSnapshot(a[:, 0], a[:, 1], a[:, 2], slack, a[:, 3], 0)


def test_only_late_cycles_whose_window_meets_an_interval_count() -> None:
    lead = 300_000  # the loop wakes this long before its deadline [ns]
    s = snap([
        (10 * P, 0, 3 * P, 1),          # late; window [10P - lead, 13P]
        (20 * P, 5 * P, 100_000, 2),    # late by its wake-up; window [20P - lead, 25.05P]
        (30 * P, 0, 3 * P, 1),          # late; the publisher worked only in the idle time
        (40 * P, 0, 100_000, 0),        # on time, overlapping: not counted
    ])
    starts = np.array([12 * P, 24 * P, 29 * P, 40 * P], np.int64)
    ends = np.array([12 * P + 50_000, 24 * P + 50_000, 30 * P - lead, 40 * P + 10], np.int64)
    assert overlapping_misses(s, lead, starts, ends) == 2
    # the idle-time work before cycle 3 counts once the window reaches back to it
    assert overlapping_misses(s, P, starts, ends) == 3
    assert overlapping_misses(s, lead, np.zeros(0, np.int64), np.zeros(0, np.int64)) == 0


def test_busy_ring_keeps_closed_intervals_in_order() -> None:
    ring = BusyRing(size=4)
    ring.end()  # nothing open: nothing recorded
    for _ in range(6):
        ring.begin()
        ring.end()
    starts, ends = ring.intervals()
    assert ring.count == 6
    assert len(starts) == 3  # size - 1 kept (the slot being written is never read)
    assert np.all(ends >= starts) and np.all(np.diff(starts) >= 0)


def test_pairwise_growth_ignores_a_burst_in_one_pair() -> None:
    from mmctl.bench.telemetry_overhead import Phase, _pairs, _report

    def phase(on: bool, compute_us: float, burst: bool = False, missed: int = 0) -> Phase:
        compute = np.full(1000, compute_us * 1e3, dtype=np.int64)
        if burst:
            compute[:50] *= 5  # 5 % of the cycles: moves p99, not the median of the pairs
        late = np.zeros(1000, np.int64)
        late[:missed] = 1
        rows = [(i * P, 0, int(c), int(m)) for i, (c, m) in enumerate(zip(compute, late))]
        return Phase(on, snap(rows), 1000 if on else 0, 0, 0.0)

    phases = [phase(False, 300), phase(True, 315, missed=1),   # +5 %, one more miss
              phase(False, 300), phase(True, 315, burst=True),  # a burst in one "on" window
              phase(False, 300), phase(True, 315)]
    out = _pairs(phases)
    assert out["compute_p99_growth_pairs"] == [0.05, 4.25, 0.05]  # 1575 / 300 - 1
    assert out["compute_p99_growth_pair_median"] == 0.05
    assert out["extra_misses_pairs"] == [1, 0, 0]
    pooled = _report(phases)
    assert pooled["compute_p99_growth"] > 1.0  # the pooled p99 took the burst
    assert pooled["compute_p99_growth_pair_median"] == 0.05
    assert _pairs(phases[:1]) == {}


def _phases(pairs: int, on_scale: float, misses_on: int = 0, seed: int = 3) -> list:
    """Alternating off/on windows of 1000 gamma-distributed compute times whose scale
    drifts from pair to pair (the machine); "on" multiplies them by ``on_scale`` and
    has ``misses_on`` late cycles (one in every 1000 cycles in both conditions too)."""
    from mmctl.bench.telemetry_overhead import Phase

    rng = np.random.default_rng(seed)
    out = []
    for i in range(pairs):
        drift = 1.0 + 0.1 * np.sin(i)
        for on in (False, True):
            c = rng.gamma(20.0, 15_000.0, 1000) * drift * (on_scale if on else 1.0)
            missed = np.zeros(1000, np.int64)
            missed[500] = 1
            missed[:misses_on if on else 0] = 1
            s = TimingSnapshot(np.arange(1000, dtype=np.int64) * P, np.zeros(1000, np.int64),
                               c.astype(np.int64), np.zeros(1000, np.int64), missed, 0)
            out.append(Phase(on, s, 0, 0, 0.0))
    return out


def test_growth_interval_covers_the_true_growth_and_judges_the_target() -> None:
    from mmctl.bench.telemetry_overhead import growth_interval, verdict

    ci = growth_interval(_phases(60, 1.05))
    lo, hi = ci["compute_p99_growth_ci"]
    assert ci["pairs"] == 60 and ci["confidence"] == 0.95
    assert lo < 0.05 < hi and hi - lo < 0.05  # the true +5 %, to within a few per cent
    assert ci["extra_misses_per_1e5_ci"] == [0.0, 0.0]  # the same misses in both
    lines = verdict({"interval": ci}).splitlines()
    assert lines[0].startswith("target telemetry compute p99 growth < 10 %: met")
    assert "none shown" in lines[1]

    worse = growth_interval(_phases(60, 1.25, misses_on=3))
    assert worse["compute_p99_growth_ci"][0] > 0.2
    assert worse["extra_misses_per_1e5"] == 300.0  # 3 more in every 1000 cycles
    assert worse["extra_misses_per_1e5_ci"][0] > 0
    lines = verdict({"interval": worse}).splitlines()
    assert "NOT met" in lines[0] and "telemetry adds misses" in lines[1]


def test_growth_interval_of_an_aa_contains_zero_and_needs_pairs() -> None:
    from mmctl.bench.telemetry_overhead import MIN_PAIRS, growth_interval, verdict

    ci = growth_interval(_phases(40, 1.0))
    lo, hi = ci["compute_p99_growth_ci"]
    assert lo < 0.0 < hi
    assert growth_interval(_phases(MIN_PAIRS - 1, 1.0)) == {}
    assert "too few" in verdict({"interval": {}})


def test_a_stall_of_the_machine_changes_no_interval() -> None:
    """Cycles beyond every window's p99 share the histograms' last bin: the longest
    cycle of the run stretched to 60 ms gives the same intervals, and the histograms
    stay as wide as the largest window p99, not the stall."""
    from mmctl.bench.telemetry_overhead import Phase, _pair_histograms, growth_interval

    calm = _phases(20, 1.05)
    k = int(np.argmax([p.snapshot.compute_ns.max() for p in calm]))
    s = calm[k].snapshot
    c = s.compute_ns.copy()
    c[np.argmax(c)] = 60_000_000  # 60 ms
    stalled = list(calm)
    stalled[k] = Phase(calm[k].telemetry, TimingSnapshot(s.deadline_ns, s.latency_ns, c,
                                                         s.slack_ns, s.missed, 0), 0, 0, 0.0)
    assert growth_interval(stalled) == growth_interval(calm)
    hist = _pair_histograms(stalled)
    assert hist is not None
    assert hist.off.shape[1] == hist.on.shape[1] < 2000  # [1 us bins]; the stall: 60 000
    assert hist.on.sum() + hist.off.sum() == 40 * 1000  # no cycle lost
