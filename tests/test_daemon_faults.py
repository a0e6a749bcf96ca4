"""A few SPEC §5 faults end to end: the daemon on the real transports and the simulated
robot's fakes, each fault injected into a fake and the stop read from the fakes' own
command logs.

The daemon runs in-process next to the fakes (fake UR controller in its own process, fake
CAN sensor and CiA 402 drives on python-can's in-process virtual bus) and is stepped by
hand with ``Daemon.step_once`` (the last test runs the real loop thread).  Covered here:
a wrench over the limit (the CAN sensor's samples), an arm protective stop (RTDE safety
bits), a drive in FAULT that the operator's enable resets (CiA 402), an arm controller
that dies (refused while it is gone), a fault after the arm hold (a frozen stream), and
overruns of the real loop thread.  Each one: the detecting cycle sends no speedJ (a
drive fault found by the base's twist: after that cycle's own speedJ), after its last
motion command the fake controller receives at most the arm hold's zero speedJs, then
the stop and nothing but stops, all with ``arm.stop_deceleration``, the drives get zero
targets and are disabled, one ``fault`` event names the cause, enabling is refused
while it persists.

Every SPEC §5 condition (these, and the sensor's staleness, status and saturation, the
arm's not-PLAYING, emergency stop and frozen timestamp, a drive's lost heartbeat, a
base link error, non-finite numbers, a singular pose, an exception in a cycle), with
its exact detecting cycle, the stop's order and deceleration, the refusal and the
latch, is tested at the daemon-cycle level with scripted peers and a scripted clock in
``test_fault_matrix.py``; the transports' own detection (status words, rails, stale
samples and streams, heartbeats, reboots, malformed frames) in their own tests.

The configuration gives every staleness timeout and the loop's miss budget a size that
a loaded machine cannot exhaust in these tests, so any fault but the injected one fails.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import pytest
from structlog.testing import capture_logs

from loopback import free_loopback_host
from mmctl.config import Config, config_from_dict
from mmctl.errors import FaultCause, MmctlError
from mmctl.runtime.daemon import Daemon
from mmctl.runtime.factory import create_daemon
from mmctl.runtime.safety import EnableRefused, SafetyState
from mmctl.sim.fake_ur import CommandKind
from mmctl.sim.world import SimWorld
from waiting import wait_for

pytestmark = pytest.mark.timeout(600)

PUSH = [15.0, 0.0, 0.0]  # [N] world frame: the arm moves, speedJ commands are non-zero
STOP_DECELERATION = 7.5  # [rad/s^2] no transport's or fake's default
_uid = itertools.count()


def fault_config() -> Config:
    uid = next(_uid)
    return config_from_dict({
        "name": "fault-tests",
        "sim": {"enabled": True, "human": False, "auto_enable": False},
        # stepped by hand, with pauses between the steps: the arm's stream may answer
        # late (stale_cycles: reads without an answer) and the controller's watchdog is
        # as long as allowed (1 Hz; its own test: test_stop_path)
        "arm": {"host": free_loopback_host(201), "stale_cycles": 10_000,
                "watchdog_min_frequency": 1.0, "stop_deceleration": STOP_DECELERATION},
        "sensor": {"transport": "can",
                   "can": {"interface": "virtual", "channel": f"flt-s-{uid}"},
                   "wrench": {"stale_timeout": 5.0}},
        "base": {"transport": "canopen",
                 "canopen": {"interface": "virtual", "channel": f"flt-b-{uid}",
                             # (sdo_timeout: the in-process drives answered no SDO
                             # within 5 s at a start-up with both cores busy, CI)
                             "heartbeat_timeout": 5.0, "sdo_timeout": 10.0,
                             "stop_timeout": 10.0},
                 "command_watchdog": 10.0},
        "loop": {"max_consecutive_misses": 200, "max_total_misses": 1_000_000_000},
    })


@dataclass
class World:
    cfg: Config
    daemon: Daemon
    sim: SimWorld

    def arm_log(self) -> list[Any]:
        kinds = (CommandKind.SPEEDJ, CommandKind.SPEED_STOP)
        return [c for c in self.sim.ur.commands() if c.kind in kinds]


@contextlib.contextmanager
def open_world() -> Iterator[World]:
    """The fakes and a daemon on them (opened, tared, disarmed), closed at the end."""
    cfg = fault_config()
    sim = SimWorld(cfg)
    sim.start()
    daemon = create_daemon(cfg, socket_path=None)
    assert daemon.sim is None  # virtual CAN: the fakes are this test's, not a process's
    try:
        daemon.open()
    except BaseException:
        sim.close()
        raise
    w = World(cfg, daemon, sim)
    try:
        step(w, 3)
        daemon.call("tare")
        steps_until(w, lambda: not daemon.core.taring, "the tare")
        yield w
    finally:
        daemon.shutdown()
        sim.close()


@pytest.fixture(scope="module")
def world() -> Iterator[World]:
    with open_world() as w:
        yield w


@pytest.fixture
def own_world() -> Iterator[World]:
    with open_world() as w:
        yield w


def step(w: World, n: int = 1) -> None:
    for _ in range(n):
        w.daemon.step_once()
        time.sleep(0.002)  # let the fakes stream a new sample (one RTDE period)


def steps_until(w: World, pred: Callable[[], Any], what: str, timeout: float = 60.0) -> None:
    """Step until ``pred()``: the daemon keeps talking to the devices while the test
    waits (the controller's watchdog stays fed)."""
    wait_for(lambda: (step(w), pred())[1], what, timeout)


def moving(commands: list[Any]) -> bool:
    """Any of these fake-controller commands is a speedJ with motion."""
    return any(c.kind is CommandKind.SPEEDJ and any(c.qd) for c in commands)


def conditions(w: World) -> set[str]:
    return {c.value for c in w.daemon.last_conditions}


#: Refusals a loaded machine causes while the daemon is stepped by hand or starved: the
#: enable's base SDOs take long enough for the arm's 1 Hz RTDE watchdog to stop its
#: program, or the in-process drives answer late.  The next enable reconnects the arm.
_LOAD_REFUSALS = ("arm_not_playing", "arm_timestamp_stale", "the base did not enable")


def enable_eventually(w: World, stepping: bool = True, attempts: int = 4) -> None:
    """``enable``, again after a refusal in :data:`_LOAD_REFUSALS` (any other refusal
    fails the test)."""
    for attempt in range(attempts):
        try:
            w.daemon.call("enable")
            return
        except MmctlError as exc:
            if not any(r in str(exc) for r in _LOAD_REFUSALS) or attempt == attempts - 1:
                raise
        if stepping:
            step(w, 3)
        else:
            time.sleep(0.2)


def arm_and_push(w: World, latched: frozenset[str] = frozenset()) -> None:
    """Enable once the conditions are gone (but ``latched`` ones, which the enable
    resets), push, and see speedJ commands with motion reach the fake controller."""
    d = w.daemon
    steps_until(w, lambda: conditions(w) <= latched, "a healthy cycle")
    enable_eventually(w)
    assert d.safety.armed
    w.sim.set_push(PUSH)
    steps_until(w, lambda: moving(w.arm_log()[-3:])
                and any(w.sim.drives.target_counts()), "motion at the fake UR and drives")
    assert d.safety.armed, d.safety.as_dict()


def detect(w: World, inject: Callable[[], None], cause: FaultCause,
           found_by_twist: bool = False) -> None:
    """Inject, step to the fault: exactly ``cause``, one fault event, and the
    detecting cycle sent the stop and no speedJ (``found_by_twist``: a drive fault may be
    found by that cycle's twist, after its speedJ)."""
    d = w.daemon
    sent = d.commands_sent
    before = dict(sent)
    with capture_logs() as logs:
        inject()
        deadline = time.monotonic() + 60.0
        while d.safety.armed and time.monotonic() < deadline:
            before = dict(sent)
            d.step_once()
            time.sleep(0.002)
    assert d.safety.state is SafetyState.FAULT, f"{cause.value} not detected"
    assert d.safety.latched is cause, d.safety.as_dict()
    assert [e["cause"] for e in logs if e["event"] == "fault"] == [cause.value], logs
    in_cycle = {k: sent[k] - before[k] for k in sent}
    allowed = [{"speed_j": 0, "twist": 0, "stop": 1}]
    if found_by_twist:
        allowed.append({"speed_j": 1, "twist": 0, "stop": 1})
    assert in_cycle in allowed, in_cycle
    w.sim.set_push(None)


def after_motion(w: World) -> list[Any]:
    """The fake controller's arm commands after the last speedJ with motion."""
    log = w.arm_log()
    last = max(i for i, c in enumerate(log) if moving([c]))
    return log[last + 1:]


def is_stop(c: Any) -> bool:
    """A stop as the fake controller logs it: speedStop (any deceleration: checked
    after), or speedJ(0) at the stop deceleration."""
    return c.kind is CommandKind.SPEED_STOP or (
        not any(c.qd) and c.acceleration == pytest.approx(STOP_DECELERATION))


def split_at_stop(w: World) -> tuple[list[Any], list[Any]] | None:
    """The arm commands after the last speedJ with motion, split at the first stop:
    (those before it, it and those after it); None while no stop followed the motion."""
    tail = after_motion(w)
    first = next((i for i, c in enumerate(tail) if is_stop(c)), None)
    return None if first is None else (tail[:first], tail[first:])


def assert_arm_stopped(w: World, stepping: bool = True) -> None:
    """At the fake controller: a stop arrived after the last speedJ with motion, and
    from the first stop on nothing but stops, each with the configured deceleration
    (speedStop; speedJ(0) when the arm is unfit for it).  Between the motion and the
    stop only the arm hold's rest may come: speedJ(0) at the normal acceleration, sent
    while still armed (the fake controller's stream stalled for ``arm.hold_cycles``
    cycles before the fault, and the hold braked the command to zero).  One link
    carries them in order: nothing the daemon sent before the stop can arrive after it,
    so a speedJ sent after the stop shows here after it."""
    what = "the stop at the fake UR"
    try:
        if stepping:
            steps_until(w, lambda: split_at_stop(w), what)
        else:
            wait_for(lambda: split_at_stop(w), what)
    except AssertionError as exc:
        programs = [c.text for c in w.sim.ur.commands() if c.kind is CommandKind.PROGRAM]
        raise AssertionError(f"{exc}; after the last motion: {after_motion(w)}; "
                             f"the program's log: {programs[-3:]}") from None
    # what the daemon sent right after the stop arrives a little later: look again then
    cycles = w.daemon.cycles
    if stepping:
        step(w, 10)
    else:
        wait_for(lambda: w.daemon.cycles >= cycles + 50, "the loop to run on")
    split = split_at_stop(w)
    assert split is not None, f"motion after the stop: {w.arm_log()[-20:]}"
    rest, stops = split
    acc = w.cfg.arm.speedj_acceleration
    assert acc != pytest.approx(STOP_DECELERATION)  # else a hold's zero passes for a stop
    for c in rest:
        assert (c.kind is CommandKind.SPEEDJ and not any(c.qd)
                and c.acceleration == pytest.approx(acc)), split
    for c in stops:
        if c.kind is CommandKind.SPEED_STOP:
            assert c.deceleration == pytest.approx(STOP_DECELERATION), split
        else:
            assert not any(c.qd) and c.acceleration == pytest.approx(STOP_DECELERATION), split


def assert_base_stopped(w: World) -> None:
    """After motion, every drive's last target is zero, and no drive is left enabled
    (in FAULT the daemon sends the drives nothing more)."""
    drives = w.sim.drives
    ids = w.cfg.base.canopen.node_ids
    assert any(c for n in ids for _t, c in drives.command_log(n)), "the base never moved"
    steps_until(w, lambda: all(drives.command_log(n)[-1][1] == 0 for n in ids)
                and not any(drives.target_counts()), "zero targets at the drives")
    steps_until(w, lambda: all(s.state != "OPERATION ENABLED" for s in drives.states()),
                "the drives disabled")


def refused_while(w: World, cause: FaultCause) -> None:
    step(w, 3)
    assert cause.value in conditions(w)
    with pytest.raises(EnableRefused, match=cause.value):
        w.daemon.call("enable")
    assert w.daemon.safety.state is SafetyState.FAULT


@pytest.mark.parametrize(("fault", "cause"), [
    ("wrench_over_limit", FaultCause.WRENCH_LIMIT),
    ("arm_protective_stop", FaultCause.ARM_PROTECTIVE_STOP),
])
def test_a_fault_stops_the_fakes_and_refuses_until_gone(world: World, fault: str,
                                                       cause: FaultCause) -> None:
    arm_and_push(world)
    detect(world, lambda: world.sim.inject(fault), cause)
    assert_arm_stopped(world)
    assert_base_stopped(world)
    refused_while(world, cause)
    world.sim.inject(fault, on=False)
    step(world, 3)
    assert world.daemon.safety.latched is cause  # until the operator enables
    arm_and_push(world)
    world.daemon.call("disable")


def test_a_drive_fault_is_reset_by_the_operators_enable(world: World) -> None:
    arm_and_push(world)
    detect(world, lambda: world.sim.inject("drive_fault"), FaultCause.DRIVE_FAULT,
           found_by_twist=True)
    assert_arm_stopped(world)
    assert_base_stopped(world)
    step(world, 3)
    # the transport latches it until its enable (a CiA 402 fault reset) succeeds
    assert conditions(world) == {"drive_fault"}
    assert world.daemon.safety.latched is FaultCause.DRIVE_FAULT
    arm_and_push(world, latched=frozenset({"drive_fault"}))  # the enable resets the drive
    world.daemon.call("disable")


def test_a_dead_arm_controller_refuses_until_it_is_back(own_world: World) -> None:
    """The fake controller's process is killed (no arm log to read any more); the
    re-arm after it is back is the scripted matrix's (arm_disconnected)."""
    w = own_world
    arm_and_push(w)
    detect(w, lambda: w.sim.inject("arm_disconnected"), FaultCause.ARM_DISCONNECTED)
    assert_base_stopped(w)
    with pytest.raises(MmctlError, match="refused to enable: the arm did not reconnect"):
        w.daemon.call("enable")  # nothing answers: the reconnect fails
    assert w.daemon.safety.latched is FaultCause.ARM_DISCONNECTED
    step(w, 3)
    assert "arm_disconnected" in conditions(w)


def test_a_fault_after_the_arm_hold_stops_after_its_zero_commands(own_world: World) -> None:
    """The fake controller's stream freezes while the arm moves: after
    ``arm.hold_cycles`` repeated samples the hold brakes the command to zero (speedJ(0)
    at the normal acceleration, still armed); then a fault, whose stop (speedJ(0) at
    the stop deceleration: the newest sample is stale) arrives after those zeros and
    nothing after it.  A stream that stalls on a loaded machine does the same to the
    real loop's test below.  (Frozen for less than ur_rtde's own 2.5 s timeout.)"""
    w = own_world
    arm_and_push(w)
    w.sim.ur.freeze_stream(True)
    try:
        steps_until(w, lambda: any(not any(c.qd) for c in after_motion(w)),
                    "the arm hold's zero speedJ", timeout=2.0)
        detect(w, lambda: w.sim.inject("wrench_over_limit"), FaultCause.WRENCH_LIMIT)
    finally:
        w.sim.ur.freeze_stream(False)
        w.sim.inject("wrench_over_limit", on=False)
    assert_arm_stopped(w)
    split = split_at_stop(w)
    assert split is not None and split[0], split  # the hold's zeros came before the stop
    assert split[1][0].kind is CommandKind.SPEEDJ, split  # unfit for speedStop: stale


def test_loop_overruns_on_the_real_loop(own_world: World) -> None:
    """The loop thread runs; a slow per-cycle hook then overruns every deadline until
    ``loop.max_consecutive_misses`` cycles in a row have."""
    w = own_world
    d = w.daemon
    steps_until(w, lambda: not conditions(w), "a healthy cycle")
    slow = threading.Event()
    d.start()
    d.sample_hook = lambda *_: time.sleep(0.008) if slow.is_set() else None
    wait_for(lambda: d.cycles > 50, "the loop to run")
    enable_eventually(w, stepping=False)
    w.sim.set_push(PUSH)
    wait_for(lambda: moving(w.arm_log()[-3:]), "motion at the fake UR")
    assert d.safety.armed, d.safety.as_dict()
    with capture_logs() as logs:
        slow.set()
        wait_for(lambda: d.safety.state is SafetyState.FAULT, "the overrun fault")
        slow.clear()
    speed_j = d.commands_sent["speed_j"]  # the fault's cycle sends none: FAULT is seen first
    w.sim.set_push(None)
    assert d.safety.latched is FaultCause.LOOP_OVERRUN, d.safety.as_dict()
    faults = [e for e in logs if e["event"] == "fault"]
    assert [e["cause"] for e in faults] == ["loop_overrun"]
    assert faults[0]["consecutive"] == w.cfg.loop.max_consecutive_misses
    assert_arm_stopped(w, stepping=False)
    wait_for(lambda: not any(w.sim.drives.target_counts()), "zero wheel targets")
    assert d.commands_sent["speed_j"] == speed_j  # none since the fault, whatever arrived
    # on time again: the enable is accepted
    wait_for(lambda: not d.safety.active, "the loop on time again")
    enable_eventually(w, stepping=False)  # a loop_overrun refusal fails
    assert d.safety.armed
    d.call("disable")
