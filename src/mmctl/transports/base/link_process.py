"""Any base transport in a process of its own, behind two shared-memory mailboxes.

The loop never waits on the base (SPEC §7, issue 28): :class:`BaseLinkProcess` runs the
transport ``open_base(cfg)`` builds (CANopen or serial) in a ``spawn`` child and is
itself a :class:`~mmctl.transports.base.protocol.Base`:

* **odometry and health** (child -> parent, :data:`BASE_ODOMETRY_LAYOUT`): the child
  calls its transport's ``read_odometry()`` ``batch_delay`` after each command (its SYNC
  answered by then: the drives' TPDO batch is in), and at least every ``period`` when no
  command comes; each call is published with its outcome: the odometry, or a health
  code (a SafetyFault and its cause, LinkLost, another TransportError) whose details go
  first on a side pipe.  The header's time stamp is when the child took that health
  sample.  :meth:`BaseLinkProcess.read_odometry` copies the newest record and never
  blocks.  (Polling ``read_odometry()`` until the batch shows was tried first: at every
  100-500 us it took the child's interpreter from the CAN threads and the commands,
  whose latency went to several ms, and the drives' RPDO deadline expired under load;
  one sample per command is what the in-process loop takes too);
* **commands** (parent -> child, :data:`BASE_COMMAND_LAYOUT` and a
  :class:`~mmctl.runtime.mailbox.Wake`): ``send_twist``, ``stop`` and ``disable(wait=False)``
  leave the command in the mailbox and wake the child (eventfd), which runs the
  transport's ``send_twist`` / ``stop`` / ``disable(wait=False)`` at once.  Each kind
  carries the index of its newest command, so a stop or disable is never lost under a
  newer twist and goes first: a twist older than a pending stop or disable is dropped;
* **everything that blocks** (``connect``, ``enable``, ``check``, ``drive_status``,
  ``reconnect``, ``disable(wait=True)``, ``close``): a request and its reply over a
  pipe, served in the child by its main thread while a second thread keeps publishing
  and obeying commands (as the loop thread goes on beside an enable in-process).  Before
  it replies, the child publishes a fresh record, so a fault cleared by ``enable`` is
  gone from the mailbox when ``enable`` returns.  Off the loop thread, by contract.
  While ``enable`` or ``reconnect`` runs, the child takes no health sample (they reset
  and rebuild the transport's health state; a sample taken half-way would latch a fault
  the enable has just cleared; in-process the loop leaves the base alone meanwhile):
  the records age, commands are still obeyed.

Errors are the transport's own: ``read_odometry`` raises what the in-process
transport's raised in the child (``SafetyFault`` with its cause and details,
``LinkLost`` naming the link, ``TransportError``) for every read while the newest
record says so, and once for an error that a newer good record overwrote before the
parent looked (a command's error: the child's ``send_twist`` raised).  **A SafetyFault
the child's send raised comes back with the next read** (or the next ``send_twist``):
``send_twist`` returns before the child has sent.  It keeps the in-process contract
where that is cheap: it raises the newest record's fault (latched faults are: the
transport raises them from every call until ``enable``) after commanding zero,
``TransportError`` before ``enable``, and ``SafetyFault(NON_FINITE)`` for a non-finite
twist (the parent computes the wheel speeds' scaling itself, also to return the twist
commanded).  ``stop`` and ``disable(wait=False)`` raise the LinkLost already known.

Freshness by the record's own time stamp: a record older than the transport's own
silence limit (``base.canopen.heartbeat_timeout``; ``base.serial.link_timeout``) means
the drives' health is unknown for that long.  That is the cause the in-process
transport gives drives it no longer hears from: ``DRIVE_HEARTBEAT`` (CANopen),
``BASE_LINK`` (serial, a SafetyFault as the transport's own); the stop and the operator's
reaction are the same, and a child that only stalls (stopped, starved) is not a lost
link: it may come back, and enable re-arms then.  A child that ended (killed, crashed)
is ``LinkLost(link, BASE_LINK)``; the drives' own watchdogs (consumer heartbeat,
RPDO deadline, 0x6007) stop the wheels: the child's heartbeat producer died with it.
:meth:`BaseLinkProcess.reconnect` then starts a new child (left disabled); with the
child alive it asks the child's transport to ``reconnect()`` (nothing while its link
works).

Process hygiene as :mod:`mmctl.transports.sensor.link_process`: ``spawn``; the child
leaves the terminal's session and ignores the terminating signals (the daemon ends it);
it closes its transport (stop, disable) and ends when the parent's pipe closes.  The
parent owns the segments and unlinks them at ``close()``, also after the child died.
"""

from __future__ import annotations

import math
import select
import threading
import time
from collections.abc import Sequence
from enum import IntEnum
from typing import Any

import structlog

from mmctl.config import Config
from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.control.mecanum import wheel_matrix
from mmctl.errors import FaultCause, LinkLost, MmctlError, SafetyFault, TransportError, again
from mmctl.runtime.mailbox import Mailbox, MailboxLayout, Sample, Wake, check_clocks, now_ns
from mmctl.transports.base.protocol import Base, DriveStatus
from mmctl.transports.child import Described, LinkProcess
from mmctl.types import Odometry, Twist

log = structlog.get_logger("mmctl.base.process")

BASE_ODOMETRY_LAYOUT = MailboxLayout("base_odometry", (
    ("odometry", 6),      # x, y [m], yaw [rad] (odometry frame); vx, vy [m/s], wz [rad/s]
    ("odometry_t", 1),    # Odometry.timestamp: the newest encoder sample's [s, monotonic]
    ("error", 1),         # LinkError of this health sample (0 = healthy)
    ("cause", 1),         # with SAFETY: the FaultCause's index + 1
    ("errors", 1),        # error records published since the child started
    ("detail", 1),        # id of the side-pipe message describing the newest error
    ("commands", 1),      # commands the child has run
    ("command_ns", 1),    # when it ran the newest [ns, CLOCK_MONOTONIC]
))
"""The base's record; the header's t_ns is when the child took this health sample."""

BASE_COMMAND_LAYOUT = MailboxLayout("base_command", (
    ("twist", 3),         # vx, vy [m/s], wz [rad/s] of the newest send_twist
    ("twist_at", 1),      # index of the newest send_twist (0: none)
    ("stop_at", 1),       # index of the newest stop()
    ("disable_at", 1),    # index of the newest disable(wait=False)
    ("index", 1),         # index of the newest command of any kind
))
"""The parent's commands; the header's t_ns is when the parent left the newest."""

_O = {name: BASE_ODOMETRY_LAYOUT.slice(name).start for name, _ in BASE_ODOMETRY_LAYOUT.fields}
_ODO_T, _ERROR, _CAUSE, _ERRORS, _DETAIL, _COMMANDS, _COMMAND_NS = (
    _O["odometry_t"], _O["error"], _O["cause"], _O["errors"], _O["detail"], _O["commands"],
    _O["command_ns"])
_C = {name: BASE_COMMAND_LAYOUT.slice(name).start for name, _ in BASE_COMMAND_LAYOUT.fields}
_TWIST_AT, _STOP_AT, _DISABLE_AT, _INDEX = (
    _C["twist_at"], _C["stop_at"], _C["disable_at"], _C["index"])
_CAUSES = tuple(FaultCause)

START_TIMEOUT = 60.0
"""[s] for the child to start (imports on a loaded machine), on top of the transport's
own connect time (its SDO and start-up timeouts)."""
CLOSE_TIMEOUT = 5.0
"""[s] for the child to end after ``close``, on top of its transport's stop time; then
it is killed."""
REQUEST_TIMEOUT = 30.0
"""[s] a blocking request may take on top of the transport's own timeouts; a child that
does not answer by then is ended (the drives' watchdogs stop them) and LinkLost raised:
a request reported as failed must never take effect later (SPEC §5)."""
DETAIL_INTERVAL_NS = 50_000_000
"""[ns] between two details messages of one kind of error whose values change (a silent
drive's age): the side pipe carries a few messages a second at most."""


class LinkError(IntEnum):
    """The outcome of the child's newest health sample or command (the record's ``error``)."""

    NONE = 0
    SAFETY = 1  # SafetyFault (cause in the record)
    LINK_LOST = 2  # LinkLost, or the client library's own error (OSError, CanError)
    TRANSPORT = 3  # another TransportError (e.g. send_twist before enable)
    INTERNAL = 4  # any other exception: a bug


def describe(exc: BaseException, link: str) -> tuple[LinkError, Described]:
    """An exception of the child's transport as (code, :data:`Described`); ``link`` names
    the link for an error the client library raised bare (OSError, CanError)."""
    if isinstance(exc, SafetyFault):
        return LinkError.SAFETY, ("safety", exc.cause.value, dict(exc.details), str(exc))
    if isinstance(exc, LinkLost):
        return LinkError.LINK_LOST, ("link_lost", exc.cause.value,
                                     {"link": exc.link, "reason": exc.reason}, str(exc))
    if isinstance(exc, TransportError):
        return LinkError.TRANSPORT, ("transport", None, {}, str(exc))
    what = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, OSError) or type(exc).__name__ == "CanError":
        return LinkError.LINK_LOST, ("link_lost", FaultCause.BASE_LINK.value,
                                     {"link": link, "reason": what}, what)
    return LinkError.INTERNAL, ("link_lost", FaultCause.BASE_LINK.value,
                                {"link": link, "reason": f"the link process failed: {what}"},
                                what)


def link_name(cfg: BaseConfig, port: str | None = None) -> str:
    """The link as the transport names it in its LinkLost: ``socketcand:chan@host:port``
    (CANopen), the serial port."""
    if cfg.transport == "canopen":
        from mmctl.transports.canbus import describe as describe_can

        return describe_can(cfg.canopen)
    return port or cfg.serial.port


def rebuild(data: Described) -> MmctlError:
    """The exception :func:`describe` described, as the in-process transport raised it."""
    kind, cause, details, message = data
    if kind == "safety":
        return SafetyFault(FaultCause(cause), **details)
    if kind == "link_lost":
        return LinkLost(str(details["link"]), FaultCause(cause), str(details["reason"]))
    return TransportError(message)


class BaseLinkProcess(LinkProcess[LinkLost]):
    """:class:`~mmctl.transports.base.protocol.Base` whose transport runs in a child
    process (see the module doc).  No I/O before :meth:`connect`.

    cfg: the whole config or the ``base:`` section (the child builds
    ``open_base(cfg, limits=limits, port=port)``); limits: the ``limits:`` section
    (default: the whole config's, else the defaults); port: overrides
    ``base.serial.port``;
    period: the loop's period [s] (``1 / loop.rate_hz``): the child publishes a health
    sample at least this often; batch_delay: how long after a command the child takes
    its health sample [s] (the drives' answer to the command's SYNC is in by then: the
    simulator's socketcand round trip is 0.4 ms p50, 0.7 ms p90 on a 2-core machine;
    None: half the period);
    stale_timeout: a record older than this is a fault [s] (default: the transport's
    own silence limit, see the module doc);
    rt_priority, cpu_affinity: the child's SCHED_FIFO priority (0: normal) and CPUs,
    best effort as the loop's (:func:`mmctl.runtime.loop.apply_realtime`): when the
    loop runs real-time, so must its base link;
    log_setup: (level, json) for the child's structlog (the daemon's own).
    """

    def __init__(self, cfg: Config | BaseConfig, *, limits: LimitsConfig | None = None,
                 port: str | None = None, period: float = 0.002,
                 batch_delay: float | None = None, stale_timeout: float | None = None,
                 rt_priority: int = 0, cpu_affinity: Sequence[int] = (),
                 log_setup: tuple[str, bool | None] = ("info", None)) -> None:
        if isinstance(cfg, Config):
            limits = limits or cfg.limits
            cfg = cfg.base
        if not 1e-4 <= period <= 1.0:
            raise ValueError(f"period {period} s must be within 0.1 ms .. 1 s")
        if batch_delay is None:
            batch_delay = 0.5 * period
        if not 0.0 <= batch_delay <= period:
            raise ValueError(f"batch_delay {batch_delay} s must be within 0 .. the "
                             f"period {period} s")
        canopen = cfg.transport == "canopen"
        silence = cfg.canopen.heartbeat_timeout if canopen else cfg.serial.link_timeout
        stale = silence if stale_timeout is None else stale_timeout
        if not stale > 0.0:
            raise ValueError(f"stale_timeout {stale} s must be > 0")
        super().__init__(CLOSE_TIMEOUT)
        self.cfg = cfg
        self.limits = limits or LimitsConfig()
        self.port = port
        self.period_ns = round(period * 1e9)
        self.batch_delay_ns = round(batch_delay * 1e9)
        self.stale_ns = round(stale * 1e9)
        self._silent_cause = FaultCause.DRIVE_HEARTBEAT if canopen else FaultCause.BASE_LINK
        self.realtime = (int(rt_priority), tuple(cpu_affinity))
        self.log_setup = log_setup
        co, se = cfg.canopen, cfg.serial
        # the transport's own worst cases: connect (SDO probes and writes, the drives'
        # first heartbeats), enable/disable (a ramp to rest, SDO retries)
        self._connect_wait = (START_TIMEOUT + 20 * co.sdo_timeout + 5 * co.heartbeat_timeout
                              + 10 * se.timeout)
        self._request_wait = REQUEST_TIMEOUT + 2 * co.stop_timeout + 20 * co.sdo_timeout \
            + 10 * se.timeout
        self._close_wait = CLOSE_TIMEOUT + 2 * co.stop_timeout + 10 * co.sdo_timeout
        # the wheel-limit scaling of WheelCommand in plain floats (numpy costs ~28 us a
        # call here): the twist send_twist returns; the child's transport sends
        self._rows = tuple(tuple(float(x) for x in row) for row in wheel_matrix(cfg.mecanum))
        self._wheel_limit = float(self.limits.wheel_velocity)
        self._link: str | None = None
        # _conn: requests and replies; _events: the child's details messages (EOF: the
        # child ended)
        self._box: Mailbox | None = None
        self._cmd: Mailbox | None = None
        self._cmd_f: Any = None  # the staging record as a memoryview of doubles
        self._wake: Wake | None = None
        self._sample = Sample(BASE_ODOMETRY_LAYOUT)
        self._index = 0
        self._errors_seen = 0
        self._missed_error = False
        self._lost: LinkLost | None = None  # the newest record's LinkLost, for stop()
        self._enabled = False
        # _lock: the mailboxes, held for a copy or a swap only
        self._req_lock = threading.Lock()  # one request at a time on the pipe
        self._req_id = 0
        self.requests = 0
        """Requests sent over the pipe (each waits for a reply): a figure for tests."""

    @property
    def link(self) -> str:
        """The transport's link (``socketcand:chan@host:port``, ``/dev/ttyUSB0``)."""
        if self._link is None:
            self._link = link_name(self.cfg, self.port)
        return self._link

    @property
    def connected(self) -> bool:
        return self._box is not None and self._gone is None

    # -- lifecycle ---------------------------------------------------------------------

    def connect(self) -> None:
        """Start the child; return once its transport connected (and published a first
        record), or raise what its ``connect()`` raised."""
        if self._box is not None:
            return
        check_clocks()
        box = Mailbox.create(BASE_ODOMETRY_LAYOUT)
        cmd = Mailbox.create(BASE_COMMAND_LAYOUT)
        wake = Wake()

        def install(reply: tuple[Any, ...]) -> None:
            self._link = reply[1]
            self._box, self._cmd, self._wake = box, cmd, wake
            self._cmd_f = memoryview(cmd.staging.data)
            self._sample = Sample(BASE_ODOMETRY_LAYOUT)
            self._index = 0
            self._errors_seen = reply[2]
            self._missed_error = False
            self._lost = None
            self._enabled = False
            box.read_into(self._sample)

        self._start(_serve, (self.cfg, self.limits, self.port, box.name, cmd.name, wake,
                             (self.period_ns, self.batch_delay_ns), self.realtime,
                             self.log_setup),
                    "mmctl-base", (box, cmd, wake), self._connect_wait, install, side_pipe=True)
        log.info("base_process_started", link=self._link, pid=self.pid, mailbox=box.name)

    def reconnect(self) -> None:
        """After a lost link: a child that ended is replaced by a new one (its transport
        connected, the drives left disabled); a child whose transport lost its link
        reconnects it.  Does nothing while the link works.  Raises LinkLost naming the
        link while it does not answer.  Blocks: never on the loop thread."""
        if self._box is not None:
            with self._lock:
                self._check_child()
            if self._gone is None:
                if self._lost is not None:
                    self._enabled = False  # the transport's reconnect leaves it disabled
                self._request("reconnect")
                return
        # as the transport's reconnect: a drive still on ramps to rest
        self._restart(self.link, FaultCause.BASE_LINK, then=self.disable)
        log.info("base_reconnected", transport="process", link=self.link)

    def enable(self) -> None:
        """The transport's ``enable()`` in the child (blocks; see its doc)."""
        self._enabled = False
        self._request("enable")
        self._enabled = True

    def check(self) -> None:
        """The transport's ``check()`` in the child (a request: not for the loop thread;
        the loop's read_odometry raises the same faults)."""
        self._request("check")

    def drive_status(self) -> list[DriveStatus]:
        """The transport's ``drive_status()`` in the child."""
        return list(self._request("drive_status"))

    def disable(self, wait: bool = True) -> None:
        """``wait``: the transport's ``disable()`` in the child, waited for (blocks).
        False: a command to the child, never waiting (as :meth:`stop`)."""
        self._enabled = False
        if wait:
            if self._box is not None:
                self._request("disable")
            return
        self._post(_DISABLE_AT)

    def stop(self) -> None:
        """Zero wheel speed: a command to the child (its transport's ``stop()``), before
        any twist still pending; never waits.  Raises the LinkLost already known."""
        self._post(_STOP_AT)

    def close(self) -> None:
        """Ask the child to close its transport (stop, disable) and end; kill it if it
        does not in time; unlink the mailboxes.  Safe to call twice."""
        with self._req_lock:
            proc = self._close_child(self._close_wait)
        if proc is not None:
            log.info("base_process_closed", link=self._link, exit_code=proc.exitcode)

    # -- per cycle ---------------------------------------------------------------------

    def read_odometry(self) -> Odometry:
        """The newest odometry from the mailbox, or the fault of the newest health
        sample; never blocks (see the module doc)."""
        with self._lock:
            return self._read()

    def send_twist(self, vx: float, vy: float, wz: float) -> Twist:
        """Leave the twist for the child and wake it; never blocks.  Returns the twist
        commanded (scaled to the wheel speed limit).  Raises TransportError before
        enable, SafetyFault(NON_FINITE), and the newest record's fault (after commanding
        zero); a fault of the child's send comes with the next call (module doc)."""
        if not self._enabled:
            raise TransportError("send_twist() before enable()")
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            self._post(_STOP_AT)
            raise SafetyFault(FaultCause.NON_FINITE, twist=(vx, vy, wz))
        peak = 0.0
        for a, b, c in self._rows:
            peak = max(peak, abs(a * vx + b * vy + c * wz))
        s = 1.0 if peak <= self._wheel_limit else self._wheel_limit / peak
        with self._lock:
            if self._gone is not None:
                raise again(self._gone)
            if self._sample.fields[_ERROR]:
                self._post_locked(_STOP_AT)
                raise self._error()
            self._post_locked(_TWIST_AT, vx, vy, wz)
        return Twist(vx * s, vy * s, wz * s)

    def commands(self) -> tuple[int, int]:
        """(commands the child has run, when it ran the newest [ns, CLOCK_MONOTONIC]) as
        of the newest record read: for benchmarks."""
        f = self._sample.fields
        return int(f[_COMMANDS]), int(f[_COMMAND_NS])

    # -- internals ---------------------------------------------------------------------

    def _read(self) -> Odometry:
        box = self._box
        if box is None:
            raise TransportError(f"base {self.link}: not connected (call connect() first)")
        s = self._sample
        f = s.fields  # plain floats: numpy's scalar paths cost tens of us when cold
        now = now_ns()
        if box.read_into(s):
            errors = int(f[_ERRORS])
            if errors != self._errors_seen:
                self._errors_seen = errors
                self._missed_error = True
        elif now - s.t_ns > 2 * self.period_ns:
            self._check_child()  # quiet for two periods: is the child there? (a syscall)
        if self._gone is not None:
            raise again(self._gone)
        if f[_ERROR] or self._missed_error:
            self._missed_error = False
            raise self._error()
        age = now - s.t_ns
        if age > self.stale_ns:
            self._check_child()
            if self._gone is not None:
                raise again(self._gone)
            raise SafetyFault(self._silent_cause, link=self.link,
                              silent_for=round(age * 1e-9, 4), source="link_process")
        return Odometry(f[0], f[1], f[2], f[3], f[4], f[5], f[_ODO_T])

    def _post(self, at: int, vx: float = 0.0, vy: float = 0.0, wz: float = 0.0) -> None:
        with self._lock:
            if self._cmd is None:
                return  # not connected: nothing to stop (as the transports)
            if self._gone is not None:
                raise again(self._gone)
            if self._lost is not None and at != _TWIST_AT:
                raise self._lost  # as the transport's stop on a lost link: at once
            self._post_locked(at, vx, vy, wz)

    def _post_locked(self, at: int, vx: float = 0.0, vy: float = 0.0, wz: float = 0.0) -> None:
        box, v, wake = self._cmd, self._cmd_f, self._wake
        if box is None or v is None or wake is None:
            return
        self._index += 1
        if at == _TWIST_AT:
            v[0], v[1], v[2] = vx, vy, wz
        v[at] = v[_INDEX] = float(self._index)
        box.publish(now_ns())
        wake.notify()

    def _request(self, name: str, *args: Any) -> Any:
        """Run the transport's ``name(*args)`` in the child; its result, or what it
        raised.  A child that does not answer in time is ended (LinkLost)."""
        with self._req_lock:
            conn = self._conn
            if conn is None or self._box is None:
                raise TransportError(f"base {self.link}: not connected (call connect() first)")
            with self._lock:
                self._check_child()
            if self._gone is not None:
                raise again(self._gone)
            self._req_id += 1
            ident = self._req_id
            self.requests += 1
            try:
                conn.send(("call", ident, name, args))
                while True:
                    if not conn.poll(self._request_wait):
                        self._kill(f"{name}() not answered within {self._request_wait:g} s")
                        assert self._gone is not None
                        raise again(self._gone)
                    reply = conn.recv()
                    if reply[1] == ident:
                        break
            except (EOFError, OSError):
                with self._lock:
                    self._check_child()
                raise self._gone or LinkLost(self.link, FaultCause.BASE_LINK,
                                             "the link process ended") from None
            kind, _, value, errors = reply
            with self._lock:  # the record the child published after the call is in
                box = self._box
                if box is not None and box.read_into(self._sample):
                    self._errors_seen = max(errors, int(self._sample.fields[_ERRORS]))
                    self._missed_error = False
                    self._lost = None
        if kind == "error":
            raise rebuild(value)
        return value

    def _kill(self, why: str) -> None:
        proc = self._proc
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(CLOSE_TIMEOUT)
        self._gone = LinkLost(self.link, FaultCause.BASE_LINK,
                              f"the link process was ended: {why}")
        log.error("base_process_killed", link=self._link, why=why)

    # _check_child (the side pipe's messages; a closed pipe is a child that ended): under
    # ``_lock`` (one reader of the side pipe)

    def _who(self) -> str:
        return f"base {self.link}: the link process"

    def _refused(self, reply: tuple[Any, ...]) -> MmctlError:
        return rebuild(reply[1])

    def _child_ended(self, exit_code: int | None) -> LinkLost:
        log.error("base_process_lost", link=self._link, exit_code=exit_code)
        return LinkLost(self.link, FaultCause.BASE_LINK,
                        f"the link process ended (exit code {exit_code})")

    def _detach(self) -> None:
        self._box = self._cmd = None
        self._cmd_f = None
        self._wake = None
        self._enabled = False

    def _error(self) -> MmctlError:
        """The exception of the newest record's error (of the newest error overwritten
        before this reader saw it, if the record is a good one)."""
        f = self._sample.fields
        ident = int(f[_DETAIL])
        if ident not in self._details:
            self._check_child()  # the details were sent before the record: take them
        sent_code, data = self._details.get(ident, (-1, None))
        code = int(f[_ERROR]) or sent_code
        if data is not None and sent_code == code:
            exc = rebuild(data)
        else:  # no details (the child skips them while the side pipe is full)
            why = "details not received from the link process"
            cause = int(f[_CAUSE])
            if code == LinkError.SAFETY and 0 < cause <= len(_CAUSES):
                exc = SafetyFault(_CAUSES[cause - 1], link=self.link, why=why)
            elif code == LinkError.TRANSPORT:
                exc = TransportError(f"base {self.link}: {why}")
            else:
                exc = LinkLost(self.link, FaultCause.BASE_LINK, f"error {code} ({why})")
        if isinstance(exc, LinkLost) and int(f[_ERROR]) == LinkError.LINK_LOST:
            self._lost = exc
        return exc


# -- the child ---------------------------------------------------------------------------

def _serve(conn: Any, events: Any, cfg: BaseConfig, limits: LimitsConfig, port: str | None,
           box_name: str, cmd_name: str, wake: Wake, timing: tuple[int, int],
           realtime: tuple[int, tuple[int, ...]], log_setup: tuple[str, bool | None]) -> None:
    """Entry point of the base's process (see the module doc)."""
    from mmctl.transports.base import open_base
    from mmctl.transports.child import start_device_child

    start_device_child(log_setup, realtime)
    box = Mailbox.attach(box_name, BASE_ODOMETRY_LAYOUT)
    cmd = Mailbox.attach(cmd_name, BASE_COMMAND_LAYOUT)
    transport = open_base(cfg, limits=limits, port=port)
    link = link_name(cfg, port)
    try:
        transport.connect()
    except Exception as exc:  # noqa: BLE001 - sent to the parent, raised there
        conn.send(("error", describe(exc, link)[1]))
        box.close()
        cmd.close()
        return
    child = _Child(events, box, cmd, wake, transport, link, timing)
    child.sample()  # the first record is there when the parent's connect returns
    worker = threading.Thread(target=child.run, name="mmctl-base-cycle", daemon=True)
    worker.start()
    try:
        conn.send(("connected", link, child.errors))
        _answer(conn, child, transport, link)
    finally:
        child.finish()
        worker.join()
        try:
            transport.close()
        finally:
            box.close()
            cmd.close()
            wake.close()


def _answer(conn: Any, child: _Child, transport: Base, link: str) -> None:
    """The main thread: run the parent's requests until it says close or goes away."""
    calls = {"enable": transport.enable, "check": transport.check,
             "drive_status": transport.drive_status, "reconnect": transport.reconnect,
             "disable": transport.disable}
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return  # the parent is gone: close (stop, disable) and end
        if msg[0] != "call":
            return
        _, ident, name, args = msg
        # enable and reconnect reset and rebuild the transport's health state: no health
        # sample beside them (in-process, the loop leaves the base alone meanwhile), or
        # one taken half-way would latch a fault the enable has just cleared
        exclusive = child.sampling if name in ("enable", "reconnect") else None
        if exclusive is not None:
            exclusive.acquire()
        try:
            reply: tuple[Any, ...] = ("ok", ident, calls[name](*args))
        except Exception as exc:  # noqa: BLE001 - sent to the parent, raised there
            reply = ("error", ident, describe(exc, link)[1])
        finally:
            if exclusive is not None:
                exclusive.release()
        errors = child.sync()  # a fresh record before the reply
        try:
            conn.send((*reply, errors))
        except OSError:
            return


class _Child:
    """The child's cycle thread: commands from the mailbox, health samples into it."""

    def __init__(self, events: Any, box: Mailbox, cmd: Mailbox, wake: Wake, transport: Base,
                 link: str, timing: tuple[int, int]) -> None:
        self.events = events
        self.box = box
        self.cmd = cmd
        self.command = Sample(BASE_COMMAND_LAYOUT)
        self.wake = wake
        self.transport = transport
        self.link = link
        self.period_ns, self.batch_delay_ns = timing
        self.done = 0  # the newest command index run
        self.commands = 0
        self.command_ns = 0
        self.errors = 0
        self.detail = 0
        self.described: Described | None = None
        self.described_at = 0
        self.odometry: Odometry | None = None
        self.published_ns = 0
        self.commanded = False  # a command since the last health sample
        self.stopping = False
        self.sampling = threading.Lock()  # held by a health sample, or by enable/reconnect
        self.sync_asked = threading.Event()
        self.synced = threading.Event()

    def run(self) -> None:
        while not self.stopping:
            woke = self.wake.wait(max(0, self.due() - now_ns()) * 1e-9)
            if self.stopping:
                return
            if woke:
                self.obey()
            sync = self.sync_asked.is_set()
            if (sync or now_ns() >= self.due()) \
                    and self.sampling.acquire(blocking=False):  # else enable/reconnect runs
                try:
                    self.sample()
                finally:
                    self.sampling.release()
            if sync:
                self.sync_asked.clear()
                self.synced.set()

    def due(self) -> int:
        """When the next health sample is due [ns]: a period after the last record, or
        ``batch_delay`` after a command if that is sooner."""
        at = self.published_ns + self.period_ns
        if self.commanded:
            at = min(at, self.command_ns + self.batch_delay_ns)
        return at

    def sync(self) -> int:
        """From the request thread: have a fresh record published; the errors count."""
        self.synced.clear()
        self.sync_asked.set()
        self.wake.notify()
        self.synced.wait(5.0)  # a cycle thread that is gone: the reply goes anyway
        return self.errors

    def finish(self) -> None:
        self.stopping = True
        self.wake.notify()

    def obey(self) -> None:
        """Run the newest commands: disable or stop first, then a newer twist."""
        if not self.cmd.read_into(self.command):
            return
        f = self.command.fields
        index = int(f[_INDEX])
        twist_at, stop_at, disable_at = int(f[_TWIST_AT]), int(f[_STOP_AT]), int(f[_DISABLE_AT])
        done, self.done = self.done, index
        transport = self.transport
        try:
            if disable_at > done:
                transport.disable(wait=False)
            elif stop_at > done:
                transport.stop()
            if twist_at > done and twist_at > stop_at and twist_at > disable_at:
                transport.send_twist(f[0], f[1], f[2])
        except Exception as exc:  # noqa: BLE001 - published, raised in the parent
            self.publish_error(exc)
        self.commands += 1
        self.command_ns = now_ns()
        self.commanded = True

    def sample(self) -> None:
        """One health sample, published."""
        now = now_ns()
        self.commanded = False
        try:
            odo = self.transport.read_odometry()
        except Exception as exc:  # noqa: BLE001 - published, raised in the parent
            self.publish_error(exc, now)
            return
        self.odometry = odo
        self.publish(LinkError.NONE, 0, now)

    def publish_error(self, exc: BaseException, t_ns: int | None = None) -> None:
        code, data = describe(exc, self.link)
        now = time.monotonic_ns()
        prev = self.described
        # details first, so the parent has them when it sees the record; once per
        # change, at most every DETAIL_INTERVAL_NS while only the values change (a
        # silent drive's age), and never blocking: a full pipe skips them
        due = prev is None or data[:2] != prev[:2] \
            or now - self.described_at >= DETAIL_INTERVAL_NS
        if data != prev and due and select.select([], [self.events], [], 0)[1]:
            self.detail += 1
            self.described, self.described_at = data, now
            try:
                self.events.send(("detail", self.detail, int(code), data))
            except OSError:
                pass  # the parent is gone: the main thread ends us
        self.errors += 1
        if code is LinkError.INTERNAL:  # a bug (a lost link is the transport's own event)
            log.error("base_process_failed", link=self.link, error=data[3], exc_info=exc)
        cause = _CAUSES.index(exc.cause) + 1 if isinstance(exc, SafetyFault) else 0
        self.publish(code, cause, now if t_ns is None else t_ns)

    def publish(self, code: LinkError, cause: int, t_ns: int) -> None:
        v = self.box.staging
        odo = self.odometry
        if odo is not None:
            v[0:7] = odo
        v[_ERROR] = code
        v[_CAUSE] = cause
        v[_ERRORS] = self.errors
        v[_DETAIL] = self.detail
        v[_COMMANDS] = self.commands
        v[_COMMAND_NS] = self.command_ns
        self.box.publish(t_ns)
        self.published_ns = t_ns
