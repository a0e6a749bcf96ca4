"""Opening a CAN bus from a configuration section, on any python-can interface.

``socketcan`` on the robot, ``socketcand`` (host, port, channel) for the simulated
robot (:mod:`mmctl.sim.socketcand` serves its channels) or a remote bus, ``virtual``
in one process (unit tests).  The sensor's bus and the canopen master's go through
:func:`bus_options`, so both take the same keys.

python-can's socketcand client retries a refused connect for 10 s in a busy loop and
waits without a timeout for the server's greeting; :func:`probe_socketcand` checks
the server first, with a timeout, so a missing simulated robot is one clear error.
"""

from __future__ import annotations

import logging
import socket
from typing import Any, Protocol

from mmctl.errors import TransportError


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
        # ("incomplete message => waiting for more data"): normal on a stream socket
        logging.getLogger("can.interfaces.socketcand.socketcand").setLevel(logging.ERROR)
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
