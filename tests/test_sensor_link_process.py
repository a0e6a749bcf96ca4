"""SensorLinkProcess: the real transports in the link's child process, against the fakes.

CAN: the real CanForceSensor in the link's child talks python-can's socketcand client to
a SocketcandServer serving the fake sensor's ``virtual`` channel, in a third process
(as the simulated robot does), on a loopback address of the test's own.  RDT: the real
RdtForceSensor in the child against FakeRdtServer (UDP, loopback) in this process.
Conditions are asserted, never timing.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from multiprocessing.connection import Connection
from typing import Any, TypeVar, cast

import numpy as np
import pytest

from mmctl.config import default_config
from mmctl.config.sensor import SensorConfig
from mmctl.errors import FaultCause, LinkLost, ProtocolError, SafetyFault, TransportError
from mmctl.sim.fake_ft_can import STATUS_DAC_ADC_TOO_HIGH, FakeFtCanSensor
from mmctl.sim.fake_rdt import STATUS_ERROR, FakeRdtServer
from mmctl.sim.wrench_source import ConstantWrench
from mmctl.transports.sensor import ForceSensor
from mmctl.transports.sensor.can_ft import check_status
from mmctl.transports.sensor.link_process import SensorLinkProcess, next_deadline
from mmctl.types import Wrench
from waiting import wait_for

T = TypeVar("T")
CHANNEL = "mmctl-sensor"
WRENCH = (3.0, -4.0, 10.0, 0.25, -0.5, 0.125)


# -- the simulated robot's side: socketcand server + fake sensor, in a process --------

def _serve_can(conn: Connection, host: str) -> None:
    """Spawned: the fake sensor on a virtual channel served by socketcand at ``host``;
    obeys ("set", attribute, value), ("drop",); ("stop",) or a closed pipe ends it."""
    from mmctl.sim.socketcand import SocketcandServer

    with SocketcandServer(host, port=0, channels=[CHANNEL]) as server, \
            FakeFtCanSensor(ConstantWrench(WRENCH), channel=CHANNEL) as fake:
        conn.send(server.address)
        while True:
            try:
                msg = conn.recv()
            except EOFError:
                return
            if msg[0] == "set":  # fault injection: status, saturate, garbage
                setattr(fake, msg[1], msg[2])
            elif msg[0] == "drop":  # a pulled USB-CAN adapter: the TCP connections end
                conn.send(("ok", server.drop_clients()))
                continue
            elif msg[0] == "stop":
                return
            conn.send(("ok", fake.requests))


class CanSide:
    """The simulated robot's CAN side in its own process (see :func:`_serve_can`)."""

    def __init__(self, host: str) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_serve_can, args=(child, host), daemon=True)
        self.proc.start()
        child.close()
        if not self.conn.poll(60.0):
            raise RuntimeError("the fake CAN side did not start")
        self.address: tuple[str, int] = self.conn.recv()

    def command(self, *msg: Any) -> Any:
        self.conn.send(msg)
        return self.conn.recv()

    def stop(self) -> None:
        self.conn.send(("stop",))
        self.proc.join(10.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(10.0)
        self.conn.close()


def replaced(section: T, **changes: Any) -> T:
    """dataclasses.replace typed for config sections (``@section`` hides the dataclass)."""
    return cast(T, dataclasses.replace(cast(Any, section), **changes))


def can_sensor_config(address: tuple[str, int]) -> SensorConfig:
    cfg = default_config().sensor
    host, port = address
    # generous timeouts: a loaded CI machine must not turn into faults (conditions only)
    return replaced(
        cfg, transport="can",
        can=replaced(cfg.can, interface="socketcand", channel=CHANNEL, host=host,
                                port=port, timeout=0.05, connect_timeout=5.0),
        wrench=replaced(cfg.wrench, stale_timeout=5.0))


def rdt_sensor_config(address: tuple[str, int]) -> SensorConfig:
    cfg = default_config().sensor
    host, port = address
    return replaced(
        cfg, transport="rdt",
        rdt=replaced(cfg.rdt, host=host, port=port, connect_timeout=5.0),
        wrench=replaced(cfg.wrench, stale_timeout=5.0))


def _segments() -> set[str]:
    return {f for f in os.listdir("/dev/shm") if f.startswith(f"mmctl-force_sensor-{os.getpid()}-")}


@pytest.fixture(autouse=True)
def _no_leaked_segments() -> Iterator[None]:
    before = _segments()
    yield
    assert _segments() == before, "a mailbox segment was left in /dev/shm"


@pytest.fixture(scope="module")
def can_side() -> Iterator[CanSide]:
    from loopback import free_loopback_host

    side = CanSide(free_loopback_host(block=231))
    yield side
    side.stop()


@pytest.fixture
def can_link(can_side: CanSide) -> Iterator[SensorLinkProcess]:
    for attr, value in (("status", 0), ("saturate", False), ("garbage", False)):
        can_side.command("set", attr, value)
    link = SensorLinkProcess(can_sensor_config(can_side.address))
    yield link
    link.close()


def read_until(link: SensorLinkProcess, pred: Any, what: str) -> Any:
    """read() until ``pred(result)`` (a Wrench or the exception raised) is truthy."""
    def once() -> Any:
        try:
            got: Wrench | Exception = link.read()
        except (SafetyFault, TransportError) as exc:
            got = exc
        return got if pred(got) else None
    return wait_for(once, what, timeout=60.0, interval=0.001)


# -- CAN ------------------------------------------------------------------------------

def test_it_is_a_force_sensor_and_does_no_io_before_connect(can_side: CanSide) -> None:
    link = SensorLinkProcess(can_sensor_config(can_side.address))
    assert isinstance(link, ForceSensor)
    assert link.pid is None and not link.connected
    assert link.link.startswith("socketcand:mmctl-sensor@")
    with pytest.raises(TransportError, match="not connected"):
        link.read()
    link.close()
    link.close()


def test_samples_arrive_and_their_sequence_advances(can_link: SensorLinkProcess) -> None:
    fake = FakeFtCanSensor(ConstantWrench(WRENCH), channel="unused")  # for its arithmetic
    with can_link:
        first = can_link.read()
        seqs = [first.sequence]

        def advanced(w: Wrench | Exception) -> bool:
            if not isinstance(w, Wrench):
                return False
            seqs.append(w.sequence)
            return w.sequence >= first.sequence + 50

        read_until(can_link, advanced, "50 more samples")
        last = can_link.read()
        assert seqs == sorted(seqs)  # never backwards
        expected = np.asarray(WRENCH)
        bound = fake.quantisation_bound() + 1e-9
        assert np.all(np.abs(last.as_array() - expected) <= bound), last
        assert last.status == 0
        stats = can_link.stats()
        assert stats.received >= last.sequence and stats.out_of_order == 0


def test_read_returns_at_once_when_nothing_is_new(can_side: CanSide) -> None:
    """One sample a second (the child's grid): 2000 reads in a row see at most two
    samples; an in-process read() would have asked the sensor and waited every time."""
    link = SensorLinkProcess(can_sensor_config(can_side.address), period=1.0, lead=0.5)
    with link:
        seqs = {link.read().sequence for _ in range(2000)}
        assert len(seqs) <= 2, seqs


def test_the_phase_follows_the_loops_grid(can_side: CanSide) -> None:
    assert next_deadline(1_000, 0, 2_000, 600) == 2_000
    assert next_deadline(1_500, 0, 2_000, 600) == 4_000  # 1 400 is past: the next one
    assert next_deadline(-700, 10, 2_000, 600) == 10  # asked at -590: still ahead
    link = SensorLinkProcess(can_sensor_config(can_side.address), period=1.0, lead=1e-3)
    with link:
        before = link.read().sequence
        with pytest.raises(ValueError, match="within the lead"):
            link.set_phase(0, period=0.0005)
        link.set_phase(0, period=0.002)  # now 500 Hz: samples come quickly again
        read_until(link, lambda w: isinstance(w, Wrench) and w.sequence >= before + 20,
                   "samples at the loop's new rate")


def test_a_killed_child_is_a_lost_link_and_reconnect_brings_samples_back(
        can_link: SensorLinkProcess) -> None:
    with can_link:
        can_link.read()
        old_pid = can_link.pid
        assert old_pid is not None
        os.kill(old_pid, signal.SIGKILL)
        exc = read_until(can_link, lambda r: isinstance(r, TransportError), "TransportError")
        assert isinstance(exc, LinkLost) and exc.cause is FaultCause.SENSOR_LINK
        assert "ended" in str(exc) and exc.link == can_link.link
        with pytest.raises(LinkLost):  # and it stays so
            can_link.read()
        can_link.reconnect()
        assert can_link.pid != old_pid
        first = can_link.read().sequence
        read_until(can_link, lambda w: isinstance(w, Wrench) and w.sequence > first + 10,
                   "samples after reconnect")


def test_a_lost_can_link_is_link_lost_and_reconnect_brings_it_back(
        can_side: CanSide, can_link: SensorLinkProcess) -> None:
    with can_link:
        can_link.read()
        pid = can_link.pid
        can_link.reconnect()  # the link works: nothing happens
        assert can_link.pid == pid
        assert can_side.command("drop")[1] == 1
        exc = read_until(can_link, lambda r: isinstance(r, TransportError), "the lost link")
        assert isinstance(exc, LinkLost) and exc.cause is FaultCause.SENSOR_LINK, exc
        assert can_link.link.startswith(exc.link)  # the bus's, as the transport names it
        with pytest.raises(LinkLost):  # every read, until reconnect
            can_link.read()
        can_link.reconnect()
        assert can_link.pid != pid
        first = can_link.read().sequence
        read_until(can_link, lambda w: isinstance(w, Wrench) and w.sequence > first + 10,
                   "samples after reconnect")


def test_a_status_error_is_the_same_safety_fault_as_in_process(
        can_side: CanSide, can_link: SensorLinkProcess) -> None:
    with can_link:
        can_link.read()
        can_side.command("set", "status", STATUS_DAC_ADC_TOO_HIGH)
        exc = read_until(can_link, lambda r: isinstance(r, SafetyFault), "the status fault")
        try:
            check_status(STATUS_DAC_ADC_TOO_HIGH | 0x8000, np.zeros(6))
        except SafetyFault as direct:
            assert exc.cause is direct.cause is FaultCause.SENSOR_STATUS
            assert exc.details == direct.details, (exc.details, direct.details)
        with pytest.raises(SafetyFault):  # while the sensor says so, every read
            can_link.read()
        can_side.command("set", "status", 0)
        read_until(can_link, lambda w: isinstance(w, Wrench), "a good sample again")


def test_saturation_and_garbage_come_back_as_in_process(
        can_side: CanSide, can_link: SensorLinkProcess) -> None:
    with can_link:
        can_link.read()
        can_side.command("set", "saturate", True)
        exc = read_until(can_link, lambda r: isinstance(r, SafetyFault), "the saturation")
        assert exc.cause is FaultCause.SENSOR_SATURATION and exc.details == {"gauges": ["sg2"]}
        can_side.command("set", "saturate", False)
        read_until(can_link, lambda w: isinstance(w, Wrench), "a good sample again")
        can_side.command("set", "garbage", True)  # a 3-byte reply: malformed
        exc = read_until(can_link, lambda r: isinstance(r, ProtocolError), "ProtocolError")
        assert not isinstance(exc, LinkLost) and "DLC 3" in str(exc)  # the transport's words
        can_side.command("set", "garbage", False)
        read_until(can_link, lambda w: isinstance(w, Wrench), "a good sample again")


def test_connect_raises_what_the_transport_raised() -> None:
    from loopback import free_loopback_host

    cfg = can_sensor_config((free_loopback_host(block=232), 29536))  # nothing listens
    cfg = replaced(cfg, can=replaced(cfg.can, connect_timeout=0.2))
    link = SensorLinkProcess(cfg)
    with pytest.raises(TransportError) as info:
        link.connect()
    assert not isinstance(info.value, ProtocolError)
    assert link.pid is None and not link.connected


# -- RDT ------------------------------------------------------------------------------

@pytest.fixture
def rdt_fake(loopback_host: str) -> Iterator[FakeRdtServer]:
    with FakeRdtServer(ConstantWrench(WRENCH), host=loopback_host, port=0) as fake:
        yield fake


def test_rdt_streams_through_the_child(rdt_fake: FakeRdtServer) -> None:
    with SensorLinkProcess(rdt_sensor_config(rdt_fake.address)) as link:
        assert link.link == f"udp://{rdt_fake.address[0]}:{rdt_fake.address[1]}"
        first = link.read()
        read_until(link, lambda w: isinstance(w, Wrench) and w.sequence > first.sequence + 50,
                   "50 more records")
        w = link.read()
        assert np.allclose(w.as_array(), WRENCH, atol=1e-6)
        rdt_fake.status = STATUS_ERROR
        exc = read_until(link, lambda r: isinstance(r, SafetyFault), "the status fault")
        assert exc.cause is FaultCause.SENSOR_STATUS
        rdt_fake.status = 0
        read_until(link, lambda w: isinstance(w, Wrench), "a good record again")


def test_a_silent_rdt_sensor_is_stale_by_the_samples_own_time(rdt_fake: FakeRdtServer) -> None:
    cfg = rdt_sensor_config(rdt_fake.address)
    cfg = replaced(cfg, wrench=replaced(cfg.wrench, stale_timeout=0.05))
    with SensorLinkProcess(cfg) as link:
        read_until(link, lambda w: isinstance(w, Wrench), "a first record")
        rdt_fake.silent = True
        exc = read_until(link, lambda r: isinstance(r, SafetyFault), "the stale fault")
        assert exc.cause is FaultCause.SENSOR_STALE
        rdt_fake.silent = False
        read_until(link, lambda w: isinstance(w, Wrench), "records again")


def test_close_is_idempotent_and_the_segment_goes(rdt_fake: FakeRdtServer) -> None:
    link = SensorLinkProcess(rdt_sensor_config(rdt_fake.address))
    link.connect()
    link.connect()  # already connected: nothing
    assert len(_segments()) == 1
    pid = link.pid
    link.close()
    link.close()
    assert not _segments()
    assert pid is not None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)


def test_the_child_ends_with_its_parent_pipe(rdt_fake: FakeRdtServer) -> None:
    """A daemon that dies closes the pipe: the child closes its transport and ends."""
    link = SensorLinkProcess(rdt_sensor_config(rdt_fake.address))
    link.connect()
    proc = link._proc
    link._conn.close()  # what the daemon's death does to the pipe
    proc.join(30.0)
    assert proc.exitcode == 0
    link.close()  # the parent still unlinks the segment


def test_a_process_that_never_closes_the_link_still_exits(rdt_fake: FakeRdtServer) -> None:
    """multiprocessing's exit handler joins daemonic children without a timeout and the
    child ignores SIGTERM: the link closes itself at exit first (the segment goes too)."""
    host, port = rdt_fake.address
    script = (
        "import dataclasses as d, os\n"
        "from mmctl.config import default_config\n"
        "from mmctl.transports.sensor.link_process import SensorLinkProcess\n"
        "c = default_config().sensor\n"
        f"c = d.replace(c, transport='rdt', rdt=d.replace(c.rdt, host={host!r}, port={port}))\n"
        "link = SensorLinkProcess(c, stale_timeout=5.0)\n"
        "link.connect()\n"
        "print(os.getpid(), link.read().sequence > 0, flush=True)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          check=False, timeout=120)  # a hang guard, not a timing
    assert done.returncode == 0, done.stderr[-2000:]
    ours = [line.split() for line in done.stdout.splitlines() if line.endswith((" True", " False"))]
    assert len(ours) == 1 and ours[0][1] == "True", done.stdout[-2000:]  # (log lines besides)
    pid = ours[0][0]
    assert not [f for f in os.listdir("/dev/shm") if f.startswith(f"mmctl-force_sensor-{pid}-")]
