"""ATI force/torque sensor on CAN (the Net F/T CAN layout), over any python-can interface.

Reference: ATI Industrial Automation, *Net F/T Installation and Operation Manual*, document
9620-05-NET FT, section "CAN interface" (the same layout as ATI's Net CAN OEM board,
document 9610-05-1030).  See ``docs/sensor-can.md`` for what was taken from it and how it
was checked.

Wire protocol (what this client sends and expects; all frames 11-bit standard ids,
``id = (base_id << 4) | opcode``, default base 0x20 -> ids 0x200..0x20F; integers and
floats big-endian, as ATI's CAN layout sends them):

============  =====================================  ==========================================
opcode        request (client -> sensor)             reply (sensor -> client)
============  =====================================  ==========================================
0x0 gauges    id base|0x0, DLC 0                     id base|0x0, DLC 8: uint16 status, int16
                                                     sg0, int16 sg2, int16 sg4; then id
                                                     base|0x1, DLC 6: int16 sg1, sg3, sg5 (DLC
                                                     7-8 accepted, extra bytes ignored)
0x2 matrix    id base|0x2, DLC 1: uint8 row          three frames, DLC 8, two float32 each:
              (0 Fx, 1 Fy, 2 Fz, 3 Tx, 4 Ty, 5 Tz)   id base|0x2 = (c[r][0], c[r][1]), id
                                                     base|0x3 = (c[r][2], c[r][3]), id
                                                     base|0x4 = (c[r][4], c[r][5])
0x7 counts    id base|0x7, DLC 0                     id base|0x7, DLC 8: uint32 counts per force
                                                     unit, uint32 counts per torque unit
0x8 units     id base|0x8, DLC 0                     id base|0x8, DLC 2: uint8 force unit,
                                                     uint8 torque unit (ATI codes: 2 = N,
                                                     3 = N m; anything else is refused)
============  =====================================  ==========================================

A matrix row is placed frame by frame by CAN id, so the three frames may arrive in any
order.  While a row is read, frames that are not its answer are ignored: requests (another
master's row read: id base|0x2, DLC 1), other opcodes' frames, and an exact repeat of a
frame already received.  A second, *different* frame on the same id, or a matrix frame
that is not 8 bytes, is a :class:`~mmctl.errors.ProtocolError`; a row with a frame still
missing after ``sensor.can.connect_timeout`` is a :class:`~mmctl.errors.TransportError`
naming the row, the missing frame's CAN id and coefficients, and the frames that came.

Conversion: ``w = diag(1/cpf, 1/cpf, 1/cpf, 1/cpt, 1/cpt, 1/cpt) C sg`` with ``C`` the 6x6
calibration matrix (row r = output axis), ``sg`` the six gauges.  The sensor has no bias
of its own on this link; the tare is the wrench pipeline's
(:mod:`mmctl.control.wrench`), the same for every transport.  Frames on our ids that have the *request's*
length are another master's requests and are ignored; frames of our reply ids with any
other unexpected length are a :class:`~mmctl.errors.ProtocolError`.

Status word (uint16, 0 = healthy), bits as ATI defines them (:data:`STATUS_BITS`): 0
watchdog reset, 1 DAC/ADC check result too high, 2 DAC/ADC check result too low, 3
artificial analog ground out of range, 4/5 power supply too high/low, 6 bad active
calibration, 7 EEPROM failure, 8 configuration invalid, 11/12 sensor temperature too
high/low, 14 CAN bus error, 15 any error (9, 10 and 13 reserved).  Any set bit raises
``SafetyFault(SENSOR_STATUS, status="0x8002", bits=["dac_adc_check_too_high",
"any_error"])``, each set bit named.  No status bit means saturation: a gauge at the int16
rail (-32768 or 32767) raises ``SafetyFault(SENSOR_SATURATION, gauges=["sg2"])``.
``sensor.can.status_saturation_mask`` is not used (ATI's CAN status word has no
saturation bit).

Timing (why a read is cheap): reads are *pipelined*.  After a reply is decoded, the next
request goes out at once — or, once the caller uses :meth:`CanForceSensor.request_next`
(the daemon does, at the end of each cycle), when the caller sends it — so the sensor
answers before the next :meth:`CanForceSensor.read`, which normally finds both reply
frames already queued (the sample is then up to one period old, 2 ms at 500 Hz, against
a 53 ms admittance time constant).  When the request in flight is older than
``sensor.can.timeout`` (the caller paused), its reply would be too old: it is discarded and a fresh request is waited for.
A request that gets no complete reply within ``timeout`` counts as lost and is sent
again at once; the previous sample is returned again until the newest one is older than
``sensor.wrench.stale_timeout``, then ``SafetyFault(SENSOR_STALE)`` is raised.  A read
blocks at most ``timeout`` (only while replies are missing).

Garbage costs the current sample only: a malformed reply raises ``ProtocolError`` after
everything queued behind it is dropped, and the next request (``read()`` or
:meth:`CanForceSensor.request_next`) drops what came in between before it goes out, so
once the garbage stops the first or second read is fresh (a queue of stale bad frames
used to be consumed one per cycle: 1.6-16.5 s before a re-arm).

A lost link (the CAN channel fails: socketcand connection closed, adapter gone;
:class:`~mmctl.transports.canbus.GuardedBus`) raises
:class:`~mmctl.errors.LinkLost` (cause ``sensor_link_lost``) from every call, at once,
until :meth:`CanForceSensor.reconnect` succeeds.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Sequence
from types import TracebackType
from typing import TYPE_CHECKING

import can
import numpy as np
import structlog

from mmctl.config.sensor import SensorCanConfig
from mmctl.errors import FaultCause, LinkLost, ProtocolError, SafetyFault, TransportError
from mmctl.transports.canbus import GuardedBus, describe, open_bus
from mmctl.transports.sensor.protocol import SensorStats
from mmctl.types import Vec, Wrench

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self

log = structlog.get_logger("mmctl.sensor.can")

OP_GAUGES = 0x0
OP_GAUGES_2 = 0x1
OP_MATRIX = 0x2
OP_COUNTS = 0x7
OP_UNITS = 0x8

#: ATI's status-word bits (bit -> name used in fault details); 9, 10 and 13 are reserved.
STATUS_BITS: dict[int, str] = {
    0: "watchdog_reset",
    1: "dac_adc_check_too_high",
    2: "dac_adc_check_too_low",
    3: "analog_ground_out_of_range",
    4: "supply_voltage_too_high",
    5: "supply_voltage_too_low",
    6: "bad_active_calibration",
    7: "eeprom_failure",
    8: "configuration_invalid",
    11: "temperature_too_high",
    12: "temperature_too_low",
    14: "can_bus_error",
    15: "any_error",
}
STATUS_BUS_ERROR = 0x4000
STATUS_ANY_ERROR = 0x8000
MATRIX_OPCODES = (0x2, 0x3, 0x4)  # the three frames of a matrix-row answer
AXES = ("Fx", "Fy", "Fz", "Tx", "Ty", "Tz")
UNIT_NEWTON = 2
UNIT_NEWTON_METRE = 3
GAUGE_RAILS = (-32768, 32767)

_FIRST = struct.Struct(">hhhh")
_SECOND = struct.Struct(">hhh")
_TWO_FLOATS = struct.Struct(">ff")
_COUNTS = struct.Struct(">II")
_ID_MASK = 0x7F0


def frame_id(base_id: int, opcode: int) -> int:
    """The 11-bit CAN id of ``opcode`` for a sensor at ``base_id``."""
    return ((base_id << 4) | opcode) & 0x7FF


def decode_gauges(first: bytes, second: bytes) -> tuple[int, Vec]:
    """The two gauge frames -> (status word uint16, gauges (6,) sg0..sg5 [counts])."""
    if len(first) != 8:
        raise ProtocolError(f"gauge frame 1 must have 8 data bytes, got {len(first)}")
    if not 6 <= len(second) <= 8:
        raise ProtocolError(f"gauge frame 2 must have 6 data bytes, got {len(second)}")
    status, sg0, sg2, sg4 = _FIRST.unpack(first)
    sg1, sg3, sg5 = _SECOND.unpack_from(second)
    return status & 0xFFFF, np.array((sg0, sg1, sg2, sg3, sg4, sg5), dtype=np.float64)


def decode_matrix_row(frames: Sequence[bytes]) -> tuple[float, ...]:
    """The three frames answering a matrix-row request (ids base|0x2, base|0x3, base|0x4,
    in that order) -> the row's 6 coefficients c[r][0..5]."""
    if len(frames) != 3 or any(len(f) != 8 for f in frames):
        lengths = [len(f) for f in frames]
        raise ProtocolError(f"a matrix row is 3 frames of 8 bytes, got lengths {lengths}")
    row = tuple(v for f in frames for v in _TWO_FLOATS.unpack(f))
    if not all(np.isfinite(row)):
        raise ProtocolError(f"calibration matrix row is not finite: {row}")
    return row


def decode_counts(data: bytes) -> tuple[int, int]:
    """The counts-per-unit reply -> (counts per force unit, counts per torque unit)."""
    if len(data) != 8:
        raise ProtocolError(f"counts-per-unit reply must have 8 bytes, got {len(data)}")
    cpf, cpt = _COUNTS.unpack(data)
    if cpf == 0 or cpt == 0:
        raise ProtocolError(f"counts per unit must be > 0, got force {cpf}, torque {cpt}")
    return cpf, cpt


def decode_units(data: bytes) -> tuple[int, int]:
    """The unit-codes reply -> (force unit code, torque unit code); only N and N m pass."""
    if len(data) < 2:
        raise ProtocolError(f"unit-codes reply must have 2 bytes, got {len(data)}")
    force_unit, torque_unit = data[0], data[1]
    if (force_unit, torque_unit) != (UNIT_NEWTON, UNIT_NEWTON_METRE):
        raise ProtocolError(
            f"sensor reports unit codes force={force_unit}, torque={torque_unit}; mmctl needs "
            f"N ({UNIT_NEWTON}) and N m ({UNIT_NEWTON_METRE}): reconfigure the sensor"
        )
    return force_unit, torque_unit


def conversion_matrix(calibration: Sequence[Sequence[float]], cpf: float, cpt: float) -> Vec:
    """(6, 6) gauges -> wrench [N, N m]: ``diag(1/cpf x3, 1/cpt x3) @ calibration``."""
    c = np.asarray(calibration, dtype=np.float64)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)):
        raise ProtocolError(f"calibration matrix must be a finite 6x6, got shape {c.shape}")
    scale = np.array((cpf,) * 3 + (cpt,) * 3, dtype=np.float64)
    return c / scale[:, None]


def status_bit_names(status: int) -> tuple[str, ...]:
    """The names of the set bits of a status word, bit 0 first (``reserved_bitN`` if
    ATI defines no meaning for bit N)."""
    return tuple(STATUS_BITS.get(b, f"reserved_bit{b}") for b in range(16) if status >> b & 1)


def check_status(status: int, gauges: Vec) -> None:
    """Raise SafetyFault(SENSOR_STATUS / SENSOR_SATURATION) if the sample is not healthy."""
    if status:
        raise SafetyFault(FaultCause.SENSOR_STATUS, status=f"0x{status:04X}",
                          bits=list(status_bit_names(status)))
    low, high = GAUGE_RAILS
    if gauges.min() <= low or gauges.max() >= high:
        at_rail = [f"sg{i}" for i, g in enumerate(gauges) if g <= low or g >= high]
        raise SafetyFault(FaultCause.SENSOR_SATURATION, gauges=at_rail)


class CanForceSensor:
    """:class:`~mmctl.transports.sensor.protocol.ForceSensor` on CAN (see module doc).

    cfg: the ``sensor.can`` section; stale_timeout: no fresh sample for longer -> fault
    [s].  No I/O before :meth:`connect`.
    """

    def __init__(self, cfg: SensorCanConfig, *, stale_timeout: float = 0.010) -> None:
        self._cfg = cfg
        self._stale = stale_timeout
        self._timeout = cfg.timeout
        self._id_g0 = frame_id(cfg.base_id, OP_GAUGES)
        self._id_g1 = frame_id(cfg.base_id, OP_GAUGES_2)
        self._request = can.Message(arbitration_id=self._id_g0, data=b"", is_extended_id=False)
        self._bus: GuardedBus | None = None
        self._resync = False  # a malformed reply: drop what is queued before asking again
        self._conv = np.zeros((6, 6))
        self._calibration = np.zeros((6, 6))
        self._counts = (0, 0)
        self._pending: float | None = None  # monotonic time the request in flight was sent
        self._caller_paced = False  # request_next() was called: it sends the requests
        self._first: bytes | None = None  # gauge frame 1 waiting for frame 2
        self._tail_expected = False  # a reply was abandoned: its frame 2 may still come
        self._last: Wrench | None = None
        self._last_fresh = 0.0
        self._seq = 0
        self._lost = 0

    @property
    def link(self) -> str:
        """Where the sensor is expected, for messages: ``interface:channel@0xBASE``."""
        return f"{describe(self._cfg)}@0x{self._cfg.base_id:02X}"

    @property
    def calibration(self) -> Vec:
        """The (6, 6) calibration matrix read at connect (gauges -> counts)."""
        return self._calibration.copy()

    @property
    def counts_per_unit(self) -> tuple[int, int]:
        """(counts per N, counts per N m) read at connect."""
        return self._counts

    # -- lifecycle ---------------------------------------------------------------------

    def connect(self) -> None:
        """Open the bus, read units, counts per unit and the matrix, take a first sample."""
        if self._bus is not None:
            return
        cfg = self._cfg
        self._bus = open_bus(
            cfg, FaultCause.SENSOR_LINK, connect_timeout=cfg.connect_timeout,
            can_filters=[{"can_id": cfg.base_id << 4, "can_mask": _ID_MASK, "extended": False}],
        )
        try:
            decode_units(self._transact(OP_UNITS, b"", 1)[0])
            cpf, cpt = decode_counts(self._transact(OP_COUNTS, b"", 1)[0])
            rows = [decode_matrix_row(self._read_matrix_row(r)) for r in range(6)]
            self._counts = (cpf, cpt)
            self._calibration = np.array(rows, dtype=np.float64)
            self._conv = conversion_matrix(rows, cpf, cpt)
            self._seq = self._lost = 0
            self._pending = None
            self._caller_paced = False
            self._resync = False
            self._first = None
            self._last = None
            first = self._read_sync(cfg.connect_timeout)
        except BaseException:
            self.close()
            raise
        self._last = first
        log.info("sensor_connected", transport="can", link=self.link,
                 counts_per_force=cpf, counts_per_torque=cpt)

    def reconnect(self) -> None:
        """Bring a lost link back: close what is left of it (no I/O on it) and connect
        again (units, counts per unit, matrix, a first sample).  Does nothing while the
        link works (idempotent).  Raises :class:`~mmctl.errors.LinkLost` (a
        TransportError, cause ``sensor_link_lost``) naming the link while the sensor or
        its CAN channel does not answer; SafetyFault as :meth:`connect` (status bits
        in the first sample)."""
        bus = self._bus
        if bus is not None and bus.lost is None:
            return
        self.close()
        try:
            self.connect()
        except TransportError as exc:
            raise LinkLost.wrap(self.link, FaultCause.SENSOR_LINK,
                                "reconnect failed", exc) from exc
        log.info("sensor_reconnected", transport="can", link=self.link)

    def close(self) -> None:
        """Shut the bus down; safe to call twice."""
        bus, self._bus = self._bus, None
        self._pending = None
        if bus is not None:
            bus.shutdown()

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- data --------------------------------------------------------------------------

    def read(self) -> Wrench:
        """The newest wrench [N, N m] in the sensor frame (pipelined, see module doc)."""
        bus = self._bus
        if bus is None:
            raise TransportError(f"CAN F/T sensor {self.link} is not connected")
        if bus.lost is not None:
            bus.check()
        now = time.monotonic()
        if self._pending is None or now - self._pending > self._timeout:
            self._discard_queued()
            self._send_request(now)
        sample = self._collect(self._pending + self._timeout)  # type: ignore[operator]
        if sample is None:
            self._lost += 1
            now = time.monotonic()
            self._send_request(now)  # ask again at once; the next read waits for it
            age = now - self._last_fresh
            if age > self._stale or self._last is None:
                raise SafetyFault(FaultCause.SENSOR_STALE, age_ms=round(age * 1e3, 2),
                                  lost=self._lost, link=self.link)
            return self._last
        return self._accept(sample)

    def stats(self) -> SensorStats:
        """Fresh samples and lost requests since connect."""
        return SensorStats(self._seq, self._lost, 0)

    # -- internals ---------------------------------------------------------------------

    def request_next(self) -> None:
        """Send the next gauge request now, unless one is in flight.

        The first call hands the pipelining to the caller: from then on a decoded reply
        no longer sends the next request at once, the caller does, when it likes.  The
        daemon calls this at the end of each cycle, so the sensor's answer (on the
        simulated robot: a thread of this process) comes in the loop's idle time
        instead of during its compute.  ``read()`` alone still works: with no request
        in flight it sends one and waits for the reply.
        """
        bus = self._bus
        if bus is None:
            raise TransportError(f"CAN F/T sensor {self.link} is not connected")
        if bus.lost is not None:
            bus.check()
        self._caller_paced = True
        if self._pending is None:
            if self._resync:
                self._discard_queued()
            self._send_request(time.monotonic())

    def _accept(self, sample: tuple[int, Vec]) -> Wrench:
        status, gauges = sample
        t = time.monotonic()
        if self._caller_paced:
            self._pending = None  # answered; request_next() sends the next one
        else:
            self._send_request(t)  # pipeline: the sensor answers while the cycle computes
        check_status(status, gauges)
        w = self._conv @ gauges
        self._seq += 1
        wrench = Wrench(w[:3], w[3:], t, self._seq, status)
        self._last = wrench
        self._last_fresh = t
        return wrench

    def _read_sync(self, timeout: float) -> Wrench:
        self._discard_queued()
        self._send_request(time.monotonic())
        sample = self._collect(time.monotonic() + timeout)
        if sample is None:
            raise TransportError(
                f"no gauge reply from the F/T sensor {self.link} within {timeout * 1e3:.0f} ms"
            )
        return self._accept(sample)

    def _send(self, msg: can.Message) -> None:
        """Raises LinkLost (a TransportError) when the link fails (GuardedBus)."""
        self._bus.send(msg)  # type: ignore[union-attr]

    def _send_request(self, now: float) -> None:
        self._send(self._request)
        self._pending = now

    def _recv(self, timeout: float) -> can.Message | None:
        """The next frame or None; raises LinkLost when the link failed (GuardedBus
        records the failure and returns None)."""
        bus = self._bus
        assert bus is not None
        msg = bus.recv(timeout)
        if msg is None and bus.lost is not None:
            bus.check()
        return msg

    def _discard_queued(self) -> None:
        """Drop what is queued: the requests in flight are abandoned.  The rest of an
        abandoned reply may still arrive (its first frame dropped here, its second one
        sent after a stall of either side): until the next first frame, one second
        frame on its own is that tail, not garbage."""
        while self._recv(0.0) is not None:
            pass
        self._first = None
        self._tail_expected = True
        self._resync = False

    def _collect(self, deadline: float) -> tuple[int, Vec] | None:
        """Wait until ``deadline`` for a complete gauge reply, then take the newest queued."""
        newest: tuple[int, Vec] | None = None
        timeout = max(0.0, deadline - time.monotonic())
        try:
            while True:
                msg = self._recv(timeout)
                if msg is None:
                    return newest
                got = self._feed(msg)
                if got is not None:
                    newest = got
                timeout = 0.0 if newest is not None else max(0.0, deadline - time.monotonic())
        except ProtocolError:
            # garbage costs this sample only: what is queued behind the bad frame (more
            # of it, replies to abandoned requests) goes now, and whatever comes before
            # the next request is sent goes then (read() or request_next())
            self._pending = None
            self._discard_queued()
            self._resync = True
            raise

    def _feed(self, msg: can.Message) -> tuple[int, Vec] | None:
        aid = msg.arbitration_id
        if aid == self._id_g0:
            if msg.dlc == 0:
                return None  # another master's request
            if msg.dlc != 8:
                raise ProtocolError(f"gauge frame 1 (id 0x{aid:03X}) has DLC {msg.dlc}, expected 8")
            self._first = bytes(msg.data)
            self._tail_expected = False
            return None
        if aid == self._id_g1:
            if self._first is None:
                if self._tail_expected:  # the end of a reply abandoned by _discard_queued
                    self._tail_expected = False
                    return None
                raise ProtocolError(f"gauge frame 2 (id 0x{aid:03X}) arrived without frame 1")
            first, self._first = self._first, None
            return decode_gauges(first, bytes(msg.data))
        return None  # late calibration replies, other opcodes

    def _read_matrix_row(self, row: int) -> list[bytes]:
        """Ask for calibration row ``row``; its three frames (ids base|2, |3, |4, in any
        order) in id order.  See the module doc for what is ignored or refused."""
        base = self._cfg.base_id
        ids = [frame_id(base, op) for op in MATRIX_OPCODES]
        timeout = self._cfg.connect_timeout
        self._discard_queued()
        self._send(can.Message(arbitration_id=ids[0], data=bytes((row,)), is_extended_id=False))
        frames: dict[int, bytes] = {}
        deadline = time.monotonic() + timeout
        while len(frames) < len(ids):
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                break
            msg = self._recv(remaining)
            if msg is None or msg.arbitration_id not in ids or msg.is_extended_id:
                continue  # timeout slice, other opcodes
            aid, data = msg.arbitration_id, bytes(msg.data)
            if aid == ids[0] and len(data) == 1:
                continue  # a row request (another master's)
            if len(data) != 8:
                raise ProtocolError(f"matrix frame on CAN id 0x{aid:03X} has {len(data)} data "
                                    f"bytes, expected 8 (row {row}, sensor {self.link})")
            if aid in frames and frames[aid] != data:
                raise ProtocolError(f"two different frames on CAN id 0x{aid:03X} answering "
                                    f"matrix row {row} from {self.link}: "
                                    f"{frames[aid].hex()} then {data.hex()}")
            frames[aid] = data
        if not frames:
            raise TransportError(
                f"no reply from the F/T sensor {self.link} to opcode 0x{OP_MATRIX:X} "
                f"(CAN id 0x{ids[0]:03X}, matrix row {row}) within {timeout * 1e3:.0f} ms"
            )
        if len(frames) < len(ids):
            missing = ", ".join(f"0x{fid:03X} (c[{row}][{2 * k}], c[{row}][{2 * k + 1}])"
                                for k, fid in enumerate(ids) if fid not in frames)
            got = ", ".join(f"0x{fid:03X}" for fid in ids if fid in frames)
            raise TransportError(
                f"calibration matrix row {row} ({AXES[row]}) from the F/T sensor {self.link} "
                f"is incomplete: no frame on CAN id {missing} within {timeout * 1e3:.0f} ms "
                f"(got {got})"
            )
        return [frames[fid] for fid in ids]

    def _transact(self, opcode: int, payload: bytes, n_replies: int) -> list[bytes]:
        """Request/response used at connect; replies are the frames on the same id."""
        fid = frame_id(self._cfg.base_id, opcode)
        timeout = self._cfg.connect_timeout
        self._discard_queued()
        self._send(can.Message(arbitration_id=fid, data=payload, is_extended_id=False))
        frames: list[bytes] = []
        deadline = time.monotonic() + timeout
        while len(frames) < n_replies:
            remaining = deadline - time.monotonic()
            if remaining <= 0.0:
                raise TransportError(
                    f"no reply from the F/T sensor {self.link} to opcode 0x{opcode:X} "
                    f"(CAN id 0x{fid:03X}) within {timeout * 1e3:.0f} ms"
                )
            msg = self._recv(remaining)
            if msg is None or msg.arbitration_id != fid or msg.dlc == len(payload):
                continue  # timeout slice, other ids, or a request (ours is never echoed)
            frames.append(bytes(msg.data))
        return frames
