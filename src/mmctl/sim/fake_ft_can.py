"""A simulated ATI F/T sensor answering the Net F/T CAN layout on a python-can bus.

Reference: ATI Industrial Automation, *Net F/T Installation and Operation Manual*, document
9620-05-NET FT, section "CAN interface" (see ``docs/sensor-can.md``).

It runs as a thread with its *own* bus object on the client's channel (python-can's
``virtual`` interface connects every bus opened on the same channel name in one process;
a bus never receives its own frames).  It answers exactly the requests documented in
:mod:`mmctl.transports.sensor.can_ft` — gauges (0x0), matrix rows (0x2), counts per unit
(0x7), unit codes (0x8) — encoding with its own code, so the tests check the client
against an independent implementation.  A matrix row ``r`` is answered as ATI frames it:
three frames, id base|0x2 = (c[r][0], c[r][1]), base|0x3 = (c[r][2], c[r][3]), base|0x4 =
(c[r][4], c[r][5]), two big-endian float32 each.  The calibration matrix is deliberately
not the identity, so a client that ignores it reads wrong values.

Gauges for a wrench ``w``: ``sg = round(C^-1 (w * counts_per_unit))``, clipped to int16.

Fault injection (plain attributes, read by the thread at each request):

* ``status``: ATI status bits sent with every sample (``STATUS_WATCHDOG_RESET``,
  ``STATUS_DAC_ADC_TOO_HIGH``, ``STATUS_DAC_ADC_TOO_LOW``, ``STATUS_BUS_ERROR``, any other
  bit 0..14); like the sensor, bit 15 (``STATUS_ANY_ERROR``) is set with any of them.
  ``STATUS_SATURATION`` is not a status bit (ATI has none for it): it makes the sensor
  saturate, i.e. the gauges go to the int16 rail, as does ``saturate = True``;
* ``silent`` (answer nothing), ``garbage`` (answer gauge requests with a 3-byte frame on
  the reply id);
* ``matrix_opcodes``: which frames of a matrix-row answer go out, in that order (default
  ``(0x2, 0x3, 0x4)``; e.g. ``(0x4, 0x2)`` reorders and leaves out base|0x3).

Usage::

    with FakeFtCanSensor(ConstantWrench([0, 0, 10, 0, 0, 0]), channel="demo"):
        with CanForceSensor(replace(cfg.sensor.can, channel="demo")) as sensor:
            sensor.read()
"""

from __future__ import annotations

import struct
import threading
import time
from types import TracebackType
from typing import TYPE_CHECKING

import can
import numpy as np
import structlog
from numpy.typing import ArrayLike

from mmctl.sim.wrench_source import WrenchSource, as_wrench6
from mmctl.types import Vec

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self

log = structlog.get_logger("mmctl.sim.fake_ft_can")

# ATI's status word (uint16, first two bytes of gauge frame 1)
STATUS_WATCHDOG_RESET = 0x0001
STATUS_DAC_ADC_TOO_HIGH = 0x0002  # DAC/ADC check result too high
STATUS_DAC_ADC_TOO_LOW = 0x0004  # DAC/ADC check result too low
STATUS_BUS_ERROR = 0x4000
STATUS_ANY_ERROR = 0x8000
#: Not on the wire: in ``status`` it makes the simulated gauges saturate (int16 rail).
STATUS_SATURATION = 0x10000
RAIL = 32767

#: A plausible, well-conditioned, non-identity calibration (gauges -> counts).
DEFAULT_CALIBRATION: tuple[tuple[float, ...], ...] = (
    (1.00, 0.04, -0.03, 0.02, 0.01, -0.02),
    (0.03, 0.95, 0.02, -0.01, 0.03, 0.01),
    (-0.02, 0.03, 1.10, 0.04, -0.02, 0.03),
    (0.01, -0.02, 0.03, 0.90, 0.05, -0.01),
    (0.02, 0.01, -0.04, 0.03, 1.05, 0.02),
    (-0.01, 0.02, 0.01, -0.03, 0.02, 0.97),
)
#: Counts per N and per N m: the M20 ranges (500/900 N, 20 N m) stay inside int16 gauges.
DEFAULT_COUNTS_PER_FORCE = 30
DEFAULT_COUNTS_PER_TORQUE = 1000


class FakeFtCanSensor:
    """The sensor end of the CAN link (see module doc); start()/stop() or ``with``.

    source: what the sensor measures; channel/interface: the python-can bus to serve
    (tests: ``virtual`` only); base_id: CAN base id; calibration: (6, 6), sent as float32;
    counts_per_force [counts/N], counts_per_torque [counts/(N m)]; units: ATI unit codes.
    """

    def __init__(
        self,
        source: WrenchSource,
        *,
        channel: str,
        interface: str = "virtual",
        base_id: int = 0x20,
        calibration: ArrayLike = DEFAULT_CALIBRATION,
        counts_per_force: int = DEFAULT_COUNTS_PER_FORCE,
        counts_per_torque: int = DEFAULT_COUNTS_PER_TORQUE,
        units: tuple[int, int] = (2, 3),
    ) -> None:
        self.source = source
        self.channel = channel
        self.interface = interface
        self.base_id = base_id
        #: exactly what goes on the wire (float32), as float64
        self.calibration = np.asarray(calibration, dtype=np.float32).astype(np.float64)
        self._inverse = np.linalg.inv(self.calibration)
        self.counts = (int(counts_per_force), int(counts_per_torque))
        self._cpu = np.array((counts_per_force,) * 3 + (counts_per_torque,) * 3, dtype=np.float64)
        self.units = units
        self.status = 0
        self.saturate = False
        self.matrix_opcodes: tuple[int, ...] = (0x2, 0x3, 0x4)
        self.silent = False
        self.garbage = False
        self.requests = 0
        self.error: BaseException | None = None
        self._bus: can.BusABC | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._t0 = 0.0

    # -- what a correct client computes (for tests) ----------------------------------

    def gauges_for(self, wrench: ArrayLike) -> Vec:
        """The int16 gauges (6,) this sensor sends for ``wrench`` [N, N m]."""
        w = as_wrench6(wrench)
        if not np.all(np.isfinite(w)):
            raise ValueError(f"the simulated sensor cannot measure a non-finite wrench {w}")
        g = np.rint(self._inverse @ (w * self._cpu))
        return np.clip(g, -32768, 32767)

    def quantisation_bound(self) -> Vec:
        """(6,) worst-case |error| [N, N m] of one decoded sample from gauge rounding."""
        bound: Vec = 0.5 * np.abs(self.calibration).sum(axis=1) / self._cpu
        return bound

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> Self:
        """Open the bus and start answering."""
        if self._thread is not None:
            return self
        self._bus = can.Bus(interface=self.interface, channel=self.channel)
        self._stop.clear()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"fake-ft-can-{self.channel}",
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop answering, close the bus; re-raise an error the thread met.  Idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=5.0)
        bus, self._bus = self._bus, None
        if bus is not None:
            bus.shutdown()
        self.check()

    def check(self) -> None:
        """Re-raise the exception that ended the thread, if any."""
        if self.error is not None:
            raise RuntimeError(f"fake F/T CAN sensor failed: {self.error!r}") from self.error

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # -- the thread --------------------------------------------------------------------

    def _run(self) -> None:
        bus = self._bus
        assert bus is not None
        try:
            while not self._stop.is_set():
                msg = bus.recv(timeout=0.05)
                if msg is not None and not self.silent:
                    self._handle(bus, msg)
        except Exception as exc:  # noqa: BLE001 - stored, re-raised by stop()/check()
            self.error = exc
            log.error("fake_sensor_failed", channel=self.channel, error=repr(exc))

    def _send(self, bus: can.BusABC, opcode: int, data: bytes) -> None:
        aid = ((self.base_id << 4) | opcode) & 0x7FF
        bus.send(can.Message(arbitration_id=aid, data=data, is_extended_id=False))

    def _handle(self, bus: can.BusABC, msg: can.Message) -> None:
        if msg.is_extended_id or (msg.arbitration_id >> 4) != self.base_id:
            return
        opcode = msg.arbitration_id & 0xF
        data = bytes(msg.data)
        if opcode == 0x0 and not data:
            self.requests += 1
            if self.garbage:
                self._send(bus, 0x0, b"\xde\xad\xbe")
                return
            g = self.gauges_for(self.source.wrench(time.monotonic() - self._t0)).astype(int)
            status = self.status
            if self.saturate or status & STATUS_SATURATION:
                g[2] = RAIL  # Fz's main gauge over range
            word = status & 0xFFFF
            if word & ~STATUS_ANY_ERROR:
                word |= STATUS_ANY_ERROR
            self._send(bus, 0x0, struct.pack(">Hhhh", word, g[0], g[2], g[4]))
            self._send(bus, 0x1, struct.pack(">hhh", g[1], g[3], g[5]))
        elif opcode == 0x2 and len(data) == 1 and data[0] < 6:
            row = self.calibration[data[0]]
            for op in self.matrix_opcodes:  # base|2: c[r][0..1], base|3: [2..3], base|4: [4..5]
                k = 2 * (op - 0x2)
                self._send(bus, op, struct.pack(">ff", row[k], row[k + 1]))
        elif opcode == 0x7 and not data:
            self._send(bus, 0x7, struct.pack(">II", *self.counts))
        elif opcode == 0x8 and not data:
            self._send(bus, 0x8, bytes(self.units))
