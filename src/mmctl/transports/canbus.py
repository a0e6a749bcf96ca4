"""Opening a CAN bus from a configuration section, on any python-can interface.

``socketcan`` on the robot, ``socketcand`` (host, port, channel) for the simulated
robot (:mod:`mmctl.sim.socketcand` serves its channels) or a remote bus, ``virtual``
in one process (unit tests).  The sensor's bus and the canopen master's go through
:func:`bus_options`, so both take the same keys.

python-can's socketcand client retries a refused connect for 10 s in a busy loop and
waits without a timeout for the server's greeting; :func:`probe_socketcand` checks
the server first, with a timeout, so a missing simulated robot is one clear error.

**A link that fails** (:class:`GuardedBus`, opened by :func:`open_bus`).  The client
libraries report a failing link in many ways: ``can.CanError`` (python-can wraps a
failed socket read in it and logs the traceback), a raw ``OSError`` from a send
(``BrokenPipeError``, ``ConnectionResetError``; ``ENETDOWN``/``ENOBUFS`` on SocketCAN),
or nothing at all: python-can's socketcand client takes the server's EOF for "no frame"
and busy-waits out every receive timeout.  A helper thread that meets one of them (the
notifier's receive thread, a cyclic-send task) dies with a traceback.  The guard turns
all of them into one state: the first failure is recorded (:class:`LinkLost`, naming
the link; one warning event named after the fault, ``sensor_link_lost`` or
``base_link_lost``, without a traceback) and from then on the bus is
*dead*: ``send`` raises that :class:`LinkLost` at once, ``recv`` returns nothing (after
its timeout, so a receive thread idles instead of spinning), periodic tasks send
nothing.  No helper thread dies.  The owner (the sensor, the CANopen master) raises
:attr:`GuardedBus.lost` from its next call, and gets a working link only by opening a
new bus (its ``reconnect()``).
"""

from __future__ import annotations

import logging
import socket
import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import can
import structlog
from can.broadcastmanager import CyclicSendTaskABC, ThreadBasedCyclicSendTask

from mmctl.errors import FaultCause, LinkLost, TransportError

log = structlog.get_logger(__name__)


class CanLink(Protocol):
    """The keys of a CAN section (``sensor.can``, ``base.canopen``)."""

    interface: str
    channel: str
    bitrate: int
    host: str
    port: int


def bus_options(link: CanLink) -> dict[str, Any]:
    """Keyword arguments for ``can.Bus`` / ``canopen.Network.connect``."""
    if link.interface == "socketcand":
        # python-can's client logs a WARNING each time a TCP read ends inside a frame
        # ("incomplete message => waiting for more data"): normal on a stream socket;
        # and an ERROR with a traceback for a failed read, which GuardedBus reports as
        # one can_link_lost event instead
        logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.CRITICAL)
        # tcp_tune: TCP_NODELAY (+ QUICKACK): without it Nagle and delayed ACKs hold a
        # small frame back for up to 40 ms
        return {"interface": "socketcand", "channel": link.channel, "host": link.host,
                "port": link.port, "tcp_tune": True}
    return {"interface": link.interface, "channel": link.channel, "bitrate": link.bitrate}


def describe(link: CanLink) -> str:
    """``socketcand:mmctl-base@127.0.0.2:29536`` or ``socketcan:can0`` (for messages)."""
    where = f"@{link.host}:{link.port}" if link.interface == "socketcand" else ""
    return f"{link.interface}:{link.channel}{where}"


def probe_socketcand(host: str, port: int, timeout: float = 2.0) -> None:
    """Raise :class:`TransportError` unless a socketcand server greets at host:port."""
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.settimeout(timeout)
            hello = s.recv(64)
    except OSError as exc:
        raise TransportError(f"no socketcand server at {host}:{port} ({exc}); is the "
                             "simulated robot (`mmctl sim`) running?") from exc
    if not hello.startswith(b"< hi >"):
        raise TransportError(f"{host}:{port} is not a socketcand server (it said {hello[:40]!r})")


def check_link(link: CanLink, timeout: float = 2.0) -> None:
    """Before opening ``link``: its socketcand server answers (other interfaces: no-op)."""
    if link.interface == "socketcand":
        probe_socketcand(link.host, link.port, timeout)


def _peer_closed_probe(bus: can.BusABC) -> Callable[[], bool] | None:
    """For python-can's socketcand client: a check that the server closed the TCP
    connection (EOF).  The client itself takes an EOF for "no frame yet"."""
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    if not isinstance(sock, socket.socket):
        return None

    def peer_closed() -> bool:
        try:
            return sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT) == b""
        except (BlockingIOError, InterruptedError):
            return False  # nothing queued: the connection is open

    return peer_closed


class _QuietSender:
    """What a cyclic-send task sends through: the guarded bus's send, with a lost link
    recorded (by :meth:`GuardedBus.send`) instead of raised into the task's thread."""

    def __init__(self, bus: GuardedBus) -> None:
        self._bus = bus

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._bus.lost is not None:
            return
        try:
            self._bus.send(msg, timeout)
        except LinkLost:
            pass  # recorded and logged once by the bus; the owner raises it


class GuardedBus(can.BusABC):
    """A python-can bus whose failures are one recorded state (see the module doc).

    inner: the open bus it owns (shut down with it); link: its name for messages
    (``socketcand:can0@127.0.0.2:29536``); cause: the fault a lost link means for its
    device (``FaultCause.SENSOR_LINK``, ``FaultCause.BASE_LINK``).  Filtering is the
    inner bus's (its ``can_filters``).
    """

    def __init__(self, inner: can.BusABC, link: str, cause: FaultCause) -> None:
        self._inner = inner
        self.link = link
        self.cause = cause
        self._lost: LinkLost | None = None
        self._lost_lock = threading.Lock()
        self._closed = threading.Event()
        self._peer_closed = _peer_closed_probe(inner)
        super().__init__(channel=inner.channel_info, can_filters=None)
        self.channel_info = f"guarded {inner.channel_info}"

    @property
    def lost(self) -> LinkLost | None:
        """The recorded link failure, or None while the link works."""
        return self._lost

    def check(self) -> None:
        """Raise :class:`LinkLost` (a new instance, chained to the first failure) if the
        link failed."""
        lost = self._lost
        if lost is not None:
            raise LinkLost(lost.link, lost.cause, lost.reason) from lost.__cause__

    def fail(self, exc: BaseException, where: str) -> LinkLost:
        """Record ``exc`` (met while doing ``where``) as the link's failure, once; log
        one warning event named after the fault (no traceback).  Returns the recorded failure."""
        with self._lost_lock:
            if self._lost is None:
                reason = f"{where} failed: {type(exc).__name__}: {exc}".rstrip(": ")
                lost = LinkLost(self.link, self.cause, reason)
                lost.__cause__ = exc
                self._lost = lost
                log.warning(self.cause.value, link=self.link, during=where,
                            error=f"{type(exc).__name__}: {exc}")
            return self._lost

    # -- BusABC ------------------------------------------------------------------------

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame, or None after ``timeout`` [s].  Never raises for a failing
        link: the failure is recorded (:attr:`lost`) and None returned (at once when it
        happens; after ``timeout`` once the link is dead, so a receive thread idles)."""
        if self._lost is not None:
            self._closed.wait(timeout)
            return None
        try:
            msg = self._inner.recv(timeout)
            if msg is None and self._peer_closed is not None and self._peer_closed():
                raise EOFError("the socketcand server closed the connection")
        except Exception as exc:  # noqa: BLE001 - any library failure is a lost link
            if not self._closed.is_set():
                self.fail(exc, "receive")
            return None
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), True

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg``; raises :class:`LinkLost` (at once, no I/O, once the link is
        dead) when the library fails to."""
        if self._lost is not None:
            self.check()
        try:
            self._inner.send(msg, timeout)
        except (can.CanError, OSError, EOFError) as exc:
            self.fail(exc, "send")
            self.check()

    def _send_periodic_internal(
        self,
        msgs: Sequence[can.Message] | can.Message,
        period: float,
        duration: float | None = None,
        autostart: bool = True,
        modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> CyclicSendTaskABC:
        """python-can's thread-based task, sending through :class:`_QuietSender`: its
        thread never meets an exception (it would log a traceback and die)."""
        lock = getattr(self, "_lock_send_periodic", None)
        if lock is None:
            lock = self._lock_send_periodic = threading.Lock()
        return ThreadBasedCyclicSendTask(
            bus=_QuietSender(self),  # type: ignore[arg-type]  # only .send is used
            lock=lock, messages=msgs, period=period, duration=duration,
            autostart=autostart, modifier_callback=modifier_callback)

    def shutdown(self) -> None:
        """Stop the periodic tasks, close the inner bus; idempotent."""
        self._closed.set()
        super().shutdown()
        self._inner.shutdown()


def open_bus(link: CanLink, cause: FaultCause, *, connect_timeout: float = 2.0,
             **kwargs: Any) -> GuardedBus:
    """Open ``link`` (``kwargs`` to ``can.Bus``, e.g. ``can_filters``) behind a
    :class:`GuardedBus`.  Raises :class:`TransportError` naming the link when it cannot
    be opened (a socketcand server is probed first, within ``connect_timeout`` [s])."""
    check_link(link, connect_timeout)
    try:
        inner = can.Bus(**bus_options(link), **kwargs)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise TransportError(f"cannot open CAN bus {describe(link)}: {exc}") from exc
    return GuardedBus(inner, describe(link), cause)
