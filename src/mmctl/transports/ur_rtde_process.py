"""The UR10e link in a process of its own: ur_rtde can crash, hang or hold the GIL there,
never in the daemon.

ur_rtde 1.6.5 cannot be made safe in the daemon's process (read from its source, see
``docs/stop-path.md``): after 2.5 s without RTDE data, ``RTDEControlInterface``'s
receive thread reconnects by itself, starts a second receive thread while the first
keeps resetting the socket the second one reads (SIGSEGV in ``RTDE::isDataAvailable``),
and its destructor leaves that detached thread reading freed memory (the segfaults at
shutdown).  Its constructors and destructors also hold the GIL (a destructor sleeps
0.5 s), stalling the loop thread.  So :class:`UrRtdeProcessArm` runs
:class:`~mmctl.transports.ur_rtde_arm.UrRtdeArm` in a child process (``spawn``) and
talks to it over a pipe:

* ``read_state`` is one round trip (the child reads ur_rtde and answers with the sample,
  its digital inputs and any fault, which is raised here as it was there), asked for
  at the end of each read and taken by the next one, so the loop does not wait for
  it; ``arm.stale_cycles`` reads in a row without an answer are ``ARM_STALE``;
* ``speed_j``, ``kick_watchdog`` and ``stop`` are one-way messages; a fault they raise in
  the child comes back with the next read;
* on ``ARM_STALE`` or ``ARM_DISCONNECTED`` the child sends speedJ(0) with the stop
  deceleration (a real-time command: never waits), answers, and ends itself with
  ``os._exit`` before ur_rtde's own reconnect can start; the arm's RTDE watchdog stops
  the program.  A child that dies (a crash included) is ``ARM_DISCONNECTED`` here;
  ``reconnect`` starts a new one;
* ``close`` asks the child for speedStop + stopScript (if the link is healthy), then it
  exits without ur_rtde's teardown; a child that does not end in time is killed;
* the child leaves the terminal's session and ignores the terminating signals: the
  daemon sends its stop commands through it, then ends it.  A daemon that dies closes
  the pipe: the child sends speedJ(0) and ends.
"""

from __future__ import annotations

import math
import multiprocessing
import os
import select
import signal
import threading
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog
from numpy.typing import NDArray

from mmctl.config.arm import ArmConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import FaultCause, MmctlError, SafetyFault, TransportError
from mmctl.types import ArmState

if TYPE_CHECKING:
    from typing_extensions import Self

    from mmctl.transports.ur_rtde_arm import UrRtdeArm

log = structlog.get_logger("mmctl.arm")

FATAL = frozenset({FaultCause.ARM_STALE, FaultCause.ARM_DISCONNECTED})
"""Faults after which the child ends itself (ur_rtde's own reconnect must never run)."""
START_TIMEOUT = 60.0
"""[s] for the child to start (imports on a loaded machine) and connect."""


class UrRtdeProcessArm:
    """:class:`~mmctl.transports.arm.Arm` whose ur_rtde client runs in a child process
    (see the module docstring).  config: the ``arm:`` section; limits: ``limits:``;
    log_setup: (level, json) for the child's structlog (the daemon's own)."""

    def __init__(self, config: ArmConfig, limits: LimitsConfig | None = None,
                 log_setup: tuple[str, bool | None] = ("info", None)):
        self.config = config
        self.limits = LimitsConfig() if limits is None else limits
        self.log_setup = log_setup
        self.reply_wait = 1.0 / config.frequency
        """[s] how long the first read of a connection waits for its sample."""
        self._proc: Any = None
        self._conn: Any = None
        self._lock = threading.Lock()
        self._poller = select.poll()
        self._seq = 0
        self._missed = 0
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

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else int(self._proc.pid)

    # -- lifecycle -----------------------------------------------------------------------

    def connect(self) -> None:
        """Start the child and let it connect; raises what its connect raised."""
        if self._conn is not None:
            return
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=_serve, args=(child, self.config, self.limits,
                                                self.log_setup),
                           name=f"mmctl-arm-{self.host}", daemon=True)
        proc.start()
        child.close()
        try:
            if not parent.poll(START_TIMEOUT + 3 * self.config.connect_timeout):
                raise TransportError(f"{self.host}: the arm process did not report within "
                                     f"{START_TIMEOUT + 3 * self.config.connect_timeout:g} s")
            reply = parent.recv()
        except (EOFError, OSError):
            reply = ("error", "transport", None,
                     {}, f"{self.host}: the arm process ended (exit code {proc.exitcode})")
        except TransportError:
            _end(proc, parent)
            raise
        if reply[0] != "connected":
            _end(proc, parent)
            raise _rebuild(reply[1:])
        _, self.controller_version, self.serial_number = reply
        self._proc, self._conn = proc, parent
        self._poller = select.poll()
        self._poller.register(parent.fileno(), select.POLLIN)
        self._missed = 0
        self.last_state = None
        self._seq += 1
        parent.send(("read", self._seq))  # the first sample, for the first read
        # wait until it is there (not read here): a starved child's first answer must
        # not make the first read after a (re)connect a stale fault
        parent.poll(self.config.connect_timeout)
        log.info("arm_process_started", host=self.host, pid=proc.pid)

    def reconnect(self) -> None:
        """End the child, start a new one."""
        self.close()
        self.connect()

    def close(self) -> None:
        """speedStop + stopScript in the child (healthy link), then it ends (idempotent)."""
        with self._lock:
            proc, conn = self._proc, self._conn
            self._proc = self._conn = None
        if proc is None:
            return
        try:
            conn.send(("close",))
            conn.poll(5.0)  # its "closed", or the pipe closing, or nothing
        except (EOFError, OSError):
            pass
        _end(proc, conn)
        log.info("arm_closed", host=self.host, exit_code=proc.exitcode)

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- per cycle -----------------------------------------------------------------------

    def read_state(self) -> ArmState:
        """The child's newest sample; raises the SafetyFault it found (see the module
        docstring), ARM_STALE after ``arm.stale_cycles`` reads in a row without a new
        answer, ARM_DISCONNECTED when the child is gone.

        The loop never waits for the child: each read takes the answers that arrived
        (the newest wins, one carrying a fault first), then asks for the next sample,
        which the child reads and sends during the loop's idle time.  The sample is
        thus about one period old (its controller time says exactly); only the first
        read of a connection waits for one (at most a period).
        """
        with self._lock:
            conn = self._conn
            if conn is None:
                raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host,
                                  why="not connected")
            # the answer was asked for a period ago; missing, it is rarely worth the
            # loop's time to wait (a starved child), except for a first sample
            reply, gone = self._drain(conn, None,
                                      self.reply_wait * 1e3 if self.last_state is None else 0.0)
            if not gone:
                self._seq += 1
                try:
                    conn.send(("read", self._seq))  # answered before the next cycle
                except OSError:  # the child ended: its last answer, if any, says why first
                    reply, gone = self._drain(conn, reply)[0], True
            if reply is None and gone:
                raise self._gone()
            if reply is None:
                self._missed += 1
                if self._missed >= self.config.stale_cycles or self.last_state is None:
                    raise SafetyFault(FaultCause.ARM_STALE, host=self.host,
                                      why="no answer from the arm process",
                                      cycles=self._missed)
                return self.last_state
            self._missed = 0
        _, _, t, q, qd, runtime, bits, scaling, self._di, fault = reply
        if t is not None:
            self.last_state = ArmState(np.array(q), np.array(qd), t, runtime, bits, scaling)
        if fault is not None:
            raise _rebuild(fault)
        assert self.last_state is not None
        return self.last_state

    def speed_j(self, qd: NDArray[np.float64] | Sequence[float],
                acceleration: float | None = None, dt: float | None = None) -> bool:
        """speedJ in the child (clamped there as :meth:`UrRtdeArm.speed_j` does);
        non-finite input raises SafetyFault(NON_FINITE) here and sends nothing."""
        v = [float(x) for x in qd]
        if len(v) != 6:
            raise ValueError(f"qd must have 6 joint speeds, got {len(v)}")
        a = self.config.speedj_acceleration if acceleration is None else float(acceleration)
        t = 1.0 / self.config.frequency if dt is None else float(dt)
        if not math.isfinite(sum(v) + a + t):
            raise SafetyFault(FaultCause.NON_FINITE, source="speed_j", qd=v, acceleration=a, dt=t)
        self._send(("speedj", v, a, t))
        return True

    def kick_watchdog(self) -> None:
        """The controller's watchdog (set by the child on its first kick or speedJ)."""
        self._send(("kick",))

    def stop(self, deceleration: float | None = None) -> None:
        """The child's :meth:`UrRtdeArm.stop`; never blocks, never raises."""
        d = self.config.stop_deceleration if deceleration is None else float(deceleration)
        try:
            self._send(("stop", d))
        except SafetyFault as exc:
            log.warning("arm_stop_not_sent", host=self.host, why=str(exc))

    def digital_input(self, index: int) -> bool:
        """Digital input ``index`` as the newest read saw it."""
        if self._conn is None:
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host, why="not connected")
        return bool((self._di >> index) & 1)

    # -- internals -----------------------------------------------------------------------

    def _drain(self, conn: Any, reply: tuple[Any, ...] | None, wait_ms: float = 0.0
               ) -> tuple[tuple[Any, ...] | None, bool]:
        """(answer, gone): every answer there is taken (waiting ``wait_ms`` for the
        first), the newest kept unless an older one carries a fault; gone when the pipe
        closed (the answers the child sent before it ended are still taken)."""
        try:
            while self._poller.poll(wait_ms):  # (Connection.poll builds a selector per call)
                got = conn.recv()  # answers come in order
                if reply is None or reply[-1] is None:
                    reply = got
                wait_ms = 0.0
        except (EOFError, OSError):
            return reply, True
        return reply, False

    def _send(self, msg: tuple[Any, ...]) -> None:
        with self._lock:
            conn = self._conn
            if conn is None:
                raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host,
                                  why="not connected")
            try:
                conn.send(msg)
            except OSError:
                last = self._drain(conn, None)[0]  # the child's fault, if it said one
                if last is not None and last[-1] is not None:
                    raise _rebuild(last[-1]) from None
                raise self._gone() from None

    def _gone(self) -> SafetyFault:
        proc = self._proc
        code = None if proc is None else proc.exitcode
        return SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.host,
                           why=f"the arm process ended (exit code {code})")


def _end(proc: Any, conn: Any) -> None:
    proc.join(5.0)
    if proc.is_alive():
        proc.kill()
        proc.join(5.0)
    conn.close()


def _describe(exc: MmctlError) -> tuple[str, str | None, dict[str, Any], str]:
    """An exception as plain data for the pipe: (kind, cause, details, message)."""
    if isinstance(exc, SafetyFault):
        return ("safety", exc.cause.value, dict(exc.details), str(exc))
    return ("transport", None, {}, str(exc))


def _rebuild(data: Sequence[Any]) -> MmctlError:
    kind, cause, details, message = data
    if kind == "safety":
        return SafetyFault(FaultCause(cause), **details)
    return TransportError(message)


# -- the child ---------------------------------------------------------------------------

def _serve(conn: Any, config: ArmConfig, limits: LimitsConfig,
           log_setup: tuple[str, bool | None]) -> None:
    """Entry point of the arm's process (see the module docstring)."""
    try:
        os.setsid()  # a terminal's Ctrl-C reaches the daemon only
    except OSError:
        pass
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"):  # the daemon ends this process
        signal.signal(getattr(signal, name), signal.SIG_IGN)
    from mmctl.runtime.logging import setup_logging
    from mmctl.transports.ur_rtde_arm import UrRtdeArm

    setup_logging(log_setup[0], json=log_setup[1])
    arm = UrRtdeArm(config, limits)
    try:
        arm.connect()
    except MmctlError as exc:
        conn.send(("error", *_describe(exc)))
        os._exit(0)
    conn.send(("connected", arm.controller_version, arm.serial_number))
    _Child(conn, arm).run()


class _Child:
    def __init__(self, conn: Any, arm: UrRtdeArm):
        self.conn = conn
        self.arm = arm
        self.pending: MmctlError | None = None

    def run(self) -> None:
        conn, arm = self.conn, self.arm
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):  # the daemon is gone: stop the arm, end
                arm.stop()
                os._exit(0)
            op = msg[0]
            if op == "read":
                self._read(msg[1])
            elif op == "speedj":
                self._call(arm.speed_j, msg[1], msg[2], msg[3])
            elif op == "kick":
                self._call(arm.kick_watchdog)
            elif op == "stop":
                arm.stop(msg[1])
            elif op == "close":
                arm.end()
                try:
                    conn.send(("closed", 0))
                finally:
                    os._exit(0)  # no ur_rtde teardown: no disconnect, no destructor

    def _call(self, fn: Any, *args: Any) -> None:
        try:
            fn(*args)
        except MmctlError as exc:
            if self.pending is None:
                self.pending = exc

    def _read(self, seq: int) -> None:
        arm = self.arm
        fault, self.pending = self.pending, None
        if fault is None:
            try:
                arm.read_state()
            except MmctlError as exc:
                fault = exc
        s = arm.last_state
        reply = ("state", seq,
                 None if s is None else s.controller_time,
                 None if s is None else s.q.tolist(), None if s is None else s.qd.tolist(),
                 None if s is None else s.runtime_state, None if s is None else s.safety_bits,
                 None if s is None else s.speed_scaling,
                 arm.digital_inputs() if fault is None else 0,
                 None if fault is None else _describe(fault))
        fatal = isinstance(fault, SafetyFault) and fault.cause in FATAL \
            or isinstance(fault, TransportError)
        try:
            conn_ok = True
            self.conn.send(reply)  # first: the daemon learns the cause at once
        except OSError:
            conn_ok = False
        if fatal:
            arm.stop()  # speedJ(0): real-time, never waits; before ur_rtde reconnects
        if fatal or not conn_ok:
            os._exit(0)
