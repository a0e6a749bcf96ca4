"""LoopPacer: publisher steps only in the idle part of the loop's period (fake clock)."""

from __future__ import annotations

from mmctl.telemetry.pacer import LoopPacer

PERIOD = 2_000_000  # 500 Hz [ns]
SPIN = 300_000


class FakeClock:
    """perf_counter_ns stand-in; ``sleep`` advances it and records the request."""

    def __init__(self, now: int):
        self.now = now
        self.slept: list[int] = []

    def __call__(self) -> int:
        return self.now

    def sleep(self, seconds: float) -> None:
        ns = round(seconds * 1e9)
        self.slept.append(ns)
        self.now += ns


def _pacer(clock: FakeClock, busy: int = 200_000) -> LoopPacer:
    p = LoopPacer(PERIOD, SPIN, guard_ns=100_000, step_ns=300_000, clock=clock,
                  sleep=clock.sleep)
    p.update(10 * PERIOD, busy)  # a deadline on the grid
    return p


def test_no_anchor_never_waits() -> None:
    clock = FakeClock(0)
    p = LoopPacer(PERIOD, SPIN, clock=clock, sleep=clock.sleep)
    p.wait()
    assert clock.slept == [] and p.waits == 0


def test_window_is_between_busy_part_and_the_next_wake_up() -> None:
    p = _pacer(FakeClock(0))
    start, end = p.window()
    assert start == 200_000 + 100_000  # busy + guard after the deadline
    assert end == PERIOD - SPIN - 100_000  # guard before the loop wakes to spin


def test_inside_the_window_returns_at_once() -> None:
    clock = FakeClock(12 * PERIOD + 500_000)  # phase 0.5 ms: idle, 0.3 ms step fits
    p = _pacer(clock)
    p.wait()
    assert clock.slept == [] and p.waits == 0


def test_during_the_busy_part_sleeps_to_the_window_start() -> None:
    clock = FakeClock(12 * PERIOD + 100_000)  # phase 0.1 ms: the loop is busy
    p = _pacer(clock)
    p.wait()
    assert clock.slept == [200_000]  # to phase 0.3 ms
    assert (clock.now - 10 * PERIOD) % PERIOD == p.window()[0]


def test_too_close_to_the_next_wake_up_sleeps_into_the_next_period() -> None:
    clock = FakeClock(12 * PERIOD + 1_400_000)  # step would end at 1.7 ms > 1.6 ms
    p = _pacer(clock)
    p.wait()
    assert clock.slept == [PERIOD - 1_400_000 + 300_000]
    assert (clock.now - 10 * PERIOD) % PERIOD == p.window()[0]
    assert p.waits == 1


def test_no_room_in_the_period_does_not_stall_the_publisher() -> None:
    clock = FakeClock(12 * PERIOD + 100_000)
    p = _pacer(clock, busy=1_500_000)  # the loop leaves less idle time than one step
    p.wait()
    assert clock.slept == []
