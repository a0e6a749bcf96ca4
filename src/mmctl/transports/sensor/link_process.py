"""Any force/torque transport in a process of its own, behind a shared-memory mailbox.

The loop never waits on the sensor (SPEC §7, issue 28): :class:`SensorLinkProcess` runs
the transport ``open_sensor(cfg)`` builds (CAN or RDT) in a ``spawn`` child, which does
all of the link's I/O and publishes each fresh sample into a
:class:`~mmctl.runtime.mailbox.Mailbox` (:data:`FORCE_SENSOR_LAYOUT`); the parent's
:meth:`~SensorLinkProcess.read` copies the newest record out and never blocks.

The child's timing:

* a request/reply transport (one with ``request_next()``: CAN) is polled phased to the
  loop: the parent gives the loop's grid (``origin_ns``: any deadline of the loop, in
  ``perf_counter_ns``; ``period``), and the child sends the request ``lead`` before each
  deadline, then ``read()``s, which in the child may wait for the reply: the sample is
  published the moment it is decoded, so a fresh one is waiting when the cycle starts
  (its age at the loop's read is about ``lead`` minus the round trip);
* a streaming transport (RDT) is read every ``stream_poll`` and a sample is published
  when it is new.

Errors the child's transport raises become values: the record carries an error code
(:class:`LinkError`), a count of errors published and the id of a details message sent
first on the side pipe; the parent's ``read()`` raises the same exception the
in-process transport would have raised — ``SafetyFault`` with its cause and details
(stale, status bits, saturation), ``ProtocolError``, ``LinkLost`` with its link and
reason, ``TransportError`` — for every read while the newest record is an error, and
once for an error that a newer good record overwrote before the parent looked.  A lost
link (any ``TransportError`` but a ``ProtocolError``; a bare ``OSError``/``CanError``
of the client library is taken as ``LinkLost``) is published and the child then only
waits: the parent decides (``reconnect()``, which ``enable`` triggers, ends the child
and starts a new one; it does nothing while the link works, as the transports'
``reconnect()``).

The parent judges freshness by the sample's own time stamp (CLOCK_MONOTONIC, taken in
the child at reception): older than ``stale_timeout`` is ``SafetyFault(SENSOR_STALE)``;
a child that ended (killed, crashed) is ``LinkLost`` (cause ``sensor_link_lost``)
naming the link.

Process hygiene as :mod:`mmctl.transports.ur_rtde_process`: ``spawn``; the child leaves
the terminal's session and ignores the terminating signals (the daemon ends it); it
ends when the parent's pipe closes.  The parent owns the shared-memory segment and
unlinks it at ``close()``, also after the child died.
"""

from __future__ import annotations

import select
import time
from collections.abc import Sequence
from enum import IntEnum
from typing import Any, NamedTuple

import numpy as np
import structlog

from mmctl.config.sensor import SensorConfig
from mmctl.errors import (
    FaultCause,
    LinkLost,
    MmctlError,
    ProtocolError,
    SafetyFault,
    TransportError,
    again,
)
from mmctl.runtime.mailbox import Mailbox, MailboxLayout, Sample, check_clocks, now_ns
from mmctl.transports.child import Described, LinkProcess
from mmctl.transports.sensor.protocol import ForceSensor, SensorStats
from mmctl.types import Wrench

log = structlog.get_logger("mmctl.sensor.process")

FORCE_SENSOR_LAYOUT = MailboxLayout("force_sensor", (
    ("status", 1),        # the device's status word of the sample (0 = ok)
    ("wrench", 6),        # fx, fy, fz [N], tx, ty, tz [N m], sensor frame
    ("sequence", 1),      # the transport's sample counter
    ("error", 1),         # LinkError of the newest read in the child (0 = none)
    ("errors", 1),        # error records published since the child started
    ("detail", 1),        # id of the side-pipe message describing the newest error
    ("published_ns", 1),  # when the child published this record [ns, CLOCK_MONOTONIC]
    ("requested_ns", 1),  # when the child asked for the sample it read (0: streaming)
    ("received", 1), ("lost", 1), ("out_of_order", 1), ("resets", 1), ("restarts", 1),
))
"""The sensor's record; the header's t_ns is the *sample's* reception time."""

_I = {name: FORCE_SENSOR_LAYOUT.slice(name).start for name, _ in FORCE_SENSOR_LAYOUT.fields}
_STATUS, _SEQUENCE, _ERROR, _ERRORS, _DETAIL = (
    _I["status"], _I["sequence"], _I["error"], _I["errors"], _I["detail"])
_PUBLISHED, _REQUESTED = _I["published_ns"], _I["requested_ns"]
_WRENCH = FORCE_SENSOR_LAYOUT.slice("wrench")
_FORCE = slice(_WRENCH.start, _WRENCH.start + 3)
_TORQUE = slice(_WRENCH.start + 3, _WRENCH.stop)
_STATS = FORCE_SENSOR_LAYOUT.slice("received").start

START_TIMEOUT = 60.0
"""[s] for the child to start (imports on a loaded machine), on top of the link's own
connect timeouts."""
DEFAULT_LEAD = 1e-3
"""[s] the default ``lead`` (see :class:`SensorLinkProcess`)."""
CLOSE_TIMEOUT = 5.0
"""[s] for the child to end after ``close``; then it is killed."""
DETAIL_INTERVAL_NS = 50_000_000
"""[ns] between two details messages of one kind of error whose values change (a stale
fault's age): the side pipe carries a few messages a second at most."""


class LinkTiming(NamedTuple):
    """When the newest record's sample was asked for, decoded and published by the child
    [ns, CLOCK_MONOTONIC; 0: not known] (for telemetry and benchmarks)."""

    requested_ns: int
    received_ns: int
    published_ns: int


class LinkError(IntEnum):
    """What went wrong in the child's last read (the record's ``error`` field)."""

    NONE = 0
    STALE = 1  # SafetyFault(SENSOR_STALE) from the transport
    STATUS = 2  # SafetyFault(SENSOR_STATUS)
    SATURATION = 3  # SafetyFault(SENSOR_SATURATION)
    SAFETY = 4  # another SafetyFault cause
    PROTOCOL = 5  # ProtocolError
    LINK_LOST = 6  # TransportError: the child stops polling, the parent reconnects
    INTERNAL = 7  # any other exception (a bug): the child stops polling


_CAUSE_CODES = {FaultCause.SENSOR_STALE: LinkError.STALE,
                FaultCause.SENSOR_STATUS: LinkError.STATUS,
                FaultCause.SENSOR_SATURATION: LinkError.SATURATION}


def describe(exc: BaseException, link: str) -> tuple[LinkError, Described]:
    """An exception of the child's transport as (code, :data:`Described`); ``link`` names
    the link for a lost one that the client library raised bare (OSError, CanError)."""
    if isinstance(exc, SafetyFault):
        return (_CAUSE_CODES.get(exc.cause, LinkError.SAFETY),
                ("safety", exc.cause.value, dict(exc.details), str(exc)))
    if isinstance(exc, ProtocolError):
        return LinkError.PROTOCOL, ("protocol", None, {}, str(exc))
    if isinstance(exc, LinkLost):
        return LinkError.LINK_LOST, ("link_lost", exc.cause.value,
                                     {"link": exc.link, "reason": exc.reason}, str(exc))
    if isinstance(exc, TransportError):
        return LinkError.LINK_LOST, ("transport", None, {}, str(exc))
    what = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, OSError) or type(exc).__name__ == "CanError":  # the client library's
        return LinkError.LINK_LOST, ("link_lost", FaultCause.SENSOR_LINK.value,
                                     {"link": link, "reason": what}, what)
    return LinkError.INTERNAL, ("link_lost", FaultCause.SENSOR_LINK.value,
                                {"link": link, "reason": f"the link process failed: {what}"},
                                what)


def rebuild(data: Described) -> MmctlError:
    """The exception :func:`describe` described, as the in-process transport raised it."""
    kind, cause, details, message = data
    if kind == "safety":
        return SafetyFault(FaultCause(cause), **details)
    if kind == "protocol":
        return ProtocolError(message)
    if kind == "link_lost":
        return LinkLost(str(details["link"]), FaultCause(cause), str(details["reason"]))
    return TransportError(message)


class SensorLinkProcess(LinkProcess[LinkLost]):
    """:class:`~mmctl.transports.sensor.protocol.ForceSensor` whose transport runs in a
    child process (see the module doc).  No I/O before :meth:`connect`.

    cfg: the ``sensor:`` section (the child builds ``open_sensor(cfg)``);
    period: the loop's period [s] (``1 / loop.rate_hz``); origin_ns: one deadline of the
    loop [ns, ``perf_counter_ns``] (None: the child picks its own grid until
    :meth:`set_phase`); lead: how long before each deadline a request/reply sensor is
    asked [s]: the round trip's p90-p99 plus the child's wake-up lateness (~0.1 ms);
    the simulator's socketcand round trip is 0.4 ms p50, 0.7 ms p90 on a 2-core
    machine (docs/mailbox.md), hence 1 ms by default (None), or half the period if
    that is shorter;
    stream_poll: how often a streaming sensor is read [s]; stale_timeout: a sample
    older than this is ``SENSOR_STALE`` [s] (default ``sensor.wrench.stale_timeout``);
    rt_priority, cpu_affinity: the child's SCHED_FIFO priority (0: normal) and CPUs,
    best effort as the loop's (:func:`mmctl.runtime.loop.apply_realtime`; the child's
    timer slack is 1 us either way): when the loop runs real-time, so must its sensor,
    or anything at normal priority delays the samples;
    log_setup: (level, json) for the child's structlog (the daemon's own).
    """

    def __init__(self, cfg: SensorConfig, *, period: float = 0.002,
                 origin_ns: int | None = None, lead: float | None = None,
                 stream_poll: float = 250e-6, stale_timeout: float | None = None,
                 rt_priority: int = 0, cpu_affinity: Sequence[int] = (),
                 log_setup: tuple[str, bool | None] = ("info", None)) -> None:
        if not 1e-4 <= period <= 1.0:
            raise ValueError(f"period {period} s must be within 0.1 ms .. 1 s")
        if lead is None:
            lead = min(DEFAULT_LEAD, 0.5 * period)
        if not 0.0 <= lead < period:
            raise ValueError(f"lead {lead} s must be >= 0 and < the period {period} s")
        if not 1e-5 <= stream_poll <= 0.1:
            raise ValueError(f"stream_poll {stream_poll} s must be within 10 us .. 100 ms")
        stale = cfg.wrench.stale_timeout if stale_timeout is None else stale_timeout
        if not stale > 0.0:
            raise ValueError(f"stale_timeout {stale} s must be > 0")
        super().__init__(CLOSE_TIMEOUT)
        self.cfg = cfg
        self.period_ns = round(period * 1e9)
        self.origin_ns = origin_ns
        self.lead_ns = round(lead * 1e9)
        self.stream_poll = stream_poll
        self.stale_ns = round(stale * 1e9)
        self.realtime = (int(rt_priority), tuple(cpu_affinity))
        self.log_setup = log_setup
        self._link: str | None = None
        self._box: Mailbox | None = None
        self._sample = Sample(FORCE_SENSOR_LAYOUT)
        self._wrench: Wrench | None = None
        self._wrench_t_ns = 0
        self._errors_seen = 0
        self._missed_error = False

    @property
    def link(self) -> str:
        """The transport's link (``socketcand:chan@host:port@0x20``, ``udp://h:p``)."""
        if self._link is None:
            from mmctl.transports.sensor import open_sensor

            self._link = open_sensor(self.cfg).link  # builds it, no I/O
        return self._link

    @property
    def connected(self) -> bool:
        return self._box is not None and self._gone is None

    # -- lifecycle ---------------------------------------------------------------------

    def connect(self) -> None:
        """Start the child; return once its transport connected (and published a first
        sample), or raise what its ``connect()`` raised."""
        if self._box is not None:
            return
        check_clocks()
        box = Mailbox.create(FORCE_SENSOR_LAYOUT)

        def install(reply: tuple[Any, ...]) -> None:
            self._link = reply[1]
            self._box = box
            self._sample = Sample(FORCE_SENSOR_LAYOUT)
            self._wrench = None
            self._wrench_t_ns = 0
            self._errors_seen = 0
            self._missed_error = False

        phase = (self.origin_ns, self.period_ns, self.lead_ns)
        wait = START_TIMEOUT + 2 * max(self.cfg.can.connect_timeout, self.cfg.rdt.connect_timeout)
        self._start(_serve, (self.cfg, box.name, phase, self.stream_poll, self.realtime,
                             self.log_setup), "mmctl-sensor", (box,), wait, install)
        log.info("sensor_process_started", link=self._link, pid=self.pid, mailbox=box.name)

    def reconnect(self) -> None:
        """After a lost link (the child ended, or its transport lost the link and
        stopped): end the child and start a new one.  Does nothing while the link works.
        Raises LinkLost naming the link while the sensor does not answer, SafetyFault as
        :meth:`connect`.  Blocks (a process start, the transport's connect): never on
        the loop thread."""
        if self._box is not None and not self._lost():
            return
        self._restart(self.link, FaultCause.SENSOR_LINK)
        log.info("sensor_reconnected", transport="process", link=self.link)

    def set_phase(self, origin_ns: int, period: float | None = None) -> None:
        """Move the child's polling onto the loop's grid: ``origin_ns`` one deadline
        [ns, perf_counter_ns], ``period`` [s] (None: unchanged).  Never blocks."""
        if period is not None:
            if not self.lead_ns < round(period * 1e9) <= 1_000_000_000:
                raise ValueError(f"period {period} s must be within the lead "
                                 f"{self.lead_ns * 1e-9:g} s .. 1 s")
            self.period_ns = round(period * 1e9)
        self.origin_ns = origin_ns
        if self._conn is not None and self._gone is None:
            try:
                self._conn.send(("phase", origin_ns, self.period_ns))
            except OSError:
                pass  # the child is gone: the next read says so

    def close(self) -> None:
        """Ask the child to close its transport and end; kill it if it does not within
        CLOSE_TIMEOUT; unlink the mailbox.  Safe to call twice."""
        proc = self._close_child()
        if proc is not None:
            log.info("sensor_process_closed", link=self._link, exit_code=proc.exitcode)

    # -- per cycle ---------------------------------------------------------------------

    def read(self) -> Wrench:
        """The newest sample from the mailbox; never blocks (see the module doc).  The
        lock is only ever held briefly (here, and to swap the mailbox in connect/close)."""
        with self._lock:
            return self._read()

    def _read(self) -> Wrench:
        box = self._box
        if box is None:
            raise TransportError(f"F/T sensor {self.link}: the link process is not connected")
        s = self._sample
        f = s.fields  # plain floats: numpy's scalar paths cost tens of us when cold
        now = now_ns()
        if box.read_into(s):
            errors = int(f[_ERRORS])
            if errors != self._errors_seen:
                self._errors_seen = errors
                self._missed_error = True
            t_ns = s.t_ns
            if t_ns != self._wrench_t_ns and t_ns:
                self._wrench_t_ns = t_ns
                self._wrench = Wrench(np.array(f[_FORCE]), np.array(f[_TORQUE]), t_ns * 1e-9,
                                      int(f[_SEQUENCE]), int(f[_STATUS]))
        elif now - f[_PUBLISHED] > self.period_ns:
            self._check_child()  # quiet for a period: is the child still there? (a syscall)
        if self._gone is not None:
            raise again(self._gone)
        if f[_ERROR] or self._missed_error:
            self._missed_error = False
            raise self._error()
        age = now - self._wrench_t_ns
        if self._wrench is None or age > self.stale_ns:
            raise SafetyFault(FaultCause.SENSOR_STALE, age_ms=round(age * 1e-6, 2),
                              link=self.link, source="link_process")
        return self._wrench

    def timing(self) -> LinkTiming:
        """The newest record's times, as of the last :meth:`read`."""
        s = self._sample
        return LinkTiming(int(s.values[_REQUESTED]), s.t_ns, int(s.values[_PUBLISHED]))

    def stats(self) -> SensorStats:
        """The child transport's counters, as of the newest record read."""
        v = self._sample.values
        return SensorStats(*(int(x) for x in v[_STATS:_STATS + 5]))

    # -- internals ---------------------------------------------------------------------

    def _lost(self) -> bool:
        """The child ended, or its transport lost the link (it polls no more)."""
        self._check_child()
        code = int(self._sample.values[_ERROR])
        return self._gone is not None or code in (LinkError.LINK_LOST, LinkError.INTERNAL)

    def _who(self) -> str:
        return f"F/T sensor {self.link}: the link process"

    def _refused(self, reply: tuple[Any, ...]) -> MmctlError:
        return rebuild(reply[1])

    def _child_ended(self, exit_code: int | None) -> LinkLost:
        log.error("sensor_process_lost", link=self._link, exit_code=exit_code)
        return LinkLost(self.link, FaultCause.SENSOR_LINK,
                        f"the link process ended (exit code {exit_code})")

    def _detach(self) -> None:
        self._box = None

    def _error(self) -> MmctlError:
        """The exception of the newest record's error (of the newest error overwritten
        before this reader saw it, if the record is a good one)."""
        v = self._sample.values
        ident = int(v[_DETAIL])
        if ident not in self._details:
            self._check_child()  # the details were sent before the record: take them
        sent_code, data = self._details.get(ident, (-1, None))
        code = int(v[_ERROR]) or sent_code
        if data is not None and sent_code == code:
            return rebuild(data)
        # no details of this error (the child skips them while the side pipe is full):
        # the same class and cause, without the transport's own details
        link, why = self.link, "details not received from the link process"
        if code == LinkError.STALE:
            return SafetyFault(FaultCause.SENSOR_STALE, link=link, why=why)
        if code == LinkError.STATUS:
            return SafetyFault(FaultCause.SENSOR_STATUS, status=f"0x{int(v[_STATUS]):04X}",
                               link=link, why=why)
        if code == LinkError.SATURATION:
            return SafetyFault(FaultCause.SENSOR_SATURATION, link=link, why=why)
        if code == LinkError.SAFETY:
            return SafetyFault(FaultCause.INTERNAL, link=link, why=why)
        if code == LinkError.PROTOCOL:
            return ProtocolError(f"F/T sensor {link}: malformed reply ({why})")
        return LinkLost(link, FaultCause.SENSOR_LINK, f"error {code} ({why})")


def next_deadline(now_ns: int, origin_ns: int, period_ns: int, lead_ns: int) -> int:
    """The first deadline ``origin + k period`` whose request time ``deadline - lead``
    is still ahead of ``now_ns``."""
    k = (now_ns + lead_ns - origin_ns) // period_ns + 1
    return origin_ns + k * period_ns


# -- the child ---------------------------------------------------------------------------

def _serve(conn: Any, cfg: SensorConfig, box_name: str, phase: tuple[int | None, int, int],
           stream_poll: float, realtime: tuple[int, tuple[int, ...]],
           log_setup: tuple[str, bool | None]) -> None:
    """Entry point of the sensor's process (see the module doc)."""
    from mmctl.transports.child import start_device_child
    from mmctl.transports.sensor import open_sensor

    start_device_child(log_setup, realtime)
    box = Mailbox.attach(box_name, FORCE_SENSOR_LAYOUT)
    transport = open_sensor(cfg)
    try:
        transport.connect()
    except Exception as exc:  # noqa: BLE001 - sent to the parent, raised there
        conn.send(("error", describe(exc, transport.link)[1]))
        box.close()
        return
    child = _Child(conn, box, transport, phase, stream_poll)
    try:
        child.poll_once()  # the first sample is there when the parent's connect returns
        conn.send(("connected", transport.link))
        child.run()
    finally:
        transport.close()
        box.close()


class _Child:
    def __init__(self, conn: Any, box: Mailbox, transport: ForceSensor,
                 phase: tuple[int | None, int, int], stream_poll: float) -> None:
        self.conn = conn
        self.box = box
        self.transport = transport
        origin, self.period_ns, self.lead_ns = phase
        self.origin_ns = time.perf_counter_ns() if origin is None else origin
        self.stream_poll_ns = round(stream_poll * 1e9)
        request_next = getattr(transport, "request_next", None)
        self.request_next = request_next if callable(request_next) else None
        self.last: Wrench | None = None
        self.requested_ns = 0
        self.errors = 0
        self.detail = 0
        self.described: Described | None = None
        self.described_at = 0
        self.polling = True

    def run(self) -> None:
        """Poll (phased or streaming) until the parent says close or goes away."""
        while True:
            if self.polling:
                now = time.perf_counter_ns()
                if self.request_next is not None:
                    at = next_deadline(now, self.origin_ns, self.period_ns,
                                       self.lead_ns) - self.lead_ns
                else:
                    at = now + self.stream_poll_ns
                timeout: float | None = max(0, at - now) * 1e-9
            else:
                timeout = None  # link lost: only the parent's word
            if select.select([self.conn], [], [], timeout)[0]:
                if not self._control():
                    return
                continue  # a phase change moves the next request
            self.poll_once()

    def poll_once(self) -> None:
        """One request (if the sensor needs one) and read; publish what came."""
        try:
            if self.request_next is not None:
                self.requested_ns = now_ns()
                self.request_next()
            w = self.transport.read()
        except Exception as exc:  # noqa: BLE001 - published, raised in the parent
            self._publish_error(exc)
            return
        if self.last is not None and w.timestamp == self.last.timestamp \
                and w.sequence == self.last.sequence:
            return  # nothing new (a streaming sensor between records)
        self.last = w
        self._publish(LinkError.NONE)

    def _control(self) -> bool:
        """Take one message from the parent; False: end."""
        try:
            msg = self.conn.recv()
        except (EOFError, OSError):
            return False  # the parent is gone
        if msg[0] == "phase":
            _, self.origin_ns, self.period_ns = msg
            return True
        return bool(msg[0] != "close")

    def _publish_error(self, exc: BaseException) -> None:
        code, data = describe(exc, self.transport.link)
        now = time.monotonic_ns()
        prev = self.described
        # details first, so the parent has them when it sees the record; once per
        # change, at most every DETAIL_INTERVAL_NS while only the values change (a stale
        # fault's age), and never blocking: a full pipe skips them
        due = prev is None or data[:2] != prev[:2] \
            or now - self.described_at >= DETAIL_INTERVAL_NS
        if data != prev and due and select.select([], [self.conn], [], 0)[1]:
            self.detail += 1
            self.described, self.described_at = data, now
            self.conn.send(("detail", self.detail, int(code), data))
        self.errors += 1
        if code in (LinkError.LINK_LOST, LinkError.INTERNAL):
            self.polling = False  # the parent decides: reconnect ends this process
        if code is LinkError.INTERNAL:  # a bug (a lost link is the transport's own event)
            log.error("sensor_process_failed", link=self.transport.link, error=data[3],
                      exc_info=exc)
        self._publish(code)

    def _publish(self, code: LinkError) -> None:
        v = self.box.staging
        w = self.last
        if w is not None:
            v[_STATUS] = w.status
            v[_WRENCH.start:_WRENCH.start + 3] = w.force
            v[_WRENCH.start + 3:_WRENCH.stop] = w.torque
            v[_SEQUENCE] = w.sequence
        v[_ERROR] = code
        v[_ERRORS] = self.errors
        v[_DETAIL] = self.detail
        v[_PUBLISHED] = now_ns()
        v[_REQUESTED] = self.requested_ns
        v[_STATS:_STATS + 5] = np.asarray(self.transport.stats(), dtype=np.float64)
        self.box.publish(0 if w is None else round(w.timestamp * 1e9))
