"""The real SerialBase against the simulated bridge over a pseudo-terminal pair."""

from __future__ import annotations

import os
import time
import tty
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from mmctl.config import Config, config_from_dict
from mmctl.control.mecanum import wheel_matrix
from mmctl.errors import FaultCause, LinkLost, SafetyFault, TransportError
from mmctl.sim.fake_serial_bridge import FakeSerialBridge
from mmctl.transports.base.serial_base import SerialBase
from mmctl.types import Odometry

PERIOD = 0.002


def wait_until(pred: Callable[[], bool], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.002)


def cycles(base: SerialBase, twist: tuple[float, float, float], n: int) -> list[Odometry]:
    out = []
    nxt = time.monotonic()
    for _ in range(n):
        base.send_twist(*twist)
        out.append(base.read_odometry())
        nxt += PERIOD
        left = nxt - time.monotonic()
        if left > 0:
            time.sleep(left)
    return out


def settle(base: SerialBase, bridge: FakeSerialBridge) -> Odometry:
    def still() -> bool:
        base.stop()
        time.sleep(PERIOD)
        o = base.read_odometry()
        return bool(np.all(bridge.wheel_velocities() == 0.0)) and o.vx == o.vy == o.wz == 0.0

    wait_until(still)
    return base.read_odometry()


@pytest.fixture
def cfg() -> Config:
    # generous link timeout: a loaded test machine must not look like a dead link
    return config_from_dict({"base": {"serial": {"link_timeout": 5.0, "timeout": 1.0}}})


@pytest.fixture
def bridge(cfg: Config) -> Iterator[FakeSerialBridge]:
    with FakeSerialBridge(cfg) as b:
        yield b


@pytest.fixture
def base(cfg: Config, bridge: FakeSerialBridge) -> Iterator[SerialBase]:
    b = SerialBase(cfg.base, cfg.limits, port=bridge.port)
    b.connect()
    b.enable()
    yield b
    b.close()


def test_enable_twist_and_odometry(cfg: Config, bridge: FakeSerialBridge, base: SerialBase) -> None:
    assert bridge.enabled
    assert [d.state for d in base.drive_status()] == ["OPERATION ENABLED"] * 4
    twist = (0.25, -0.1, 0.5)
    cycles(base, twist, 150)
    wait_until(lambda: len(bridge.commands()) >= 150)
    want = wheel_matrix(cfg.base.mecanum) @ np.array(twist)
    last = bridge.commands()[-1][1]
    assert np.allclose(last, want, atol=1e-3)  # mrad/s resolution
    end = settle(base, bridge)
    assert (end.x, end.y, end.yaw) == pytest.approx(bridge.pose(), abs=1e-4)
    assert end.x > 0.01 and end.yaw > 0.02
    assert base.stats.crc_errors == base.stats.malformed == base.stats.out_of_sequence == 0


def test_wheel_limit_scaling_reaches_the_bridge(
    cfg: Config, bridge: FakeSerialBridge, base: SerialBase
) -> None:
    sent = base.send_twist(4.0, 0.0, 2.0)
    assert sent.vx == pytest.approx(4.0 * sent.wz / 2.0)
    wait_until(lambda: len(bridge.commands()) > 0 and bridge.commands()[-1][1][0] != 0.0)
    got = np.array(bridge.commands()[-1][1])
    assert np.max(np.abs(got)) == pytest.approx(cfg.limits.wheel_velocity, abs=1e-3)


@pytest.mark.parametrize(("kind", "counters"), [
    ("crc", ("crc_errors",)), ("truncate", ("malformed", "crc_errors")),
    ("garbage", ("malformed", "crc_errors")), ("out_of_sequence", ("out_of_sequence",)),
])
def test_corrupted_frames_are_rejected_counted_and_never_applied(
    bridge: FakeSerialBridge, base: SerialBase, kind: str, counters: tuple[str, ...]
) -> None:
    cycles(base, (0.2, 0.0, 0.0), 50)
    settle(base, bridge)

    def count() -> int:
        return sum(int(getattr(base.stats, c)) for c in counters)

    before, good = count(), base.stats.frames
    bridge.inject(kind, count=3)

    def rejected() -> int:
        base.check()  # reads what is waiting
        return count() - before

    wait_until(lambda: rejected() >= 3)
    for _ in range(20):  # a few more good frames
        base.stop()
        time.sleep(PERIOD)
    end = base.read_odometry()
    assert base.stats.frames > good  # good frames after them still get through
    # the out-of-sequence frames carried positions 1 rad off: never integrated
    assert (end.x, end.y, end.yaw) == pytest.approx(bridge.pose(), abs=1e-4)
    assert base.stats.frames > 0


def test_silent_bridge_is_a_base_link_fault() -> None:
    cfg = config_from_dict({})  # link_timeout 0.1 s, the default
    with FakeSerialBridge(cfg) as bridge, SerialBase(cfg.base, cfg.limits, bridge.port) as base:
        base.enable()
        _silence_and_recover(cfg, bridge, base)


def _silence_and_recover(cfg: Config, bridge: FakeSerialBridge, base: SerialBase) -> None:
    cycles(base, (0.1, 0.0, 0.0), 10)
    t0 = time.monotonic()
    bridge.inject_silence()
    n = 0
    nxt = time.monotonic()
    with pytest.raises(SafetyFault) as err:
        while True:
            base.send_twist(0.1, 0.0, 0.0)
            base.read_odometry()
            n += 1
            nxt += PERIOD
            time.sleep(max(0.0, nxt - time.monotonic()))
    elapsed = time.monotonic() - t0
    print(f"\nsilent bridge detected after {n} cycles, {elapsed * 1e3:.1f} ms "
          f"(link_timeout {cfg.base.serial.link_timeout * 1e3:.0f} ms)")
    assert err.value.cause is FaultCause.BASE_LINK
    assert elapsed >= cfg.base.serial.link_timeout - cfg.base.serial.timeout
    assert [d.link for d in base.drive_status()] == ["LINK DOWN"] * 4
    bridge.resume()
    base.enable()  # re-arm after the link is back
    cycles(base, (0.1, 0.0, 0.0), 5)


def test_bridge_fault_then_enable_resets_it(bridge: FakeSerialBridge, base: SerialBase) -> None:
    cycles(base, (0.1, 0.0, 0.0), 10)
    bridge.inject_fault(wheel=2, code=0x0101)
    with pytest.raises(SafetyFault) as err:
        for _ in range(2000):
            base.send_twist(0.1, 0.0, 0.0)
            time.sleep(PERIOD)
    assert err.value.cause is FaultCause.DRIVE_FAULT
    assert err.value.details["fault_code"] == "0x0101"
    assert err.value.details["fault_wheel"] == "BL"
    base.enable()
    assert bridge.enabled
    cycles(base, (0.1, 0.0, 0.0), 5)


def test_nothing_answers_on_the_port() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        cfg = config_from_dict({"base": {"serial": {"timeout": 0.01}}})
        base = SerialBase(cfg.base, cfg.limits, port=os.ttyname(slave))
        with pytest.raises(TransportError, match="no bridge answers on serial port"):
            base.connect()
    finally:
        os.close(master)
        os.close(slave)


def test_port_that_does_not_exist() -> None:
    cfg = config_from_dict({})
    with pytest.raises(TransportError, match="cannot open serial port '/nonexistent/tty'"):
        SerialBase(cfg.base, cfg.limits, port="/nonexistent/tty").connect()


def test_port_gone_is_link_lost_until_reconnect(cfg: Config) -> None:
    """The bridge's port disappears under the running base (a USB adapter pulled):
    LinkLost naming the port from every call, and from reconnect() while the port is
    gone (issue 28, point 4)."""
    with FakeSerialBridge(cfg) as bridge:
        base = SerialBase(cfg.base, cfg.limits, port=bridge.port)
        base.connect()
        base.reconnect()  # the link works: nothing to do
        base.enable()
        cycles(base, (0.1, 0.0, 0.0), 5)
    try:
        with pytest.raises(LinkLost) as lost:
            cycles(base, (0.1, 0.0, 0.0), 5)
        assert lost.value.cause is FaultCause.BASE_LINK and base.port in str(lost.value)
        for call in (base.stop, base.disable, base.read_odometry):
            with pytest.raises(LinkLost):
                call()
        with pytest.raises(LinkLost, match="reconnect failed"):
            base.reconnect()
    finally:
        base.close()
