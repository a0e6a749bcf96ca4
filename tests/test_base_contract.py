"""One contract for every Base transport, run against each one's protocol fake."""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Iterator
from contextlib import ExitStack
from typing import Any

import pytest

from mmctl.config import config_from_dict
from mmctl.errors import FaultCause, SafetyFault, TransportError
from mmctl.sim.fake_drives import FakeDrives
from mmctl.sim.fake_serial_bridge import FakeSerialBridge
from mmctl.sim.socketcand import SocketcandServer
from mmctl.transports.base import Base, open_base
from mmctl.transports.base.link_process import BaseLinkProcess
from mmctl.types import Odometry, Twist


@pytest.fixture(params=["canopen", "serial", "canopen-process", "serial-process"])
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[Base, Any]]:
    """An unconnected Base from open_base() and the running fake it talks to;
    ``*-process``: the transport in a BaseLinkProcess's child, which reaches the fake
    drives through the simulated robot's socketcand server (a ``virtual`` bus is reached
    from its own process only), the fake bridge through its pty."""
    kind, _, process = str(request.param).partition("-")
    with ExitStack() as stack:
        canopen: dict[str, Any] = {"interface": "virtual"}
        if process and kind == "canopen":
            host = request.getfixturevalue("loopback_host")
            server = stack.enter_context(SocketcandServer(host, port=0))
            canopen = {"interface": "socketcand", "host": host, "port": server.address[1]}
        cfg = config_from_dict({"base": {
            "transport": kind,
            "canopen": {**canopen, "channel": f"contract-{uuid.uuid4().hex[:10]}",
                        "heartbeat_timeout": 5.0,
                        "sdo_timeout": 5.0},
            "serial": {"link_timeout": 5.0, "timeout": 1.0},
            # a stalled test is not a dead master (2 s: a drive faulted 0x8250, RPDO timeout,
            # during an enable that took 3.5 s with both cores busy)
            "command_watchdog": 10.0,
        }})
        fake: Any = FakeDrives(cfg) if kind == "canopen" else FakeSerialBridge(cfg)
        stack.enter_context(fake)
        port = getattr(fake, "port", None)
        base: Base = BaseLinkProcess(cfg, port=port) if process else open_base(cfg, port=port)
        try:
            yield base, fake
        finally:
            base.close()


def test_full_lifecycle(rig: tuple[Base, Any]) -> None:
    base, _ = rig
    assert isinstance(base, Base)
    base.connect()
    base.connect()  # idempotent
    base.check()
    assert len(base.drive_status()) == 4
    base.enable()
    assert [d.state for d in base.drive_status()] == ["OPERATION ENABLED"] * 4
    sent = base.send_twist(0.2, 0.0, 0.0)
    assert isinstance(sent, Twist) and sent == pytest.approx((0.2, 0.0, 0.0))
    nxt = time.monotonic()
    deadline = nxt + 20.0
    for k in range(100_000):  # at least 100 cycles, then until odometry shows the motion
        base.send_twist(0.2, 0.0, 0.0)
        odo = base.read_odometry()
        if k >= 100 and odo.x > 0.0 and odo.vx > 0.0:
            break
        assert time.monotonic() < deadline
        nxt += 0.002
        time.sleep(max(0.0, nxt - time.monotonic()))
    assert isinstance(odo, Odometry)
    assert odo.timestamp <= time.monotonic()
    base.stop()
    base.disable()
    base.close()
    base.close()  # twice is fine
    with pytest.raises(TransportError):
        base.read_odometry()


def test_context_manager_connects_and_closes(rig: tuple[Base, Any]) -> None:
    base, _ = rig
    with base as b:
        assert b is base
        b.enable()
        b.send_twist(0.0, 0.1, 0.0)
    with pytest.raises(TransportError):
        base.check()


def test_send_twist_before_enable_is_refused(rig: tuple[Base, Any]) -> None:
    base, _ = rig
    with base, pytest.raises(TransportError, match="before enable"):
        base.send_twist(0.1, 0.0, 0.0)


def test_non_finite_twist_is_a_safety_fault(rig: tuple[Base, Any]) -> None:
    base, _ = rig
    with base:
        base.enable()
        with pytest.raises(SafetyFault) as err:
            base.send_twist(math.nan, 0.0, 0.0)
        assert err.value.cause is FaultCause.NON_FINITE


def test_close_without_connect_and_disable_twice(rig: tuple[Base, Any]) -> None:
    base, _ = rig
    base.close()
    base.stop()  # not connected: nothing to stop
    with base:
        base.enable()
        base.disable()
        base.disable()
