"""The keys every CAN section has (``sensor.can``, ``base.canopen``): which python-can
interface, which channel, and for socketcand where its server is.  Each call makes a
new field (a dataclass field belongs to one class)."""

from __future__ import annotations

from typing import Any

from mmctl.config.schema import param


def interface() -> Any:
    return param(
        "virtual", min_len=1,
        doc="python-can interface: 'socketcan' on the robot, 'socketcand' for the simulated "
        "robot or a remote bus (host, port), 'virtual' in one process (unit tests)")


def channel(default: str) -> Any:
    return param(default, min_len=1, doc="python-can channel (socketcand: the bus it serves)")


def host() -> Any:
    return param("127.0.0.2", min_len=1, doc="socketcand server address (socketcand only)")


def port() -> Any:
    return param(29536, gt=0, le=65535, doc="socketcand server port (socketcand only)")


def bitrate() -> Any:
    return param(1_000_000, gt=0, unit="bit/s")
