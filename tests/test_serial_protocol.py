"""Serial bridge framing: round trips, the documented bytes, and rejection of bad frames."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.transports.base import serial_protocol as sp
from mmctl.transports.base.serial_protocol import FrameDecoder, MsgType

payloads = st.binary(max_size=sp.MAX_PAYLOAD)
seqs = st.integers(0, 0xFFFF)
types = st.integers(0, 0xFF)


def test_crc_check_value() -> None:
    assert sp.crc16_ccitt_false(b"123456789") == 0x29B1


def test_documented_example_bytes() -> None:
    assert sp.encode_frame(1, MsgType.HEARTBEAT).hex(" ") == "00 02 01 02 04 03 b0 3e 00"
    frame = sp.encode_frame(2, MsgType.WHEEL_CMD, sp.pack_wheel_cmd([1.0, -1.0, 0.5, 0.0]))
    assert frame.hex(" ") == (
        "00 02 02 05 03 10 e8 03 01 07 18 fc ff ff f4 01 01 01 01 01 01 03 f1 45 00")


@settings(deadline=None)
@given(st.binary(max_size=1200))
def test_cobs_round_trip_has_no_zero(data: bytes) -> None:
    enc = sp.cobs_encode(data)
    assert 0 not in enc
    assert sp.cobs_decode(enc) == data


@settings(deadline=None)
@given(seqs, types, payloads)
def test_frame_round_trip(seq: int, msg_type: int, payload: bytes) -> None:
    wire = sp.encode_frame(seq, msg_type, payload)
    assert wire[0] == 0 and wire[-1] == 0 and 0 not in wire[1:-1]
    assert len(wire) <= sp.MAX_FRAME
    dec = FrameDecoder()
    assert dec.feed(wire) == [sp.Frame(seq, msg_type, payload)]


@settings(deadline=None)
@given(st.lists(st.tuples(types, payloads), min_size=1, max_size=8), seqs,
       st.integers(1, 64))
def test_stream_split_anywhere_decodes_in_order(
    msgs: list[tuple[int, bytes]], seq0: int, chunk: int
) -> None:
    wire = b"".join(sp.encode_frame(seq0 + i, t, p) for i, (t, p) in enumerate(msgs))
    dec = FrameDecoder()
    got = []
    for i in range(0, len(wire), chunk):
        got += dec.feed(wire[i:i + chunk])
    assert [(f.type, f.payload) for f in got] == msgs
    assert dec.stats.frames == len(msgs) and dec.stats.lost == 0


@settings(deadline=None)
@given(st.tuples(st.integers(0, 2**32 - 1), seqs, st.integers(0, 0xFFFF), st.integers(0, 255)),
       st.lists(st.integers(0, 255), min_size=4, max_size=4),
       st.lists(st.integers(-(2**31), 2**31 - 1), min_size=8, max_size=8))
def test_state_payload_round_trip(head: tuple[int, int, int, int], ws: list[int],
                                  ints: list[int]) -> None:
    s = sp.WheelState(*head, tuple(ws), tuple(ints[:4]), tuple(ints[4:]))  # type: ignore[arg-type]
    assert sp.unpack_state(sp.pack_state(s)) == s


@settings(deadline=None)
@given(st.lists(st.floats(-2000.0, 2000.0, allow_nan=False), min_size=4, max_size=4))
def test_wheel_cmd_round_trip_to_a_millirad(wheels: list[float]) -> None:
    back = sp.unpack_wheel_cmd(sp.pack_wheel_cmd(wheels))
    assert back == pytest.approx(wheels, abs=0.5e-3 + 1e-12)  # half a unit, ties included


def _good(seq: int, payload: bytes = b"ok") -> bytes:
    return sp.encode_frame(seq, MsgType.STATE, payload)


def test_bad_crc_is_rejected_and_counted() -> None:
    packet = bytearray(sp.encode_packet(7, MsgType.STATE, b"abc"))
    packet[-2] ^= 0x01
    dec = FrameDecoder()
    frames = dec.feed(b"\x00" + sp.cobs_encode(bytes(packet)) + b"\x00" + _good(8))
    assert [f.seq for f in frames] == [8]
    assert dec.stats.crc_errors == 1 and dec.stats.malformed == 0


def test_truncated_frame_is_rejected_and_the_next_one_survives() -> None:
    cut = _good(1, b"0123456789")[:-5]
    dec = FrameDecoder()
    frames = dec.feed(cut + _good(2))
    assert [f.seq for f in frames] == [2]
    assert dec.stats.malformed + dec.stats.crc_errors == 1
    assert dec.stats.lost == 0  # the first accepted frame sets the reference


@pytest.mark.parametrize("garbage", [b"\x13\x37\xff\xfe", b"\x01\x02\x00\x05\x06", b"\xff" * 300])
def test_garbage_between_frames(garbage: bytes) -> None:
    dec = FrameDecoder()
    frames = dec.feed(_good(1) + garbage + _good(2) + garbage + _good(3))
    assert [f.seq for f in frames] == [1, 2, 3]
    assert dec.stats.frames == 3
    assert dec.stats.malformed + dec.stats.crc_errors >= 1
    assert dec.stats.garbage_bytes > 0


def test_out_of_sequence_frames_are_dropped_and_gaps_counted() -> None:
    dec = FrameDecoder()
    got = dec.feed(_good(10) + _good(11) + _good(11) + _good(5) + _good(14) + _good(12))
    assert [f.seq for f in got] == [10, 11, 14]
    assert dec.stats.out_of_sequence == 3
    assert dec.stats.lost == 2


def test_sequence_wraps_and_resync() -> None:
    dec = FrameDecoder()
    assert [f.seq for f in dec.feed(_good(0xFFFE) + _good(0xFFFF) + _good(0) + _good(1))] == [
        0xFFFE, 0xFFFF, 0, 1]
    assert dec.feed(_good(1)) == [] and dec.stats.out_of_sequence == 1
    dec.resync()
    assert [f.seq for f in dec.feed(_good(1))] == [1]


def test_resync_types_are_always_accepted() -> None:
    dec = FrameDecoder(resync_types=frozenset({MsgType.ENABLE}))
    dec.feed(_good(500))
    got = dec.feed(sp.encode_frame(3, MsgType.ENABLE) + _good(4) + _good(2))
    assert [(f.type, f.seq) for f in got] == [(MsgType.ENABLE, 3), (MsgType.STATE, 4)]


def test_unterminated_flood_is_discarded() -> None:
    dec = FrameDecoder()
    assert dec.feed(b"\x55" * (sp.MAX_FRAME + 1)) == []
    assert dec.stats.malformed == 1
    assert [f.seq for f in dec.feed(_good(9))] == [9]


@pytest.mark.parametrize("bad", [b"\x05\x01\x02", b"\x02\x00", b"\x01"])
def test_cobs_decode_rejects_malformed(bad: bytes) -> None:
    with pytest.raises(sp.FrameError):
        sp.decode_packet(sp.cobs_decode(bad))


def test_length_field_mismatch_is_rejected() -> None:
    packet = bytearray(sp.encode_packet(1, MsgType.STATE, b"abcd"))
    packet[3] = 9  # len field lies
    with pytest.raises(sp.FrameError, match="length"):
        sp.decode_packet(bytes(packet))
