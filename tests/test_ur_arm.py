"""UrRtdeArm: the real ur_rtde client against the fake UR controller (its own process).

Fault latency is counted in read_state cycles, never timed.  The fake records the
controller time at which an injected fault took effect; every sample newer than that
carries the fault, so "detected on the first sample that shows it" is checkable
exactly.  STALE = arm.stale_cycles in these tests (generous, so a loaded 2-core
machine that stalls the fake for a few ms cannot fake a frozen stream).
"""

from __future__ import annotations

import random
import time
from collections.abc import Iterator

import numpy as np
import pytest

from mmctl.config import config_from_dict
from mmctl.errors import FaultCause, SafetyFault, TransportError
from mmctl.sim.fake_ur import CommandKind, FakeURController, start_fake_ur
from mmctl.transports.arm import Arm
from mmctl.transports.ur_rtde_arm import UrRtdeArm
from mmctl.types import ArmState

PERIOD = 0.002
STALE = 250  # 0.5 s: a loaded machine starves the fake UR's process for tens of ms
Q0 = [0.2, -1.6, 1.5, -1.4, -1.57, 0.1]
pytestmark = pytest.mark.timeout(120)


def unused_host() -> str:
    """A loopback address nobody serves on (random: other test runs share the machine)."""
    return f"127.{random.randint(100, 254)}.{random.randint(0, 255)}.{random.randint(2, 254)}"


def make_arm(host: str, **arm: object) -> UrRtdeArm:
    """watchdog_min_frequency 2 Hz unless given: a test process that a loaded machine
    stalls for 100 ms must not have its program stopped by the controller."""
    arm = {"stale_cycles": STALE, "watchdog_min_frequency": 2.0, **arm}
    cfg = config_from_dict({"arm": {"host": host, **arm}})
    return UrRtdeArm.from_config(cfg)


@pytest.fixture
def fake(loopback_host: str) -> Iterator[FakeURController]:
    with start_fake_ur(loopback_host, q_init=Q0) as f:
        yield f


@pytest.fixture
def arm(fake: FakeURController) -> Iterator[UrRtdeArm]:
    a = make_arm(fake.host)
    a.connect()
    yield a
    a.close()


class Cycles:
    """A 500 Hz loop for tests: after a stall it resynchronises instead of bursting
    (a burst of reads would all see the same sample and look like a frozen stream)."""

    def __init__(self) -> None:
        self.next = time.perf_counter()

    def wait(self) -> None:
        self.next += PERIOD
        now = time.perf_counter()
        if now < self.next:
            time.sleep(self.next - now)
        elif now - self.next > PERIOD:
            self.next = now


def fresh_state(arm: UrRtdeArm, limit: int = 5000) -> ArmState:
    """read_state until a new sample arrives (so that stop() may use speedStop).  The
    receive interface's first samples may predate the control script's start (not yet
    PLAYING on a loaded machine): the first healthy one counts."""
    first = wait_healthy(arm, limit)
    clock = Cycles()
    for _ in range(limit):
        clock.wait()
        s = arm.read_state()
        if s.controller_time != first.controller_time:
            return s
    raise AssertionError("no new sample")


def run_until_fault(arm: UrRtdeArm, qd: np.ndarray | None = None,
                    limit: int = 5000) -> tuple[SafetyFault, list[ArmState]]:
    """read_state (+ speed_j) each cycle until one raises; the states read."""
    states: list[ArmState] = []
    clock = Cycles()
    for _ in range(limit):
        try:
            states.append(arm.read_state())
            if qd is not None:
                arm.speed_j(qd)  # raises too once the link is found broken
        except SafetyFault as fault:
            return fault, states
        clock.wait()
    raise AssertionError(f"no fault within {limit} cycles")


def wait_commands(fake: FakeURController, kind: CommandKind, count: int,
                  timeout: float = 20.0) -> list:  # type: ignore[type-arg]
    """The log entries of ``kind`` once there are at least ``count`` (the socket and the
    control pipe are different channels: the log may lag what the client sent)."""
    deadline = time.monotonic() + timeout
    while len(got := fake.commands(kind)) < count:
        assert time.monotonic() < deadline, f"fewer than {count} {kind.value} commands"
        time.sleep(0.005)
    return got


def wait_healthy(arm: UrRtdeArm, limit: int = 5000) -> ArmState:
    clock = Cycles()
    for _ in range(limit):
        try:
            return arm.read_state()
        except SafetyFault:
            clock.wait()
    raise AssertionError("the arm did not become healthy")


def test_is_an_arm() -> None:
    assert isinstance(make_arm("127.0.0.1"), Arm)


def test_speedj_loop_moves_joints_by_the_integral_and_speed_stop_rests(
        fake: FakeURController, arm: UrRtdeArm) -> None:
    qd = np.array([0.3, -0.2, 0.25, 0.0, 0.1, -0.3])
    start = fresh_state(arm)
    states = [start]
    clock = Cycles()
    for _ in range(600):  # >= 1 s at 500 Hz
        arm.speed_j(qd, 4.0, PERIOD)
        clock.wait()
        states.append(arm.read_state())
    samples = {s.controller_time: s for s in states}  # distinct samples, in time order
    t = np.array(sorted(samples))
    q = np.array([samples[k].q for k in t])
    v = np.array([samples[k].qd for k in t])
    assert t[-1] - t[0] >= 1.0
    moved = q[-1] - q[0]
    integral = (0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None]).sum(axis=0)  # ∫ q̇ dt
    np.testing.assert_allclose(moved, integral, atol=2e-3)
    # and against the command: the ramp (0.3 rad/s at 4 rad/s^2) costs < 0.1 s of travel
    np.testing.assert_allclose(moved, qd * (t[-1] - t[0]), atol=0.1 * 0.3 + 1e-3)
    np.testing.assert_allclose(v[-1], qd, atol=1e-12)
    np.testing.assert_allclose(fake.state().qd, qd, atol=1e-12)

    fresh_state(arm)
    arm.stop(7.5)
    clock = Cycles()
    for _ in range(5000):
        s = arm.read_state()
        if not s.qd.any():
            break
        clock.wait()
    assert not s.qd.any()
    rest = fake.state()
    assert not rest.qd.any() and rest.q.tolist() == pytest.approx(s.q.tolist(), abs=1e-12)
    [stop] = wait_commands(fake, CommandKind.SPEED_STOP, 1)
    assert stop.deceleration == 7.5
    speedj = fake.commands(CommandKind.SPEEDJ)
    assert len(speedj) >= 600 and all(c.qd == pytest.approx(qd) for c in speedj)
    assert all((c.acceleration, c.time) == (4.0, PERIOD) for c in speedj)


def test_the_speed_slider_is_read_through_rtde_and_slows_speedj(
        fake: FakeURController, arm: UrRtdeArm) -> None:
    """The pendant's speed slider at 40 %: ur_rtde reads target_speed_fraction (times
    speed_scaling) into ArmState.speed_scaling, and the fake controller runs a speedJ at
    40 % of its speeds, as a UR does."""
    assert fresh_state(arm).speed_scaling == 1.0
    fake.set_speed_slider(0.4)
    clock = Cycles()
    qd = np.array([0.3, -0.2, 0.0, 0.0, 0.1, 0.0])
    for _ in range(400):  # 0.8 s: well past the ramp (0.12 rad/s at 4 rad/s^2)
        arm.speed_j(qd, 4.0, PERIOD)
        clock.wait()
        s = arm.read_state()
    assert s.speed_scaling == pytest.approx(0.4)
    np.testing.assert_allclose(fake.state().qd, 0.4 * qd, atol=1e-12)
    fake.set_speed_slider(1.0)
    for _ in range(400):
        arm.speed_j(qd, 4.0, PERIOD)
        clock.wait()
        s = arm.read_state()
    assert s.speed_scaling == 1.0
    np.testing.assert_allclose(fake.state().qd, qd, atol=1e-12)
    with pytest.raises(ValueError, match="fraction 0..1"):
        fake.set_speed_slider(1.5)


def test_speedj_is_clamped_to_the_joint_speed_limits(fake: FakeURController,
                                                     arm: UrRtdeArm) -> None:
    limits = np.array(arm.joint_speed_limits)  # 120 deg/s base/shoulder, 180 deg/s others
    fresh_state(arm)
    n0 = len(fake.commands(CommandKind.SPEEDJ))
    wanted = np.array([3.0, 0.5, 0.0, 0.0, 0.0, -4.0])
    arm.speed_j(wanted, 100.0)
    arm.speed_j(limits * 0.5)
    sent, within = wait_commands(fake, CommandKind.SPEEDJ, n0 + 2)[n0:]
    got = np.array(sent.qd)
    assert np.abs(got / limits).max() == pytest.approx(1.0)  # the leading joint at its limit
    np.testing.assert_allclose(got, wanted * (limits[0] / 3.0))  # direction kept
    assert sent.acceleration == 40.0  # ur_rtde's maximum
    np.testing.assert_allclose(within.qd, limits * 0.5)  # within limits: untouched
    assert within.acceleration == arm.config.speedj_acceleration
    with pytest.raises(SafetyFault) as bad:
        arm.speed_j(np.array([0.1, np.nan, 0, 0, 0, 0]))
    assert bad.value.cause is FaultCause.NON_FINITE
    with pytest.raises(SafetyFault):
        arm.speed_j(np.zeros(6), np.inf)
    assert len(fake.commands(CommandKind.SPEEDJ)) == n0 + 2  # nothing sent


@pytest.mark.parametrize("inject, clear, cause", [
    ("set_protective_stop", "set_protective_stop", FaultCause.ARM_PROTECTIVE_STOP),
    ("set_emergency_stop", "set_emergency_stop", FaultCause.ARM_EMERGENCY_STOP),
])
def test_safety_stop_is_detected_on_the_first_sample_that_shows_it(
        fake: FakeURController, arm: UrRtdeArm, inject: str, clear: str,
        cause: FaultCause) -> None:
    qd = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.2])
    fresh_state(arm)
    arm.kick_watchdog()  # set while healthy, as the daemon's idle cycles do
    t_fault = getattr(fake, inject)(True)
    fault, states = run_until_fault(arm, qd)
    assert fault.cause is cause
    assert all(s.controller_time <= t_fault for s in states)  # none missed the fault
    # raised on its first sample (the one stamped at the injection may already carry it;
    # a later one would have shown up in ``states`` above, stamped after t_fault)
    assert fault.details["controller_time"] >= t_fault
    print(f"{cause.value}: {len(states)} cycles from injection to detection "
          "(0 after the first sample carrying it)")
    arm.stop()  # never blocks: speedJ(0) since the arm is not healthy
    clock = Cycles()
    for _ in range(50):
        with pytest.raises(SafetyFault):
            arm.read_state()
        arm.speed_j(qd)  # ignored by the controller in a safety stop
        clock.wait()
    assert not fake.state().qd.any()
    getattr(fake, clear)(False)
    wait_healthy(arm)
    for _ in range(100):
        arm.read_state()
        arm.speed_j(qd)
        clock.wait()
    assert fake.state().qd[5] > 0.0  # moves again without a reconnect


def test_controller_watchdog_stops_the_arm_when_the_client_goes_quiet(
        fake: FakeURController) -> None:
    """A daemon that stops talking (hung, SIGSTOPped, dead) leaves the arm at rest:
    the first speedJ sets the script's RTDE watchdog; when the packages stop, the
    controller stops the program and the joints within 1/f plus the braking time."""
    # 4 Hz (0.25 s): a loaded machine's stall of the test's own client while it still
    # commands must not trip the watchdog before the client goes quiet on purpose
    arm = make_arm(fake.host, watchdog_min_frequency=4.0)
    arm.connect()
    try:
        fresh_state(arm)
        qd = np.array([0.5, 0.0, 0.0, 0.0, 0.0, 0.0])
        clock = Cycles()
        for _ in range(250):
            arm.read_state()
            arm.speed_j(qd, 40.0, PERIOD)
            clock.wait()
        assert arm.watchdog_on
        # the client goes quiet: no read, no speedJ, no kick
        deadline = time.monotonic() + 30.0
        while fake.state().runtime_state == 2 or fake.state().qd.any():
            assert time.monotonic() < deadline, "the arm kept moving without commands"
            time.sleep(0.01)
        stopped = [c for c in fake.commands(CommandKind.PROGRAM)
                   if (c.text or "").startswith("stopped (rtde watchdog")]
        assert len(stopped) == 1, fake.commands(CommandKind.PROGRAM)
        last = fake.commands(CommandKind.SPEEDJ)[-1]
        assert last.qd == pytest.approx(tuple(qd))
        quiet = stopped[0].controller_time - last.controller_time
        assert 0.25 <= quiet <= 0.25 + 0.01  # 1/f after the last package, to a few periods
        print(f"program stopped {quiet * 1e3:.0f} ms after the last speedJ")
        with pytest.raises(SafetyFault) as info:
            arm.read_state()
        assert info.value.cause is FaultCause.ARM_NOT_PLAYING
    finally:
        arm.close()


def test_kicks_keep_the_program_running_without_motion(fake: FakeURController) -> None:
    arm = make_arm(fake.host, watchdog_min_frequency=1.0)
    arm.connect()
    try:
        fresh_state(arm)
        arm.kick_watchdog()  # the first kick of a connection sets the watchdog
        assert arm.watchdog_on
        [setting] = [c for c in fake.commands(CommandKind.RTDE_COMMAND) if c.code == 35]
        t_end = time.monotonic() + 3.0  # three watchdog periods of kicks only
        while time.monotonic() < t_end:
            arm.read_state()
            arm.kick_watchdog()
            time.sleep(0.01)
        assert arm.read_state().runtime_state == 2
        assert not [c for c in fake.commands(CommandKind.PROGRAM)
                    if (c.text or "").startswith("stopped")]
        assert setting.controller_time > 0
    finally:
        arm.close()


def test_program_stop_is_detected_and_reconnect_restarts_the_script(
        fake: FakeURController, arm: UrRtdeArm) -> None:
    fresh_state(arm)
    arm.kick_watchdog()  # set (speed_j would set it on a program that is already stopped)
    t_fault = fake.stop_program()
    fault, states = run_until_fault(arm, np.zeros(6))
    assert fault.cause is FaultCause.ARM_NOT_PLAYING and fault.details["runtime_state"] == 1
    assert all(s.controller_time <= t_fault for s in states)
    assert fault.details["controller_time"] > t_fault
    print(f"arm_not_playing: {len(states)} cycles from injection to detection")
    arm.stop()
    arm.reconnect()
    assert wait_healthy(arm).runtime_state == 2
    started = [c for c in fake.commands(CommandKind.PROGRAM) if c.text.startswith("started")]
    assert len(started) == 2


def test_frozen_stream_is_detected_after_stale_cycles(fake: FakeURController,
                                                       arm: UrRtdeArm) -> None:
    qd = np.array([0.1, 0, 0, 0, 0, 0])
    fresh_state(arm)
    arm.kick_watchdog()  # set while the link is fresh, as the daemon's idle cycles do
    s0 = fresh_state(arm)
    n0 = len(fake.commands(CommandKind.SPEEDJ))
    fake.freeze_stream(True)
    try:
        fault, states = run_until_fault(arm, qd)
        arm.stop(6.0)  # stale: speedJ(0, 6.0), which never waits for the controller
    finally:
        fake.freeze_stream(False)  # back within ur_rtde's own 2.5 s timeout
    assert fault.cause is FaultCause.ARM_STALE and fault.details["cycles"] == STALE, fault
    read = [s0, *states]
    last = read[-1].controller_time
    repeats = [s for s in read if s.controller_time == last]
    assert len(repeats) == STALE  # the last fresh sample, then STALE - 1 repeats, then the fault
    print(f"arm_timestamp_stale: {STALE} cycles after the last fresh sample")
    n1 = len(states) - 1 + n0  # speedJ after every read_state but the failing one
    stop = wait_commands(fake, CommandKind.SPEEDJ, n1 + 1)[-1]
    assert stop.qd == (0.0,) * 6 and stop.acceleration == 6.0
    assert fake.commands(CommandKind.SPEED_STOP) == []
    assert wait_healthy(arm).controller_time > last  # no reconnect needed


def test_close_while_the_stream_is_frozen_returns_and_reconnect_works(
        fake: FakeURController, arm: UrRtdeArm) -> None:
    """Kept well under ur_rtde's 2.5 s timeout: beyond it ur_rtde reconnects by itself
    (parked or not), which has crashed the process once the controller came back."""
    fresh_state(arm)
    fake.freeze_stream(True)
    try:
        fault, _ = run_until_fault(arm)
        assert fault.cause is FaultCause.ARM_STALE
        arm.close()  # a 0.5 s RTDE probe finds the silence: parks, does not hang
        assert not arm.connected
    finally:
        fake.freeze_stream(False)
    arm.connect()
    assert wait_healthy(arm).runtime_state == 2


def test_killed_controller_is_detected_and_reconnect_after_restart(
        fake: FakeURController, arm: UrRtdeArm) -> None:
    qd = np.array([0.0, 0.0, 0.1, 0.0, 0.0, 0.0])
    for _ in range(50):
        arm.read_state()
        arm.speed_j(qd)
        time.sleep(PERIOD)
    before = fresh_state(arm)
    fake.kill()
    # read_state only: a speedJ whose write hits the reset socket makes ur_rtde reconnect
    # in this thread while its receive thread does the same, a race that has crashed the
    # process (ur_rtde 1.6.5); see the transport's docstring.
    fault, states = run_until_fault(arm)
    assert fault.cause in (FaultCause.ARM_DISCONNECTED, FaultCause.ARM_STALE)
    repeats = sum(1 for s in states if s.controller_time == states[-1].controller_time)
    # at worst the stale rule fires: the last fresh sample and its repeats, STALE in all
    assert repeats <= STALE
    print(f"killed controller: {fault.cause.value} on cycle {len(states) + 1} after the kill")
    # stop() while ur_rtde still thinks the link up sends speedJ(0) into the reset
    # socket: the crash race above (a loaded run segfaulted in this very call, taking
    # the test worker down); what this line tests is stop() on a link ur_rtde knows is
    # down, so it waits for that first
    down = False
    deadline = time.monotonic() + 30.0
    while not down and time.monotonic() < deadline:
        try:
            arm.read_state()
        except SafetyFault as exc:
            down = exc.cause is FaultCause.ARM_DISCONNECTED
        time.sleep(PERIOD)
    if down:
        arm.stop()  # link down: nothing sent, returns at once (speedStop would hang ~300 s)
    with pytest.raises(SafetyFault) as again:
        arm.read_state()
    assert again.value.cause is FaultCause.ARM_DISCONNECTED or fault.cause is FaultCause.ARM_STALE
    fake.restart()  # a rebooted controller at the pose the old one published last
    arm.reconnect()
    s = wait_healthy(arm)
    assert s.runtime_state == 2 and s.controller_time < before.controller_time + 1.0
    np.testing.assert_allclose(s.q, fake.state().q)
    assert abs(s.q[2] - before.q[2]) < 0.05


def test_connect_failures_are_fast_and_named(loopback_host: str) -> None:
    with pytest.raises(TransportError, match="nothing answers"):
        make_arm(unused_host(), connect_timeout=0.5).connect()  # nothing listens
    with start_fake_ur(loopback_host) as fake:
        arm = make_arm(fake.host, connect_timeout=0.5)
        fake.set_remote_control(False)
        with pytest.raises(TransportError, match="remote control is off"):
            arm.connect()
        fake.set_remote_control(True)
        fake.set_protective_stop(True)
        with pytest.raises(SafetyFault) as fault:
            arm.connect()
        assert fault.value.cause is FaultCause.ARM_PROTECTIVE_STOP
        fake.set_protective_stop(False)
        fake.freeze_stream(True)
        with pytest.raises(TransportError, match="RTDE"):
            arm.connect()  # accepts but never streams: would hang ur_rtde's constructor
        assert not arm.connected
    with pytest.raises(SafetyFault) as down:
        arm.read_state()
    assert down.value.cause is FaultCause.ARM_DISCONNECTED
    arm.close()  # never connected: nothing to do
    arm.stop()
