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
from collections.abc import Iterator

import numpy as np
import pytest

from mmctl.config import config_from_dict
from mmctl.errors import FaultCause, SafetyFault
from mmctl.sim.fake_ur import CommandKind, FakeURController, start_fake_ur
from mmctl.transports.arm import Arm
from mmctl.transports.ur_rtde_process import UrRtdeProcessArm

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
                assert fault is not None and fault.cause is FaultCause.ARM_STALE, fault
                time.sleep(3.5)
            finally:
                fake.freeze_stream(False)
            time.sleep(0.5)
            with pytest.raises(SafetyFault) as info:
                arm.read_state()
            assert info.value.cause is FaultCause.ARM_DISCONNECTED  # the child ended itself
            with pytest.raises(ProcessLookupError):
                os.kill(child, 0)  # type: ignore[arg-type]
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
