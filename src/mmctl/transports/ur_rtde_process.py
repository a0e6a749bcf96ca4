"""The UR10e link in a process of its own: ur_rtde can crash, hang or hold the GIL there,
never in the daemon.

ur_rtde 1.6.5 cannot be made safe in the daemon's process (read from its source, see
``docs/stop-path.md``): after 2.5 s without RTDE data, ``RTDEControlInterface``'s
receive thread reconnects by itself, starts a second receive thread while the first
keeps resetting the socket the second one reads (SIGSEGV in ``RTDE::isDataAvailable``),
and its destructor leaves that detached thread reading freed memory (the segfaults at
shutdown).  Its constructors and destructors also hold the GIL (a destructor sleeps
0.5 s), stalling the loop thread.  So :class:`UrRtdeProcessArm` runs
:class:`~mmctl.transports.ur_rtde_arm.UrRtdeArm` in a child process (``spawn``).  The
per-cycle traffic goes through two shared-memory mailboxes
(:mod:`mmctl.runtime.mailbox`, ``docs/mailbox.md``); a pipe carries the rest:

* **state** (:data:`ARM_STATE_LAYOUT`): the child reads ur_rtde at the RTDE rate
  (``arm.frequency``, absolute deadlines) and publishes each new sample (its controller
  time advanced) the moment it has it: q, qd, controller time, runtime state, safety
  bits, speed scaling, digital inputs, and a fault code with the id of its details.
  ``read_state`` copies the newest record (no syscall, no pickling, never waits) and
  raises the fault it carries as it was raised in the child: every read while the
  newest record carries it, and once for a fault a newer good record overwrote before
  the parent looked.  ``arm.stale_cycles`` reads in a row without a new sample are
  ``ARM_STALE`` (the child's own ``UrRtdeArm`` counts its polls the same way);
* **commands** (:data:`ARM_COMMAND_LAYOUT`): ``speed_j``, ``kick_watchdog`` and ``stop``
  each bump a sequence number of their own in one record, published, and wake the
  child (:class:`~mmctl.runtime.mailbox.Wake`, an eventfd), which calls ur_rtde at once:
  the stop first, then the newest speedJ if it was posted after that stop (a burst
  before the child woke is coalesced to its newest; a stop is never lost behind it),
  then a kick if no speedJ went out (a speedJ feeds the controller's watchdog too).  A
  fault such a call raises is published at once and comes back with the next read;
* **the pipe**: connect's answer, the details of faults (plain data, at most one message
  per change and every 50 ms while only the values change; never blocking), ``close``;
  and the child's way of noticing the parent's death (EOF: speedJ(0), end).  The parent
  looks at it only when the newest record is older than a period (a child that ended, a
  crash included, is ``ARM_DISCONNECTED``) or for a fault's details;
* on ``ARM_STALE``, ``ARM_DISCONNECTED`` or a ``TransportError`` the child publishes the
  fault, sends speedJ(0) with the stop deceleration (a real-time command: never waits)
  and ends itself with ``os._exit`` before ur_rtde's own reconnect can start; the arm's
  RTDE watchdog stops the program.  ``reconnect`` starts a new child;
* ``close`` asks the child for speedStop + stopScript (if the link is healthy), then it
  exits without ur_rtde's teardown; a child that does not end in time is killed; the
  parent unlinks both segments (also after the child died, and at interpreter exit if
  nobody closed the arm);
* the child leaves the terminal's session and ignores the terminating signals: the
  daemon sends its stop commands through it, then ends it.
"""

from __future__ import annotations

import math
import os
import select
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog
from numpy.typing import NDArray

from mmctl.config.arm import ArmConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import FaultCause, MmctlError, SafetyFault, TransportError, again
from mmctl.runtime.mailbox import Mailbox, MailboxLayout, Sample, Wake, check_clocks, now_ns
from mmctl.transports.child import Described, LinkProcess
from mmctl.types import ArmState

if TYPE_CHECKING:
    from mmctl.transports.ur_rtde_arm import UrRtdeArm

log = structlog.get_logger("mmctl.arm")

FATAL = frozenset({FaultCause.ARM_STALE, FaultCause.ARM_DISCONNECTED})
"""Faults after which the child ends itself (ur_rtde's own reconnect must never run)."""
START_TIMEOUT = 60.0
"""[s] for the child to start (imports on a loaded machine) and connect."""
CLOSE_TIMEOUT = 5.0
"""[s] for the child to end after ``close``; then it is killed."""
DETAIL_INTERVAL_NS = 50_000_000
"""[ns] between two details messages of one fault whose values change (its controller
time): the pipe carries a few messages a second at most."""

ARM_STATE_LAYOUT = MailboxLayout("ur_arm_state", (
    ("sample", 1),           # 1: the fields below hold a sample (0: none read yet)
    ("controller_time", 1),  # [s] the controller's timestamp of the sample
    ("q", 6),                # [rad]
    ("qd", 6),               # [rad/s]
    ("runtime_state", 1), ("safety_bits", 1), ("speed_scaling", 1),
    ("digital_inputs", 1),   # actual_digital_input_bits (0 in a fault record)
    ("fault", 1),            # 0 none, 1 + index in FaultCause (SafetyFault), -1 TransportError
    ("faults", 1),           # fault records published since the child started
    ("detail", 1),           # id of the pipe's newest details message
    ("published_ns", 1),     # when the child published the record [ns, CLOCK_MONOTONIC]
    ("speedj_done", 1), ("kick_done", 1), ("stop_done", 1),  # command seqs taken
))
"""The arm's record; the header's t_ns is when the child found the sample."""
ARM_COMMAND_LAYOUT = MailboxLayout("ur_arm_command", (
    ("speedj", 1),        # seq of the newest speed_j (0: none yet)
    ("qd", 6),            # [rad/s]
    ("acceleration", 1),  # [rad/s^2]
    ("time", 1),          # [s]
    ("kick", 1),          # seq of the newest kick_watchdog
    ("stop", 1),          # seq of the newest stop
    ("deceleration", 1),  # [rad/s^2] of the newest stop
    ("stop_after", 1),    # the speedj seq when the newest stop was posted
))
"""The daemon's commands; the header's t_ns is when the newest was posted."""

_S = {name: ARM_STATE_LAYOUT.slice(name) for name, _ in ARM_STATE_LAYOUT.fields}
_SAMPLE, _TIME, _RUNTIME, _BITS, _SCALING, _DI = (
    _S[n].start for n in ("sample", "controller_time", "runtime_state", "safety_bits",
                          "speed_scaling", "digital_inputs"))
_FAULT, _FAULTS, _DETAIL, _PUBLISHED = (
    _S[n].start for n in ("fault", "faults", "detail", "published_ns"))
_SPEEDJ_DONE, _KICK_DONE, _STOP_DONE = (
    _S[n].start for n in ("speedj_done", "kick_done", "stop_done"))
_Q, _QD = _S["q"], _S["qd"]
_C = {name: ARM_COMMAND_LAYOUT.slice(name).start for name, _ in ARM_COMMAND_LAYOUT.fields}
_C_SPEEDJ, _C_QD, _C_ACC, _C_TIME, _C_KICK, _C_STOP, _C_DECEL, _C_AFTER = (
    _C[n] for n in ("speedj", "qd", "acceleration", "time", "kick", "stop", "deceleration",
                    "stop_after"))

_CAUSES = tuple(FaultCause)
TRANSPORT_CODE = -1
"""The record's ``fault`` of a TransportError (a SafetyFault's is 1 + its cause's index)."""


class UrRtdeProcessArm(LinkProcess[SafetyFault]):
    """:class:`~mmctl.transports.arm.Arm` whose ur_rtde client runs in a child process
    (see the module docstring).  config: the ``arm:`` section; limits: ``limits:``;
    log_setup: (level, json) for the child's structlog (the daemon's own).  No I/O
    before :meth:`connect`."""

    _ENDED_EARLY = ""  # "the arm process ended (exit code N)"

    def __init__(self, config: ArmConfig, limits: LimitsConfig | None = None,
                 log_setup: tuple[str, bool | None] = ("info", None)):
        super().__init__(CLOSE_TIMEOUT)
        self.config = config
        self.limits = LimitsConfig() if limits is None else limits
        self.log_setup = log_setup
        self.period_ns = round(1e9 / config.frequency)
        """[ns] the child's polling period (the RTDE rate)."""
        self._state: Mailbox | None = None
        self._command: Mailbox | None = None
        self._wake: Wake | None = None
        self._cmd: memoryview[float] | None = None  # the command staging, as doubles
        self._sample = Sample(ARM_STATE_LAYOUT)
        self._t = math.nan  # controller time of last_state
        self._missed = 0
        self._faults_seen = 0
        self._missed_fault = False
        self._seqs = [0, 0, 0]  # speedj, kick, stop posted on this connection
        self._di = 0
        self.last_state: ArmState | None = None
        self.controller_version = ""
        self.serial_number = ""

    @property
    def host(self) -> str:
        return self.config.host

    @property
    def connected(self) -> bool:
        return self._conn is not None and self._proc is not None and self._proc.is_alive()

    # -- lifecycle -----------------------------------------------------------------------

    def connect(self) -> None:
        """Start the child and let it connect; raises what its connect raised.  Returns
        with the child's first sample in the state mailbox."""
        if self._conn is not None:
            return
        check_clocks()
        state = Mailbox.create(ARM_STATE_LAYOUT)
        command = Mailbox.create(ARM_COMMAND_LAYOUT)
        wake = Wake()

        def install(reply: tuple[Any, ...]) -> None:
            _, self.controller_version, self.serial_number = reply
            self._state, self._command, self._wake = state, command, wake
            self._cmd = command.staging.data.cast("B").cast("d")
            self._sample = Sample(ARM_STATE_LAYOUT)
            self._t = math.nan
            self._missed = self._faults_seen = 0
            self._missed_fault = False
            self._seqs = [0, 0, 0]
            self._di = 0
            self.last_state = None

        self._start(_serve, (self.config, self.limits, self.log_setup, state.name,
                             command.name, wake),
                    f"mmctl-arm-{self.host}", (state, command, wake),
                    START_TIMEOUT + 3 * self.config.connect_timeout, install)
        log.info("arm_process_started", host=self.host, pid=self.pid, mailbox=state.name)

    def reconnect(self) -> None:
        """End the child, start a new one."""
        self.close()
        self.connect()

    def close(self) -> None:
        """speedStop + stopScript in the child (healthy link), then it ends; the mailboxes
        are unlinked (idempotent)."""
        proc = self._close_child(answer=CLOSE_TIMEOUT)  # speedStop + stopScript first
        if proc is not None:
            log.info("arm_closed", host=self.host, exit_code=proc.exitcode)

    # -- per cycle -----------------------------------------------------------------------

    def read_state(self) -> ArmState:
        """The newest sample from the state mailbox; never waits (see the module
        docstring).  Raises the SafetyFault (or TransportError) the child found,
        ARM_STALE after ``arm.stale_cycles`` reads in a row without a new sample,
        ARM_DISCONNECTED when the child is gone."""
        with self._lock:
            box = self._state
            if box is None:
                raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host,
                                  why="not connected")
            s = self._sample
            f = s.fields  # plain floats (numpy scalars cost tens of us with cold caches)
            if box.read_into(s):
                faults = int(f[_FAULTS])
                if faults != self._faults_seen:
                    self._faults_seen = faults
                    self._missed_fault = not f[_FAULT]  # overwritten before we looked
                t = f[_TIME]
                if f[_SAMPLE] and t != self._t:
                    self._t, self._missed = t, 0
                    self.last_state = ArmState(np.array(f[_Q]), np.array(f[_QD]), t,
                                               int(f[_RUNTIME]), int(f[_BITS]), f[_SCALING])
                else:
                    self._missed += 1
                self._di = int(f[_DI])
            else:
                self._missed += 1
            if now_ns() - f[_PUBLISHED] > self.period_ns:
                self._check_child()  # quiet for a period: still there? (a syscall)
            if self._gone is not None:
                raise again(self._gone)
            if f[_FAULT] or self._missed_fault:
                self._missed_fault = False
                raise self._fault()
            if self._missed >= self.config.stale_cycles or self.last_state is None:
                raise SafetyFault(FaultCause.ARM_STALE, host=self.host,
                                  why="no new sample from the arm process",
                                  cycles=self._missed)
            return self.last_state

    def speed_j(self, qd: NDArray[np.float64] | Sequence[float],
                acceleration: float | None = None, dt: float | None = None) -> bool:
        """speedJ in the child (clamped there as :meth:`UrRtdeArm.speed_j` does), at
        once; non-finite input raises SafetyFault(NON_FINITE) here and sends nothing."""
        v = [float(x) for x in qd]
        if len(v) != 6:
            raise ValueError(f"qd must have 6 joint speeds, got {len(v)}")
        a = self.config.speedj_acceleration if acceleration is None else float(acceleration)
        t = 1.0 / self.config.frequency if dt is None else float(dt)
        if not math.isfinite(sum(v) + a + t):
            raise SafetyFault(FaultCause.NON_FINITE, source="speed_j", qd=v, acceleration=a, dt=t)
        with self._lock:
            cmd = self._ready()
            cmd[_C_QD], cmd[_C_QD + 1], cmd[_C_QD + 2] = v[0], v[1], v[2]
            cmd[_C_QD + 3], cmd[_C_QD + 4], cmd[_C_QD + 5] = v[3], v[4], v[5]
            cmd[_C_ACC], cmd[_C_TIME] = a, t
            self._post(cmd, 0, _C_SPEEDJ)
        return True

    def kick_watchdog(self) -> None:
        """The controller's watchdog (set by the child on its first kick or speedJ)."""
        with self._lock:
            self._post(self._ready(), 1, _C_KICK)

    def stop(self, deceleration: float | None = None) -> None:
        """The child's :meth:`UrRtdeArm.stop`, before any speed_j posted after it; never
        blocks, never raises."""
        d = self.config.stop_deceleration if deceleration is None else float(deceleration)
        try:
            with self._lock:
                cmd = self._ready()
                cmd[_C_DECEL], cmd[_C_AFTER] = d, self._seqs[0]
                self._post(cmd, 2, _C_STOP)
        except SafetyFault as exc:
            log.warning("arm_stop_not_sent", host=self.host, why=str(exc))

    def digital_input(self, index: int) -> bool:
        """Digital input ``index`` as the newest read saw it."""
        if self._state is None:
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host, why="not connected")
        return bool((self._di >> index) & 1)

    # -- internals -----------------------------------------------------------------------

    def _ready(self) -> memoryview[float]:
        """The command staging (under the lock); ARM_DISCONNECTED without a child."""
        cmd = self._cmd
        if cmd is None:
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host, why="not connected")
        if self._gone is not None:
            raise again(self._gone)
        return cmd

    def _post(self, cmd: memoryview[float], kind: int, field: int) -> None:
        """Bump command ``kind``'s seq into ``field``, publish, wake the child."""
        seq = self._seqs[kind] + 1
        self._seqs[kind] = seq
        cmd[field] = seq
        assert self._command is not None and self._wake is not None
        self._command.publish(now_ns())
        self._wake.notify()

    def _who(self) -> str:
        return f"{self.host}: the arm process"

    def _refused(self, reply: tuple[Any, ...]) -> MmctlError:
        return _rebuild(reply[1:])

    def _child_ended(self, exit_code: int | None) -> SafetyFault:
        return SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host,
                           why=f"the arm process ended (exit code {exit_code})")

    def _detach(self) -> None:
        self._state = self._command = self._wake = None
        self._cmd = None

    def _fault(self) -> MmctlError:
        """The exception of the newest record's fault (of the newest fault a good record
        overwrote before this reader saw it, if the record is a good one)."""
        f = self._sample.fields
        ident = int(f[_DETAIL])
        if ident not in self._details:
            self._check_child()  # the details were sent before the record: take them
        sent_code, data = self._details.get(ident, (0, None))
        code = int(f[_FAULT]) or sent_code
        if data is not None and sent_code == code:
            return _rebuild(data)
        why = "details not received from the arm process"
        if code == TRANSPORT_CODE:
            return TransportError(f"{self.host}: the arm process lost the link ({why})")
        cause = _CAUSES[code - 1] if 1 <= code <= len(_CAUSES) else FaultCause.INTERNAL
        return SafetyFault(cause, host=self.host, why=why)


def _describe(exc: MmctlError) -> Described:
    """An exception as plain data for the pipe: (kind, cause, details, message)."""
    if isinstance(exc, SafetyFault):
        return ("safety", exc.cause.value, dict(exc.details), str(exc))
    return ("transport", None, {}, str(exc))


def _code(exc: MmctlError) -> int:
    """The record's ``fault`` field for ``exc``."""
    if isinstance(exc, SafetyFault):
        return 1 + _CAUSES.index(exc.cause)
    return TRANSPORT_CODE


def _rebuild(data: Sequence[Any]) -> MmctlError:
    kind, cause, details, message = data
    if kind == "safety":
        return SafetyFault(FaultCause(cause), **details)
    return TransportError(message)


# -- the child ---------------------------------------------------------------------------

def _serve(conn: Any, config: ArmConfig, limits: LimitsConfig,
           log_setup: tuple[str, bool | None], state_name: str, command_name: str,
           wake: Wake) -> None:
    """Entry point of the arm's process (see the module docstring)."""
    from mmctl.transports.child import start_device_child
    from mmctl.transports.ur_rtde_arm import UrRtdeArm

    start_device_child(log_setup)
    state = Mailbox.attach(state_name, ARM_STATE_LAYOUT)
    command = Mailbox.attach(command_name, ARM_COMMAND_LAYOUT)
    arm = UrRtdeArm(config, limits)
    try:
        arm.connect()
    except MmctlError as exc:
        conn.send(("error", *_describe(exc)))
        os._exit(0)
    child = _Child(conn, arm, state, command, wake, round(1e9 / config.frequency))
    fatal = child.poll()  # the first sample is there when the parent's connect returns
    conn.send(("connected", arm.controller_version, arm.serial_number))
    if fatal:
        os._exit(0)
    child.run()


class _Child:
    def __init__(self, conn: Any, arm: UrRtdeArm, state: Mailbox, command: Mailbox,
                 wake: Wake, period_ns: int):
        self.conn = conn
        self.arm = arm
        self.state = state
        self.command = command
        self.wake = wake
        self.period_ns = period_ns
        self.cmd = Sample(ARM_COMMAND_LAYOUT)
        self.done = [0, 0, 0]  # speedj, kick, stop taken
        self.last_t = math.nan
        self.shown_fault = False  # the newest record carries a fault
        self.faults = 0
        self.detail = 0
        self.described: Described | None = None
        self.described_at = 0

    def run(self) -> None:
        """Poll ur_rtde every period, take commands whenever woken, until the parent
        says close or goes away."""
        conn, wake_fd = self.conn, self.wake.fileno()
        next_ns = time.perf_counter_ns() + self.period_ns
        while True:
            wait = max(0, next_ns - time.perf_counter_ns()) * 1e-9
            ready = select.select([conn, wake_fd], [], [], wait)[0]
            if wake_fd in ready:
                self.wake.clear()
            if self.commands() or (ready and conn in ready and self.control()):
                os._exit(0)  # a fatal fault (published, speedJ(0) sent) or the parent's word
            now = time.perf_counter_ns()
            if now >= next_ns:
                if self.poll():
                    os._exit(0)
                next_ns += self.period_ns
                if next_ns <= now:  # late by a period or more: skip, never catch up
                    next_ns = now + self.period_ns

    def control(self) -> bool:
        """One message from the parent; True: end now."""
        arm = self.arm
        try:
            msg = self.conn.recv()
        except (EOFError, OSError):  # the daemon is gone: stop the arm, end
            arm.stop()
            return True
        if msg[0] != "close":
            return False
        arm.end()
        try:
            self.conn.send(("closed", 0))
        except OSError:
            pass
        return True  # no ur_rtde teardown: no disconnect, no destructor

    def commands(self) -> bool:
        """Take the newest commands (a stop first); True: a fatal fault was published."""
        s, arm = self.cmd, self.arm
        if not self.command.read_into(s):
            return False
        f = s.fields
        speedj, kick, stop = int(f[_C_SPEEDJ]), int(f[_C_KICK]), int(f[_C_STOP])
        done = self.done
        if stop != done[2]:
            done[2] = stop
            arm.stop(f[_C_DECEL])  # never raises
            if speedj <= f[_C_AFTER]:
                done[0] = speedj  # posted before the stop: superseded by it
        fault: MmctlError | None = None
        sent = False
        try:
            if speedj != done[0]:
                done[0], sent = speedj, True
                arm.speed_j(f[_C_QD:_C_QD + 6], f[_C_ACC], f[_C_TIME])
            if kick != done[1]:
                done[1] = kick
                if not sent:  # a speedJ feeds the controller's watchdog too
                    arm.kick_watchdog()
        except MmctlError as exc:
            fault = exc
        if fault is None:
            return False
        return self.publish(fault)

    def poll(self) -> bool:
        """Read ur_rtde; publish a new sample or a fault.  True: fatal (published, the
        arm sent speedJ(0)): the process must end."""
        arm = self.arm
        fault: MmctlError | None = None
        try:
            arm.read_state()
        except MmctlError as exc:
            fault = exc
        s = arm.last_state
        new = s is not None and s.controller_time != self.last_t
        if fault is None and not new and not self.shown_fault:
            return False
        if s is not None:
            self.last_t = s.controller_time
        return self.publish(fault)

    def publish(self, fault: MmctlError | None) -> bool:
        """The newest sample (and ``fault``) into the state mailbox; the details first,
        on the pipe.  True: fatal, and speedJ(0) was sent."""
        arm, v = self.arm, self.state.staging
        s = arm.last_state
        if s is not None:
            v[_SAMPLE], v[_TIME] = 1.0, s.controller_time
            v[_Q], v[_QD] = s.q, s.qd
            v[_RUNTIME], v[_BITS], v[_SCALING] = s.runtime_state, s.safety_bits, s.speed_scaling
        v[_DI] = arm.digital_inputs() if fault is None else 0
        v[_FAULT] = 0 if fault is None else self.describe(fault)
        v[_FAULTS], v[_DETAIL] = self.faults, self.detail
        v[_SPEEDJ_DONE], v[_KICK_DONE], v[_STOP_DONE] = self.done
        now = now_ns()
        v[_PUBLISHED] = now
        self.state.publish(now)
        self.shown_fault = fault is not None
        fatal = isinstance(fault, SafetyFault) and fault.cause in FATAL \
            or isinstance(fault, TransportError)
        if fatal:
            arm.stop()  # speedJ(0): real-time, never waits; before ur_rtde reconnects
        return fatal

    def describe(self, fault: MmctlError) -> int:
        """Count ``fault``, send its details unless the same were sent lately (never
        blocking: a full pipe skips them); its record code."""
        code = _code(fault)
        data = _describe(fault)
        self.faults += 1
        now = time.monotonic_ns()
        prev = self.described
        due = prev is None or data[:2] != prev[:2] \
            or now - self.described_at >= DETAIL_INTERVAL_NS
        if data != prev and due and select.select([], [self.conn], [], 0)[1]:
            try:
                self.conn.send(("detail", self.detail + 1, code, data))
            except OSError:  # the parent is gone: the pipe's EOF ends this process
                return code
            self.detail += 1
            self.described, self.described_at = data, now
        return code
