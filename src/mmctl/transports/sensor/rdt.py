"""ATI force/torque sensor over Ethernet: RDT (Raw Data Transfer) on UDP, port 49152.

Wire protocol (big-endian):

* request, client -> sensor, 8 bytes: ``uint16 0x1234, uint16 command, uint32 count``;
  command 0x0002 starts streaming ``count`` records (0 = until stopped), 0x0000 stops,
  0x0042 sets the device's software bias (the current load reads zero afterwards).
* record, sensor -> client, 36 bytes: ``uint32 rdt_sequence, uint32 ft_sequence,
  uint32 status, int32 Fx, Fy, Fz, Tx, Ty, Tz [counts]``; force = counts /
  counts-per-force, torque = counts / counts-per-torque (``sensor.rdt``).

Status: bits in ``sensor.rdt.status_saturation_mask`` raise
``SafetyFault(SENSOR_SATURATION)``, bits in ``status_error_mask`` (default bit 31, the
device's error summary) raise ``SafetyFault(SENSOR_STATUS)``; other bits are reported in
``Wrench.status`` and otherwise ignored.  A datagram that is not 36 bytes raises
:class:`~mmctl.errors.ProtocolError`.

Why no reader thread: :meth:`RdtForceSensor.read` drains the non-blocking socket each
call (a few ``recv_into`` of 36 bytes, ~µs each) and keeps the newest record.  The kernel
socket buffer does the queueing a thread would do, every record still passes through
the lost / out-of-order counters, nothing competes with the control loop for the GIL,
and there is no lock and no thread error to carry across.  A read never blocks: if no
record arrived since the last one the previous sample is returned again, until it is
older than ``sensor.wrench.stale_timeout`` -> ``SafetyFault(SENSOR_STALE)``.

Sequence counting (:class:`SequenceTracker`): the RDT sequence is uint32 (wraps).  A
record ahead of the newest by ``d`` counts ``d - 1`` lost and remembers the missing
numbers (the last 256); a record that fills a remembered gap is late: it counts one
out-of-order, is discarded, and the lost count goes back down by one.

Sequence resets: the device numbers the records of each stream from the start, so every
start request (ours after a silence, another client's, the device's own reboot) restarts
``rdt_sequence``.  A record at or behind the newest that fills no gap is a new stream,
accepted at once and counted in ``resets``, when it is more than 256 behind (no network
reorders that far) or numbered 0 or 1 (a stream's first record); otherwise it is
discarded as out-of-order, unless it is the third of a run of consecutive numbers behind
the newest: that record starts the new stream (the run's two before it are not counted
out-of-order).  So after any restart the client takes records again by the third one at
the latest; before this, it refused every record until the new stream passed the old
one's number.  Each reset is logged once (``rdt_sequence_reset``; at most one line a
second, with the count of those left out, should a peer reset the stream constantly).

Re-start on silence: a Net F/T streams only after a start request and forgets it when it
reboots.  When no record came for ``sensor.rdt.restart_after``, :meth:`read` sends the
start request again (``restarts`` in :meth:`RdtForceSensor.stats`), then at doubling
intervals up to 1 s while the silence lasts; the attempts 1, 2, 4, 8, ... are logged
(``rdt_restart_sent``), the first record after them too (``rdt_stream_recovered``).  The
transport only recovers the stream: every read of a silent sensor past
``stale_timeout`` still raises ``SENSOR_STALE``, and the daemon keeps its fault latched
until the operator enables again.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from collections import OrderedDict
from types import TracebackType
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import structlog

from mmctl.config.sensor import SensorRdtConfig
from mmctl.errors import FaultCause, LinkLost, ProtocolError, SafetyFault, TransportError
from mmctl.runtime.logging import RateLimiter
from mmctl.transports.sensor.protocol import SensorStats
from mmctl.types import Wrench

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self

log = structlog.get_logger("mmctl.sensor.rdt")

RDT_PORT = 49152
RDT_HEADER = 0x1234
CMD_STOP = 0x0000
CMD_START = 0x0002
REQUEST = struct.Struct(">HHI")
RECORD = struct.Struct(">III6i")
RECORD_SIZE = RECORD.size  # 36
_SEQ = struct.Struct(">I")
_WRAP = 1 << 32
_HALF = 1 << 31
_MISSING_WINDOW = 256
#: a record further behind the newest than this (and filling no gap) starts a new stream
_REORDER_WINDOW = _MISSING_WINDOW
#: a record numbered at most this, behind the newest and filling no gap: a new stream
_RESTART_NEAR = 1
#: this many consecutive numbers behind the newest (filling no gap): a new stream
_RESET_RUN = 3
#: the longest interval between start requests re-sent while the sensor is silent [s]
_RESTART_MAX_INTERVAL = 1.0


def encode_request(command: int, count: int = 0) -> bytes:
    """The 8-byte RDT request."""
    return REQUEST.pack(RDT_HEADER, command, count)


def restart_interval(restart_after: float, attempt: int) -> float:
    """Seconds from the start request ``attempt`` (1, 2, ...) re-sent on silence to the
    next one: ``restart_after`` doubled each time, at most 1 s (or ``restart_after``
    when that is longer)."""
    cap = max(restart_after, _RESTART_MAX_INTERVAL)
    return min(restart_after * 2.0 ** min(max(attempt - 1, 0), 64), cap)


class RdtRecord(NamedTuple):
    """One decoded RDT record; counts: (Fx, Fy, Fz, Tx, Ty, Tz) [counts]."""

    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: tuple[int, int, int, int, int, int]


def decode_record(data: bytes) -> RdtRecord:
    """36 bytes -> :class:`RdtRecord`; any other length is a ProtocolError."""
    if len(data) != RECORD_SIZE:
        raise ProtocolError(f"RDT record must be {RECORD_SIZE} bytes, got {len(data)}")
    rdt_seq, ft_seq, status, *counts = RECORD.unpack(data)
    return RdtRecord(rdt_seq, ft_seq, status, tuple(counts))


class SequenceTracker:
    """Lost / out-of-order / reset counters from a wrapping uint32 sequence (see module
    doc).  ``last_reset``: (newest before, first of the new stream) of the latest reset."""

    def __init__(self) -> None:
        self.newest: int | None = None
        self.lost = 0
        self.out_of_order = 0
        self.resets = 0
        self.last_reset: tuple[int, int] | None = None
        self._missing: OrderedDict[int, None] = OrderedDict()
        self._run_last: int | None = None
        self._run_len = 0

    def observe(self, seq: int) -> bool:
        """Account for ``seq``; True when it is the newest record now (newer than every
        record seen so far, or the first of a new stream)."""
        newest = self.newest
        if newest is None:
            self.newest = seq
            return True
        d = (seq - newest) % _WRAP
        if 0 < d < _HALF:
            self.lost += d - 1
            for k in range(max(1, d - _MISSING_WINDOW), d):
                self._missing[(newest + k) % _WRAP] = None
            while len(self._missing) > _MISSING_WINDOW:
                self._missing.popitem(last=False)
            self.newest = seq
            self._run_last = None
            return True
        if seq in self._missing:  # late: fills its gap
            del self._missing[seq]
            self.lost -= 1
            self.out_of_order += 1
            return False
        behind = (newest - seq) % _WRAP  # 0: the newest again
        if behind > _REORDER_WINDOW or (seq <= _RESTART_NEAR and behind > 0):
            return self._reset(seq)
        if self._run_last is not None and (seq - self._run_last) % _WRAP == 1:
            self._run_len += 1
        else:
            self._run_len = 1
        self._run_last = seq
        if self._run_len >= _RESET_RUN:
            self.out_of_order -= self._run_len - 1  # they were a new stream, not late
            return self._reset(seq)
        self.out_of_order += 1
        return False

    def _reset(self, seq: int) -> bool:
        assert self.newest is not None
        self.last_reset = (self.newest, seq)
        self.resets += 1
        self.newest = seq
        self._missing.clear()
        self._run_last = None
        return True


class RdtForceSensor:
    """:class:`~mmctl.transports.sensor.protocol.ForceSensor` over RDT/UDP (see module doc).

    cfg: the ``sensor.rdt`` section; stale_timeout: no fresh record for longer -> fault
    [s].  No I/O before :meth:`connect`.
    """

    def __init__(self, cfg: SensorRdtConfig, *, stale_timeout: float = 0.010) -> None:
        self._cfg = cfg
        self._stale = stale_timeout
        self._scale = 1.0 / np.array((cfg.counts_per_force,) * 3 + (cfg.counts_per_torque,) * 3)
        self._sock: socket.socket | None = None
        self._buf = bytearray(2048)
        self._tracker = SequenceTracker()
        self._received = 0
        self._last: Wrench | None = None
        self._last_fresh = 0.0
        self._restart_after = cfg.restart_after
        self._restarts = 0  # start requests re-sent on silence, since connect
        self._attempts = 0  # ... in the current silence
        self._restart_next = 0.0
        self._log_limit = RateLimiter(1.0)  # rdt_sequence_reset lines
        self._failed = False  # a send or receive failed (LinkLost): reconnect() reopens

    @property
    def link(self) -> str:
        """Where the sensor is expected, for messages: ``udp://host:port``."""
        return f"udp://{self._cfg.host}:{self._cfg.port}"

    # -- lifecycle ---------------------------------------------------------------------

    def connect(self) -> None:
        """Open the socket, start streaming, wait for the first record."""
        if self._sock is not None:
            return
        cfg = self._cfg
        try:
            addr = socket.getaddrinfo(cfg.host, cfg.port, socket.AF_INET, socket.SOCK_DGRAM)[0][4]
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        except OSError as exc:
            raise TransportError(f"cannot open {self.link}: {exc}") from exc
        self._sock = sock
        self._failed = False
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            sock.connect(addr)  # only the sensor's datagrams; ICMP errors become exceptions
            sock.setblocking(False)
            self._tracker = SequenceTracker()
            self._received = 0
            self._last = None
            self._restarts = self._attempts = 0
            self._restart_next = 0.0
            self._send(CMD_START)
            self._wait_records(1, cfg.connect_timeout, resend=CMD_START)
        except BaseException:
            self.close()
            raise
        log.info("sensor_connected", transport="rdt", link=self.link,
                 counts_per_force=cfg.counts_per_force, counts_per_torque=cfg.counts_per_torque)

    def reconnect(self) -> None:
        """After a failed link (a send or receive error: LinkLost): close the socket and
        connect again (new socket, start streaming, first record).  Does nothing while
        the link works (idempotent).  Raises LinkLost (cause ``sensor_link_lost``)
        naming the link while the sensor does not answer."""
        if self._sock is not None and not self._failed:
            return
        self.close()
        try:
            self.connect()
        except TransportError as exc:
            raise LinkLost.wrap(self.link, FaultCause.SENSOR_LINK,
                                "reconnect failed", exc) from exc
        log.info("sensor_reconnected", transport="rdt", link=self.link)

    def close(self) -> None:
        """Stop streaming (best effort) and close the socket; safe to call twice."""
        sock, self._sock = self._sock, None
        if sock is None:
            return
        try:
            sock.send(encode_request(CMD_STOP))
        except OSError as exc:  # the peer may be gone already; the socket closes anyway
            log.debug("rdt_stop_not_sent", link=self.link, error=str(exc))
        finally:
            sock.close()

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- data --------------------------------------------------------------------------

    def read(self) -> Wrench:
        """The newest record as a wrench [N, N m]; never blocks (see module doc)."""
        if self._sock is None:
            raise TransportError(f"RDT F/T sensor {self.link} is not connected")
        fresh = self._drain()
        if fresh is None:
            now = time.monotonic()
            age = now - self._last_fresh
            if age > self._restart_after and now >= self._restart_next:
                self._restart(now, age)
            if age > self._stale or self._last is None:
                raise SafetyFault(FaultCause.SENSOR_STALE, age_ms=round(age * 1e3, 2),
                                  lost=self._tracker.lost, link=self.link)
            return self._last
        return fresh

    def stats(self) -> SensorStats:
        """Fresh records, the sequence counters and the re-sent starts since connect."""
        t = self._tracker
        return SensorStats(self._received, t.lost, t.out_of_order, t.resets, self._restarts)

    # -- internals ---------------------------------------------------------------------

    def _send(self, command: int) -> None:
        try:
            self._sock.send(encode_request(command))  # type: ignore[union-attr]
        except OSError as exc:
            raise self._lost(f"cannot send to {self.link}: {exc}") from exc

    def _lost(self, reason: str) -> TransportError:
        """The link failed: remember it for reconnect(); the error to raise (LinkLost
        once a record came, a plain TransportError while connect() waits for one)."""
        if self._last is None:
            return TransportError(reason)
        if not self._failed:
            log.warning(FaultCause.SENSOR_LINK.value, link=self.link, error=reason)
        self._failed = True
        return LinkLost(self.link, FaultCause.SENSOR_LINK, reason)

    def _restart(self, now: float, age: float) -> None:
        """The stream fell silent: send the start request again (never raises: a silent
        sensor is the stale fault's, reported by the read)."""
        self._restarts += 1
        self._attempts = n = self._attempts + 1
        self._restart_next = now + restart_interval(self._restart_after, n)
        error = None
        try:
            self._sock.send(encode_request(CMD_START))  # type: ignore[union-attr]
        except OSError as exc:  # e.g. refused while the sensor reboots: try again later
            error = str(exc)
        if n & (n - 1) == 0:  # attempts 1, 2, 4, 8, ...: a long outage logs little
            log.warning("rdt_restart_sent", link=self.link, silent_ms=round(age * 1e3, 1),
                        attempt=n, error=error)

    def _drain(self) -> Wrench | None:
        """Read every queued datagram; the newest in-order record as a Wrench, or None."""
        sock = self._sock
        buf = self._buf
        tracker = self._tracker
        newest: bytes | None = None
        status_or = 0
        resets = tracker.resets
        while True:
            try:
                n = sock.recv_into(buf)  # type: ignore[union-attr]
            except BlockingIOError:
                break
            except ConnectionRefusedError as exc:
                raise self._lost(f"nothing answers at {self.link} (connection refused)") from exc
            except OSError as exc:
                raise self._lost(f"receive from {self.link} failed: {exc}") from exc
            if n != RECORD_SIZE:
                raise ProtocolError(f"RDT datagram of {n} bytes from {self.link}, expected 36")
            (seq,) = _SEQ.unpack_from(buf, 0)
            if tracker.observe(seq):
                newest = bytes(buf[:RECORD_SIZE])
                status_or |= _SEQ.unpack_from(buf, 8)[0]
                self._received += 1
        if newest is None:
            return None
        if tracker.resets != resets and tracker.last_reset is not None:
            suppressed = self._log_limit.allow("reset")
            if suppressed is not None:
                log.warning("rdt_sequence_reset", link=self.link, resets=tracker.resets,
                            previous=tracker.last_reset[0], first=tracker.last_reset[1],
                            suppressed=suppressed)
        rec = decode_record(newest)
        t = time.monotonic()
        if self._attempts:
            log.info("rdt_stream_recovered", link=self.link, attempts=self._attempts,
                     silent_ms=round((t - self._last_fresh) * 1e3, 1))
            self._attempts = 0
            self._restart_next = 0.0
        cfg = self._cfg
        if status_or & cfg.status_saturation_mask:
            raise SafetyFault(FaultCause.SENSOR_SATURATION, status=hex(status_or))
        if status_or & cfg.status_error_mask:
            raise SafetyFault(FaultCause.SENSOR_STATUS, status=hex(status_or))
        w = np.array(rec.counts, dtype=np.float64) * self._scale
        wrench = Wrench(w[:3], w[3:], t, rec.rdt_sequence, rec.status)
        self._last = wrench
        self._last_fresh = t
        return wrench

    def _wait_records(self, n: int, timeout: float, resend: int | None = None) -> None:
        """Block until ``n`` fresh records arrived (UDP: resend ``resend`` every 100 ms)."""
        start = self._received
        deadline = time.monotonic() + timeout
        next_resend = time.monotonic() + 0.1
        while self._received - start < n:
            now = time.monotonic()
            if now >= deadline:
                raise TransportError(
                    f"nothing answers at {self.link}: {self._received - start}/{n} RDT "
                    f"records within {timeout * 1e3:.0f} ms"
                )
            if resend is not None and now >= next_resend:
                self._send(resend)
                next_resend = now + 0.1
            wake = deadline if resend is None else min(deadline, next_resend)
            sock = self._sock
            assert sock is not None
            select.select([sock], [], [], max(0.0, wake - now))
            self._drain()
