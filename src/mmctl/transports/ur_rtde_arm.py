"""The UR10e link through ur_rtde (``RTDEControlInterface`` + ``RTDEReceiveInterface``).

The daemon runs this class in a process of its own
(:class:`~mmctl.transports.ur_rtde_process.UrRtdeProcessArm`, which says why: ur_rtde
1.6.5 can crash its process); tools and tests use it directly.

Per cycle the daemon calls :meth:`UrRtdeArm.read_state`, then :meth:`UrRtdeArm.speed_j`
(armed) or :meth:`UrRtdeArm.kick_watchdog` (not armed).

**The net under the daemon: the controller's RTDE watchdog.**  ur_rtde's control script
runs speedj in a thread with the latest target until told otherwise, so a daemon that
hangs, is stopped (SIGSTOP) or dies would leave the arm moving.  Before the first
speedJ of every connection (and on the first :meth:`UrRtdeArm.kick_watchdog`) this
module calls ``setWatchdog(arm.watchdog_min_frequency)``: the script's
``rtde_set_watchdog("input_int_register_0", f, "stop")``, after which the controller
stops the program, and the arm with it, when that input register is not updated for
1/f seconds.  Every speedJ updates it (its command number goes there) and so does
``kickWatchdog()`` (it writes 0); the daemon calls one of the two every cycle.
Health is judged here, from what the controller streams, never from speedJ's return
value (it stays True after a lost link).  ``read_state`` raises
:class:`~mmctl.errors.SafetyFault` with, in this order of precedence:

* ``ARM_DISCONNECTED``: either ur_rtde interface reports it is not connected;
* ``ARM_EMERGENCY_STOP``: safety status bit 5, 6 or 7;
* ``ARM_PROTECTIVE_STOP``: bit 2 (protective), 4 (safeguard), 8 (violation), 9 (fault)
  or 10 (stopped due to safety);
* ``ARM_NOT_PLAYING``: runtime state is not PLAYING (our control script is not running);
* ``ARM_STALE``: the controller timestamp has not advanced for ``arm.stale_cycles``
  consecutive calls (ur_rtde itself only notices a silent stream after ~2.5 s).

ur_rtde pitfalls measured against the fake controller (:mod:`mmctl.sim.fake_ur`) that
shape this module:

* its constructors and destructors hold the GIL (its methods release it);
  ``speedStop`` waits for the script's "done" handshake and, once the link is lost,
  keeps waiting for ~300 s.  :meth:`UrRtdeArm.stop` therefore
  calls ``speedStop`` only when the newest sample was fresh and the arm healthy, and
  otherwise ``speedJ(0, deceleration)`` (a real-time command that never waits), or
  nothing when the link is down;
* its constructors block (holding the GIL) on an unreachable host and forever on a
  controller that accepts but never streams: :meth:`UrRtdeArm.connect` first checks
  the dashboard and RTDE ports with plain sockets and a timeout;
* each interface's destructor sleeps 0.5 s with the GIL held, after ``disconnect()``
  too (which sleeps 0.5 s with the GIL released): ``close()`` disconnects both and
  never destroys them (a reconnect would otherwise stall the loop thread for 1 s);
* a write that fails inside speedJ makes ur_rtde reconnect synchronously; when that
  fails too, speedJ raises (reported here as ARM_DISCONNECTED).  If the controller
  resets the connection (its process died, the host is up), that synchronous reconnect
  can race the receive thread's own and crash the process (seen once in ~15
  killed-controller test runs): a ur_rtde 1.6.5 bug that only isolating the link in its own
  process (or patching ur_rtde) removes;
* after a silent stream of more than 2.5 s ``RTDEControlInterface`` reconnects by
  itself from its receive thread and, if the controller still streams nothing, waits
  forever for a first sample (seen too: a segfault in that path); destroying it then
  hangs.  ``close()`` therefore checks a link that is not fresh with a plain-socket
  RTDE probe, and if the controller answers but streams nothing it *parks* both
  interfaces (keeps them alive for good, threads included) instead of destroying them.
  If such a silence lasts beyond 2.5 s, ur_rtde's self-reconnect still runs (parked
  or not) and, when the controller comes back, has crashed the process in our tests
  (segfault): with ur_rtde 1.6.5 a frozen stream longer than 2.5 s is not survivable
  for sure.  The daemon must treat ARM_STALE as a fault at once.
"""

from __future__ import annotations

import ctypes
import math
import re
import socket
import struct
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog
from numpy.typing import NDArray

from mmctl.config.arm import ArmConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import FaultCause, SafetyFault, TransportError
from mmctl.types import ArmState

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing_extensions import Self

log = structlog.get_logger("mmctl.arm")

DASHBOARD_PORT = 29999
RTDE_PORT = 30004
PLAYING = 2
UR_ACCELERATION_MAX = 40.0
"""[rad/s^2] ur_rtde refuses larger speedJ accelerations."""
EMERGENCY_BITS = (1 << 5) | (1 << 6) | (1 << 7)
PROTECTIVE_BITS = (1 << 2) | (1 << 4) | (1 << 8) | (1 << 9) | (1 << 10)
RECEIVE_VARIABLES = [
    "timestamp", "actual_q", "actual_qd", "runtime_state", "safety_status_bits",
    "robot_status_bits", "robot_mode", "safety_mode", "actual_digital_input_bits",
    "speed_scaling", "target_speed_fraction",
]
"""What the receive interface asks the controller to stream (not ur_rtde's ~60 default)."""


class UrRtdeArm:
    """A UR e-Series arm through ur_rtde (see the module docstring for the fault rules).

    config: the ``arm:`` section (host, frequency, speedJ acceleration, stop
    deceleration, stale cycles, connect timeout); limits: the ``limits:`` section, whose
    ``joint_velocity`` (6,) [rad/s] caps every speedJ (default: the UR10e's).
    No I/O here: :meth:`connect` does it.
    """

    def __init__(self, config: ArmConfig, limits: LimitsConfig | None = None):
        limits = LimitsConfig() if limits is None else limits
        self.config = config
        self.joint_speed_limits = tuple(float(v) for v in limits.joint_velocity)
        self._inv_limits = [1.0 / v for v in self.joint_speed_limits]
        self._dt = 1.0 / config.frequency
        self._ctrl: Any = None
        self._recv: Any = None
        self._last_time = math.nan
        self._stale = 0
        self._healthy = False
        self._ctrl_checked: bool | None = None
        """The control link's state as the newest read_state saw it, for the next speed_j
        (None: speed_j asks ur_rtde itself)."""
        self.watchdog_on = False
        """The control script's RTDE watchdog is set on this connection."""
        self.last_state: ArmState | None = None
        """The newest sample read, also when read_state raised on it."""
        self.controller_version = ""
        """PolyScope version reported by the dashboard, e.g. "5.11.0.108249"."""
        self.serial_number = ""

    @classmethod
    def from_config(cls, cfg: Any) -> UrRtdeArm:
        """From a whole :class:`~mmctl.config.Config` (its ``arm`` and ``limits``)."""
        return cls(cfg.arm, cfg.limits)

    @property
    def host(self) -> str:
        return self.config.host

    @property
    def connected(self) -> bool:
        """Both ur_rtde interfaces exist and report a connection."""
        ctrl, recv = self._ctrl, self._recv
        return ctrl is not None and recv is not None and ctrl.isConnected() and recv.isConnected()

    # -- lifecycle -----------------------------------------------------------------------

    def connect(self) -> None:
        """Check the controller with short timeouts, then open both ur_rtde interfaces.

        Raises TransportError when nothing answers, remote control is off, the RTDE port
        sends no data or ur_rtde fails; SafetyFault when the arm is in an emergency or
        protective stop (the control script could not start).
        """
        if self._ctrl is not None:
            return
        host, timeout = self.config.host, self.config.connect_timeout
        version, remote = _dashboard_check(host, timeout)
        self.controller_version = version
        if remote is False:
            raise TransportError(f"{host}: remote control is off (enable Remote Control on "
                                 "the teach pendant)")
        t, _runtime, bits = _rtde_first_sample(host, self.config.frequency, timeout)
        _check_safety(bits, t)
        import rtde_control
        import rtde_receive

        try:
            recv = rtde_receive.RTDEReceiveInterface(host, self.config.frequency,
                                                     RECEIVE_VARIABLES)
        except RuntimeError as exc:
            raise TransportError(f"{host}: ur_rtde receive interface: {exc}") from None
        try:
            ctrl = rtde_control.RTDEControlInterface(
                host, self.config.frequency, rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT)
        except RuntimeError as exc:
            del recv
            raise TransportError(f"{host}: ur_rtde control interface: {exc}") from None
        self._ctrl, self._recv = ctrl, recv
        self._last_time, self._stale, self._healthy = math.nan, 0, True
        self._ctrl_checked = None
        self.watchdog_on = False  # a new program: its watchdog is set before any motion
        log.info("arm_connected", host=host, controller_version=version,
                 frequency=self.config.frequency)

    def reconnect(self) -> None:
        """Close both interfaces and connect again (ur_rtde's own receive interface never
        reconnects, and its control interface's reconnect races its receive thread)."""
        self.close()
        self.connect()

    def close(self) -> None:
        """speedStop and stopScript if the link is healthy, then disconnect (idempotent).

        Never runs ur_rtde's destructors: each sleeps 0.5 s holding the GIL (the loop
        thread would stall that long) even after ``disconnect()``, which sleeps as long
        but releases the GIL.  So both interfaces are disconnected explicitly, then kept
        alive for good (:func:`_park`: a few kB per reconnect, which is an operator's
        action).  A stream that is silent is not even disconnected (ur_rtde would block
        in it), only parked.  Costs ~1 s, the GIL free for all but a few ms.
        """
        ctrl, recv = self._ctrl, self._recv
        if ctrl is None and recv is None:
            return
        fresh = self._fresh()
        self._ctrl = self._recv = None  # nothing of this link is used from here on
        self._healthy = False
        try:
            if fresh:
                if not ctrl.speedStop(self.config.stop_deceleration):
                    log.warning("arm_speed_stop_refused", host=self.host)
                ctrl.stopScript()
            if self._stream_silent():
                log.warning("arm_interfaces_parked", host=self.host,
                            why="the controller accepts RTDE clients but streams nothing; "
                            "disconnecting ur_rtde's interfaces now would block or hang")
            else:
                for interface in (ctrl, recv):
                    if interface is not None:
                        interface.disconnect()  # the GIL released while it sleeps
        except RuntimeError as exc:
            log.warning("arm_close_stop_failed", host=self.host, why=str(exc))
        finally:
            for interface in (ctrl, recv):
                if interface is not None:
                    _park(interface)
            self.watchdog_on = False
            log.info("arm_closed", host=self.host)

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- per cycle -----------------------------------------------------------------------

    def read_state(self) -> ArmState:
        """The newest RTDE sample; raises SafetyFault (see the module docstring)."""
        # No local references to the ur_rtde objects in methods that raise: a kept
        # exception's traceback would keep them alive after close(), and their
        # destructors (0.5 s with the GIL held) would run at some later moment.
        if self._ctrl is None or self._recv is None:
            self._healthy = False
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host, why="not connected")
        t = self._recv.getTimestamp()
        state = ArmState(np.array(self._recv.getActualQ()), np.array(self._recv.getActualQd()), t,
                         self._recv.getRuntimeState(), self._recv.getSafetyStatusBits(),
                         self._recv.getSpeedScalingCombined())
        self.last_state = state
        if t != self._last_time:
            self._last_time = t
            self._stale = 0
        else:
            self._stale += 1
        self._healthy = False
        control, receive = self._ctrl.isConnected(), self._recv.isConnected()
        self._ctrl_checked = control  # speed_j's check, once (each call releases the GIL)
        if not (control and receive):
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host,
                              control=control, receive=receive)
        _check_safety(state.safety_bits, t)
        if state.runtime_state != PLAYING:
            raise SafetyFault(FaultCause.ARM_NOT_PLAYING, runtime_state=state.runtime_state,
                              controller_time=t)
        if self._stale >= self.config.stale_cycles:
            raise SafetyFault(FaultCause.ARM_STALE, cycles=self._stale, controller_time=t)
        if not math.isfinite(float(state.q.sum() + state.qd.sum())):
            raise SafetyFault(FaultCause.NON_FINITE, source="arm state", controller_time=t)
        self._healthy = True
        return state

    def speed_j(self, qd: NDArray[np.float64] | Sequence[float], acceleration: float | None = None,
                dt: float | None = None) -> bool:
        """speedJ(qd, acceleration, dt) with qd (6,) [rad/s] scaled down as a whole (its
        direction kept) so that no joint exceeds its speed limit; acceleration
        [rad/s^2] (default ``arm.speedj_acceleration``, capped at 40); dt [s] (default
        one period).  Returns ur_rtde's answer, which says nothing about the link's
        health.  Non-finite input raises SafetyFault(NON_FINITE) and sends nothing."""
        checked, self._ctrl_checked = self._ctrl_checked, None
        if self._ctrl is None or not (self._ctrl.isConnected() if checked is None else checked):
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host, why="not connected")
        v = [float(x) for x in qd]
        a = self.config.speedj_acceleration if acceleration is None else float(acceleration)
        t = self._dt if dt is None else float(dt)
        if len(v) != 6:
            raise ValueError(f"qd must have 6 joint speeds, got {len(v)}")
        if not math.isfinite(sum(v) + a + t):
            raise SafetyFault(FaultCause.NON_FINITE, source="speed_j", qd=v, acceleration=a, dt=t)
        ratio = max([abs(x) * k for x, k in zip(v, self._inv_limits)])
        if ratio > 1.0:
            v = [x / ratio for x in v]
        if not self.watchdog_on:
            self._set_watchdog()  # never a motion without the controller's watchdog
        try:
            return bool(self._ctrl.speedJ(v, min(max(a, 0.0), UR_ACCELERATION_MAX), t))
        except RuntimeError as exc:  # the write failed and ur_rtde's own reconnect too
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host,
                              why=str(exc)) from None

    def stop(self, deceleration: float | None = None) -> None:
        """Bring the joints to rest with ``deceleration`` [rad/s^2] (default
        ``arm.stop_deceleration``) without blocking for long.

        Healthy link and fresh newest sample: ``speedStop(deceleration)``.  Stale sample,
        safety stop or program not running: ``speedJ(0, deceleration)`` (a real-time
        command: never waits for the controller).  Link down: nothing can be sent.
        """
        d = self.config.stop_deceleration if deceleration is None else float(deceleration)
        d = min(max(d, 1e-3), UR_ACCELERATION_MAX) if math.isfinite(d) else UR_ACCELERATION_MAX
        if self._ctrl is None or self._recv is None or not self._ctrl.isConnected():
            log.warning("arm_stop_not_sent", host=self.config.host, why="not connected")
            return
        try:
            if self._fresh():
                if self._ctrl.speedStop(d):
                    return
                log.warning("arm_speed_stop_refused", host=self.config.host)
            self._ctrl.speedJ([0.0] * 6, d, self._dt)
        except RuntimeError as exc:  # the link broke under the call
            log.warning("arm_stop_not_sent", host=self.config.host, why=str(exc))

    def kick_watchdog(self) -> None:
        """Tell the controller the daemon is alive (every cycle without a speedJ).

        The first call of a connection sets the watchdog (``setWatchdog``, a command the
        script acknowledges: a few controller periods), later calls ``kickWatchdog()``
        (one RTDE package, never waits).  Setting it needs a fresh, healthy link (the
        newest read_state): a stale or stopped controller would keep the handshake
        waiting; then nothing is sent, and nothing can move either (speed_j sets it
        first).  Raises SafetyFault(ARM_DISCONNECTED) when the write fails.
        """
        if self._ctrl is None:
            return
        if not self.watchdog_on:
            if self._fresh():
                self._set_watchdog()
            return
        try:
            self._ctrl.kickWatchdog()
        except RuntimeError as exc:
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host,
                              why=str(exc)) from None

    def end(self, fresh_within: float = 0.05) -> None:
        """Stop the joints and the control script; nothing else (the arm's own process
        ends right after, see :mod:`mmctl.transports.ur_rtde_process`: no disconnect, no
        destructor).  Waits up to ``fresh_within`` [s] for a fresh sample: then
        speedStop (waits for the script's handshake); else, if still connected,
        speedJ(0) with the stop deceleration.  stopScript in both cases."""
        deadline = time.monotonic() + fresh_within
        while not self._fresh() and time.monotonic() < deadline and self._ctrl is not None:
            try:
                self.read_state()
            except SafetyFault:
                break
            time.sleep(0.001)
        if self._ctrl is None or not self._ctrl.isConnected():
            return
        try:
            self.stop()
            self._ctrl.stopScript()
        except RuntimeError as exc:
            log.warning("arm_close_stop_failed", host=self.host, why=str(exc))

    def digital_inputs(self) -> int:
        """All of ``actual_digital_input_bits`` (bit i = input i), 0 when not connected."""
        recv = self._recv
        return 0 if recv is None else int(recv.getActualDigitalInputBits())

    def digital_input(self, index: int) -> bool:
        """Digital input ``index`` (0-7 standard, 8-15 configurable, 16-17 tool)."""
        if self._recv is None:
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host, why="not connected")
        return bool((int(self._recv.getActualDigitalInputBits()) >> index) & 1)

    # -- internals -----------------------------------------------------------------------

    def _set_watchdog(self) -> None:
        """``setWatchdog(min frequency)`` on the running control script; SafetyFault
        (ARM_DISCONNECTED) when it fails: no motion may go out without it."""
        f = self.config.watchdog_min_frequency
        try:
            ok = bool(self._ctrl.setWatchdog(f))
        except RuntimeError as exc:
            raise SafetyFault(FaultCause.ARM_DISCONNECTED, host=self.config.host,
                              why=f"setWatchdog failed: {exc}") from None
        if not ok:  # ur_rtde refuses commands in a safety stop or without the program:
            self.read_state()  # the newest sample names that cause, if it shows it yet
            raise SafetyFault(FaultCause.ARM_NOT_PLAYING, host=self.config.host,
                              why="the control script did not take setWatchdog")
        self.watchdog_on = True
        log.info("arm_watchdog_set", host=self.config.host, min_frequency_hz=f,
                 timeout_s=round(1.0 / f, 4))

    def _stream_silent(self) -> bool:
        """The controller answers on the RTDE port but sends no data (a frozen stream)."""
        try:
            _rtde_first_sample(self.config.host, self.config.frequency,
                               min(self.config.connect_timeout, 0.5))
        except SilentStreamError:
            return True
        except TransportError:
            return False
        return False

    def _fresh(self) -> bool:
        """The newest read_state was healthy and brought a new sample."""
        return (self._healthy and self._stale == 0 and self._ctrl is not None
                and self._recv is not None and self._ctrl.isConnected()
                and self._recv.isConnected())



def _check_safety(bits: int, t: float) -> None:
    if bits & EMERGENCY_BITS:
        raise SafetyFault(FaultCause.ARM_EMERGENCY_STOP, safety_status_bits=bits, controller_time=t)
    if bits & PROTECTIVE_BITS:
        raise SafetyFault(FaultCause.ARM_PROTECTIVE_STOP, safety_status_bits=bits, controller_time=t)


URRtdeArm = UrRtdeArm
"""Alias (the spelling :mod:`mmctl.runtime.devices` uses)."""


# -- pre-flight checks with plain sockets (short timeouts, the GIL released) ------------------

def _dashboard_check(host: str, timeout: float) -> tuple[str, bool | None]:
    """(PolyScope version, in remote control?) from the dashboard server; the remote
    answer is None on PolyScope < 5.6, which cannot tell."""
    lines = _dashboard_query(host, ["PolyscopeVersion"], timeout)
    found = re.search(r"\d+\.\d+\.\d+\.\d+", lines[0])
    version = found.group(0) if found else lines[0]
    major, minor = (int(x) for x in version.split(".")[:2]) if found else (0, 0)
    if major < 5 or (major == 5 and minor < 6):
        return version, None
    reply = _dashboard_query(host, ["is in remote control"], timeout)[0]
    return version, "true" in reply.lower()


def _dashboard_query(host: str, commands: list[str], timeout: float) -> list[str]:
    """Send each command line to the dashboard server; its answer lines."""
    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout) as s, \
                s.makefile("rb") as reader:
            reader.readline()  # the welcome line
            answers = []
            for cmd in commands:
                s.sendall(cmd.encode() + b"\n")
                line = reader.readline()
                if not line:
                    raise TransportError(f"{host}:{DASHBOARD_PORT} closed the connection")
                answers.append(line.decode(errors="replace").strip())
            return answers
    except OSError as exc:
        raise TransportError(f"nothing answers at {host}:{DASHBOARD_PORT} (dashboard): "
                             f"{_reason(exc)}") from None


_HEADER = struct.Struct(">HB")
_FIRST = struct.Struct(">BdII")  # recipe id, timestamp, runtime_state, safety_status_bits


class SilentStreamError(TransportError):
    """The RTDE port accepts a client and starts it, but no data package follows."""


def _rtde_first_sample(host: str, frequency: float, timeout: float) -> tuple[float, int, int]:
    """Ask the RTDE port for one package of (timestamp, runtime_state, safety bits)."""
    deadline = time.monotonic() + timeout
    started = False
    try:
        with socket.create_connection((host, RTDE_PORT), timeout=timeout) as s:
            s.settimeout(timeout)
            _rtde_request(s, b"V", struct.pack(">H", 2), deadline)
            names = b"timestamp,runtime_state,safety_status_bits"
            reply = _rtde_request(s, b"O", struct.pack(">d", frequency) + names, deadline)
            if b"NOT_FOUND" in reply or not reply or reply[0] == 0:
                raise TransportError(f"{host}:{RTDE_PORT} refused the output recipe: {reply!r}")
            _rtde_request(s, b"S", b"", deadline)
            started = True
            while True:
                kind, body = _rtde_receive(s, deadline)
                if kind == ord("U") and len(body) == _FIRST.size:
                    _, t, runtime, bits = _FIRST.unpack(body)
                    return t, runtime, bits
    except OSError as exc:
        if started:
            raise SilentStreamError(f"{host}:{RTDE_PORT} (RTDE) accepts clients but sends no "
                                    f"data: {_reason(exc)}") from None
        raise TransportError(f"nothing answers at {host}:{RTDE_PORT} (RTDE): "
                             f"{_reason(exc)}") from None


_PARKED: list[Any] = []


def _park(interface: Any) -> None:
    """Keep a ur_rtde interface alive for good: its destructor sleeps 0.5 s with the GIL
    held (after a disconnect too), and on a controller that streams nothing it joins a
    receive thread blocked in a read, or in ur_rtde's own reconnect, which waits without
    a timeout for a first sample (hanging the process, the GIL held).  The extra
    reference makes sure it is not finalised at interpreter exit either."""
    _PARKED.append(interface)
    ctypes.pythonapi.Py_IncRef(ctypes.py_object(interface))


def _rtde_request(s: socket.socket, kind: bytes, payload: bytes, deadline: float) -> bytes:
    s.sendall(_HEADER.pack(_HEADER.size + len(payload), kind[0]) + payload)
    while True:
        got, body = _rtde_receive(s, deadline)
        if got == kind[0]:
            return body


def _rtde_receive(s: socket.socket, deadline: float) -> tuple[int, bytes]:
    size, kind = _HEADER.unpack(_read_exactly(s, _HEADER.size, deadline))
    if size < _HEADER.size:
        raise TransportError(f"RTDE package with size {size}")
    return kind, _read_exactly(s, size - _HEADER.size, deadline)


def _read_exactly(s: socket.socket, n: int, deadline: float) -> bytes:
    data = b""
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("no RTDE data before the timeout")
        s.settimeout(left)
        chunk = s.recv(n - len(data))
        if not chunk:
            raise ConnectionResetError("connection closed")
        data += chunk
    return data


def _reason(exc: OSError) -> str:
    if isinstance(exc, TimeoutError):
        return "timed out"
    return exc.strerror or str(exc) or type(exc).__name__
