"""The fixed-period loop and its timing ring (no timed assertions: only counts/ordering)."""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from structlog.testing import capture_logs

from mmctl.runtime.loop import CycleLoop, Tick, apply_realtime
from mmctl.runtime.timing import TimingRing, summarize


def _run(loop: CycleLoop, done: threading.Event) -> None:
    loop.start()
    assert done.wait(30.0), "loop did not reach the expected cycle"
    loop.join(10.0)


def test_deadlines_are_absolute_and_spaced_by_whole_periods() -> None:
    ticks: list[Tick] = []
    done = threading.Event()

    def body(t: Tick) -> None:
        ticks.append(t)
        if len(ticks) == 50:
            done.set()

    loop = CycleLoop(body, rate_hz=500.0, spin_margin=0.0002)
    _run(loop, done)
    assert [t.index for t in ticks[:50]] == list(range(50))
    gaps = np.diff([t.deadline_ns for t in ticks])
    assert np.all(gaps % loop.period_ns == 0) and np.all(gaps >= loop.period_ns)
    # A cycle never starts before its deadline (sleep-then-spin never wakes early).
    assert all(t.wake_ns >= t.deadline_ns for t in ticks)
    snap = loop.ring.snapshot()
    assert len(snap) == loop.cycles >= 50
    assert np.all(snap.latency_ns >= 0) and np.all(snap.compute_ns >= 0)


def test_overruns_skip_deadlines_count_them_and_exhaust_the_budget() -> None:
    ticks: list[Tick] = []
    done = threading.Event()

    def body(t: Tick) -> None:
        ticks.append(t)
        if 3 <= t.index < 10:
            time.sleep(0.025)  # five periods at 200 Hz: always an overrun
        if t.overrun or t.index > 200:
            done.set()

    loop = CycleLoop(body, rate_hz=200.0, spin_margin=0.0, max_consecutive_misses=4,
                     max_total_misses=10_000)
    _run(loop, done)
    first_overrun = next(t for t in ticks if t.overrun)
    assert first_overrun.consecutive_misses >= 4
    slow = [t for t in ticks if 3 <= t.index < 10]
    # After a slow cycle the next deadline is in the future: the missed ones were skipped.
    for a, b in itertools.pairwise(slow):
        assert (b.deadline_ns - a.deadline_ns) % loop.period_ns == 0
        assert b.deadline_ns - a.deadline_ns >= 2 * loop.period_ns
    snap = loop.ring.snapshot()
    assert snap.missed.sum() >= 4 and np.all(snap.slack_ns[snap.missed > 0] < 0)


def test_total_budget_and_reset() -> None:
    seen: list[Tick] = []
    done = threading.Event()
    state = {"reset": False}

    def body(t: Tick) -> None:
        seen.append(t)
        if t.index % 2 == 0 and not state["reset"]:
            time.sleep(0.011)  # > 2 periods at 200 Hz, but never two in a row
        if t.overrun and not state["reset"]:
            state["reset"] = True
            loop.reset_misses()
        elif state["reset"] and t.index > seen[0].index + 40:
            done.set()

    loop = CycleLoop(body, rate_hz=200.0, spin_margin=0.0, max_consecutive_misses=100,
                     max_total_misses=6)
    _run(loop, done)
    trip = next(t for t in seen if t.overrun)
    assert trip.total_misses >= 6 and trip.consecutive_misses < 100
    # the reset zeroes the counters at the start of the next cycle: that tick carries
    # none of the misses before it (later ones are the machine's: not judged here)
    after = seen[seen.index(trip) + 1]
    assert (after.total_misses, after.consecutive_misses, after.overrun) == (0, 0, False)


def test_exception_in_body_is_stored_and_reraised() -> None:
    def body(t: Tick) -> None:
        if t.index == 3:
            raise ZeroDivisionError("boom")

    loop = CycleLoop(body, rate_hz=500.0)
    with capture_logs() as logs:
        loop.start()
        assert loop.wait(30.0)
    assert not loop.running
    with pytest.raises(ZeroDivisionError):
        loop.join()
    assert any(e["event"] == "loop_crashed" for e in logs)


def test_realtime_settings_are_best_effort() -> None:
    with capture_logs() as logs:
        problems = apply_realtime(0, (100_000,))
    assert problems == ["cpu_affinity"]
    assert logs[0]["event"] == "loop_affinity_not_applied"


def test_ring_wraps_and_keeps_the_newest() -> None:
    ring = TimingRing(8)
    for k in range(20):
        ring.record(k * 10, k, 2 * k, 100 - k, int(k == 15))
    snap = ring.snapshot()
    assert len(snap) == 7  # one slot kept back for a writer that may be mid-record
    assert list(snap.latency_ns) == list(range(13, 20))
    assert snap.first_index == 13
    assert list(ring.snapshot(3).compute_ns) == [34, 36, 38]
    stats = summarize(snap)
    assert stats.missed == 1 and stats.cycles == 7
    assert stats.miss_rate == pytest.approx(1 / 8)
    assert summarize(TimingRing(4).snapshot()).cycles == 0


@settings(max_examples=40, deadline=None)
@given(size=st.integers(1, 64), n=st.integers(0, 300))
def test_ring_snapshot_is_in_order(size: int, n: int) -> None:
    ring = TimingRing(size)
    for k in range(n):
        ring.record(k, k, k, k, 0)
    snap = ring.snapshot()
    assert len(snap) == min(n, size - 1)
    assert list(snap.deadline_ns) == list(range(n - len(snap), n))


def test_ring_reader_never_sees_torn_rows() -> None:
    ring = TimingRing(64)
    stop = threading.Event()

    def writer() -> None:
        k = 0
        while not stop.is_set():
            ring.record(k, k, k, k, 0)
            k += 1

    th = threading.Thread(target=writer)
    th.start()
    try:
        for _ in range(300):
            s = ring.snapshot()
            if len(s):
                assert np.all(s.deadline_ns == s.latency_ns)
                assert np.all(np.diff(s.deadline_ns) == 1)
                assert s.deadline_ns[0] == s.first_index
    finally:
        stop.set()
        th.join()


def test_the_wait_is_the_one_given_at_construction() -> None:
    """The loop waits for each deadline only through its wait strategy: a recording
    one sees every deadline, and the ticks carry the wake times it returned."""
    from mmctl.runtime.loop import PlainSleep

    seen: list[int] = []
    plain = PlainSleep()

    def wait(deadline: int) -> int:
        seen.append(deadline)
        plain(deadline)
        return deadline + 12_345  # a wake time only this wait reports

    ticks: list[Tick] = []
    done = threading.Event()

    def body(t: Tick) -> None:
        ticks.append(t)
        if len(ticks) == 20:
            done.set()

    loop = CycleLoop(body, rate_hz=500.0, wait=wait)
    _run(loop, done)
    assert [t.deadline_ns for t in ticks] == seen[:len(ticks)]
    assert all(t.wake_ns == t.deadline_ns + 12_345 for t in ticks)


def test_the_garbage_collector_runs_in_the_slack_only() -> None:
    """GcInSlack: automatic collection off while the loop runs; a collection every
    ``every`` cycles when the next deadline leaves ``margin`` (else the next cycle with
    slack); the middle generation once a second, all three once a minute; back on after."""
    import gc

    from mmctl.runtime.loop import GcInSlack

    assert gc.isenabled()
    g = GcInSlack(every=2, margin_ns=1_000_000, rate_hz=4.0)  # 2 a second, 120 a minute
    g.start()
    try:
        assert not gc.isenabled()
        far = time.perf_counter_ns() + 10**12
        g.after_cycle(far)
        assert g.collections == [0, 0, 0]  # one cycle: not yet
        g.after_cycle(time.perf_counter_ns())  # due, but no slack: waits
        assert g.collections == [0, 0, 0]
        g.after_cycle(far)
        assert g.collections == [1, 0, 0]
        for _ in range(2 * 119):
            g.after_cycle(far)
        assert g.collections == [60, 59, 1] and g.worst_ns > 0
    finally:
        g.stop()
    assert gc.isenabled()
