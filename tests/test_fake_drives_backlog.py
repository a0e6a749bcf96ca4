"""The fake drives judge their command watchdogs (consumer heartbeat 0x1016:01, RPDO
deadline 0x1400:05) by when a frame reached the bus, as a real drive does, never by when
their receive thread (one Python thread for all four drives) got round to it.

On a loaded 2-core machine that thread fell seconds behind (~5 900 frames queued after
3 s): the master's heartbeats and RPDOs, sent on time, were handled late, the supervisor
found their deadlines passed and the drives quick-stopped, although the master was never
late.  Here the receive thread is stalled on purpose (a handler for a frame no CANopen
service uses blocks until released) while the real master (CanopenBase) keeps sending;
a second bus on the channel records every frame with the same arrival stamp the fakes
see, so each test knows when the master was really silent.  Conditions are asserted,
never durations.
"""

from __future__ import annotations

import itertools
import statistics
import threading
import time
import uuid
from collections.abc import Callable, Iterator

import can
import numpy as np
import pytest

from mmctl.config import Config, config_from_dict
from mmctl.sim.fake_drives import FakeDrives
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.canopen_base import CanopenBase

#: The drives' command watchdog [s]: long, so that only a test thread starved for a whole
#: second on a loaded machine could make the master late for real.
WATCHDOG = 1.0
#: The control period here [s] (500 Hz is not needed to feed a 1 s watchdog).
PERIOD = 0.01
#: A COB-ID no CANopen service uses: only the stall handler listens to it.
STALL_ID = 0x7F0
SLOW = (0.1, 0.0, 0.0)
OTHER = (0.15, 0.0, 0.0)


@pytest.fixture
def cfg() -> Config:
    co = {"interface": "virtual", "channel": f"backlog-{uuid.uuid4().hex[:10]}",
          "heartbeat_timeout": 5.0, "sdo_timeout": 10.0}
    return config_from_dict({"base": {"canopen": co, "command_watchdog": WATCHDOG}})


@pytest.fixture
def monitor(cfg: Config) -> Iterator[can.BusABC]:
    """A bus on the channel that only collects: its frames carry the arrival stamps the
    fakes see (the virtual bus stamps a frame once, for every receiver)."""
    bus = can.Bus(interface="virtual", channel=cfg.base.canopen.channel)
    yield bus
    bus.shutdown()


@pytest.fixture
def fakes(cfg: Config, monitor: can.BusABC) -> Iterator[FakeDrives]:
    with FakeDrives(cfg) as f:
        yield f


@pytest.fixture
def base(cfg: Config, fakes: FakeDrives) -> Iterator[CanopenBase]:
    b = CanopenBase(cfg.base, cfg.limits)
    b.connect()
    b.enable()
    yield b
    b.close()


class Stall:
    """Stalls the fakes' receive thread: the frame ``STALL_ID`` blocks it until released."""

    def __init__(self, fakes: FakeDrives, node_id: int) -> None:
        self.entered = threading.Event()
        self.released = threading.Event()
        fakes.node(node_id).network.subscribe(STALL_ID, self._hold)

    def _hold(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.entered.set()
        self.released.wait(60.0)

    def release(self) -> None:
        self.released.set()


def cycle(base: CanopenBase, twist: tuple[float, float, float]) -> None:
    base.send_twist(*twist)
    base.read_odometry()
    time.sleep(PERIOD)


def cycle_until(base: CanopenBase, twist: tuple[float, float, float],
                pred: Callable[[], object], timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        cycle(base, twist)


def at_speed(fakes: FakeDrives, speed: float) -> bool:
    w = np.abs(fakes.wheel_velocities())
    reached = all(s.statusword & ds.SW_TARGET_REACHED for s in fakes.states())
    return bool(np.all(w >= speed)) and reached


def arrivals(monitor: can.BusABC) -> dict[int, list[float]]:
    """Every frame the monitor collected so far: arrival stamps (wall clock) per COB-ID."""
    out: dict[int, list[float]] = {}
    while (msg := monitor.recv(0)) is not None:
        out.setdefault(msg.arbitration_id, []).append(msg.timestamp)
    return out


def watched_ids(cfg: Config, fakes: FakeDrives) -> dict[str, int]:
    """The master's frames the drives' watchdogs judge: its heartbeat, each RPDO1."""
    ids = {"heartbeat": 0x700 + cfg.base.canopen.master_node_id}
    for nid in cfg.base.canopen.node_ids:
        rpdos = fakes.node(nid).rpdo.map
        assert rpdos is not None
        rpdo1 = next(iter(rpdos.values()))
        ids[f"rpdo1 of node {nid}"] = int(rpdo1.cob_id or 0)
    return ids


def longest_silence(stamps: list[float], start: float, end: float) -> float:
    """The longest time [s] in [start, end] (wall clock) without a frame of ``stamps``."""
    inside = [t for t in stamps if start < t < end]
    before = [t for t in stamps if t <= start]
    edges = [before[-1] if before else start, *inside, end]
    return max(b - a for a, b in itertools.pairwise(edges))


def wall_minus_monotonic() -> float:
    return statistics.median(time.time() - time.monotonic() for _ in range(5))


def watchdog_events(fakes: FakeDrives, nid: int, since: float) -> list[tuple[float, str]]:
    return [(t, w) for t, w in fakes.event_log(nid)
            if t >= since and ("timeout" in w or "deadline" in w)]


def test_frames_sent_on_time_meet_the_watchdog_however_late_they_are_handled(
    cfg: Config, monitor: can.BusABC, fakes: FakeDrives, base: CanopenBase
) -> None:
    """The receive thread stalls for 2.5 watchdog times while the master sends on time:
    no deadline passes, then or once the backlog is handled.  (Before the fix the drives
    quick-stopped during the stall: their watchdog ran on the time a frame was handled.)"""
    ids = cfg.base.canopen.node_ids
    cycle_until(base, SLOW, lambda: at_speed(fakes, 0.7))
    stall = Stall(fakes, ids[0])
    t0 = time.monotonic()
    w0 = time.time()
    net = base.network
    assert net is not None
    net.send_message(STALL_ID, b"")
    cycle_until(base, SLOW, stall.entered.is_set)
    t_stalled = time.monotonic()
    while time.monotonic() - t_stalled < 2.5 * WATCHDOG:
        cycle(base, SLOW)
    # still stalled: the drives have handled nothing for 2.5 watchdog times; looking at
    # them acts on every deadline due by now
    during = [s.state for s in fakes.states()]
    stalled_for = time.monotonic() - t_stalled
    stall.release()
    # the backlog handled: the drives follow a command sent after it
    cycle_until(base, OTHER, lambda: at_speed(fakes, 1.0))
    base.check()
    seen = arrivals(monitor)
    silences = {what: longest_silence(seen.get(cob, []), w0, time.time())
                for what, cob in watched_ids(cfg, fakes).items()}
    print(f"\nreceive thread stalled {stalled_for:.2f} s (watchdog {WATCHDOG:.1f} s); the "
          f"master's longest silence: " + ", ".join(f"{k} {v * 1e3:.0f} ms"
                                                     for k, v in silences.items()))
    assert all(v < WATCHDOG for v in silences.values()), \
        f"the master itself was late (a starved test thread), nothing to judge: {silences}"
    events = {nid: watchdog_events(fakes, nid, t0) for nid in ids}
    assert events == {nid: [] for nid in ids}
    assert during == ["OPERATION ENABLED"] * 4
    assert [s.state for s in fakes.states()] == ["OPERATION ENABLED"] * 4
    assert not [o for o in fakes.power_offs() if o[0] >= t0]


def test_a_master_silent_during_a_backlog_still_trips_the_watchdog_never_early(
    cfg: Config, monitor: can.BusABC, fakes: FakeDrives, base: CanopenBase
) -> None:
    """The master dies while its last frames wait in the stalled receive queue: once they
    are handled, both watchdogs trip (quick stop, as the master configured), each no
    earlier than a watchdog time after the last frame of its kind reached the bus."""
    ids = cfg.base.canopen.node_ids
    cycle_until(base, SLOW, lambda: at_speed(fakes, 0.7))
    stall = Stall(fakes, ids[0])
    t0 = time.monotonic()
    net = base.network
    assert net is not None
    net.send_message(STALL_ID, b"")
    cycle_until(base, SLOW, stall.entered.is_set)
    for _ in range(20):  # frames queued behind the stall, sent on time
        cycle(base, SLOW)
    watched = watched_ids(cfg, fakes)
    net.disconnect()  # the master is gone: no heartbeat, RPDO or SYNC any more
    t_quiet = time.monotonic()
    while time.monotonic() - t_quiet < 1.5 * WATCHDOG:
        time.sleep(0.05)
    stall.release()
    deadline = time.monotonic() + 60.0
    while [s.state for s in fakes.states()] != ["SWITCH ON DISABLED"] * 4:
        assert time.monotonic() < deadline, "the drives never stopped"
        time.sleep(0.01)
    offset = wall_minus_monotonic()
    seen = arrivals(monitor)
    last = {what: max(seen[cob]) - offset for what, cob in watched.items()}
    for nid in ids:
        events = {w: t for t, w in reversed(watchdog_events(fakes, nid, t0))}
        assert set(events) == {"heartbeat consumer timeout", "rpdo1 deadline missed"}
        # never before its deadline (5 ms: the two clocks read apart)
        assert events["heartbeat consumer timeout"] >= last["heartbeat"] + WATCHDOG - 0.005
        assert events["rpdo1 deadline missed"] >= last[f"rpdo1 of node {nid}"] + WATCHDOG - 0.005
        log = [w for t, w in fakes.event_log(nid) if t >= t0]
        assert log.index("state QUICK STOP ACTIVE") < log.index("at rest") \
            < log.index("state SWITCH ON DISABLED", log.index("state QUICK STOP ACTIVE"))
    assert all(v == 0.0 for t, _, v in fakes.power_offs() if t >= t0)  # off only at rest
