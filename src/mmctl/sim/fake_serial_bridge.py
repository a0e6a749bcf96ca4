"""A simulated microcontroller base bridge on a pseudo-terminal (protocol:
docs/serial-protocol.md).

``FakeSerialBridge(cfg).start()`` opens a pty pair, keeps the master side and runs the
bridge in a thread; :attr:`FakeSerialBridge.port` is the slave's path (/dev/pts/N) for
the real :class:`~mmctl.transports.base.serial_base.SerialBase` (or ``mmctl probe base
--transport serial --port``).  The bridge answers every ENABLE / DISABLE / WHEEL_CMD /
HEARTBEAT with a STATE, sends a STATE every ``report_period`` when idle, and drives a
:class:`~mmctl.sim.wheels.WheelPlant` (acceleration limit, command watchdog; the base's
latency, velocity loop and slip of the ``sim:`` section).

Fault injection (:meth:`FakeSerialBridge.inject`): ``"crc"`` (bad CRC), ``"truncate"``
(frame cut short), ``"out_of_sequence"`` (an old sequence number carrying bogus
positions, before the next good frame), ``"garbage"`` (random bytes before the next
frame) — each for the next ``count`` frames sent; :meth:`inject_silence` / :meth:`resume`;
:meth:`inject_fault` (a wheel fault: FAULT frame, the base stops until ENABLE).
"""

from __future__ import annotations

import os
import random
import select
import threading
import time
import tty
from collections import Counter, deque
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np
import structlog
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.config.runtime import SimConfig
from mmctl.errors import again
from mmctl.sim.wheels import BaseDynamics, WheelPlant
from mmctl.transports.base import serial_protocol as sp

if TYPE_CHECKING:
    from typing_extensions import Self

log = structlog.get_logger(__name__)

INJECTIONS = ("crc", "truncate", "out_of_sequence", "garbage")


class FakeSerialBridge:
    """The simulated bridge (parent-side handle).

    cfg: a Config (or its ``base:`` section plus ``limits`` and ``sim``, the base's
    dynamics); report_period: idle STATE period [s]; seed: for the garbage bytes.  No
    I/O before :meth:`start`.
    """

    def __init__(
        self, cfg: Config | BaseConfig, limits: LimitsConfig | None = None,
        report_period: float = 0.02, seed: int = 0, sim: SimConfig | None = None,
    ) -> None:
        if isinstance(cfg, Config):
            base, limits, sim = cfg.base, cfg.limits, cfg.sim
        else:
            base, limits, sim = cfg, limits or LimitsConfig(), sim or SimConfig()
        self.cfg = base
        self.report_period = report_period
        self.plant = WheelPlant(base.mecanum, limits.base_linear_acceleration
                                / base.mecanum.wheel_radius, base.command_watchdog,
                                dynamics=BaseDynamics.from_config(sim))
        self._lock = threading.RLock()
        self._rng = random.Random(seed)
        self._decoder = sp.FrameDecoder(resync_types=frozenset({sp.MsgType.ENABLE}))
        self._master = -1
        self._slave = -1
        self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._t0 = 0.0
        self._seq = 0
        self._ack = 0
        self._enabled = False
        self._fault = (0, 0xFF)  # (code, wheel); code 0 = none
        self._fault_frame_due = False
        self._silent = False
        self._pending: Counter[str] = Counter()
        self._commands: deque[tuple[float, tuple[float, ...]]] = deque(maxlen=20_000)
        self.port = ""
        self.tx_dropped = 0

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> FakeSerialBridge:
        """Open the pty pair and start the bridge thread; :attr:`port` is then set."""
        if self._thread is not None:
            return self
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self._wake_r, self._wake_w = os.pipe()
        self.port = os.ttyname(self._slave)
        self._t0 = time.monotonic()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="fake-serial-bridge", daemon=True)
        self._thread.start()
        log.info("fake_bridge_started", port=self.port)
        return self

    def stop(self) -> None:
        """Stop the thread, close the pty; re-raise an error the thread stored."""
        t, self._thread = self._thread, None
        if t is not None:
            self._stop.set()
            os.write(self._wake_w, b"x")
            t.join(timeout=5.0)
            for fd in (self._master, self._slave, self._wake_r, self._wake_w):
                os.close(fd)
            log.info("fake_bridge_stopped", port=self.port)
        self.check()

    def check(self) -> None:
        """Re-raise the exception that ended the bridge thread, if any."""
        if self._error is not None:
            raise again(self._error)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # -- what tests and the simulator read ---------------------------------------------

    def pose(self) -> tuple[float, float, float]:
        """The base pose (x, y [m], yaw [rad]) the wheels' encoders integrate to, now
        (what the master's odometry should find; :meth:`world_state` has the slip)."""
        return self.plant.get_odometry_pose(time.monotonic())

    def world_state(self) -> tuple[tuple[float, float, float], NDArray[np.float64]]:
        """Where the base actually is, now: pose (x, y [m], yaw [rad], world frame) and
        twist (3,) (v_x, v_y [m/s], ω_z [rad/s], base frame), mecanum slip included."""
        with self.plant.lock:
            return self.plant.get_pose(time.monotonic()), self.plant.twist()

    def wheel_velocities(self) -> NDArray[np.float64]:
        """Actual simulated wheel speeds (4,) [rad/s] now."""
        with self.plant.lock:
            self.plant.advance(time.monotonic())
            return self.plant.omega.copy()

    def commands(self) -> list[tuple[float, tuple[float, ...]]]:
        """Every WHEEL_CMD applied: (monotonic time [s], four wheel speeds [rad/s])."""
        with self._lock:
            return list(self._commands)

    @property
    def enabled(self) -> bool:
        """The bridge's power state."""
        return self._enabled

    @property
    def stats(self) -> sp.LinkStats:
        """The bridge's receive counters (frames from the host)."""
        return self._decoder.stats

    # -- fault injection ----------------------------------------------------------------

    def inject(self, kind: str, count: int = 1) -> None:
        """Spoil the next ``count`` frames sent (kind in :data:`INJECTIONS`)."""
        if kind not in INJECTIONS:
            raise ValueError(f"unknown injection {kind!r}; choose from {', '.join(INJECTIONS)}")
        with self._lock:
            self._pending[kind] += count
        self._wake()

    def inject_silence(self) -> None:
        """Stop sending and stop acting on commands (input is drained and dropped)."""
        self._silent = True

    def resume(self) -> None:
        """Undo :meth:`inject_silence`."""
        self._silent = False
        self._wake()

    def inject_fault(self, wheel: int = 0, code: int = 0x0101) -> None:
        """Wheel ``wheel`` faults: the bridge sends FAULT, disables and reports FAULT
        until the host sends ENABLE."""
        with self._lock:
            self._fault = (code, wheel)
            self._fault_frame_due = True
            self._set_enabled(False)
        log.info("fake_bridge_fault_injected", wheel=wheel, code=f"0x{code:04X}")
        self._wake()

    # -- the bridge thread --------------------------------------------------------------

    def _wake(self) -> None:
        if self._thread is not None:
            os.write(self._wake_w, b"x")

    def _run(self) -> None:
        try:
            next_report = time.monotonic()
            while not self._stop.is_set():
                timeout = max(0.0, next_report - time.monotonic())
                ready, _, _ = select.select([self._master, self._wake_r], [], [], timeout)
                data = b""
                if self._wake_r in ready:
                    os.read(self._wake_r, 64)
                if self._master in ready:
                    try:
                        data = os.read(self._master, 4096)
                    except BlockingIOError:
                        data = b""
                now = time.monotonic()
                reply = False
                for frame in self._decoder.feed(data):
                    reply |= self._handle(frame, now)
                if self._silent:
                    next_report = now + self.report_period
                    continue
                with self._lock:
                    if self._fault_frame_due:
                        self._fault_frame_due = False
                        self._send(sp.MsgType.FAULT, sp.pack_fault(*self._fault))
                        reply = True
                if reply or now >= next_report:
                    self._send_state(now)
                    next_report = now + self.report_period
        except Exception as exc:
            self._error = exc
            log.exception("fake_bridge_failed")

    def _set_enabled(self, on: bool) -> None:
        self._enabled = on
        now = time.monotonic()
        for i in range(4):
            self.plant.set_enabled(i, on, now)

    def _handle(self, frame: sp.Frame, now: float) -> bool:
        if self._silent:
            return False
        with self._lock:
            if frame.type == sp.MsgType.ENABLE:
                self._fault = (0, 0xFF)
                self._set_enabled(True)
            elif frame.type == sp.MsgType.DISABLE:
                self._set_enabled(False)
            elif frame.type == sp.MsgType.WHEEL_CMD:
                try:
                    wheels = sp.unpack_wheel_cmd(frame.payload)
                except sp.FrameError:
                    self._decoder.stats.malformed += 1
                    return False
                if self._enabled:
                    for i, w in enumerate(wheels):
                        self.plant.command(i, w, now)
                    self._ack = frame.seq
                    self._commands.append((now, wheels))
            elif frame.type != sp.MsgType.HEARTBEAT:
                self._decoder.stats.malformed += 1
                return False
        return True

    def _state(self, now: float) -> sp.WheelState:
        p = self.plant
        with p.lock:
            p.advance(now)
            theta, omega, expiry = p.theta.copy(), p.omega.copy(), p.last_command + p.watchdog
        code, wheel = self._fault
        status = (sp.Status.ENABLED if self._enabled else 0) | (sp.Status.FAULT if code else 0)
        ws = []
        for i in range(4):
            b = sp.Status.ENABLED if self._enabled else 0
            if code and wheel in (i, 0xFF):
                b |= sp.Status.FAULT
            if self._enabled and now >= expiry[i]:
                b |= sp.Status.WATCHDOG
            ws.append(int(b))
        if any(w & sp.Status.WATCHDOG for w in ws):
            status |= sp.Status.WATCHDOG
        pos = tuple((round(t * sp.ANGLE_SCALE) + 2**31) % 2**32 - 2**31 for t in theta)
        vel = tuple(round(w * sp.SPEED_SCALE) for w in omega)
        return sp.WheelState(round((now - self._t0) * 1e6), self._ack, code, int(status),
                             tuple(ws), pos, vel)  # type: ignore[arg-type]

    def _send_state(self, now: float) -> None:
        state = self._state(now)
        with self._lock:
            if self._pending["out_of_sequence"]:
                self._pending["out_of_sequence"] -= 1
                a, b, c, d = (p + 10**6 for p in state.position)  # 1 rad off: must not count
                bogus = state._replace(position=(a, b, c, d))
                old = (self._seq - 3) & 0xFFFF
                self._write(sp.encode_frame(old, sp.MsgType.STATE, sp.pack_state(bogus)))
        self._send(sp.MsgType.STATE, sp.pack_state(state))

    def _send(self, msg_type: sp.MsgType, payload: bytes) -> None:
        self._seq = (self._seq + 1) & 0xFFFF
        packet = bytearray(sp.encode_packet(self._seq, msg_type, payload))
        prefix = b""
        with self._lock:
            if self._pending["crc"]:
                self._pending["crc"] -= 1
                packet[-1] ^= 0x5A
            if self._pending["garbage"]:
                self._pending["garbage"] -= 1
                prefix = bytes(self._rng.randrange(1, 256) for _ in range(17))
            cut = self._pending["truncate"] > 0
            if cut:
                self._pending["truncate"] -= 1
        body = sp.cobs_encode(bytes(packet))
        if cut:
            body = body[: len(body) // 2]
        self._write(prefix + b"\x00" + body + b"\x00")

    def _write(self, data: bytes) -> None:
        try:
            os.write(self._master, data)
        except BlockingIOError:
            self.tx_dropped += 1  # nobody reads the port: the bytes are lost, as on a UART
