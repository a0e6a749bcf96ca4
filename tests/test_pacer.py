"""LoopPacer: publisher steps only in the loop's idle time, following the real timing
ring (the loop thread is played by the fake clock's sleep)."""

from __future__ import annotations

from mmctl.runtime.timing import TimingRing
from mmctl.telemetry.pacer import LoopPacer

PERIOD = 2_000_000  # 500 Hz [ns]
SPIN = 300_000
BODY = 400_000  # wake latency + body of every simulated cycle [ns]


class FakeLoop:
    """A clock whose ``sleep`` also runs the loop: each cycle is recorded in the ring
    when its body ends (deadline + BODY), like CycleLoop does."""

    def __init__(self, now: int, ring: TimingRing, first_deadline: int, body: int = BODY):
        self.now = now
        self.ring = ring
        self.next_deadline = first_deadline
        self.body = body
        self.slept: list[int] = []
        self._advance()

    def __call__(self) -> int:
        return self.now

    def _advance(self) -> None:
        while self.next_deadline + self.body <= self.now:
            d = self.next_deadline
            self.ring.record(d, 0, self.body, PERIOD - self.body, 0)
            self.next_deadline += PERIOD

    def sleep(self, seconds: float) -> None:
        ns = round(seconds * 1e9)
        self.slept.append(ns)
        self.now += ns
        self._advance()


def _setup(phase: int, body: int = BODY) -> tuple[LoopPacer, FakeLoop]:
    ring = TimingRing(64)
    loop = FakeLoop(10 * PERIOD + phase, ring, first_deadline=0, body=body)
    pacer = LoopPacer(ring, PERIOD, SPIN, guard_ns=100_000, step_ns=300_000, clock=loop,
                      sleep=loop.sleep)
    pacer.update(body)
    return pacer, loop


def _phase(loop: FakeLoop) -> int:
    return loop.now % PERIOD


def test_no_cycle_recorded_never_waits() -> None:
    ring = TimingRing(8)
    slept: list[float] = []
    LoopPacer(ring, PERIOD, SPIN, clock=lambda: 5, sleep=slept.append).wait()
    assert slept == []


def test_ring_last_is_the_newest_row() -> None:
    ring = TimingRing(4)
    assert ring.last() is None
    for k in range(6):
        ring.record(k * PERIOD, 1, 2, 3, k % 2)
    assert ring.last() == (5 * PERIOD, 1, 2, 3, 1)


def test_idle_with_room_returns_at_once() -> None:
    pacer, loop = _setup(phase=600_000)  # body ended at 0.4 ms; step fits before 1.3 ms
    pacer.wait()
    assert loop.slept == [] and pacer.waits == 0


def test_during_the_body_waits_until_the_cycle_is_recorded() -> None:
    pacer, loop = _setup(phase=100_000)  # the current cycle's body is running
    pacer.wait()
    assert loop.slept  # it waited ...
    assert _phase(loop) >= BODY  # ... until the body had ended,
    assert _phase(loop) + 300_000 <= PERIOD - SPIN - 100_000  # with room for a step
    assert pacer.waits == 1


def test_too_close_to_the_next_wake_up_waits_for_the_next_period() -> None:
    pacer, loop = _setup(phase=1_400_000)  # a step would run into the spin window
    before = loop.now
    pacer.wait()
    assert loop.now - before >= PERIOD - 1_400_000 + BODY  # after the next body
    assert BODY <= _phase(loop) <= PERIOD - SPIN - 100_000 - 300_000


def test_a_long_body_makes_it_wait_longer() -> None:
    pacer, loop = _setup(phase=100_000, body=1_000_000)
    pacer.wait()
    assert 1_000_000 <= _phase(loop) <= 1_300_000


def test_a_stopped_loop_does_not_stall_the_publisher() -> None:
    ring = TimingRing(8)
    ring.record(0, 0, BODY, PERIOD - BODY, 0)
    now = [10 * PERIOD]  # long after the next deadline: the loop is not running
    slept: list[float] = []
    LoopPacer(ring, PERIOD, SPIN, clock=lambda: now[0], sleep=slept.append).wait()
    assert slept == []


def test_wait_is_bounded() -> None:
    ring = TimingRing(8)
    ring.record(0, 0, BODY, PERIOD - BODY, 0)
    now = [PERIOD + 100_000]  # the next body never gets recorded (a stuck cycle) ...
    def sleep(s: float) -> None:
        now[0] = min(now[0] + round(s * 1e9), 3 * PERIOD - 1)  # ... within the stall bound
    pacer = LoopPacer(ring, PERIOD, SPIN, max_wait_ns=1_000_000, clock=lambda: now[0],
                      sleep=sleep)
    pacer.wait()
    assert pacer.gave_up == 1
