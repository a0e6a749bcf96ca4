"""Links that fail and come back (issue 28, point 4): the real CAN clients against the
project's fakes, over the real transport.

The F/T sensor (:class:`CanForceSensor`) and the CANopen master (:class:`CanopenBase`)
reach their fakes (:class:`FakeFtCanSensor`, :class:`FakeDrives`, on ``virtual``
channels in this process) through the simulated robot's socketcand server, as the
daemon does.  The server then closes the TCP connections under them (as a pulled
USB-CAN adapter would): the next calls raise ``LinkLost`` (a ``TransportError`` naming
the link and the fault), never a raw ``OSError``, no thread dies with an uncaught
exception, and ``reconnect()`` brings the device back once its peer answers.

Also: ``disable(wait=False)`` on a bus whose drives went silent sends frames only (no
SDO waits for an answer), and a burst of malformed sensor frames costs one sample, not
one stale bad frame per cycle.  Conditions and frame counts are asserted, never times.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import uuid
from collections.abc import Callable, Iterator

import can
import numpy as np
import pytest

from mmctl.config import Config, config_from_dict, default_config
from mmctl.config.sensor import SensorCanConfig
from mmctl.errors import FaultCause, LinkLost, ProtocolError, TransportError
from mmctl.sim.fake_drives import FakeDrives
from mmctl.sim.fake_ft_can import FakeFtCanSensor
from mmctl.sim.socketcand import SocketcandServer
from mmctl.sim.wrench_source import ConstantWrench
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.canopen_base import CanopenBase
from mmctl.transports.sensor.can_ft import CanForceSensor

PERIOD = 0.002  # [s], the control period
WRENCH = (3.0, -2.0, 10.0, 0.1, -0.2, 0.3)  # [N, N m]


def channel(kind: str) -> str:
    return f"link-{kind}-{uuid.uuid4().hex[:10]}"


def wait_until(pred: Callable[[], object], timeout: float = 30.0) -> None:
    """Poll ``pred`` (a condition, not a duration, is what the tests assert)."""
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.002)


@pytest.fixture
def thread_failures() -> Iterator[list[threading.ExceptHookArgs]]:
    """Every exception a thread ends with, uncaught, while the test runs."""
    failures: list[threading.ExceptHookArgs] = []
    previous = threading.excepthook
    threading.excepthook = failures.append
    try:
        yield failures
    finally:
        threading.excepthook = previous


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    with SocketcandServer(port=0) as srv:
        yield srv


# -- the F/T sensor ------------------------------------------------------------------------


def sensor_cfg(server: SocketcandServer, ch: str) -> SensorCanConfig:
    host, port = server.address
    return dataclasses.replace(default_config().sensor.can, interface="socketcand", host=host,
                               port=port, channel=ch, timeout=0.05, connect_timeout=0.5)


def read_fresh(sensor: CanForceSensor, after: int) -> float:
    """Read until a sample newer than sequence ``after`` comes; its Fz [N]."""
    for _ in range(100):
        w = sensor.read()
        if w.sequence > after:
            return float(w.force[2])
    raise AssertionError("no fresh sample in 100 reads")


def test_sensor_link_lost_then_reconnected(server: SocketcandServer,
                                           thread_failures: list[threading.ExceptHookArgs]
                                           ) -> None:
    ch = channel("ft")
    with FakeFtCanSensor(ConstantWrench(WRENCH), channel=ch) as fake:
        sensor = CanForceSensor(sensor_cfg(server, ch), stale_timeout=5.0)
        try:
            sensor.connect()
            assert read_fresh(sensor, 0) == pytest.approx(WRENCH[2], abs=0.1)
            connections = server.stats["connections"]
            sensor.reconnect()  # the link works: nothing to do
            assert server.stats["connections"] == connections

            assert server.drop_clients(ch) == 1
            with pytest.raises(LinkLost) as lost:
                for _ in range(3):  # a reply already queued may still be read
                    sensor.read()
            assert lost.value.cause is FaultCause.SENSOR_LINK
            assert sensor.link.split("@0x")[0] in str(lost.value)
            assert not isinstance(lost.value, OSError)
            # every later call: the same fault at once, no I/O
            for call in (sensor.read, sensor.request_next):
                with pytest.raises(LinkLost):
                    call()

            fake.silent = True  # nothing answers: reconnect says so, naming the link
            with pytest.raises(LinkLost, match="reconnect failed") as failed:
                sensor.reconnect()
            assert failed.value.cause is FaultCause.SENSOR_LINK
            assert sensor.link in str(failed.value)
            assert isinstance(failed.value, TransportError)

            fake.silent = False
            sensor.reconnect()
            seq = sensor.stats().received
            assert read_fresh(sensor, seq) == pytest.approx(WRENCH[2], abs=0.1)
            sensor.request_next()
            assert read_fresh(sensor, sensor.stats().received) == pytest.approx(WRENCH[2],
                                                                                abs=0.1)
        finally:
            sensor.close()
    assert thread_failures == []


def test_sensor_garbage_burst_costs_one_sample() -> None:
    """A burst of malformed frames queued behind a request: once it ends, a fresh
    sample comes on the first or second read (it used to take one read per bad frame)."""
    ch = channel("ft-garbage")
    cfg = dataclasses.replace(default_config().sensor.can, interface="virtual", channel=ch,
                              timeout=0.05)
    bad = can.Message(arbitration_id=0x200, data=b"\xde\xad\xbe", is_extended_id=False)
    with FakeFtCanSensor(ConstantWrench(WRENCH), channel=ch), \
            can.Bus(interface="virtual", channel=ch) as wire, \
            CanForceSensor(cfg, stale_timeout=5.0) as sensor:
        sensor.request_next()  # paced by the caller, as the daemon does
        sensor.read()
        sensor.request_next()
        for _ in range(50):
            wire.send(bad)
        before = sensor.stats().received
        reads = 0
        fresh = None
        while fresh is None and reads < 50:
            reads += 1
            try:
                w = sensor.read()
                fresh = w if w.sequence > before else None
            except ProtocolError:
                pass
            sensor.request_next()
        assert fresh is not None and reads <= 2, f"fresh sample after {reads} reads"
        assert float(fresh.force[2]) == pytest.approx(WRENCH[2], abs=0.1)


# -- the CANopen base ----------------------------------------------------------------------


def base_cfg(canopen: dict[str, object]) -> Config:
    """Generous master-side timeouts: a loaded machine must not look like a dead drive."""
    return config_from_dict({"base": {"canopen": {"heartbeat_timeout": 5.0, "sdo_timeout": 1.0,
                                                  **canopen}}})


def drive(base: CanopenBase, fakes: FakeDrives) -> None:
    """Command 0.3 m/s ahead every cycle until every wheel turns."""
    def turning() -> bool:
        base.send_twist(0.3, 0.0, 0.0)
        base.read_odometry()
        time.sleep(PERIOD)
        return bool(np.all(np.abs(fakes.wheel_velocities()) > 1.0))

    wait_until(turning)


def test_base_link_lost_then_reconnected(server: SocketcandServer,
                                         thread_failures: list[threading.ExceptHookArgs]
                                         ) -> None:
    ch = channel("base")
    host, port = server.address
    cfg = base_cfg({"interface": "socketcand", "host": host, "port": port, "channel": ch})
    with FakeDrives(cfg) as fakes:
        base = CanopenBase(cfg.base, cfg.limits)
        try:
            base.connect()
            base.enable()
            drive(base, fakes)

            assert server.drop_clients(ch) == 1

            def lost() -> bool:
                try:
                    base.send_twist(0.3, 0.0, 0.0)
                    base.read_odometry()
                except LinkLost:
                    return True
                time.sleep(PERIOD)
                return False

            wait_until(lost)
            with pytest.raises(LinkLost) as info:
                base.check()
            assert info.value.cause is FaultCause.BASE_LINK
            assert ch in str(info.value)
            for call in (base.stop, lambda: base.disable(wait=False), base.read_odometry):
                with pytest.raises(LinkLost):
                    call()
            # the net under it all: each drive stops by itself (no heartbeat, no RPDOs:
            # quick stop, 0x605A = 2, then SWITCH ON DISABLED at rest)
            wait_until(lambda: [s.state for s in fakes.states()] == ["SWITCH ON DISABLED"] * 4)

            base.reconnect()
            assert server.clients() == 1
            assert [s.state for s in fakes.states()] == ["READY TO SWITCH ON"] * 4
            connections = server.stats["connections"]
            base.reconnect()  # the link works: nothing to do
            assert server.stats["connections"] == connections
            base.enable()
            drive(base, fakes)
            base.stop()
            base.disable()
        finally:
            base.close()
    assert thread_failures == []


def test_base_reconnect_fails_while_the_drives_do_not_answer(
    server: SocketcandServer, thread_failures: list[threading.ExceptHookArgs]
) -> None:
    ch = channel("base-silent")
    host, port = server.address
    cfg = base_cfg({"interface": "socketcand", "host": host, "port": port, "channel": ch,
                    "sdo_timeout": 0.2})
    with FakeDrives(cfg) as fakes:
        base = CanopenBase(cfg.base, cfg.limits)
        try:
            base.connect()
            server.drop_clients(ch)
            wait_until(lambda: isinstance(_error_of(base.check), LinkLost))
            for nid in cfg.base.canopen.node_ids:
                fakes.inject_silence(nid)
            with pytest.raises(LinkLost, match="reconnect failed") as failed:
                base.reconnect()
            assert failed.value.cause is FaultCause.BASE_LINK
            assert ch in str(failed.value)
            for nid in cfg.base.canopen.node_ids:
                fakes.resume(nid)
            base.reconnect()
            base.enable()
            drive(base, fakes)
        finally:
            base.close()
    assert thread_failures == []


def _error_of(call: Callable[[], object]) -> BaseException | None:
    try:
        call()
    except Exception as exc:  # noqa: BLE001 - returned to the test
        return exc
    return None


def test_disable_without_waiting_sends_no_sdo_on_a_silent_bus() -> None:
    """The loop thread's stop when every drive went silent: disable(wait=False) returns
    without raising and without an SDO request (nothing it sends waits for an answer):
    zero targets, then SHUTDOWN in each drive's RPDO2."""
    ch = channel("base-quiet")
    cfg = base_cfg({"interface": "virtual", "channel": ch})
    ids = cfg.base.canopen.node_ids
    with FakeDrives(cfg) as fakes, CanopenBase(cfg.base, cfg.limits) as base, \
            can.Bus(interface="virtual", channel=ch) as spy:
        base.enable()
        drive(base, fakes)
        for nid in ids:
            fakes.inject_silence(nid)
        while spy.recv(0.0) is not None:
            pass  # what went before
        base.disable(wait=False)
        frames = []
        while (msg := spy.recv(0.0)) is not None:  # virtual: delivered on send
            frames.append(msg)
        sdo = [m for m in frames if 0x600 < m.arbitration_id < 0x680]
        assert sdo == [], [hex(m.arbitration_id) for m in sdo]
        shutdowns = {m.arbitration_id - 0x300: bytes(m.data) for m in frames
                     if 0x300 < m.arbitration_id < 0x380}
        assert shutdowns == dict.fromkeys(ids, int(ds.Controlword.SHUTDOWN).to_bytes(2, "little"))
        targets = [m for m in frames if 0x200 < m.arbitration_id < 0x280]
        assert sorted(m.arbitration_id - 0x200 for m in targets) == sorted(ids)
        assert all(bytes(m.data) == bytes(4) for m in targets)
        # the silent drives stop by their own watchdog (they no longer hear us)
        wait_until(lambda: all(s.state != "OPERATION ENABLED" for s in fakes.states()))
        for nid in ids:
            fakes.resume(nid)


def test_disable_without_waiting_shuts_the_drives_down_through_rpdo2() -> None:
    """With the drives answering, the RPDO2 SHUTDOWN does what the SDO one did: each
    drive ramps to rest (0x605B = 1), then opens its power stage."""
    ch = channel("base-rpdo2")
    cfg = base_cfg({"interface": "virtual", "channel": ch})
    with FakeDrives(cfg) as fakes, CanopenBase(cfg.base, cfg.limits) as base:
        base.enable()
        drive(base, fakes)
        t0 = time.monotonic()
        base.disable(wait=False)
        wait_until(lambda: [s.state for s in fakes.states()] == ["READY TO SWITCH ON"] * 4)
        offs = [v for t, _, v in fakes.power_offs() if t >= t0]
        assert len(offs) == 4 and all(abs(v) < 1e-9 for v in offs)
