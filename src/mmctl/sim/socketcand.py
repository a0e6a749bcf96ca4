"""A socketcand server (raw mode) in front of python-can's in-process ``virtual`` bus.

The simulated robot runs its CAN fakes (force sensor, CiA 402 drives) on ``virtual``
channels, which only exist inside the simulator's process.  This server lets another
process (the control daemon) reach those channels over TCP with the linux-can
*socketcand* ASCII protocol, which python-can speaks as a client
(``can.Bus(interface="socketcand", host=..., port=..., channel=...)``).  See
``docs/socketcand.md``.

Protocol subset (the raw mode of linux-can/socketcand, ``doc/protocol.md``)::

    server: < hi >                      on connect
    client: < open CHANNEL >            server: < ok >   (unknown channel: < error ... >, close)
    client: < rawmode >                 server: < ok >
    client: < send ID LEN B0 B1 ... >   a frame onto the channel (ID: 1-3 hex digits =
                                        standard, 8 = extended; LEN 0..8; bytes 1-2 hex digits)
    server: < frame ID SEC.USEC DATA >  a frame from the channel (ID 3 or 8 upper-case hex
                                        digits, DATA one upper-case hex string, no spaces)
    server: < error CLASS SEC.USEC >    an error frame from the channel
    client: < echo >                    server: < echo >   (in every mode)

Anything else (bad syntax, unknown command, ``send`` before ``rawmode``, a command
longer than :data:`MAX_COMMAND` characters, BCM/control/ISO-TP mode) is answered with
``< error TEXT >`` and the connection is closed; the server and the other clients carry
on.  Remote (RTR) and CAN FD frames on the virtual side are not forwarded (socketcand's
raw mode does not forward RTR either, and python-can's client parses neither); they are
counted in ``stats["dropped"]``.

Bus semantics: every connection that opened channel ``C`` owns one
``can.Bus(interface="virtual", channel=C)`` in this process, so a frame a client sends
reaches every other bus on ``C`` (the fakes and the other clients) but not the sender;
a frame a fake sends reaches every client on ``C``.

Threads: one accept thread per server; per client one reader (TCP -> bus, also runs the
handshake) and, once in raw mode, one forwarder (bus -> TCP).  All are daemon threads
named ``socketcand-...``.

Usage::

    with SocketcandServer(port=0, channels=["can0"]) as server:
        host, port = server.address
        bus = can.Bus(interface="socketcand", host=host, port=port, channel="can0",
                      tcp_tune=True)
"""

from __future__ import annotations

import ipaddress
import re
import selectors
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from enum import Enum
from types import TracebackType
from typing import TYPE_CHECKING

import can
import structlog

from mmctl.errors import MmctlError, ProtocolError

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self

log = structlog.get_logger("mmctl.sim.socketcand")

DEFAULT_HOST = "127.0.0.2"
#: socketcand's registered default port.
DEFAULT_PORT = 29536
#: Longest command accepted, in characters from ``<`` to ``>`` (a full extended
#: ``send`` is 44).
MAX_COMMAND = 256
#: How long after the rawmode ``< ok >`` frames are held back unless the client speaks
#: first [s] (see :meth:`_Client._forward`).
HANDSHAKE_GRACE_S = 0.1
#: Frames held back during the grace before the oldest are dropped (~10 s at 1 kHz).
HELD_FRAMES_MAX = 10_000
#: A client that reads nothing for this long while its socket buffer is full is
#: dropped [s] (so a stalled client cannot grow its virtual-bus queue without bound).
SEND_TIMEOUT_S = 5.0
#: Wake-up period of the forwarder to notice a closing connection [s] (frames do not
#: wait for it: ``bus.recv`` returns as soon as one arrives).
POLL_S = 0.1
#: Bound on each thread join in :meth:`SocketcandServer.stop` [s].
JOIN_TIMEOUT_S = 2.0
#: Frames written to the socket in one ``sendall`` at most.
MAX_BATCH = 64
#: Time to read what a refused client still sends before closing, so the kernel does
#: not answer with a reset that could discard our ``< error ... >`` line [s].
ERROR_LINGER_S = 1.0

_HEX = re.compile(r"[0-9A-Fa-f]+")
_BYTE = re.compile(r"[0-9A-Fa-f]{1,2}")
_STD_MAX = 0x7FF
_EXT_MAX = 0x1FFFFFFF
_UNSERVED_MODES = ("bcmmode", "controlmode", "isotpmode")

_STAT_KEYS = ("connections", "frames_in", "frames_out", "errors", "dropped")


class _Mode(Enum):
    """Where a connection is in the socketcand state machine."""

    NO_BUS = "no bus"  # greeted, no channel opened yet
    BUS_OPEN = "bus open"  # channel chosen, waiting for < rawmode >
    RAW = "raw"  # frames flow both ways


def _check_loopback(host: str) -> None:
    try:
        addr = ipaddress.ip_address(host)
    except ValueError:
        raise ValueError(
            f"socketcand server host {host!r} is not an IP address: give a loopback "
            "address (127.0.0.0/8 or ::1), e.g. '127.0.0.2'"
        ) from None
    if not addr.is_loopback:
        raise ValueError(
            f"socketcand server host {host!r} is not a loopback address: the simulator "
            "serves its CAN channels on 127.0.0.0/8 or ::1 only"
        )


def format_frame(msg: can.Message) -> str | None:
    """The socketcand raw-mode line for ``msg``, or None if raw mode cannot carry it.

    ``< frame ID SEC.USEC DATA >`` with ID as 3 (standard) or 8 (extended) upper-case hex
    digits and DATA one upper-case hex string without spaces (empty for a 0-byte frame:
    two spaces then ``>``), as linux-can socketcand writes it and python-can parses it
    (``split(" ", 3)`` then ``bytearray.fromhex``).  Error frames become
    ``< error CLASS SEC.USEC >``; remote and CAN FD frames give None.
    """
    total_us = round(msg.timestamp * 1_000_000)
    sec, usec = divmod(total_us, 1_000_000)
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & _EXT_MAX:03X} {sec}.{usec:06d} >"
    if msg.is_remote_frame or msg.is_fd or len(msg.data) > 8:
        return None
    if msg.is_extended_id:
        can_id = f"{msg.arbitration_id & _EXT_MAX:08X}"
    else:
        can_id = f"{msg.arbitration_id & _STD_MAX:03X}"
    return f"< frame {can_id} {sec}.{usec:06d} {bytes(msg.data).hex().upper()} >"


def parse_send(args: list[str]) -> can.Message:
    """The frame of ``< send ID LEN B0 ... >`` given its arguments ``[ID, LEN, B0, ...]``.

    ID: 1-3 hex digits for a standard id (<= 0x7FF), 8 for an extended one
    (<= 0x1FFFFFFF); LEN: hex, 0..8, equal to the number of bytes; bytes: 1-2 hex digits.
    Raises :class:`~mmctl.errors.ProtocolError` naming what is wrong (the server sends
    its text back as ``< error TEXT >``).
    """
    if len(args) < 2:
        raise ProtocolError("send needs ID LEN [bytes], e.g. < send 123 2 11 22 >")
    id_text, len_text, byte_texts = args[0], args[1], args[2:]
    if not _HEX.fullmatch(id_text):
        raise ProtocolError(f"send: id {id_text!r} is not hex")
    can_id = int(id_text, 16)
    if len(id_text) == 8:
        extended = True
        if can_id > _EXT_MAX:
            raise ProtocolError(f"send: extended id {id_text} is above 1FFFFFFF")
    elif len(id_text) <= 3:
        extended = False
        if can_id > _STD_MAX:
            raise ProtocolError(f"send: standard id {id_text} is above 7FF")
    else:
        raise ProtocolError(
            f"send: id {id_text!r} has {len(id_text)} digits: 3 for a standard id, "
            "8 for an extended one"
        )
    if not _HEX.fullmatch(len_text) or int(len_text, 16) > 8:
        raise ProtocolError(f"send: length {len_text!r} is not 0..8")
    length = int(len_text, 16)
    if len(byte_texts) != length:
        raise ProtocolError(f"send: length {length} but {len(byte_texts)} data bytes")
    for b in byte_texts:
        if not _BYTE.fullmatch(b):
            raise ProtocolError(f"send: data byte {b!r} is not 1-2 hex digits")
    return can.Message(
        arbitration_id=can_id,
        is_extended_id=extended,
        dlc=length,
        data=bytes(int(b, 16) for b in byte_texts),
    )


def _safe_text(text: str) -> str:
    """``text`` fit for ``< error TEXT >``: no brackets, one line, printable ASCII."""
    out = "".join(c if 32 <= ord(c) < 127 and c not in "<>" else "?" for c in text)
    return out[:200]


class SocketcandServer:
    """A socketcand raw-mode server over python-can ``virtual`` channels (module doc).

    host: loopback address to listen on (127.0.0.0/8 or ::1, else ValueError); port: TCP
    port (0 = any free one, read :attr:`address` after :meth:`start`); channels: the
    channel names a client may open (None: any name); handshake_grace: how long frames
    are held back after the rawmode ``< ok >`` unless the client sends first [s].

    ``stats`` counts ``connections`` (accepted), ``frames_in`` (client -> bus),
    ``frames_out`` (bus -> client), ``errors`` (connections refused with
    ``< error ... >``) and ``dropped`` (frames not forwarded: remote/FD frames, held
    frames beyond :data:`HELD_FRAMES_MAX`).  No I/O before :meth:`start`.
    """

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        channels: Iterable[str] | None = None,
        handshake_grace: float = HANDSHAKE_GRACE_S,
    ) -> None:
        _check_loopback(host)
        if not 0 <= port <= 65535:
            raise ValueError(f"socketcand server port {port} is not 0..65535 (0 = any free)")
        if not handshake_grace >= 0.0:
            raise ValueError(f"handshake_grace {handshake_grace} s must be >= 0")
        self.host = host
        self.port = port
        self.channels: frozenset[str] | None = None if channels is None else frozenset(channels)
        self.handshake_grace = handshake_grace
        self.stats: dict[str, int] = dict.fromkeys(_STAT_KEYS, 0)
        self._stats_lock = threading.Lock()
        self._lock = threading.Lock()  # guards _clients and _stopping
        self._clients: set[_Client] = set()
        self._stopping = False
        self._started = False
        self._bound: tuple[str, int] | None = None
        self._listener: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._accept_thread: threading.Thread | None = None
        self._failures: list[BaseException] = []
        #: channels whose adapter is pulled (:meth:`unplug`)
        self.unplugged: set[str] = set()

    # -- public API ----------------------------------------------------------------------

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) actually bound; valid after :meth:`start`."""
        if self._bound is None:
            raise MmctlError("the socketcand server is not started: call start() first")
        return self._bound

    def clients(self) -> int:
        """Connections open right now (from accept until their teardown is done)."""
        with self._lock:
            return len(self._clients)

    def unplug(self, channel: str, unplugged: bool = True) -> int:
        """A pulled (``unplugged``) or re-plugged USB-CAN adapter of ``channel``: while
        unplugged, its connections are dropped and ``< open >`` of it is refused as for
        a bus that does not exist.  Returns how many connections were dropped."""
        with self._lock:
            if unplugged:
                self.unplugged.add(channel)
            else:
                self.unplugged.discard(channel)
        log.info("socketcand_channel_unplugged" if unplugged else "socketcand_channel_plugged",
                 channel=channel)
        return self.drop_clients(channel) if unplugged else 0

    def drop_clients(self, channel: str | None = None) -> int:
        """Close every client connection (only those on ``channel`` if given), as a
        pulled USB-CAN adapter or a crashed server would: the clients see the TCP
        connection end.  The server keeps listening; a client may connect again.
        Returns how many connections were closed."""
        with self._lock:
            doomed = [c for c in self._clients if channel is None or c.channel == channel]
        for client in doomed:
            client.close()
        log.info("socketcand_clients_dropped", channel=channel, clients=len(doomed))
        return len(doomed)

    def start(self) -> Self:
        """Bind (SO_REUSEADDR), listen and start the accept thread.

        Returns the server; a second call while running does nothing.  Raises OSError
        naming the address if it cannot be bound (port taken), and MmctlError after
        :meth:`stop` (make a new server instead).
        """
        if self._started:
            if self._stopping:
                raise MmctlError("this socketcand server was stopped: make a new one")
            return self
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((self.host, self.port))
            listener.listen(16)
        except OSError as exc:
            listener.close()
            raise OSError(
                exc.errno,
                f"socketcand server cannot listen on {self.host}:{self.port}: {exc.strerror}"
                " (another server, e.g. a simulator or socketcand, holds it? pick another "
                "port, or 0 for any free one)",
            ) from exc
        self._started = True
        self._listener = listener
        self._bound = (self.host, int(listener.getsockname()[1]))
        self._wake_r, self._wake_w = socket.socketpair()
        self._accept_thread = threading.Thread(
            target=self._accept_loop, name=f"socketcand-accept-{self._bound[1]}", daemon=True
        )
        self._accept_thread.start()
        log.info("socketcand_listening", host=self._bound[0], port=self._bound[1],
                 channels=None if self.channels is None else sorted(self.channels))
        return self

    def stop(self) -> None:
        """Close the listener and every client, join all threads (each bounded).

        Idempotent.  Raises MmctlError afterwards if a server thread died of an
        unexpected exception (a bug: protocol errors and disconnects are not failures).
        """
        with self._lock:
            if self._stopping or not self._started:
                return
            self._stopping = True
            clients = list(self._clients)
        if self._wake_w is not None:
            self._wake_w.send(b"x")
        if self._accept_thread is not None:
            self._accept_thread.join(JOIN_TIMEOUT_S)
        for sock in (self._listener, self._wake_r, self._wake_w):
            if sock is not None:
                sock.close()
        for client in clients:
            client.close()  # wakes its threads; the reader then tears the connection down
        for client in clients:
            client.join(JOIN_TIMEOUT_S)
        alive = [t.name for c in clients for t in c.threads() if t.is_alive()]
        if self._accept_thread is not None and self._accept_thread.is_alive():
            alive.append(self._accept_thread.name)
        log.info("socketcand_stopped", port=self._bound[1] if self._bound else None,
                 threads_left=alive or None, **self.stats)
        if self._failures:
            raise MmctlError(
                f"a socketcand server thread failed: {self._failures[0]!r}"
            ) from self._failures[0]

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # -- internals -------------------------------------------------------------------------

    def _count(self, key: str, n: int = 1) -> None:
        with self._stats_lock:
            self.stats[key] += n

    def _failed(self, exc: BaseException, where: str) -> None:
        self._failures.append(exc)
        log.error("socketcand_thread_failed", where=where, error=repr(exc))

    def _accept_loop(self) -> None:
        listener, wake = self._listener, self._wake_r
        assert listener is not None and wake is not None
        try:
            with selectors.DefaultSelector() as sel:
                sel.register(listener, selectors.EVENT_READ)
                sel.register(wake, selectors.EVENT_READ)
                while True:
                    ready = {key.fileobj for key, _ in sel.select()}
                    if wake in ready:
                        return
                    try:
                        sock, peer = listener.accept()
                    except OSError as exc:  # e.g. EMFILE: log, back off, keep serving
                        log.warning("socketcand_accept_failed", error=str(exc))
                        time.sleep(POLL_S)
                        continue
                    self._admit(sock, peer)
        except Exception as exc:  # noqa: BLE001 - stored, re-raised by stop()
            self._failed(exc, "accept")

    def _admit(self, sock: socket.socket, peer: tuple[object, ...]) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sec = int(SEND_TIMEOUT_S)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO,
                        struct.pack("ll", sec, int((SEND_TIMEOUT_S - sec) * 1e6)))
        client = _Client(self, sock, f"{peer[0]}:{peer[1]}")
        with self._lock:
            if self._stopping:
                sock.close()
                return
            self._clients.add(client)
        self._count("connections")
        log.info("socketcand_client_connected", peer=client.peer)
        client.start()

    def _forget(self, client: _Client) -> None:
        with self._lock:
            self._clients.discard(client)


class _Client:
    """One TCP connection: its handshake state, its virtual bus and its two threads."""

    def __init__(self, server: SocketcandServer, sock: socket.socket, peer: str) -> None:
        self.server = server
        self.sock = sock
        self.peer = peer
        self.mode = _Mode.NO_BUS
        self.channel: str | None = None
        self.bus: can.BusABC | None = None
        self.frames_in = 0
        self.frames_out = 0
        self.closing = threading.Event()
        self.spoke = threading.Event()  # the client sent a command after the rawmode < ok >
        self.ok_at = 0.0  # monotonic time of the rawmode < ok > [s]
        self.forward_error: str | None = None  # why the forwarder gave up, if it did
        self._send_lock = threading.Lock()  # reader (echo, errors) and forwarder share the socket
        port = peer.rsplit(":", 1)[-1]
        self.reader = threading.Thread(target=self._read, name=f"socketcand-rx-{port}",
                                       daemon=True)
        self.forwarder = threading.Thread(target=self._forward, name=f"socketcand-tx-{port}",
                                          daemon=True)
        self._commands: dict[_Mode, dict[str, Callable[[list[str]], None]]] = {
            _Mode.NO_BUS: {"open": self._cmd_open, "echo": self._cmd_echo},
            _Mode.BUS_OPEN: {"rawmode": self._cmd_rawmode, "echo": self._cmd_echo},
            _Mode.RAW: {"send": self._cmd_send, "echo": self._cmd_echo},
        }

    def start(self) -> None:
        self.reader.start()

    def threads(self) -> list[threading.Thread]:
        return [self.reader, self.forwarder]

    def close(self) -> None:
        """Wake both threads (blocked recv/sendall return); the reader tears down."""
        self.closing.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass  # already shut down or reset by the peer

    def join(self, timeout: float) -> None:
        self.reader.join(timeout)

    def _send(self, text: str) -> None:
        with self._send_lock:
            self.sock.sendall(text.encode("ascii"))

    # -- reader: TCP -> bus ------------------------------------------------------------------

    def _read(self) -> None:
        reason = "client closed"
        try:
            self._send("< hi >")
            buf = bytearray()
            while not self.closing.is_set():
                data = self.sock.recv(4096)
                if not data:
                    break
                if hasattr(socket, "TCP_QUICKACK"):  # ack at once, like socketcand -q
                    self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_QUICKACK, 1)
                buf += data
                self._handle_buffer(buf)
        except ProtocolError as exc:
            reason = "protocol error"
            self._refuse(str(exc))
        except OSError as exc:
            reason = "stopped" if self.closing.is_set() else f"connection lost: {exc}"
        except Exception as exc:  # noqa: BLE001 - stored, re-raised by SocketcandServer.stop()
            reason = "server failure"
            self.server._failed(exc, f"reader {self.peer}")
        finally:
            self._teardown(reason)

    def _handle_buffer(self, buf: bytearray) -> None:
        """Run every complete ``< ... >`` command in ``buf`` and remove it from ``buf``."""
        while True:
            start = 0
            while start < len(buf) and buf[start] in b" \t\r\n":
                start += 1
            del buf[:start]
            if not buf:
                return
            if buf[0] != ord("<"):
                raise ProtocolError(
                    f"expected '<' to start a command, got {bytes(buf[:20])!r}")
            end = buf.find(b">")
            if end < 0:
                if len(buf) > MAX_COMMAND:
                    raise ProtocolError(
                        f"no '>' within {MAX_COMMAND} characters of '<'")
                return
            if end + 1 > MAX_COMMAND:
                raise ProtocolError(f"command longer than {MAX_COMMAND} characters")
            raw = bytes(buf[1:end])
            del buf[:end + 1]
            self._handle_command(raw)

    def _handle_command(self, raw: bytes) -> None:
        if b"<" in raw:
            raise ProtocolError("'<' inside a command")
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            raise ProtocolError("non-ASCII bytes in a command") from None
        words = text.split()
        if not words:
            raise ProtocolError("empty command < >")
        if self.mode is _Mode.RAW:
            self.spoke.set()  # the client has read the rawmode < ok >: frames may flow
        handler = self._commands[self.mode].get(words[0])
        if handler is None:
            raise ProtocolError(self._why_not(words[0]))
        handler(words[1:])

    def _why_not(self, command: str) -> str:
        known = " ".join(sorted(self._commands[self.mode]))
        if command in _UNSERVED_MODES:
            return f"{command} is not served: this server speaks raw mode only (< rawmode >)"
        if command == "send" and self.mode is not _Mode.RAW:
            return "send before < rawmode >"
        if command == "rawmode" and self.mode is _Mode.NO_BUS:
            return "rawmode before < open CHANNEL >"
        return (f"unknown command {command!r} in {self.mode.value} mode "
                f"(known here: {known})")

    def _cmd_open(self, args: list[str]) -> None:
        if len(args) != 1:
            raise ProtocolError("open takes one channel name: < open CHANNEL >")
        name = args[0]
        allowed = self.server.channels
        if allowed is not None and name not in allowed:
            raise ProtocolError(
                f"could not open bus {name} (served: {' '.join(sorted(allowed)) or 'none'})")
        if name in self.server.unplugged:
            raise ProtocolError(f"could not open bus {name} (its adapter is unplugged)")
        self.channel = name
        self.mode = _Mode.BUS_OPEN
        self._send("< ok >")

    def _cmd_rawmode(self, args: list[str]) -> None:
        if args:
            raise ProtocolError("rawmode takes no arguments")
        # The bus exists before the < ok > goes out: no frame sent after the client's
        # handshake is missed.
        self.bus = can.Bus(interface="virtual", channel=self.channel,
                           receive_own_messages=False)
        self.mode = _Mode.RAW
        self.ok_at = time.monotonic()
        self._send("< ok >")
        self.forwarder.start()

    def _cmd_echo(self, args: list[str]) -> None:
        if args:
            raise ProtocolError("echo takes no arguments")
        self._send("< echo >")

    def _cmd_send(self, args: list[str]) -> None:
        msg = parse_send(args)
        assert self.bus is not None
        self.bus.send(msg)
        self.frames_in += 1
        self.server._count("frames_in")

    def _refuse(self, text: str) -> None:
        """Answer ``< error text >``, close our side, read what is left, then let go."""
        self.server._count("errors")
        log.warning("socketcand_client_error", peer=self.peer, channel=self.channel,
                    error=text)
        try:
            self._send(f"< error {_safe_text(text)} >")
            self.sock.shutdown(socket.SHUT_WR)
            # Closing with unread input would make the kernel send a reset, which may
            # destroy the error line before the client reads it: drain first (bounded).
            self.sock.settimeout(ERROR_LINGER_S)
            deadline = time.monotonic() + ERROR_LINGER_S
            while not self.closing.is_set() and time.monotonic() < deadline:
                if not self.sock.recv(4096):
                    break
        except OSError:
            pass  # the client is gone already: nothing left to tell it

    def _teardown(self, reason: str) -> None:
        self.close()
        reason = self.forward_error or reason
        if self.forwarder.is_alive():
            self.forwarder.join(JOIN_TIMEOUT_S)
        if self.bus is not None:
            self.bus.shutdown()
        self.sock.close()
        self.server._forget(self)
        log.info("socketcand_client_closed", peer=self.peer, channel=self.channel,
                 reason=reason, frames_in=self.frames_in, frames_out=self.frames_out)

    # -- forwarder: bus -> TCP ---------------------------------------------------------------

    def _forward(self) -> None:
        """Send every frame of the virtual channel to the client, in order.

        python-can's client reads the rawmode answer with one ``recv(256)`` and requires
        it to be exactly ``< ok >``: a frame that lands in the client's socket buffer
        before that read would be returned with it and fail its handshake.  So frames are
        held back (in order, up to :data:`HELD_FRAMES_MAX`) until the client has sent
        something -- proof that it has read the ``< ok >`` -- or ``handshake_grace``
        (~100 ms) has passed since the ``< ok >`` for a client that only listens.
        """
        bus = self.bus
        assert bus is not None
        held: deque[can.Message] = deque()
        release_at = self.ok_at + self.server.handshake_grace
        gate_open = False
        try:
            while not self.closing.is_set():
                timeout = POLL_S
                if not gate_open:
                    left = release_at - time.monotonic()
                    gate_open = self.spoke.is_set() or left <= 0.0
                    timeout = min(POLL_S, max(left, 0.0))
                msg = bus.recv(timeout=timeout)
                if msg is not None:
                    self._hold(held, msg)
                if not gate_open:
                    continue
                while len(held) < MAX_BATCH:
                    more = bus.recv(timeout=0.0)
                    if more is None:
                        break
                    self._hold(held, more)
                if held:
                    self._flush(held)
        except BlockingIOError:  # SO_SNDTIMEO expired: the reader tears down
            if not self.closing.is_set():
                self.forward_error = f"client read nothing for {SEND_TIMEOUT_S} s"
        except (OSError, can.CanError) as exc:
            if not self.closing.is_set():  # peer gone: the reader tears down
                self.forward_error = f"sending to the client failed: {exc}"
        except Exception as exc:  # noqa: BLE001 - stored, re-raised by SocketcandServer.stop()
            self.server._failed(exc, f"forwarder {self.peer}")
        finally:
            self.close()

    def _hold(self, held: deque[can.Message], msg: can.Message) -> None:
        if len(held) >= HELD_FRAMES_MAX:
            held.popleft()
            self.server._count("dropped")
        held.append(msg)

    def _flush(self, held: deque[can.Message]) -> None:
        lines = []
        while held:
            line = format_frame(held.popleft())
            if line is None:
                self.server._count("dropped")
            else:
                lines.append(line)
        if lines:
            self._send("".join(lines))
            self.frames_out += len(lines)
            self.server._count("frames_out", len(lines))
