"""Every SPEC §5 fault, injected through the fakes, stops the robot in the same cycle.

One daemon runs in-process next to the simulated robot's fakes (fake UR controller
process, fake CAN sensor and CiA 402 drives on python-can's in-process virtual bus: the
test steps the daemon by hand, so the fakes' threads cannot disturb its timing)
through the real transports; the tests drive it cycle by
cycle with ``Daemon.step_once`` so that "within one period" is checked on the fakes'
command logs, not on a clock: the cycle that detects the fault sends no speedJ and no
base twist, and the first arm command the fake UR receives from that cycle on is a
stop (speedStop, or speedJ to zero when the link is unfit for speedStop).  Each fault
must log one ``fault`` event naming its cause, and enabling must be refused while the
cause persists.  The last test runs the real loop thread and overruns it.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

from mmctl.config import Config, config_from_dict
from mmctl.errors import FaultCause, MmctlError
from mmctl.runtime.daemon import Daemon
from mmctl.runtime.factory import create_daemon
from mmctl.runtime.safety import EnableRefused, SafetyState
from mmctl.sim.fake_ur import CommandKind
from mmctl.sim.world import SimWorld
from mmctl.types import Wrench
from waiting import wait_for

pytestmark = pytest.mark.timeout(600)

PUSH = [15.0, 0.0, 0.0]  # [N] world frame: the arm moves, speedJ commands are non-zero
Q_SINGULAR = [0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]  # stretched up, wrist aligned
_uid = itertools.count()


def _host() -> str:
    digits = "".join(ch for ch in os.environ.get("PYTEST_XDIST_WORKER", "gw0") if ch.isdigit())
    return f"127.{10 + int(digits or 0)}.201.{next(_uid) + 2}"


@dataclass
class World:
    cfg: Config
    daemon: Daemon
    sim: SimWorld

    def arm_log(self) -> list[Any]:
        kinds = (CommandKind.SPEEDJ, CommandKind.SPEED_STOP)
        return [c for c in self.sim.ur.commands() if c.kind in kinds]

    def sent(self) -> int:
        """Arm commands the daemon sent (speedJ + stops) so far."""
        c = self.daemon.commands_sent
        return c["speed_j"] + c["stop"]


def until(get: Callable[[], Any], ok: Callable[[Any], bool], what: str,
          timeout: float = 60.0) -> Any:
    """Poll ``get()`` until ``ok(value)``; return that value."""
    box: list[Any] = []
    wait_for(lambda: (box.append(get()), ok(box[-1]))[1], what, timeout)
    return box[-1]


def settled_offset(w: World) -> int:
    """Fake-log length minus commands the daemon counted, once the fake has received
    everything (the daemon is not stepping meanwhile): earlier tests may have counted
    stops that a dead link never delivered."""
    last = -1
    while True:
        n = len(w.arm_log())
        if n == last:
            return n - w.sent()
        last = n
        time.sleep(0.05)


def step(w: World, n: int = 1) -> None:
    for _ in range(n):
        w.daemon.step_once()
        time.sleep(0.002)  # let the fakes stream a new sample (one RTDE period)


def conditions(w: World) -> set[str]:
    return {c.value for c in w.daemon.last_conditions}


#: Conditions only an enable can clear: the base transport latches its faults until its
#: enable() (a CiA 402 fault reset); the arm's link ones need the reconnect enable does.
ENABLE_CLEARS = {"drive_fault", "drive_heartbeat_lost", "base_link_lost",
                 "arm_not_playing", "arm_disconnected", "arm_timestamp_stale"}


def arm_until_ok(w: World) -> None:
    """Step until no condition is present (but those only an enable can clear), then
    enable; retry while one flickers (a loaded machine)."""
    for _ in range(20):
        wait_for(lambda: (step(w), conditions(w) <= ENABLE_CLEARS)[1], "a healthy cycle", 60.0)
        try:
            w.daemon.call("enable")
            return
        except MmctlError:
            continue
    raise AssertionError(f"could not enable: {conditions(w)}")


@pytest.fixture(scope="module")
def world() -> Iterator[World]:
    uid = next(_uid)
    cfg = config_from_dict({
        "name": "fault-tests",
        "sim": {"enabled": True, "human": False, "auto_enable": False},
        # these tests step the daemon by hand, with pauses between the steps: the
        # controller's watchdog (its own test: test_stop_path) and the drives' at 1 s
        "arm": {"host": _host(), "stale_cycles": 50, "watchdog_min_frequency": 1.0},
        "sensor": {"transport": "can", "can": {"interface": "virtual", "channel": f"flt-s-{uid}"},
                   "wrench": {"stale_timeout": 0.1}},
        "base": {"transport": "canopen", "canopen": {
            "interface": "virtual", "channel": f"flt-b-{uid}", "heartbeat_timeout": 0.5},
                 "command_watchdog": 1.0},
    })
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
        wait_for(lambda: (step(w), not daemon.core.taring)[1], "the tare")
        yield w
    finally:
        daemon.shutdown()
        sim.close()


#: Causes a loaded 2-core machine can produce on its own (a starved fake or thread).
LOAD_FLAKES = {FaultCause.SENSOR_STALE, FaultCause.DRIVE_HEARTBEAT, FaultCause.ARM_STALE,
               FaultCause.LOOP_OVERRUN}


def inject_and_detect(w: World, inject: Callable[[], None], cause: FaultCause,
                      clear: Callable[[], None] | None = None, link_alive: bool = True,
                      deaf_drive: int | None = None) -> None:
    """Arm, push, inject, step to the fault; assert the stop went out in that cycle.

    If the machine's load trips another (staleness) fault first, clear the injection
    and try again: the assertions are about the injected cause.
    """
    d = w.daemon
    for _attempt in range(4):
        arm_until_ok(w)
        w.sim.set_push(PUSH)
        step(w, 5)
        if d.safety.state is not SafetyState.ARMED:
            assert d.safety.latched in LOAD_FLAKES, d.safety.as_dict()
            continue
        offset = settled_offset(w) if link_alive else 0
        inject()
        detected = False
        deadline = time.monotonic() + 60.0
        with capture_logs() as logs:
            while time.monotonic() < deadline:
                before_arm, before_twist = w.sent(), d.commands_sent["twist"]
                d.step_once()
                if d.safety.state is SafetyState.FAULT:
                    detected = True
                    break
                time.sleep(0.002)
        assert detected, f"{cause.value} not detected; conditions {conditions(w)}"
        if d.safety.latched is cause or d.safety.latched not in LOAD_FLAKES or clear is None:
            break
        clear()  # the load won the race: undo the injection and start over
    faults = [e for e in logs if e["event"] == "fault"]
    assert [e["cause"] for e in faults] == [cause.value], logs
    assert d.safety.latched is cause
    # The detecting cycle ended with the stop.  A fault found while reading sends no
    # motion at all; one found by a send itself (a drive that fails between the read
    # and send_twist, a link that dies between the read and speedJ) may follow that
    # cycle's own speedJ/twist, and the same cycle stops both devices.
    in_cycle = w.sent() - before_arm
    assert d.commands_sent["stop"] >= 1 and in_cycle in (1, 2)
    if in_cycle == 1:
        assert d.commands_sent["twist"] == before_twist
    w.sim.set_push(None)
    if link_alive and cause is FaultCause.ARM_STALE:
        # the arm's process stops the arm itself (speedJ(0), the stop deceleration) and
        # ends before ur_rtde's own reconnect: what the daemon sent after that child's
        # last read never reached the controller
        settled_offset(w)
        log = w.arm_log()
        assert log[-1].kind is CommandKind.SPEEDJ and not any(log[-1].qd), log[-3:]
        assert log[-1].acceleration == pytest.approx(w.cfg.arm.stop_deceleration)
        assert len(log) <= before_arm + offset + in_cycle + 1
    elif link_alive:
        k = before_arm + offset  # the detecting cycle's first command in the fake's log
        end = k + in_cycle
        log = until(w.arm_log, lambda lg: len(lg) >= end, "the stop at the fake UR")
        assert len(log) == end, "the fake received commands the daemon did not send"
        assert log[k - 1].kind is CommandKind.SPEEDJ
        assert any(abs(x) > 1e-6 for x in log[k - 1].qd), "expected motion before the fault"
        stop = log[end - 1]  # the cycle's last command; nothing follows it
        if stop.kind is CommandKind.SPEED_STOP:
            assert stop.deceleration == pytest.approx(w.cfg.arm.stop_deceleration)
        else:  # arm in a safety stop / stale: speedJ(0) with the stop deceleration
            assert stop.kind is CommandKind.SPEEDJ and not any(stop.qd)
            assert stop.acceleration == pytest.approx(w.cfg.arm.stop_deceleration)
    # The base: zero target on every drive that still listens.
    ids = [n for n in w.cfg.base.canopen.node_ids if n != deaf_drive]
    wait_for(lambda: all(w.sim.drives.command_log(n)[-1][1] == 0 for n in ids),
             "zero wheel targets")
    for n in ids:
        assert int(w.sim.drives.node(n).sdo[0x60FF].raw) == 0


def refused_while(w: World, cause: FaultCause) -> None:
    step(w, 3)
    assert cause.value in conditions(w)
    with pytest.raises(EnableRefused, match=cause.value):
        w.daemon.call("enable")
    assert w.daemon.safety.state is SafetyState.FAULT


SENSOR_CASES = [
    ("sensor_silent", FaultCause.SENSOR_STALE),
    ("sensor_status", FaultCause.SENSOR_STATUS),
    ("sensor_saturation", FaultCause.SENSOR_SATURATION),
    ("wrench_over_limit", FaultCause.WRENCH_LIMIT),
    ("arm_protective_stop", FaultCause.ARM_PROTECTIVE_STOP),
    ("arm_emergency_stop", FaultCause.ARM_EMERGENCY_STOP),
    ("drive_silent", FaultCause.DRIVE_HEARTBEAT),
    ("sensor_garbage", FaultCause.SENSOR_LINK),
]


@pytest.mark.parametrize(("fault", "cause"), SENSOR_CASES, ids=[c[0] for c in SENSOR_CASES])
def test_fault_stops_within_the_cycle_and_latches(world: World, fault: str,
                                                  cause: FaultCause) -> None:
    deaf = world.cfg.base.canopen.node_ids[0] if fault == "drive_silent" else None
    inject_and_detect(world, lambda: world.sim.inject(fault), cause,
                      clear=lambda: world.sim.inject(fault, on=False), deaf_drive=deaf)
    refused_while(world, cause)
    world.sim.inject(fault, on=False)
    arm_until_ok(world)
    assert world.daemon.safety.armed
    world.daemon.call("disable")


@pytest.mark.parametrize("fault", ["drive_fault", "drive_reboot"])
def test_drive_fault_is_reset_by_the_operators_enable(world: World, fault: str) -> None:
    """A drive in FAULT, or one that rebooted (a power glitch: its objects back at their
    defaults): a drive fault, latched; the operator's enable resets or reconfigures it."""
    # a rebooted drive waits in PRE-OPERATIONAL: it takes no RPDO until reconfigured
    deaf = world.cfg.base.canopen.node_ids[0] if fault == "drive_reboot" else None
    inject_and_detect(world, lambda: world.sim.inject(fault), FaultCause.DRIVE_FAULT,
                      clear=lambda: None, deaf_drive=deaf)
    step(world, 2)
    assert world.daemon.safety.state is SafetyState.FAULT  # latched until the operator acts
    arm_until_ok(world)  # enable = CiA 402 fault reset; the fake drive recovers
    assert world.daemon.safety.armed
    world.daemon.call("disable")


def test_arm_not_playing_is_fixed_by_reconnecting_on_enable(world: World) -> None:
    # With the program stopped the controller executes nothing: no arm log to check.
    inject_and_detect(world, lambda: world.sim.inject("arm_not_playing"),
                      FaultCause.ARM_NOT_PLAYING, clear=lambda: None, link_alive=False)
    step(world, 2)
    assert world.daemon.safety.state is SafetyState.FAULT
    arm_until_ok(world)  # reconnect re-uploads the control script: PLAYING again
    assert world.daemon.safety.armed
    world.daemon.call("disable")


@pytest.mark.parametrize(("fault", "cause", "alive"), [
    ("arm_frozen", FaultCause.ARM_STALE, True),
    ("arm_disconnected", FaultCause.ARM_DISCONNECTED, False),
])
def test_arm_link_faults_refuse_until_the_link_is_back(world: World, fault: str,
                                                       cause: FaultCause, alive: bool) -> None:
    inject_and_detect(world, lambda: world.sim.inject(fault), cause,
                      clear=lambda: world.sim.inject(fault, on=False), link_alive=alive)
    step(world, 2)
    with pytest.raises(MmctlError, match="refused to enable"):
        world.daemon.call("enable")  # the reconnect finds no streaming controller
    assert world.daemon.safety.state is SafetyState.FAULT
    world.sim.inject(fault, on=False)
    arm_until_ok(world)
    assert world.daemon.safety.armed
    world.daemon.call("disable")


def test_singular_configuration(world: World) -> None:
    q_des = list(world.cfg.robot.q_des)
    inject_and_detect(world, lambda: world.sim.ur.set_q(Q_SINGULAR), FaultCause.SINGULAR,
                      clear=lambda: world.sim.ur.set_q(q_des))
    refused_while(world, FaultCause.SINGULAR)
    world.sim.ur.set_q(q_des)
    arm_until_ok(world)
    world.daemon.call("disable")


class NaNSensor:
    """The real CAN sensor transport, with NaN written into its samples on demand.

    The CAN gauges are int16 and the client refuses a non-finite calibration, so no
    fake can put a NaN on this wire; this peer corrupts the decoded sample instead.
    """

    def __init__(self, inner: Any):
        self.inner = inner
        self.nan = False

    def read(self) -> Wrench:
        w = self.inner.read()
        if self.nan:
            return w._replace(force=np.array([np.nan, 0.0, 0.0]))
        return w

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def test_nan_in_the_wrench(world: World) -> None:
    devices = world.daemon.devices
    peer = NaNSensor(devices.sensor)
    devices.sensor = peer  # type: ignore[assignment]
    try:
        inject_and_detect(world, lambda: setattr(peer, "nan", True), FaultCause.NON_FINITE,
                          clear=lambda: setattr(peer, "nan", False))
        refused_while(world, FaultCause.NON_FINITE)
        peer.nan = False
        arm_until_ok(world)
        world.daemon.call("disable")
    finally:
        devices.sensor = peer.inner


def test_the_sample_hook_runs_after_the_stop_decision_and_before_the_motion_commands(
        world: World) -> None:
    """Telemetry goes before speedJ and the base twist (whose frames wake the device
    threads); a stop is decided, and sent, before it."""
    d = world.daemon
    seen: list[tuple[dict[str, int], str]] = []
    arm_until_ok(world)
    world.sim.set_push(PUSH)
    d.sample_hook = lambda r, cycle, t, safety: seen.append((dict(d.commands_sent), safety))
    checked = 0
    try:
        for _ in range(20):
            before = dict(d.commands_sent)
            seen.clear()
            d.step_once()
            if d.safety.state is not SafetyState.ARMED:
                break  # a load flake stopped the robot: the cycles before still count
            (at_hook, safety), = seen
            assert safety == "armed"
            assert at_hook == before  # nothing of this cycle sent yet when the hook ran
            assert d.commands_sent["speed_j"] == before["speed_j"] + 1  # then speedJ went out
            checked += 1
            time.sleep(0.002)
    finally:
        d.sample_hook = None
        world.sim.set_push(None)
        if d.safety.armed:
            d.call("disable")
    assert checked >= 1


def test_loop_overrun_budget_on_the_real_loop(world: World) -> None:
    """Last: starts the loop thread, then a slow per-cycle hook overruns every deadline."""
    d = world.daemon
    arm_until_ok(world)
    d.call("disable")
    slow = threading.Event()
    d.start()
    d.sample_hook = lambda *_: time.sleep(0.008) if slow.is_set() else None
    wait_for(lambda: d.cycles > 50, "the loop to run")
    arm = wait_for(lambda: _try_enable(d), "enable on the loop", 60.0)
    assert arm
    world.sim.set_push(PUSH)
    with capture_logs() as logs:
        slow.set()
        wait_for(lambda: d.safety.state is SafetyState.FAULT, "the overrun fault")
        slow.clear()
    world.sim.set_push(None)
    assert d.safety.latched is FaultCause.LOOP_OVERRUN, d.safety.as_dict()
    assert [e["cause"] for e in logs if e["event"] == "fault"] == ["loop_overrun"]
    # The stop reached the fake UR: after the last speedJ with motion, only stops.
    settled_offset(world)  # in FAULT the loop sends the arm nothing more
    log = world.arm_log()
    tail = log[max(i for i, c in enumerate(log) if c.kind is CommandKind.SPEEDJ and any(c.qd))
               + 1:]
    assert tail and all(c.kind is CommandKind.SPEED_STOP or not any(c.qd) for c in tail)
    wait_for(lambda: not any(world.sim.drives.target_counts()), "zero wheel targets")
    # On time again: the budget resets on enable.
    wait_for(lambda: _try_enable(d), "re-enable after the overrun")
    d.call("disable")


def _try_enable(d: Daemon) -> bool:
    try:
        d.call("enable")
        return True
    except MmctlError:
        return False
