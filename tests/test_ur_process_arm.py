"""UrRtdeProcessArm: ur_rtde in a child process, against the fake UR controller.

ur_rtde 1.6.5 crashes its process (SIGSEGV in RTDE::isDataAvailable) when the RTDE
stream stays silent for more than 2.5 s and then resumes: its control interface's
receive thread reconnects by itself and races a second receive thread.  Here the stream
freezes for longer than that; the child must end itself first, the test process (the
daemon's stand-in) must carry on, and a reconnect must give a healthy arm again.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from mmctl.config import config_from_dict
from mmctl.errors import FaultCause, SafetyFault
from mmctl.sim.fake_ur import CommandKind, FakeCommand, FakeURController, start_fake_ur
from mmctl.transports.arm import Arm
from mmctl.transports.ur_rtde_process import UrRtdeProcessArm
from waiting import wait_for

pytestmark = pytest.mark.timeout(300)
PERIOD = 0.002
Q0 = [0.2, -1.6, 1.5, -1.4, -1.57, 0.1]


@pytest.fixture
def fake(loopback_host: str) -> Iterator[FakeURController]:
    with start_fake_ur(loopback_host, q_init=Q0) as f:
        yield f


def make_arm(host: str) -> UrRtdeProcessArm:
    cfg = config_from_dict({"arm": {"host": host, "stale_cycles": 100,
                                    "watchdog_min_frequency": 2.0}})
    return UrRtdeProcessArm(cfg.arm, cfg.limits)


def cycles(arm: UrRtdeProcessArm, n: int, qd: np.ndarray | None = None) -> SafetyFault | None:
    """n loop cycles of read_state + speed_j (or a kick); the first fault, or None."""
    next_t = time.perf_counter()
    for _ in range(n):
        try:
            arm.read_state()
            if qd is None:
                arm.kick_watchdog()
            else:
                arm.speed_j(qd, 4.0, PERIOD)
        except SafetyFault as fault:
            return fault
        next_t += PERIOD
        now = time.perf_counter()
        if now < next_t:
            time.sleep(next_t - now)
        else:
            next_t = now
    return None


def healthy(arm: UrRtdeProcessArm) -> None:
    deadline = time.monotonic() + 60.0
    while cycles(arm, 50) is not None:
        assert time.monotonic() < deadline, "the arm did not become healthy"


def test_is_an_arm(fake: FakeURController) -> None:
    assert isinstance(make_arm(fake.host), Arm)


def test_motion_and_close_through_the_child(fake: FakeURController) -> None:
    arm = make_arm(fake.host)
    arm.connect()
    pid = arm.pid
    try:
        healthy(arm)
        assert cycles(arm, 300, np.array([0.3, 0, 0, 0, 0, 0])) is None
        assert fake.state().qd[0] == pytest.approx(0.3)
        assert arm.controller_version == "5.11.0.108249"
    finally:
        arm.close()
    assert arm.pid is None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # type: ignore[arg-type]
    kinds = [c.kind for c in fake.commands()]
    assert CommandKind.SPEED_STOP in kinds and CommandKind.STOP_SCRIPT in kinds
    assert not fake.state().qd.any() or fake.state().runtime_state != 2


def _ended(pid: int) -> bool:
    """The process is gone, or a zombie waiting to be reaped (it has exited)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            return any(line.startswith("State:") and "Z" in line.split()[1] for line in f)
    except OSError:
        return True


def test_a_stream_frozen_beyond_ur_rtdes_own_timeout_never_takes_the_daemon_down(
        fake: FakeURController) -> None:
    """Three times: the stream freezes for 3.5 s (ur_rtde's own reconnect would start
    after 2.5 s and crash its process when the stream resumes), then resumes."""
    arm = make_arm(fake.host)
    arm.connect()
    try:
        for _ in range(3):
            healthy(arm)
            child = arm.pid
            fake.freeze_stream(True)
            try:
                fault = cycles(arm, 5000, np.array([0.1, 0, 0, 0, 0, 0]))
                # the parent's count of stale reads comes first, unless this loop reads
                # so slowly (both cores busy) that the child's own stale fault has
                # already ended it (it sent speedJ(0) first): either way the arm stops
                assert fault is not None and (
                    fault.cause is FaultCause.ARM_STALE
                    or (fault.cause is FaultCause.ARM_DISCONNECTED
                        and "arm process ended" in str(fault))), fault
                time.sleep(3.5)
            finally:
                fake.freeze_stream(False)
            time.sleep(0.5)
            with pytest.raises(SafetyFault) as info:
                arm.read_state()
            assert info.value.cause is FaultCause.ARM_DISCONNECTED  # the child ended itself
            # (its pipe closes before its exit is through: seen still running 0.5 s after
            # the stream resumed with both cores busy; a condition, waited for)
            assert child is not None
            wait_for(lambda pid=child: _ended(pid), f"the arm's process {child} to end",
                     timeout=60.0)
            arm.reconnect()
        healthy(arm)
    finally:
        arm.close()
    stops = [c for c in fake.commands(CommandKind.SPEEDJ) if not any(c.qd)]
    assert len(stops) >= 3  # the child's speedJ(0) on each stale link


def test_a_crashed_child_is_arm_disconnected_and_reconnect_recovers(
        fake: FakeURController) -> None:
    arm = make_arm(fake.host)
    arm.connect()
    try:
        healthy(arm)
        os.kill(arm.pid, signal.SIGSEGV)  # type: ignore[arg-type]
        deadline = time.monotonic() + 30.0
        fault = None
        while fault is None:
            assert time.monotonic() < deadline
            fault = cycles(arm, 10)
        assert fault.cause is FaultCause.ARM_DISCONNECTED, fault
        assert "arm process ended" in str(fault)
        arm.reconnect()
        healthy(arm)
    finally:
        arm.close()


# -- the mailboxes (issue 28): counted, never timed -------------------------------------

def segments() -> set[str]:
    """This process's mailbox segments in /dev/shm (named mmctl-<layout>-<pid>-<random>)."""
    return {n for n in os.listdir("/dev/shm")
            if n.startswith("mmctl-ur_arm_") and f"-{os.getpid()}-" in n}


def is_stop(c: FakeCommand) -> bool:
    return c.kind is CommandKind.SPEED_STOP or (c.kind is CommandKind.SPEEDJ
                                                and c.qd is not None and not any(c.qd))


def motions(fake: FakeURController, since: int) -> list[FakeCommand]:
    """speedJ and speedStop the fake received from its log entry ``since`` on."""
    return [c for c in fake.commands() if c.seq >= since
            and c.kind in (CommandKind.SPEEDJ, CommandKind.SPEED_STOP)]


def wait_for_log(arm: UrRtdeProcessArm, fake: FakeURController, since: int,
                 pred: Callable[[FakeCommand], bool]) -> None:
    """Cycles (reads and kicks) until the fake logged a motion command ``pred`` takes."""
    deadline = time.monotonic() + 30.0
    while not any(pred(c) for c in motions(fake, since)):
        assert time.monotonic() < deadline, "the command never reached the controller"
        cycles(arm, 10)  # kicks: the controller's watchdog stays fed


def test_a_read_never_waits_for_the_child(fake: FakeURController) -> None:
    """With the child stopped (SIGSTOP), reads keep returning the newest sample at once,
    until ``stale_cycles`` reads without a new one are ARM_STALE: counted, not timed (a
    read that waited for the child would hang here)."""
    arm = make_arm(fake.host)
    arm.connect()
    try:
        healthy(arm)
        child = arm.pid
        assert child is not None
        os.kill(child, signal.SIGSTOP)
        try:
            stat = Path(f"/proc/{child}/stat")
            while stat.read_text().rsplit(")", 1)[1].split()[0] != "T":
                time.sleep(0.001)  # until it is stopped: no record after this
            times, fault = [], None
            for _ in range(10 * arm.config.stale_cycles):
                try:
                    times.append(arm.read_state().controller_time)
                except SafetyFault as exc:
                    fault = exc
                    break
        finally:
            os.kill(child, signal.SIGCONT)
        assert fault is not None and fault.cause is FaultCause.ARM_STALE, fault
        # the first read may still take a record published before the stop
        assert arm.config.stale_cycles - 1 <= len(times) <= arm.config.stale_cycles
        assert len(set(times[1:])) <= 1
        arm.reconnect()
        healthy(arm)
    finally:
        arm.close()


def test_a_burst_of_speed_j_then_stop_reaches_the_controller_stop_last(
        fake: FakeURController) -> None:
    """speed_j 200 times back to back, then stop: the child may coalesce the burst (or
    drop all of it, superseded by the stop), but nothing of it reaches the controller
    after the stop; a speed_j posted after a stop goes out after it."""
    arm = make_arm(fake.host)
    arm.connect()
    try:
        healthy(arm)
        since = fake.commands()[-1].seq + 1
        for i in range(200):
            arm.speed_j([0.01 * (1 + i % 7), 0, 0, 0, 0, 0], 4.0, PERIOD)
        arm.stop()
        wait_for_log(arm, fake, since, is_stop)
        for _ in range(50):  # anything still on its way lands now
            cycles(arm, 1, None)
        sent = motions(fake, since)
        first_stop = next(i for i, c in enumerate(sent) if is_stop(c))
        # any of the burst that went out (the child may have taken none) did so before
        assert all(is_stop(c) for c in sent[first_stop:]), sent[first_stop:]

        healthy(arm)
        since = fake.commands()[-1].seq + 1
        arm.speed_j([0.2, 0, 0, 0, 0, 0], 4.0, PERIOD)
        arm.stop()
        arm.speed_j([0.05, 0, 0, 0, 0, 0], 4.0, PERIOD)
        wait_for_log(arm, fake, since, lambda c: c.qd is not None and c.qd[0] == 0.05)
        sent = motions(fake, since)
        first_stop = next(i for i, c in enumerate(sent) if is_stop(c))
        assert sent[-1].qd is not None and sent[-1].qd[0] == 0.05
        assert first_stop < len(sent) - 1
    finally:
        arm.close()


def test_a_protective_stop_comes_back_with_its_details_on_every_read(
        fake: FakeURController) -> None:
    arm = make_arm(fake.host)
    arm.connect()
    try:
        healthy(arm)
        fake.set_protective_stop(True)
        deadline = time.monotonic() + 30.0
        fault = None
        while fault is None:
            assert time.monotonic() < deadline
            fault = cycles(arm, 10)
        assert fault.cause is FaultCause.ARM_PROTECTIVE_STOP, fault
        bits = fault.details["safety_status_bits"]
        assert isinstance(bits, int) and bits & (1 << 2)
        raised = 0
        for _ in range(20):
            try:
                arm.read_state()
            except SafetyFault as exc:
                assert exc.cause is FaultCause.ARM_PROTECTIVE_STOP
                raised += 1
            time.sleep(PERIOD)
        assert raised == 20  # while the newest record carries it
    finally:
        fake.set_protective_stop(False)
        arm.close()


def test_a_killed_child_is_arm_disconnected_and_its_segments_go_at_close(
        fake: FakeURController) -> None:
    assert not segments()
    arm = make_arm(fake.host)
    arm.connect()
    try:
        assert len(segments()) == 2  # state and commands
        healthy(arm)
        os.kill(arm.pid, signal.SIGKILL)  # type: ignore[arg-type]
        deadline = time.monotonic() + 30.0
        fault = None
        while fault is None:
            assert time.monotonic() < deadline
            fault = cycles(arm, 10)
        assert fault.cause is FaultCause.ARM_DISCONNECTED, fault
        assert "arm process ended" in str(fault)
        for command in (lambda: arm.speed_j([0.1, 0, 0, 0, 0, 0]), arm.kick_watchdog):
            with pytest.raises(SafetyFault) as info:
                command()
            assert info.value.cause is FaultCause.ARM_DISCONNECTED
        arm.stop()  # never raises
    finally:
        arm.close()
    assert not segments()
    arm.close()  # twice: nothing
    arm.connect()
    arm.close()
    assert not segments()
