"""The base over a serial microcontroller bridge (protocol: docs/serial-protocol.md).

No thread: every call reads whatever bytes are waiting (non-blocking) and decodes
them with :class:`~mmctl.transports.base.serial_protocol.FrameDecoder`, so link
supervision happens in the per-cycle calls.  :meth:`SerialBase.send_twist` writes one
WHEEL_CMD; the bridge answers each command with a STATE (and sends one every report
period when idle), which :meth:`SerialBase.read_odometry` integrates.

Faults (raised as SafetyFault from ``send_twist``, ``read_odometry`` and ``check``):
no valid frame for ``base.serial.link_timeout`` -> ``BASE_LINK``; the bridge reports
FAULT, or a wheel not enabled, while enabled -> ``DRIVE_FAULT``.  A read or write that
fails (the USB adapter unplugged) raises :class:`~mmctl.errors.LinkLost` (cause
``base_link_lost``) until :meth:`SerialBase.reconnect` opens the port again.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np
import serial
import structlog

from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import FaultCause, LinkLost, MmctlError, SafetyFault, TransportError, again
from mmctl.transports.base import serial_protocol as sp
from mmctl.transports.base.kinematics import OdometryIntegrator, WheelCommand, wrap_delta
from mmctl.transports.base.protocol import WHEEL_NAMES, DriveStatus
from mmctl.types import Odometry, Twist

if TYPE_CHECKING:
    from typing_extensions import Self

log = structlog.get_logger(__name__)

#: Requests (HEARTBEAT at connect, ENABLE) are repeated this many times, every
#: ``base.serial.timeout``, before giving up.
_TRIES = 10
_ZERO = (0.0, 0.0, 0.0, 0.0)


class SerialBase:
    """:class:`~mmctl.transports.base.protocol.Base` over the serial bridge.

    cfg: the ``base:`` section; limits: wheel speed limit; port: overrides
    ``base.serial.port`` (a device path or a pyserial URL).  No I/O before
    :meth:`connect`.
    """

    def __init__(self, cfg: BaseConfig, limits: LimitsConfig, port: str | None = None) -> None:
        self._cfg = cfg.serial
        self.port = port or cfg.serial.port
        self._command = WheelCommand(cfg.mecanum, limits.wheel_velocity)
        self._odo = OdometryIntegrator(cfg.mecanum)
        self._ser: serial.SerialBase | None = None
        self._decoder = sp.FrameDecoder()
        self._seq = 0
        self._last_rx = -math.inf
        self._state: sp.WheelState | None = None
        self._prev_pos: tuple[int, ...] | None = None
        self._last_fault: tuple[int, int] = (0, 0xFF)  # from the last FAULT frame
        self._enabled = False
        self._fault: SafetyFault | None = None
        self._failed = False  # a read or write failed (LinkLost): reconnect() reopens

    @property
    def stats(self) -> sp.LinkStats:
        """Receive counters (frames, crc_errors, malformed, out_of_sequence, lost...)."""
        return self._decoder.stats

    # -- lifecycle -------------------------------------------------------------------

    def connect(self) -> None:
        """Open the port and wait for the bridge to answer a HEARTBEAT with a STATE.

        Raises TransportError "no bridge answers on serial port P" otherwise."""
        if self._ser is not None:
            return
        try:
            self._ser = serial.serial_for_url(
                self.port, baudrate=self._cfg.baudrate, timeout=0,
                write_timeout=self._cfg.timeout, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"cannot open serial port {self.port!r}: {exc}") from exc
        self._decoder = sp.FrameDecoder()
        self._state, self._prev_pos, self._fault, self._enabled = None, None, None, False
        self._last_rx = -math.inf
        self._failed = False
        try:
            if not self._request(sp.MsgType.HEARTBEAT, lambda s: True):
                raise TransportError(
                    f"no bridge answers on serial port {self.port!r} "
                    f"({_TRIES} x {self._cfg.timeout} s)")
        except BaseException:
            self._release()
            raise
        self._odo.reset(self._last_rx)
        log.info("base_connected", transport="serial", port=self.port)

    def reconnect(self) -> None:
        """After a failed read or write (LinkLost): close the port, connect again
        (HEARTBEAT answered) and send DISABLE, so the bridge is left disabled.  Does
        nothing while the link works (idempotent).  Raises LinkLost (cause
        ``base_link_lost``) naming the port while the bridge does not answer."""
        if self._ser is not None and not self._failed:
            return
        self._release()
        try:
            self.connect()
            self.disable()
        except TransportError as exc:
            self._release()
            raise LinkLost.wrap(self.port, FaultCause.BASE_LINK,
                                "reconnect failed", exc) from exc
        log.info("base_reconnected", transport="serial", port=self.port)

    def enable(self) -> None:
        """ENABLE (which also resets bridge faults); wait until every wheel reports
        enabled.  Raises SafetyFault(DRIVE_FAULT) if the bridge stays in FAULT."""
        self._require_connected()
        self._fault = None
        self._decoder.resync()
        self._write(sp.MsgType.WHEEL_CMD, sp.pack_wheel_cmd(_ZERO))

        def enabled(s: sp.WheelState) -> bool:
            return bool(s.status & sp.Status.ENABLED) and not s.status & sp.Status.FAULT \
                and all(w & sp.Status.ENABLED for w in s.wheel_status)

        if not self._request(sp.MsgType.ENABLE, enabled):
            s = self._state
            if s is not None and s.status & sp.Status.FAULT:
                self._fault = SafetyFault(FaultCause.DRIVE_FAULT, port=self.port,
                                          fault_code=f"0x{s.fault_code:04X}")
                raise again(self._fault)
            raise TransportError(f"bridge on {self.port!r} did not confirm ENABLE")
        self._enabled = True
        log.info("base_enabled", transport="serial", port=self.port)

    def stop(self) -> None:
        """Write a zero WHEEL_CMD."""
        if self._ser is not None:
            self._write(sp.MsgType.WHEEL_CMD, sp.pack_wheel_cmd(_ZERO))

    def disable(self, wait: bool = True) -> None:
        """Zero command, then DISABLE (never waited for, ``wait`` or not: the bridge ramps
        to zero)."""
        if self._ser is None:
            return
        self._enabled = False
        self._write(sp.MsgType.WHEEL_CMD, sp.pack_wheel_cmd(_ZERO))
        self._write(sp.MsgType.DISABLE)

    def close(self) -> None:
        """Stop and disable (best effort, failures logged) and close the port.  Safe to
        call more than once."""
        if self._ser is None:
            return
        try:
            if self._enabled:
                self.disable()
        except MmctlError as exc:
            log.warning("base_close_disable_failed", error=str(exc))
        finally:
            self._release()
        log.info("base_closed", transport="serial", port=self.port)

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- per cycle ---------------------------------------------------------------------

    def send_twist(self, vx: float, vy: float, wz: float) -> Twist:
        """One WHEEL_CMD (wheel speeds scaled to the limit, direction kept); returns the
        twist commanded.  Raises SafetyFault (after writing zero) when unhealthy, and
        SafetyFault(NON_FINITE) for a twist whose wheel speeds are not finite."""
        if not self._enabled:
            raise TransportError("send_twist() before enable()")
        try:
            wheels, twist = self._command(vx, vy, wz)
            if not np.all(np.isfinite(wheels)):  # a finite twist near 1e308 overflows
                raise ValueError(f"wheel speeds {wheels} for the twist ({vx}, {vy}, {wz})")
        except ValueError:
            self.stop()
            raise SafetyFault(FaultCause.NON_FINITE, twist=(vx, vy, wz)) from None
        self._poll()
        fault = self._health()
        if fault is not None:
            self.stop()
            raise fault
        self._write(sp.MsgType.WHEEL_CMD, sp.pack_wheel_cmd(wheels.tolist()))
        return twist

    def read_odometry(self) -> Odometry:
        """Integrate every STATE received so far; the newest estimate."""
        self.check()
        return self._odo.odometry()

    def check(self) -> None:
        """Read what is waiting; raise SafetyFault on a silent link or a bridge fault."""
        self._require_connected()
        self._poll()
        fault = self._health()
        if fault is not None:
            raise fault

    def drive_status(self) -> list[DriveStatus]:
        """Per wheel: link (LINK UP / LINK DOWN), state from its status byte, the byte,
        and the bridge's fault code."""
        s = self._state
        up = time.monotonic() - self._last_rx <= self._cfg.link_timeout
        out = []
        for i, name in enumerate(WHEEL_NAMES):
            ws = s.wheel_status[i] if s is not None else 0
            if ws & sp.Status.FAULT:
                state = "FAULT"
            elif ws & sp.Status.ENABLED:
                state = "OPERATION ENABLED"
            else:
                state = "DISABLED"
            out.append(DriveStatus(name, i, "LINK UP" if up else "LINK DOWN", state, ws,
                                   s.fault_code if s is not None else 0))
        return out

    # -- internals ---------------------------------------------------------------------

    def _require_connected(self) -> None:
        if self._ser is None:
            raise TransportError("base is not connected (call connect() first)")

    def _write(self, msg_type: sp.MsgType, payload: bytes = b"") -> None:
        ser = self._ser
        if ser is None:
            raise TransportError("base is not connected (call connect() first)")
        if self._failed:
            raise self._lost("the link failed earlier: reconnect()")
        self._seq = (self._seq + 1) & 0xFFFF
        try:
            ser.write(sp.encode_frame(self._seq, msg_type, payload))
        except (serial.SerialException, OSError) as exc:
            raise self._lost(f"serial write to {self.port!r} failed: {exc}") from exc

    def _poll(self) -> None:
        ser = self._ser
        assert ser is not None
        if self._failed:
            raise self._lost("the link failed earlier: reconnect()")
        try:
            n = ser.in_waiting
            data = ser.read(n) if n else b""
        except (serial.SerialException, OSError) as exc:
            raise self._lost(f"serial read from {self.port!r} failed: {exc}") from exc
        if not data:
            return
        now = time.monotonic()
        for frame in self._decoder.feed(data):
            try:
                if frame.type == sp.MsgType.STATE:
                    self._on_state(sp.unpack_state(frame.payload), now)
                elif frame.type == sp.MsgType.FAULT:
                    self._last_fault = sp.unpack_fault(frame.payload)
                    log.warning("base_bridge_fault_frame", code=f"0x{self._last_fault[0]:04X}",
                                wheel=self._last_fault[1])
                else:
                    raise sp.FrameError("type", f"unexpected message type 0x{frame.type:02X}")
            except sp.FrameError:
                self._decoder.stats.malformed += 1
                continue
            self._last_rx = now

    def _lost(self, reason: str) -> LinkLost:
        """The link failed: remember it for reconnect(); the error to raise."""
        if not self._failed:
            log.warning(FaultCause.BASE_LINK.value, link=self.port, error=reason)
        self._failed = True
        return LinkLost(self.port, FaultCause.BASE_LINK, reason)

    def _on_state(self, s: sp.WheelState, now: float) -> None:
        self._state = s
        if self._prev_pos is None:
            self._prev_pos = s.position
            return
        d = np.array([wrap_delta(p, q) for p, q in zip(s.position, self._prev_pos)])
        self._prev_pos = s.position
        self._odo.update(d / sp.ANGLE_SCALE, np.array(s.velocity) / sp.SPEED_SCALE, now)

    def _request(self, msg_type: sp.MsgType, done: Callable[[sp.WheelState], bool]) -> bool:
        """Send ``msg_type`` up to _TRIES times, each time waiting ``timeout`` for a
        STATE frame for which ``done(state)`` is true."""
        for _ in range(_TRIES):
            before = self._decoder.stats.frames
            self._write(msg_type)
            deadline = time.monotonic() + self._cfg.timeout
            while time.monotonic() < deadline:
                self._poll()
                s = self._state
                if self._decoder.stats.frames > before and s is not None and done(s):
                    return True
                time.sleep(0.001)
        return False

    def _health(self) -> SafetyFault | None:
        if self._fault is not None:
            return self._fault
        now = time.monotonic()
        age = now - self._last_rx
        fault = None
        s = self._state
        if age > self._cfg.link_timeout:
            fault = SafetyFault(FaultCause.BASE_LINK, port=self.port, silent_for=round(age, 4))
        elif self._enabled and s is not None and (
            s.status & sp.Status.FAULT or not all(w & sp.Status.ENABLED for w in s.wheel_status)
        ):
            bad = [WHEEL_NAMES[i] for i, w in enumerate(s.wheel_status)
                   if w & sp.Status.FAULT or not w & sp.Status.ENABLED]
            _, wheel = self._last_fault
            fault = SafetyFault(FaultCause.DRIVE_FAULT, port=self.port, wheels=bad,
                                fault_code=f"0x{s.fault_code:04X}",
                                fault_wheel=WHEEL_NAMES[wheel] if wheel < 4 else "bridge")
        if fault is not None:
            self._fault = fault
            log.error("base_fault", transport="serial", cause=fault.cause.value, **fault.details)
        return fault

    def _release(self) -> None:
        ser, self._ser = self._ser, None
        self._enabled = False
        if ser is not None:
            ser.close()
