"""The fake controller's command log: what a client sent, stamped with controller time."""

from __future__ import annotations

import time
from collections import deque
from enum import Enum
from typing import NamedTuple


class CommandKind(str, Enum):
    """What a log entry records."""

    SPEEDJ = "speedj"  # qd, acceleration, time
    SPEED_STOP = "speed_stop"  # deceleration
    STOP_SCRIPT = "stop_script"
    RTDE_COMMAND = "rtde_command"  # any other ur_rtde command type: code
    DASHBOARD = "dashboard"  # text = the command line, reply = the answer
    SCRIPT = "script"  # text = program name (or the line), code = characters received
    PROGRAM = "program"  # text = "started" / "stopped" / "rejected: <why>"
    CONNECTION = "connection"  # text = "<port> open" / "<port> closed"


class FakeCommand(NamedTuple):
    """One entry of the command log.

    seq: running number (gaps mean the ring dropped entries); controller_time: the
    fake controller's timestamp [s] when the command arrived; kind: see
    :class:`CommandKind`; qd: (6,) joint speeds [rad/s] of a speedJ; acceleration
    [rad/s^2] and time [s] of a speedJ; deceleration [rad/s^2] of a speedStop; code:
    the ur_rtde command number (RTDE_COMMAND) or a size; text/reply: dashboard line and
    answer, program name, etc.; received: CLOCK_MONOTONIC [s] when the fake took it
    (``time.monotonic()``, comparable across the machine's processes: latency figures).
    """

    seq: int
    controller_time: float
    kind: CommandKind
    qd: tuple[float, ...] | None = None
    acceleration: float | None = None
    time: float | None = None
    deceleration: float | None = None
    code: int | None = None
    text: str | None = None
    reply: str | None = None
    received: float | None = None


_OPTIONAL = ("qd", "acceleration", "time", "deceleration", "code", "text", "reply")
_KNOWN = frozenset(_OPTIONAL)


class CommandLog:
    """A bounded ring of :class:`FakeCommand` (the oldest entries are dropped).

    The ring keeps each entry as a plain tuple of numbers and strings (the kind by its
    value), which Python's garbage collector stops tracking; :meth:`since` rebuilds the
    :class:`FakeCommand` objects.  A full ring of 200 000 ``FakeCommand`` (an enum member
    in each keeps it tracked) made every full collection of the fake's process take about
    60 ms, and the daemon faulted on the controller's stalled clock
    (``arm_timestamp_stale``) a few minutes into a run; as plain tuples it is about 5 ms.
    """

    def __init__(self, capacity: int = 200_000):
        self._ring: deque[tuple[object, ...]] = deque(maxlen=capacity)
        self._seq = 0

    def add(self, controller_time: float, kind: CommandKind, **fields: object) -> None:
        if not _KNOWN.issuperset(fields):
            raise TypeError(f"unknown command log fields: {sorted(set(fields) - _KNOWN)}")
        self._ring.append((self._seq, controller_time, kind.value,
                           *(fields.get(name) for name in _OPTIONAL), time.monotonic()))
        self._seq += 1

    def since(self, seq: int) -> list[FakeCommand]:
        """Entries with ``entry.seq >= seq`` (oldest first)."""
        ring = self._ring
        if not ring or ring[-1][0] < seq:  # type: ignore[operator]
            return []
        start = max(0, seq - ring[0][0])  # type: ignore[operator]
        return [FakeCommand(e[0], e[1], CommandKind(e[2]), *e[3:])  # type: ignore[arg-type]
                for e in (ring[i] for i in range(start, len(ring)))]
