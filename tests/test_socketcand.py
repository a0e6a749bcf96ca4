"""socketcand server: python-can's own socketcand client (and canopen) against the server
over real loopback TCP, fakes on the virtual side, exact bytes for the wire format and
the refused commands.

Every test uses port 0 and its own virtual channel name, so tests run in parallel.
Waits poll generously; no duration is asserted.
"""

from __future__ import annotations

import re
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import can
import canopen
import pytest
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.objectdictionary.datatypes import UNSIGNED32, VISIBLE_STRING

from mmctl.sim.socketcand import SocketcandServer
from waiting import wait_for

TIMEOUT = 20.0  # generous bound for anything to arrive [s]; never a measured duration


def _channel() -> str:
    return f"sc-{uuid.uuid4().hex[:12]}"


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    with SocketcandServer(port=0) as srv:
        yield srv


@contextmanager
def client(server: SocketcandServer, channel: str) -> Iterator[can.BusABC]:
    """python-can's socketcand client, as the daemon opens it."""
    host, port = server.address
    bus = can.Bus(interface="socketcand", host=host, port=port, channel=channel, tcp_tune=True)
    try:
        yield bus
    finally:
        bus.shutdown()


@contextmanager
def fake(channel: str) -> Iterator[can.BusABC]:
    """A device on the virtual side of ``channel``."""
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        yield bus
    finally:
        bus.shutdown()


def recv_n(bus: can.BusABC, n: int) -> list[can.Message]:
    """The next ``n`` frames on ``bus``; fails if they do not all come within TIMEOUT."""
    out: list[can.Message] = []
    deadline = time.monotonic() + TIMEOUT
    while len(out) < n:
        left = deadline - time.monotonic()
        assert left > 0, f"got {len(out)} of {n} frames: {out}"
        msg = bus.recv(timeout=left)
        if msg is not None:
            out.append(msg)
    return out


def key(msg: can.Message) -> tuple[int, bool, int, bytes]:
    return msg.arbitration_id, msg.is_extended_id, msg.dlc, bytes(msg.data)


def frame(can_id: int, data: bytes, extended: bool = False) -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=extended)


class RawClient:
    """A hand-written socketcand client: exact bytes out, one ``< ... >`` element in."""

    def __init__(self, server: SocketcandServer) -> None:
        self.sock = socket.create_connection(server.address, timeout=TIMEOUT)
        self.buf = b""

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def element(self) -> str:
        """The next ``< ... >`` from the server; '' at end of stream."""
        while b">" not in self.buf:
            chunk = self.sock.recv(4096)
            if not chunk:
                rest, self.buf = self.buf, b""
                return rest.decode()
            self.buf += chunk
        end = self.buf.index(b">") + 1
        text, self.buf = self.buf[:end], self.buf[end:]
        return text.decode()

    def at_eof(self) -> bool:
        """True once the server has closed (reads and discards anything else)."""
        try:
            while True:
                if not self.sock.recv(4096):
                    return True
        except ConnectionResetError:
            return True

    def handshake(self, channel: str, upto: str = "raw") -> None:
        assert self.element() == "< hi >"
        if upto == "hi":
            return
        self.send(f"< open {channel} >".encode())
        assert self.element() == "< ok >"
        if upto == "open":
            return
        self.send(b"< rawmode >")
        assert self.element() == "< ok >"

    def close(self) -> None:
        self.sock.close()


@contextmanager
def raw_client(server: SocketcandServer) -> Iterator[RawClient]:
    c = RawClient(server)
    try:
        yield c
    finally:
        c.close()


# -- frames both ways ---------------------------------------------------------------------

CLIENT_FRAMES = [
    frame(0x000, b""),
    frame(0x7FF, bytes(range(0xF8, 0x100))),
    frame(0x123, b"\x0a"),
    frame(0x601, b"\x40\x00\x10\x00\x00\x00\x00\x00"),
    frame(0x00000001, b"", extended=True),
    frame(0x1FFFFFFF, b"\xff\x0a\x00\x01\x80\x7f\x0a\x0a", extended=True),
    frame(0x00000123, b"\x0a\x0b", extended=True),  # extended although it fits 11 bits
]


def test_client_frames_reach_the_virtual_side_exactly(server: SocketcandServer) -> None:
    ch = _channel()
    with fake(ch) as device, client(server, ch) as bus:
        for msg in CLIENT_FRAMES:
            bus.send(msg)
        got = recv_n(device, len(CLIENT_FRAMES))
    assert [key(m) for m in got] == [key(m) for m in CLIENT_FRAMES]
    wait_for(lambda: server.stats["frames_in"] == len(CLIENT_FRAMES), "frames_in counted")


def test_virtual_frames_reach_the_client_intact(server: SocketcandServer) -> None:
    ch = _channel()
    every_byte = [frame(0x100 + i, bytes(range(8 * i, 8 * i + 8))) for i in range(32)]
    sent = [
        frame(0x080, b""),
        frame(0x0A0, b"\x0a" * 8),
        frame(0x0AAAAAAA, b"\x0a\x0d\x0a", extended=True),
        *every_byte,
        frame(0x1FFFFFFF, b"", extended=True),
    ]
    with fake(ch) as device, client(server, ch) as bus:
        for msg in sent:
            device.send(msg)
        got = recv_n(bus, len(sent))
    assert [key(m) for m in got] == [key(m) for m in sent]


def test_wire_format_is_socketcands(server: SocketcandServer) -> None:
    """ID 3 or 8 upper-case digits, SEC.USEC with 6 digits, data one hex string."""
    ch = _channel()
    with fake(ch) as device, raw_client(server) as c:
        c.handshake(ch)
        c.send(b"< send 7ff 0 >")  # speaks first: frames flow at once
        assert key(recv_n(device, 1)[0]) == (0x7FF, False, 0, b"")
        device.send(frame(0x080, b""))
        device.send(frame(0x00ABCDEF, b"\x0a\xb0\x01", extended=True))
        device.send(can.Message(arbitration_id=0x004, is_error_frame=True))
        assert re.fullmatch(r"< frame 080 \d+\.\d{6}  >", c.element())
        assert re.fullmatch(r"< frame 00ABCDEF \d+\.\d{6} 0AB001 >", c.element())
        assert re.fullmatch(r"< error 004 \d+\.\d{6} >", c.element())


def test_echo_is_answered_in_every_mode(server: SocketcandServer) -> None:
    ch = _channel()
    with raw_client(server) as c:
        assert c.element() == "< hi >"
        c.send(b"< echo >")
        assert c.element() == "< echo >"
        c.send(f"< open {ch} >< echo >".encode())  # two commands in one segment
        assert c.element() == "< ok >"
        assert c.element() == "< echo >"
        c.send(b"< rawmode >")
        assert c.element() == "< ok >"
        c.send(b"\n< echo >\r\n")
        assert c.element() == "< echo >"


def test_remote_frames_are_not_forwarded(server: SocketcandServer) -> None:
    ch = _channel()
    with fake(ch) as device, client(server, ch) as bus:
        bus.send(frame(0x001, b""))  # opens the flow at once
        recv_n(device, 1)
        device.send(can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1,
                                is_extended_id=False))
        device.send(frame(0x702, b"\x05"))
        assert key(recv_n(bus, 1)[0]) == (0x702, False, 1, b"\x05")
    assert server.stats["dropped"] == 1


# -- bus semantics --------------------------------------------------------------------------

def test_clients_on_a_channel_see_each_other_and_the_fake_never_themselves(
    server: SocketcandServer,
) -> None:
    ch, other_ch = _channel(), _channel()
    a_msg, b_msg = frame(0x101, b"\xaa"), frame(0x202, b"\xbb\xbb")
    from_fake = frame(0x303, b"\xcc")
    other_marker = frame(0x404, b"\xdd")
    with fake(ch) as device, fake(other_ch) as other_device, \
            client(server, ch) as a, client(server, ch) as b, \
            client(server, other_ch) as other:
        a.send(a_msg)
        b.send(b_msg)
        assert sorted(key(m) for m in recv_n(device, 2)) == sorted([key(a_msg), key(b_msg)])
        # The virtual bus delivers synchronously: once the fake has both, each client's
        # queue already holds the other's frame, so the fake's frame comes after it.
        device.send(from_fake)
        assert [key(m) for m in recv_n(a, 2)] == [key(b_msg), key(from_fake)]
        assert [key(m) for m in recv_n(b, 2)] == [key(a_msg), key(from_fake)]
        # Anything wrongly routed to the other channel would be queued before its marker.
        other_device.send(other_marker)
        assert [key(m) for m in recv_n(other, 1)] == [key(other_marker)]
        wait_for(lambda: server.clients() == 3, "three clients counted")
    wait_for(lambda: server.clients() == 0, "clients gone after shutdown")


# python-can's client does not close its socket when its handshake fails
@pytest.mark.filterwarnings("ignore::ResourceWarning")
def test_channels_limit_what_a_client_may_open() -> None:
    ch = _channel()
    with SocketcandServer(port=0, channels=[ch]) as srv:
        with raw_client(srv) as c:
            c.handshake("", upto="hi")
            c.send(b"< open can9 >")
            answer = c.element()
            assert answer.startswith("< error could not open bus can9")
            assert ch in answer
            assert c.at_eof()
        host, port = srv.address
        with pytest.raises(can.CanError, match="could not open bus"):
            can.Bus(interface="socketcand", host=host, port=port, channel="can9")
        with fake(ch) as device, client(srv, ch) as bus:
            bus.send(frame(0x123, b"\x01"))
            assert key(recv_n(device, 1)[0]) == (0x123, False, 1, b"\x01")


# -- refused commands -----------------------------------------------------------------------

MALFORMED = [
    pytest.param("raw", b"< frobnicate >", id="unknown-command"),
    pytest.param("raw", b"< send 123 2 11 >", id="len-above-bytes"),
    pytest.param("raw", b"< send 123 1 11 22 >", id="len-below-bytes"),
    pytest.param("raw", b"< send 12G 0 >", id="bad-hex-id"),
    pytest.param("raw", b"< send 123 1 1FF >", id="byte-three-digits"),
    pytest.param("raw", b"< send 123 1 0x1 >", id="byte-with-prefix"),
    pytest.param("raw", b"< send 123 1 zz >", id="byte-not-hex"),
    pytest.param("raw", b"< send 800 0 >", id="standard-id-above-7ff"),
    pytest.param("raw", b"< send 20000000 0 >", id="extended-id-above-1fffffff"),
    pytest.param("raw", b"< send 12345 0 >", id="id-five-digits"),
    pytest.param("raw", b"< send 123 9 0 0 0 0 0 0 0 0 0 >", id="len-above-8"),
    pytest.param("raw", b"< send 123 >", id="send-without-len"),
    pytest.param("raw", b"< >", id="empty-command"),
    pytest.param("raw", b"hello < echo >", id="text-outside-brackets"),
    pytest.param("raw", b"< send < 123 0 >", id="nested-bracket"),
    pytest.param("raw", b"< send 123 1 \xff >", id="non-ascii"),
    pytest.param("raw", b"< " + b"1" * 300, id="no-gt-in-300-chars"),
    pytest.param("raw", b"< echo " + b" " * 300 + b">", id="command-too-long"),
    pytest.param("raw", b"< bcmmode >", id="bcmmode"),
    pytest.param("open", b"< send 123 0 >", id="send-before-rawmode"),
    pytest.param("open", b"< isotpmode >", id="isotpmode"),
    pytest.param("hi", b"< rawmode >", id="rawmode-before-open"),
    pytest.param("hi", b"< open >", id="open-without-channel"),
    pytest.param("hi", b"< open a b >", id="open-two-channels"),
]


@pytest.mark.parametrize(("upto", "line"), MALFORMED)
def test_malformed_command_is_refused_and_closed(
    server: SocketcandServer, upto: str, line: bytes
) -> None:
    ch = _channel()
    with fake(ch) as device:
        with raw_client(server) as bystander, raw_client(server) as c:
            bystander.handshake(ch)
            c.handshake(ch, upto=upto)
            c.send(line)
            answer = c.element()
            assert answer.startswith("< error ") and answer.endswith(" >"), answer
            assert c.at_eof()
            # the other connection is unaffected
            bystander.send(b"< send 321 1 7 >")
            assert key(recv_n(device, 1)[0]) == (0x321, False, 1, b"\x07")
        wait_for(lambda: server.clients() == 0, "refused client gone")
        assert server.stats["errors"] == 1
        with client(server, ch) as bus:
            bus.send(frame(0x123, b"\x01\x02"))
            assert key(recv_n(device, 1)[0]) == (0x123, False, 2, b"\x01\x02")
            device.send(frame(0x321, b"\x03"))
            assert key(recv_n(bus, 1)[0]) == (0x321, False, 1, b"\x03")


def test_a_client_that_resets_just_goes_away(server: SocketcandServer) -> None:
    ch = _channel()
    with fake(ch) as device:
        c = RawClient(server)
        c.handshake(ch)
        c.send(b"< send 123 1 1 >")
        recv_n(device, 1)
        for i in range(50):
            device.send(frame(0x200, bytes([i])))  # unread data: close() sends a reset
        c.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        c.close()
        wait_for(lambda: server.clients() == 0, "reset client gone")
        with client(server, ch) as bus:
            device.send(frame(0x201, b""))
            assert key(recv_n(bus, 1)[0]) == (0x201, False, 0, b"")
    assert server.stats["errors"] == 0


def test_stop_returns_with_a_client_mid_command() -> None:
    ch = _channel()
    srv = SocketcandServer(port=0).start()
    with raw_client(srv) as idle, raw_client(srv) as c:
        c.handshake(ch)
        c.send(b"< send 123 2 1")  # no '>' yet
        idle.handshake(ch, upto="hi")
        wait_for(lambda: srv.clients() == 2, "both clients connected")
        srv.stop()
        wait_for(lambda: srv.clients() == 0, "clients torn down")  # joins are bounded
        assert c.at_eof()
        assert idle.at_eof()
    srv.stop()  # idempotent


# -- the handshake quirk ----------------------------------------------------------------------

def test_handshake_survives_continuous_traffic(server: SocketcandServer) -> None:
    """python-can requires the rawmode answer alone in its recv(256): frames from a busy
    bus (~1 kHz) must not be glued to it."""
    ch = _channel()
    stop = threading.Event()
    sent = [0]

    def chatter() -> None:
        with fake(ch) as device:
            while not stop.is_set():
                sent[0] += 1
                device.send(frame(0x181, sent[0].to_bytes(4, "little")))
                time.sleep(0.001)

    t = threading.Thread(target=chatter, name="test-chatter", daemon=True)
    t.start()
    try:
        wait_for(lambda: sent[0] > 0, "traffic running")
        for _ in range(20):
            with client(server, ch) as bus:  # a broken handshake raises CanError here
                first, second = recv_n(bus, 2)
                assert first.arbitration_id == second.arbitration_id == 0x181
                n1 = int.from_bytes(first.data, "little")
                assert int.from_bytes(second.data, "little") == n1 + 1
    finally:
        stop.set()
        t.join(TIMEOUT)
    assert server.stats["errors"] == 0


def test_frames_are_held_until_the_client_speaks() -> None:
    """With a long grace, frames wait (in order, none lost) for the client's first frame."""
    ch = _channel()
    with SocketcandServer(port=0, handshake_grace=600.0) as srv, fake(ch) as device, \
            raw_client(srv) as c:
        c.handshake(ch)
        held = [frame(0x500 + i, bytes([i])) for i in range(5)]
        for msg in held:
            device.send(msg)
        # Silence only proves something if it were broken, so a short look is enough.
        c.sock.settimeout(0.3)
        with pytest.raises(TimeoutError):
            c.sock.recv(4096)
        c.sock.settimeout(TIMEOUT)
        c.send(b"< send 123 0 >")
        recv_n(device, 1)
        device.send(frame(0x600, b"\x06"))
        got = [c.element() for _ in range(6)]
        ids = [int(e.split()[2], 16) for e in got]
        assert ids == [0x500, 0x501, 0x502, 0x503, 0x504, 0x600]


def test_a_listening_client_gets_frames_after_the_grace(server: SocketcandServer) -> None:
    ch = _channel()
    with fake(ch) as device, client(server, ch) as bus:
        device.send(frame(0x181, b"\x01\x02\x03"))  # the client never sends anything
        assert key(recv_n(bus, 1)[0]) == (0x181, False, 3, b"\x01\x02\x03")


# -- construction and binding -------------------------------------------------------------

@pytest.mark.parametrize("host", ["0.0.0.0", "10.1.2.3", "192.168.0.5", "::", "localhost"])
def test_non_loopback_host_is_refused(host: str) -> None:
    with pytest.raises(ValueError, match=re.escape(repr(host))):
        SocketcandServer(host, 0)


def test_ipv6_loopback_is_served() -> None:
    try:
        srv = SocketcandServer("::1", 0).start()
    except OSError:
        pytest.skip("no IPv6 loopback on this machine")
    with srv, socket.create_connection(srv.address, timeout=TIMEOUT) as s:
        assert s.recv(64) == b"< hi >"


def test_taken_port_is_a_clear_oserror(server: SocketcandServer) -> None:
    host, port = server.address
    with pytest.raises(OSError, match=rf"cannot listen on {re.escape(host)}:{port}.*port"):
        SocketcandServer(host, port).start()
    with raw_client(server) as c:  # the first server is untouched
        assert c.element() == "< hi >"


# -- canopen, as the daemon uses it ------------------------------------------------------------

def _dictionary() -> ObjectDictionary:
    od = ObjectDictionary()
    name = ODVariable("Manufacturer device name", 0x1008)
    name.data_type = VISIBLE_STRING
    # more than 4 bytes: a segmented SDO upload (several frames each way)
    name.default = "mmctl simulated drive"  # type: ignore[assignment]  # canopen types it int
    od.add_object(name)
    target = ODVariable("Target", 0x2000)
    target.data_type = UNSIGNED32
    target.default = 0
    od.add_object(target)
    return od


def test_canopen_sdo_round_trip(server: SocketcandServer) -> None:
    ch = _channel()
    host, port = server.address
    sim = canopen.Network()
    sim.connect(interface="virtual", channel=ch)
    daemon = canopen.Network()
    try:
        drive = canopen.LocalNode(5, _dictionary())
        sim.add_node(drive)
        daemon.connect(interface="socketcand", host=host, port=port, channel=ch, tcp_tune=True)
        remote = daemon.add_node(canopen.RemoteNode(5, _dictionary()))
        remote.sdo.RESPONSE_TIMEOUT = TIMEOUT
        assert remote.sdo.upload(0x1008, 0) == b"mmctl simulated drive"
        remote.sdo.download(0x2000, 0, (0xDEADBEEF).to_bytes(4, "little"))
        assert drive.get_data(0x2000, 0) == (0xDEADBEEF).to_bytes(4, "little")
    finally:
        daemon.disconnect()
        sim.disconnect()
