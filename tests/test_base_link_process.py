"""BaseLinkProcess: the real CanopenBase in the link's child, against the fake drives.

The fake CiA 402 drives (:class:`FakeDrives`) run on a ``virtual`` channel in this
process, served by the simulated robot's socketcand server on a loopback address of the
test's own; the real :class:`CanopenBase` in the link's ``spawn`` child reaches them
through it, as the daemon's would.  A ``virtual`` spy on the same channel sees every
frame the child sends.  Conditions, calls and frames are asserted, never timing.
"""

from __future__ import annotations

import os
import signal
import threading
import uuid
from collections.abc import Callable, Iterator
from typing import Any

import can
import numpy as np
import pytest

from mmctl.config import Config, config_from_dict
from mmctl.errors import FaultCause, LinkLost, MmctlError, SafetyFault, TransportError
from mmctl.sim.fake_drives import FakeDrives
from mmctl.sim.socketcand import SocketcandServer
from mmctl.transports.base import Base
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.canopen_base import CanopenBase
from mmctl.transports.base.kinematics import WheelCommand
from mmctl.transports.base.link_process import BaseLinkProcess
from mmctl.types import Odometry
from waiting import wait_for

FAULTY = 2  # the node a fault is injected into (FR)


def _segments() -> set[str]:
    pid = os.getpid()
    return {f for f in os.listdir("/dev/shm")
            if f.startswith((f"mmctl-base_odometry-{pid}-", f"mmctl-base_command-{pid}-"))}


@pytest.fixture(autouse=True)
def _no_leaked_segments() -> Iterator[None]:
    before = _segments()
    yield
    assert _segments() == before, "a mailbox segment was left in /dev/shm"


@pytest.fixture(scope="module")
def server() -> Iterator[SocketcandServer]:
    from loopback import free_loopback_host

    with SocketcandServer(free_loopback_host(block=233), port=0) as srv:
        yield srv


def base_cfg(server: SocketcandServer, **canopen: object) -> Config:
    """Generous master-side timeouts (heartbeat, SDO): a loaded machine (load 8 on 2 cores
    here) must not look like a dead drive (SDO timeouts at 1 s were seen, and at 5 s with
    both cores busy: the fake drives' receive thread falls behind);
    the drives' own watchdog at 2 s (the net when the master's process dies)."""
    host, port = server.address
    return config_from_dict({"base": {
        "canopen": {"interface": "socketcand", "host": host, "port": port,
                    "channel": f"blp-{uuid.uuid4().hex[:10]}", "heartbeat_timeout": 5.0,
                    "sdo_timeout": 10.0, **canopen},
        "command_watchdog": 2.0}})


@pytest.fixture
def rig(server: SocketcandServer) -> Iterator[tuple[BaseLinkProcess, FakeDrives, Config]]:
    cfg = base_cfg(server)
    with FakeDrives(cfg) as fakes:
        link = BaseLinkProcess(cfg)
        try:
            yield link, fakes, cfg
        finally:
            link.close()


def outcome(call: Callable[[], Any]) -> Any:
    """What ``call()`` returned, or the exception it raised."""
    try:
        return call()
    except (MmctlError, OSError) as exc:
        return exc


def drive(base: Base, fakes: FakeDrives, vx: float = 0.3) -> Odometry:
    """Command ``vx`` ahead every 2 ms until every wheel turns and odometry shows it."""
    start = base.read_odometry()

    def turning() -> Odometry | None:
        base.send_twist(vx, 0.0, 0.0)
        odo = base.read_odometry()
        moving = bool(np.all(np.abs(fakes.wheel_velocities()) > 1.0))
        return odo if moving and odo.x > start.x + 0.01 and odo.vx > 0.1 else None

    odo: Odometry = wait_for(turning, "the base moving", timeout=60.0, interval=0.002)
    return odo


def until_raised(call: Callable[[], Any], kind: type[BaseException], what: str) -> Any:
    def once() -> BaseException | None:
        got = outcome(call)
        return got if isinstance(got, kind) else None
    return wait_for(once, what, timeout=60.0, interval=0.002)


def test_it_is_a_base_and_does_no_io_before_connect(server: SocketcandServer) -> None:
    cfg = base_cfg(server)
    link = BaseLinkProcess(cfg)
    assert isinstance(link, Base)
    assert link.pid is None and not link.connected
    assert link.link == f"socketcand:{cfg.base.canopen.channel}@{server.address[0]}:" \
                        f"{server.address[1]}"
    with pytest.raises(TransportError, match="not connected"):
        link.read_odometry()
    with pytest.raises(TransportError, match="before enable"):
        link.send_twist(0.1, 0.0, 0.0)
    link.stop()  # not connected: nothing to stop, as the transports
    link.disable(wait=False)
    link.close()
    link.close()


def test_twist_reaches_the_wheels_and_odometry_advances(
        rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    link, fakes, cfg = rig
    link.connect()
    link.connect()  # idempotent
    link.check()
    assert [d.link for d in link.drive_status()] == ["OPERATIONAL"] * 4
    link.enable()
    assert [d.state for d in link.drive_status()] == ["OPERATION ENABLED"] * 4
    odo = drive(link, fakes, 0.3)
    wheels, _ = WheelCommand(cfg.base.mecanum, cfg.limits.wheel_velocity)(0.3, 0.0, 0.0)
    counts = cfg.base.canopen.counts_per_rev / (2 * np.pi)
    assert fakes.target_counts() == [round(w * counts) for w in wheels]
    later = drive(link, fakes, 0.3)
    assert later.x > odo.x and later.timestamp > odo.timestamp  # advances
    x, _, _ = fakes.pose()
    assert later.x == pytest.approx(x, abs=0.05)  # the drives' encoders agree
    link.stop()
    wait_for(lambda: fakes.target_counts() == [0] * 4, "zero targets at the drives")
    link.disable()
    assert {d.state for d in link.drive_status()} == {"READY TO SWITCH ON"}
    link.close()
    with pytest.raises(TransportError):
        link.read_odometry()


def _fault_of(base: Base, fakes: FakeDrives) -> SafetyFault:
    base.enable()
    drive(base, fakes)
    fakes.inject_fault(FAULTY)
    exc: SafetyFault = until_raised(base.read_odometry, SafetyFault, "the drive fault")
    # settled: the fault latched while the wheel ramps down is what every call raises
    assert outcome(base.read_odometry).details == exc.details
    return exc


def test_a_drive_fault_is_the_same_safety_fault_as_in_process(
        rig: tuple[BaseLinkProcess, FakeDrives, Config], server: SocketcandServer) -> None:
    link, fakes, _ = rig
    with link:
        got = _fault_of(link, fakes)
        assert got.cause is FaultCause.DRIVE_FAULT
        assert got.details["node_id"] == FAULTY and got.details["wheel"] == "FR"
        with pytest.raises(SafetyFault) as sent:  # the latched fault, zero commanded first
            link.send_twist(0.3, 0.0, 0.0)
        assert sent.value.details == got.details
        with pytest.raises(SafetyFault):
            link.check()
        wait_for(lambda: fakes.states()[FAULTY - 1].state == "FAULT", "the drive in FAULT")
        link.enable()  # resets it
        assert isinstance(link.read_odometry(), Odometry)
        drive(link, fakes)
        link.disable()

    other = base_cfg(server)  # the same scenario with the transport in this process
    with FakeDrives(other) as fakes2, CanopenBase(other.base, other.limits) as direct:
        want = _fault_of(direct, fakes2)
    assert got.cause is want.cause
    assert set(got.details) == set(want.details)
    for key in ("node_id", "wheel", "error_code"):
        assert got.details[key] == want.details[key], key
    assert {got.details["state"], want.details["state"]} <= {"FAULT", "FAULT REACTION ACTIVE"}


def test_disable_without_waiting_is_a_command_not_a_request(
        rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    """disable(wait=False) and stop() leave a command and wake the child: no request
    goes over the pipe (none waits for a reply); the child sends zero targets and then
    SHUTDOWN in every drive's RPDO2, no SDO; the drives ramp to rest and switch off."""
    link, fakes, cfg = rig
    ids = cfg.base.canopen.node_ids
    with link, can.Bus(interface="virtual", channel=cfg.base.canopen.channel) as spy:
        link.enable()
        drive(link, fakes)
        while spy.recv(0.0) is not None:
            pass  # what went before
        requests = link.requests
        link.stop()
        link.disable(wait=False)
        assert link.requests == requests
        with pytest.raises(TransportError, match="before enable"):
            link.send_twist(0.3, 0.0, 0.0)  # disabled: refused at once
        frames: list[can.Message] = []

        def shutdowns() -> dict[int, bytes]:
            while (msg := spy.recv(0.0)) is not None:
                frames.append(msg)
            return {m.arbitration_id - 0x300: bytes(m.data) for m in frames
                    if 0x300 < m.arbitration_id < 0x380}

        wait_for(lambda: len(shutdowns()) == len(ids), "SHUTDOWN to every drive")
        shutdown = int(ds.Controlword.SHUTDOWN).to_bytes(2, "little")
        assert shutdowns() == dict.fromkeys(ids, shutdown)
        first_shutdown = next(i for i, m in enumerate(frames) if 0x300 < m.arbitration_id < 0x380)
        # the targets just before it are zero (a twist sent earlier may still come first)
        zeros = [m for m in frames[:first_shutdown] if 0x200 < m.arbitration_id < 0x280][-4:]
        assert sorted(m.arbitration_id - 0x200 for m in zeros) == sorted(ids)
        assert all(bytes(m.data) == bytes(4) for m in zeros)
        assert [m for m in frames if 0x600 < m.arbitration_id < 0x680] == []  # no SDO
        wait_for(lambda: [s.state for s in fakes.states()] == ["READY TO SWITCH ON"] * 4,
                 "every drive at rest, its power stage off")
        assert link.requests == requests


def test_a_killed_child_is_a_lost_link_the_drives_stop_by_themselves_and_reconnect(
        rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    link, fakes, cfg = rig
    with link:
        link.enable()
        drive(link, fakes)
        pid = link.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        exc = until_raised(link.read_odometry, TransportError, "the lost link")
        assert isinstance(exc, LinkLost) and exc.cause is FaultCause.BASE_LINK
        assert exc.link == link.link and "ended" in str(exc)
        for call in (link.read_odometry, link.stop, lambda: link.send_twist(0.3, 0.0, 0.0),
                     lambda: link.disable(wait=False), link.check):
            with pytest.raises(LinkLost):  # every call, at once
                call()
        # the net under it all: the master's heartbeat and RPDOs died with the child; each
        # drive's consumer heartbeat (or RPDO deadline, whichever expires first) times out
        # and it quick-stops (0x6007 = 3), then SWITCH ON DISABLED at rest
        wait_for(lambda: [s.state for s in fakes.states()] == ["SWITCH ON DISABLED"] * 4,
                 "every drive quick-stopped by its own watchdog")
        assert np.all(np.abs(fakes.wheel_velocities()) < 1e-9)
        for nid in cfg.base.canopen.node_ids:
            events = [what for _, what in fakes.event_log(nid)]
            assert {"heartbeat consumer timeout", "rpdo1 deadline missed"} & set(events), events
            assert "state QUICK STOP ACTIVE" in events, events

        link.reconnect()
        assert link.pid not in (None, pid)
        assert {s.state for s in fakes.states()} <= {"SWITCH ON DISABLED", "READY TO SWITCH ON"}
        link.enable()
        drive(link, fakes)
        link.disable()


def test_a_lost_can_link_is_the_transports_link_lost_and_reconnect_brings_it_back(
        rig: tuple[BaseLinkProcess, FakeDrives, Config], server: SocketcandServer) -> None:
    link, fakes, cfg = rig
    ch = cfg.base.canopen.channel
    with link:
        link.enable()
        drive(link, fakes)
        pid = link.pid
        connections = server.stats["connections"]
        link.reconnect()  # the link works: nothing happens
        assert link.pid == pid and server.stats["connections"] == connections

        assert server.drop_clients(ch) == 1
        exc = until_raised(link.read_odometry, LinkLost, "the lost link")
        assert exc.cause is FaultCause.BASE_LINK and ch in str(exc)
        assert link.pid == pid  # the child lives; its transport lost the link
        for call in (link.read_odometry, link.stop, link.check):
            with pytest.raises(LinkLost):
                call()
        wait_for(lambda: [s.state for s in fakes.states()] == ["SWITCH ON DISABLED"] * 4,
                 "every drive quick-stopped by its own watchdog")

        link.reconnect()  # the child's transport reconnects: the same child
        assert link.pid == pid and server.clients() >= 1
        assert isinstance(link.read_odometry(), Odometry)
        link.enable()
        drive(link, fakes)
        link.disable()


def test_a_stalled_child_is_the_silent_drives_fault_by_the_records_own_time(
        server: SocketcandServer) -> None:
    """A child that stops publishing (SIGSTOP here) but lives: the records get old;
    past the stale limit that is the in-process transport's fault for drives it no
    longer hears, DRIVE_HEARTBEAT; once the child runs again, odometry comes back."""
    cfg = base_cfg(server)
    with FakeDrives(cfg), BaseLinkProcess(cfg, stale_timeout=0.2) as link:
        assert isinstance(link.read_odometry(), Odometry)
        pid = link.pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            exc = until_raised(link.read_odometry, SafetyFault, "the stale fault")
        finally:
            os.kill(pid, signal.SIGCONT)
        assert exc.cause is FaultCause.DRIVE_HEARTBEAT
        assert exc.details["source"] == "link_process" and exc.details["silent_for"] > 0.2
        wait_for(lambda: isinstance(outcome(link.read_odometry), Odometry), "records again")


def test_read_and_send_never_wait_for_the_child(
        rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    """With the child stopped (SIGSTOP: nothing it does answers), the parent's calls
    all return: 1 000 reads (the newest record) and 1 000 twists (left in the mailbox)."""
    link, fakes, _ = rig
    with link:
        link.enable()
        drive(link, fakes)
        pid = link.pid
        assert pid is not None
        os.kill(pid, signal.SIGSTOP)
        try:
            results = [outcome(link.read_odometry) for _ in range(1000)]
            sent = [outcome(lambda: link.send_twist(0.0, 0.0, 0.0)) for _ in range(1000)]
        finally:
            os.kill(pid, signal.SIGCONT)
        assert all(isinstance(r, Odometry) for r in results)
        assert len(sent) == 1000
        link.stop()
        link.disable()


def test_calls_from_two_threads(rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    """The loop thread's reads and twists beside another thread's requests (as the
    daemon's operator thread enables while the loop runs): every result is a value or
    the transport's own error, nothing else."""
    link, _, _ = rig
    with link:
        link.enable()
        stop = threading.Event()
        bad: list[BaseException] = []

        def loop() -> None:
            while not stop.is_set():
                for call in (link.read_odometry, lambda: link.send_twist(0.1, 0.0, 0.0)):
                    got = outcome(call)
                    if isinstance(got, BaseException) and not isinstance(got, TransportError):
                        bad.append(got)
                stop.wait(0.002)

        t = threading.Thread(target=loop)
        t.start()
        try:
            for _ in range(5):
                link.check()
                assert len(link.drive_status()) == 4
            link.disable()
            link.enable()
        finally:
            stop.set()
            t.join()
        assert bad == []
        link.disable()


def test_close_is_idempotent_and_the_segments_and_child_go(
        rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    link, _, _ = rig
    link.connect()
    assert len(_segments()) == 2
    pid = link.pid
    link.close()
    link.close()
    assert not _segments()
    assert pid is not None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_the_child_ends_with_its_parent_pipe(
        rig: tuple[BaseLinkProcess, FakeDrives, Config]) -> None:
    """A daemon that dies closes the pipe: the child closes its transport and ends."""
    link, _, _ = rig
    link.connect()
    proc = link._proc
    link._conn.close()  # what the daemon's death does to the pipe
    proc.join(60.0)
    assert proc.exitcode == 0
    link.close()  # the parent still unlinks the segments


def test_connect_raises_what_the_transport_raised(server: SocketcandServer) -> None:
    cfg = base_cfg(server, sdo_timeout=0.2)  # no fake drives on this channel
    link = BaseLinkProcess(cfg)
    with pytest.raises(TransportError, match="no drive answers"):
        link.connect()
    assert link.pid is None and not link.connected
