"""The keys every CAN section has (``sensor.can``, ``base.canopen``): which python-can
interface, which channel, and for socketcand where its server is.  Each call makes a
new field (a dataclass field belongs to one class)."""

from __future__ import annotations

from typing import Any

from mmctl.config.schema import param


def interface() -> Any:
    return param(
        "socketcan", min_len=1,
        doc="python-can interface: 'socketcan' on the robot, 'socketcand' for the simulated "
        "robot or a remote bus (host, port), 'virtual' in one process (unit tests)")


def channel(default: str) -> Any:
    return param(default, min_len=1, doc="python-can channel (socketcand: the bus it serves)")


def host() -> Any:
    return param("127.0.0.2", min_len=1, doc="socketcand server address (socketcand only)")


def port() -> Any:
    return param(29536, ge=1, le=65535, doc="socketcand server port (socketcand only)",
                 why="a TCP port")


def bitrate() -> Any:
    return param(1_000_000, ge=10_000, le=1_000_000, unit="bit/s",
                 doc="CAN bit rate (socketcan sets it on the interface; the others ignore it)",
                 why="classic CAN (ISO 11898) runs from 10 kbit/s to 1 Mbit/s")
