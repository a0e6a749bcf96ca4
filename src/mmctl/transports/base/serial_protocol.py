"""The serial bridge wire protocol (pure encode/decode; specified in docs/serial-protocol.md).

On the wire every frame is ``0x00 | COBS(packet) | 0x00``; a packet is::

    seq u16 | type u8 | len u8 | payload (len bytes) | crc u16

little-endian, ``crc`` = CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection,
no final xor) over ``seq .. payload``.  COBS removes every 0x00 from the packet, so a
0x00 always delimits frames: a receiver resynchronises at the next 0x00 after garbage
or a cut frame.  Each direction numbers its frames; the receiver drops frames that are
not newer than the last one it accepted (counted ``out_of_sequence``) and counts gaps
(``lost``).
"""

from __future__ import annotations

import binascii
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

from mmctl.errors import ProtocolError

MAX_PAYLOAD = 255
_HEADER = struct.Struct("<HBB")
_CRC = struct.Struct("<H")
#: Longest encoded frame: COBS overhead + delimiters.
MAX_FRAME = 2 + 1 + (_HEADER.size + MAX_PAYLOAD + _CRC.size) * 255 // 254 + 1


class MsgType(IntEnum):
    """Message types: 0x0_ host -> bridge, 0x8_ bridge -> host."""

    ENABLE = 0x01
    DISABLE = 0x02
    WHEEL_CMD = 0x03
    HEARTBEAT = 0x04
    STATE = 0x81
    FAULT = 0x82


class Status(IntEnum):
    """Bits of the bridge status byte and of each wheel status byte."""

    ENABLED = 0x01
    FAULT = 0x02
    WATCHDOG = 0x04  # no WHEEL_CMD for the command watchdog time: ramping to zero


class FrameError(ProtocolError):
    """A frame failed to decode; ``kind`` is 'cobs', 'length', 'crc' or 'type'."""

    def __init__(self, kind: str, message: str) -> None:
        self.kind = kind
        super().__init__(f"{kind}: {message}")


class Frame(NamedTuple):
    """One decoded frame: sequence number, message type (int for unknown), payload."""

    seq: int
    type: int
    payload: bytes


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value 0x29B1 for b"123456789")."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result contains no 0x00."""
    out = bytearray()
    for chunk in data.split(b"\x00"):
        while len(chunk) >= 254:
            out.append(0xFF)
            out += chunk[:254]
            chunk = chunk[254:]
        out.append(len(chunk) + 1)
        out += chunk
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; raises FrameError('cobs') on malformed input."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise FrameError("cobs", "zero byte inside a frame")
        end = i + code
        if end > n:
            raise FrameError("cobs", f"code {code} runs past the end of the frame")
        block = data[i + 1:end]
        if 0 in block:
            raise FrameError("cobs", "zero byte inside a frame")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def encode_packet(seq: int, msg_type: int, payload: bytes = b"") -> bytes:
    """The packet (before COBS): header, payload, CRC."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes > {MAX_PAYLOAD}")
    body = _HEADER.pack(seq & 0xFFFF, msg_type, len(payload)) + payload
    return body + _CRC.pack(crc16_ccitt_false(body))


def encode_frame(seq: int, msg_type: int, payload: bytes = b"") -> bytes:
    """The bytes to write: ``0x00 | COBS(packet) | 0x00``."""
    return b"\x00" + cobs_encode(encode_packet(seq, msg_type, payload)) + b"\x00"


def decode_packet(packet: bytes) -> Frame:
    """Check length and CRC of a packet (after COBS decoding) and split it."""
    if len(packet) < _HEADER.size + _CRC.size:
        raise FrameError("length", f"{len(packet)} bytes is shorter than a header and CRC")
    seq, msg_type, length = _HEADER.unpack_from(packet)
    if len(packet) != _HEADER.size + length + _CRC.size:
        raise FrameError("length", f"len field {length} but {len(packet)} bytes received")
    (crc,) = _CRC.unpack_from(packet, len(packet) - _CRC.size)
    if crc != crc16_ccitt_false(packet[:-_CRC.size]):
        raise FrameError("crc", f"CRC 0x{crc:04X} does not match")
    return Frame(seq, msg_type, bytes(packet[_HEADER.size:-_CRC.size]))


@dataclass
class LinkStats:
    """Receive counters of one direction of the link."""

    frames: int = 0  # accepted
    crc_errors: int = 0
    malformed: int = 0  # COBS, length, oversize
    out_of_sequence: int = 0  # not newer than the last accepted: dropped
    lost: int = 0  # sequence gaps among accepted frames
    garbage_bytes: int = 0  # bytes of rejected frames


class FrameDecoder:
    """Splits a byte stream into frames and keeps only good, newer ones.

    ``feed(data)`` returns the accepted frames in order.  A frame is newer when
    ``(seq - last) mod 65536`` is in [1, 32767].  After :meth:`resync` (and at the
    start) the next good frame is accepted whatever its number; frames whose type is in
    ``resync_types`` always are (the host's ENABLE, so a restarted host is heard).
    """

    def __init__(self, resync_types: frozenset[int] = frozenset()) -> None:
        self.stats = LinkStats()
        self._buf = bytearray()
        self._last: int | None = None
        self._resync_types = resync_types

    def resync(self) -> None:
        """Accept the next good frame whatever its sequence number."""
        self._last = None

    def feed(self, data: bytes) -> list[Frame]:
        """Consume received bytes; return the frames accepted."""
        self._buf += data
        if 0 not in self._buf:
            if len(self._buf) > MAX_FRAME:
                self.stats.malformed += 1
                self.stats.garbage_bytes += len(self._buf)
                self._buf.clear()
            return []
        *chunks, rest = bytes(self._buf).split(b"\x00")
        self._buf = bytearray(rest)
        out = []
        for chunk in chunks:
            if chunk:
                frame = self._accept(chunk)
                if frame is not None:
                    out.append(frame)
        return out

    def _accept(self, chunk: bytes) -> Frame | None:
        try:
            frame = decode_packet(cobs_decode(chunk))
        except FrameError as exc:
            if exc.kind == "crc":
                self.stats.crc_errors += 1
            else:
                self.stats.malformed += 1
            self.stats.garbage_bytes += len(chunk)
            return None
        if self._last is not None and frame.type not in self._resync_types:
            step = (frame.seq - self._last) & 0xFFFF
            if step == 0 or step >= 0x8000:
                self.stats.out_of_sequence += 1
                return None
            self.stats.lost += step - 1
        self._last = frame.seq
        self.stats.frames += 1
        return frame


# -- payloads -------------------------------------------------------------------------

_WHEEL_CMD = struct.Struct("<4i")
_STATE = struct.Struct("<IHHB4B4i4i")
_FAULT = struct.Struct("<HB")

#: Fixed-point scales: wheel speed in [mrad/s], wheel angle in [µrad].
SPEED_SCALE = 1000.0
ANGLE_SCALE = 1_000_000.0
_I32 = 2**31 - 1


def _sat(x: float) -> int:
    return max(-_I32, min(_I32, round(x)))


def pack_wheel_cmd(wheels: tuple[float, ...] | list[float]) -> bytes:
    """WHEEL_CMD payload: four wheel speeds [rad/s] as int32 [mrad/s] (saturated)."""
    return _WHEEL_CMD.pack(*(_sat(w * SPEED_SCALE) for w in wheels))


def unpack_wheel_cmd(payload: bytes) -> tuple[float, float, float, float]:
    """Four wheel speeds [rad/s] from a WHEEL_CMD payload."""
    if len(payload) != _WHEEL_CMD.size:
        raise FrameError("length", f"WHEEL_CMD payload of {len(payload)} bytes")
    a, b, c, d = _WHEEL_CMD.unpack(payload)
    return a / SPEED_SCALE, b / SPEED_SCALE, c / SPEED_SCALE, d / SPEED_SCALE


class WheelState(NamedTuple):
    """STATE payload.

    time_us: bridge clock [µs] (u32, wraps); ack_seq: sequence number of the last
    WHEEL_CMD applied; fault_code: 0 = none; status: bridge :class:`Status` bits;
    wheel_status: 4 status bytes; position: 4 wheel angles [µrad] (int32, wraps);
    velocity: 4 wheel speeds [mrad/s].
    """

    time_us: int
    ack_seq: int
    fault_code: int
    status: int
    wheel_status: tuple[int, int, int, int]
    position: tuple[int, int, int, int]
    velocity: tuple[int, int, int, int]


def pack_state(s: WheelState) -> bytes:
    """Encode a STATE payload (45 bytes)."""
    return _STATE.pack(s.time_us & 0xFFFF_FFFF, s.ack_seq & 0xFFFF, s.fault_code, s.status,
                       *s.wheel_status, *s.position, *s.velocity)


def unpack_state(payload: bytes) -> WheelState:
    """Decode a STATE payload."""
    if len(payload) != _STATE.size:
        raise FrameError("length", f"STATE payload of {len(payload)} bytes, want {_STATE.size}")
    v = _STATE.unpack(payload)
    return WheelState(v[0], v[1], v[2], v[3], v[4:8], v[8:12], v[12:16])


def pack_fault(code: int, wheel: int) -> bytes:
    """FAULT payload: fault code (u16), wheel index 0-3 or 0xFF for the bridge."""
    return _FAULT.pack(code, wheel)


def unpack_fault(payload: bytes) -> tuple[int, int]:
    """(code, wheel) from a FAULT payload."""
    if len(payload) != _FAULT.size:
        raise FrameError("length", f"FAULT payload of {len(payload)} bytes")
    code, wheel = _FAULT.unpack(payload)
    return code, wheel
