"""The fake controller's command log: what a client sent, stamped with controller time."""

from __future__ import annotations

import bisect
import itertools
import struct
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

_KINDS = tuple(CommandKind)
_KIND_INDEX = {kind: i for i, kind in enumerate(_KINDS)}
#: an encoded entry's head: seq, controller_time, kind (index into _KINDS), which
#: optional fields follow (_HAS_* bits), number of qd values
_HEAD = struct.Struct("<qdBBB")
_HAS_QD, _HAS_ACC, _HAS_TIME, _HAS_DEC, _HAS_CODE, _HAS_TEXT, _HAS_REPLY, _HAS_RECEIVED = (
    1 << i for i in range(8))
_FLOATS = ((_HAS_ACC, "acceleration"), (_HAS_TIME, "time"), (_HAS_DEC, "deceleration"))
_BODIES: dict[tuple[int, int], struct.Struct] = {}


def _body(flags: int, n_qd: int) -> struct.Struct:
    """The fixed-size part of an entry with these fields (text and reply follow it)."""
    key = (flags, n_qd)
    fmt = _BODIES.get(key)
    if fmt is None:
        parts = ["<qdBBB", "d" * n_qd]
        parts += ["d" for bit, _ in _FLOATS if flags & bit]
        parts += ["q" if flags & _HAS_CODE else "", "I" if flags & _HAS_TEXT else "",
                  "I" if flags & _HAS_REPLY else "", "d" if flags & _HAS_RECEIVED else ""]
        fmt = _BODIES[key] = struct.Struct("".join(parts))
    return fmt


def encode(seq: int, controller_time: float, kind: CommandKind, received: float | None,
           **fields: object) -> bytes:
    """One log entry as a single bytes object (see :class:`CommandLog`)."""
    qd = fields.get("qd")
    values: list[object] = []
    flags = 0
    if qd is not None:
        flags |= _HAS_QD
        values += qd  # type: ignore[arg-type]
    for bit, name in _FLOATS:
        if fields.get(name) is not None:
            flags |= bit
            values.append(fields[name])
    if fields.get("code") is not None:
        flags |= _HAS_CODE
        values.append(fields["code"])
    strings = b""
    for bit, name in ((_HAS_TEXT, "text"), (_HAS_REPLY, "reply")):
        text = fields.get(name)
        if text is not None:
            raw = str(text).encode("utf-8", "surrogatepass")
            flags |= bit
            values.append(len(raw))
            strings += raw
    if received is not None:
        flags |= _HAS_RECEIVED
        values.append(received)
    n_qd = 0 if qd is None else len(qd)  # type: ignore[arg-type]
    return _body(flags, n_qd).pack(seq, controller_time, _KIND_INDEX[kind], flags, n_qd,
                                   *values) + strings


def entry_seq(entry: bytes) -> int:
    """The seq of an encoded entry."""
    seq: int = _HEAD.unpack_from(entry)[0]
    return seq


def decode(entry: bytes) -> FakeCommand:
    """The :class:`FakeCommand` of an encoded entry."""
    _seq, _t, _k, flags, n_qd = _HEAD.unpack_from(entry)
    body = _body(flags, n_qd)
    seq, t, kind, _f, _n, *rest = body.unpack_from(entry)
    out: dict[str, object] = {}
    i = 0
    if flags & _HAS_QD:
        out["qd"] = tuple(rest[:n_qd])
        i = n_qd
    for bit, name in _FLOATS:
        if flags & bit:
            out[name] = rest[i]
            i += 1
    if flags & _HAS_CODE:
        out["code"] = rest[i]
        i += 1
    pos = body.size
    for bit, name in ((_HAS_TEXT, "text"), (_HAS_REPLY, "reply")):
        if flags & bit:
            n = rest[i]
            i += 1
            out[name] = entry[pos:pos + n].decode("utf-8", "surrogatepass")
            pos += n
    if flags & _HAS_RECEIVED:
        out["received"] = rest[i]
    return FakeCommand(seq, t, _KINDS[kind], **out)  # type: ignore[arg-type]


class CommandLog:
    """A bounded ring of :class:`FakeCommand` (the oldest entries are dropped).

    The ring keeps each entry as one ``bytes`` object (:func:`encode`: numbers packed,
    text and reply as UTF-8), which Python's garbage collector does not track;
    :meth:`since` rebuilds the :class:`FakeCommand` objects.  A full ring of 200 000
    ``FakeCommand`` (an enum member in each keeps it tracked) made every full collection
    of the fake's process take about 60 ms, and the daemon faulted on the controller's
    stalled clock (``arm_timestamp_stale``) a few minutes into a run.  As tuples of
    numbers, a speedJ entry was still 13 Python objects and about 500 bytes; the
    simulation's process (`mmctl sim`) keeps a copy of the controller's log (it must
    outlive a killed controller), fetched at each injected disconnection, and grew by
    hundreds of MB over an hour's soak.  Encoded, an entry is one object of about
    130 bytes, and its copy crosses the pipe as it is (:meth:`rows`, :meth:`extend`).

    first_seq: the seq of the first entry (a restarted controller's log continues its
    predecessor's numbering).
    """

    def __init__(self, capacity: int = 200_000, first_seq: int = 0):
        self._ring: deque[bytes] = deque(maxlen=capacity)
        self._seq = first_seq

    def __len__(self) -> int:
        return len(self._ring)

    @property
    def next_seq(self) -> int:
        """The seq the next entry gets."""
        return self._seq

    def add(self, controller_time: float, kind: CommandKind, **fields: object) -> None:
        if not _KNOWN.issuperset(fields):
            raise TypeError(f"unknown command log fields: {sorted(set(fields) - _KNOWN)}")
        self._ring.append(encode(self._seq, controller_time, kind, time.monotonic(),
                                 **fields))
        self._seq += 1

    def rows(self, seq: int, limit: int | None = None) -> list[bytes]:
        """The encoded entries with ``entry.seq >= seq`` (oldest first), at most
        ``limit`` of them (for :meth:`extend` of another log)."""
        ring = self._ring
        start = self._index(seq)
        stop = len(ring) if limit is None else min(len(ring), start + max(0, limit))
        return list(itertools.islice(ring, start, stop))  # (a deque's [i] walks to i)

    def extend(self, rows: list[bytes]) -> None:
        """Append encoded entries of another log (their seqs kept: ascending, above
        this log's own)."""
        if not rows:
            return
        first = entry_seq(rows[0])
        if first < self._seq:
            raise ValueError(f"entries from seq {first} do not follow this log's "
                             f"(next seq {self._seq})")
        self._ring.extend(rows)
        self._seq = entry_seq(rows[-1]) + 1

    def since(self, seq: int) -> list[FakeCommand]:
        """Entries with ``entry.seq >= seq`` (oldest first)."""
        return [decode(e) for e in self.rows(seq)]

    def _index(self, seq: int) -> int:
        """The index of the first entry with ``entry.seq >= seq`` (len: none)."""
        ring = self._ring
        if not ring or entry_seq(ring[-1]) < seq:
            return len(ring)
        guess = seq - entry_seq(ring[0])  # seqs are contiguous unless entries of another
        if guess <= 0:                    # log were dropped before they were extended
            return 0
        if guess < len(ring) and entry_seq(ring[guess]) == seq:
            return guess
        return bisect.bisect_left(ring, seq, key=entry_seq)
