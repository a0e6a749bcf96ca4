"""CAN F/T transport: exact bytes on the wire (scripted peer), decoders, fuzz."""

from __future__ import annotations

import dataclasses
import itertools
import struct
import threading

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mmctl.config import default_config
from mmctl.errors import FaultCause, ProtocolError, SafetyFault, TransportError
from mmctl.sim.fake_ft_can import (
    STATUS_BUS_ERROR,
    STATUS_DAC_ADC_TOO_HIGH,
    STATUS_DAC_ADC_TOO_LOW,
    STATUS_SATURATION,
    STATUS_WATCHDOG_RESET,
    FakeFtCanSensor,
)
from mmctl.sim.wrench_source import ConstantWrench
from mmctl.transports.sensor.can_ft import (
    CanForceSensor,
    check_status,
    conversion_matrix,
    decode_counts,
    decode_gauges,
    decode_matrix_row,
    decode_units,
    frame_id,
    status_bit_names,
)

_names = itertools.count()

# float32-exact, deliberately not the identity
MATRIX = np.array([
    [1.5, 0.25, -0.125, 0.0, 0.5, 0.0],
    [0.0, 2.0, 0.0, -0.25, 0.0, 0.125],
    [0.5, 0.0, 1.25, 0.0, 0.0, -0.5],
    [0.0, 0.125, 0.0, 0.75, 0.0, 0.0],
    [-0.25, 0.0, 0.0, 0.0, 1.0, 0.0625],
    [0.0, 0.0, 0.375, 0.0, 0.0, 0.875],
])
CPF, CPT = 40, 2000


def channel() -> str:
    return f"test-can-ft-{next(_names)}"


def can_cfg(ch: str, **over: object):
    base = default_config().sensor.can
    return dataclasses.replace(base, **{"interface": "virtual", "channel": ch, **over})


class ScriptedPeer(threading.Thread):
    """Receives the client's requests in order; answers each with scripted frames."""

    def __init__(self, ch: str, script: list[list[tuple[int, bytes]]]):
        super().__init__(daemon=True)
        self.bus = can.Bus(interface="virtual", channel=ch)
        self.script = script
        self.seen: list[tuple[int, bytes]] = []

    def run(self) -> None:
        for replies in self.script:
            msg = self.bus.recv(timeout=10.0)
            if msg is None:
                return
            self.seen.append((msg.arbitration_id, bytes(msg.data)))
            for aid, data in replies:
                self.bus.send(can.Message(arbitration_id=aid, data=data, is_extended_id=False))

    def finish(self) -> None:
        self.join(timeout=10.0)
        self.bus.shutdown()


def calibration_script(base: int, units: bytes = b"\x02\x03") -> tuple[list, list]:
    """(expected requests, replies) for the connect sequence of a sensor at ``base``."""
    b = base << 4
    requests = [(b | 0x8, b""), (b | 0x7, b"")] + [(b | 0x2, bytes((r,))) for r in range(6)]
    replies = [[(b | 0x8, units)], [(b | 0x7, struct.pack(">II", CPF, CPT))]]
    replies += [matrix_frames(base, r) for r in range(6)]
    return requests, replies


def matrix_frames(base: int, row: int, opcodes: tuple[int, ...] = (0x2, 0x3, 0x4),
                  matrix: np.ndarray = MATRIX) -> list[tuple[int, bytes]]:
    """ATI's answer to a matrix-row read: id base|0x2 = (c[r][0], c[r][1]), base|0x3 =
    (c[r][2], c[r][3]), base|0x4 = (c[r][4], c[r][5]), big-endian float32; ``opcodes``
    picks which of the three go on the bus, in that order."""
    b, r = base << 4, matrix[row]
    return [(b | op, struct.pack(">ff", r[2 * (op - 2)], r[2 * (op - 2) + 1])) for op in opcodes]


def gauge_frames(base: int, status: int, sg: tuple[int, ...]) -> list[tuple[int, bytes]]:
    b = base << 4
    return [(b | 0x0, struct.pack(">Hhhh", status, sg[0], sg[2], sg[4])),
            (b | 0x1, struct.pack(">hhh", sg[1], sg[3], sg[5]))]


def scripted_sensor(ch: str, base: int, script: list) -> tuple[ScriptedPeer, CanForceSensor]:
    """A started scripted peer and a (not yet connected) client for it."""
    peer = ScriptedPeer(ch, script)
    peer.start()
    # generous reply timeout: the pipelined request stays valid on a loaded machine
    sensor = CanForceSensor(can_cfg(ch, base_id=base, timeout=2.0, connect_timeout=5.0),
                            stale_timeout=10.0)
    return peer, sensor


def test_frame_ids_follow_the_base_id_layout() -> None:
    assert frame_id(0x20, 0x0) == 0x200
    assert frame_id(0x20, 0x7) == 0x207
    assert frame_id(0x7F, 0xF) == 0x7FF


def test_connect_and_read_exact_bytes_on_the_wire() -> None:
    ch, base = channel(), 0x21
    requests, replies = calibration_script(base)
    sg1 = (100, -200, 300, -400, 500, -600)
    sg2 = (1000, 2000, -3000, 4000, -5000, 6000)
    gauge_req = (base << 4 | 0x0, b"")
    script = replies + [gauge_frames(base, 0, sg1), gauge_frames(base, 0, sg2), []]
    peer, sensor = scripted_sensor(ch, base, script)
    try:
        sensor.connect()
        w = sensor.read()
    finally:
        sensor.close()
        peer.finish()
    # connect: units, counts, 6 matrix rows, one gauge read; then the pipelined request
    # answered by read(), and read() pipelines the next one
    assert peer.seen == requests + [gauge_req, gauge_req, gauge_req]
    np.testing.assert_array_equal(sensor.calibration, MATRIX)
    assert sensor.counts_per_unit == (CPF, CPT)
    scale = np.array([CPF] * 3 + [CPT] * 3, dtype=float)
    expected = MATRIX @ np.array(sg2, dtype=float) / scale
    np.testing.assert_allclose(w.as_array(), expected, rtol=1e-12, atol=1e-12)
    assert w.sequence == 2 and w.status == 0


def connect_only(ch: str, base: int, script: list,
                 connect_timeout: float = 5.0) -> tuple[ScriptedPeer, CanForceSensor]:
    """A started scripted peer and a client for it with ``connect_timeout`` [s]."""
    peer = ScriptedPeer(ch, script)
    peer.start()
    sensor = CanForceSensor(can_cfg(ch, base_id=base, timeout=2.0,
                                    connect_timeout=connect_timeout), stale_timeout=10.0)
    return peer, sensor


def connect_reads_the_matrix(ch: str, base: int, requests: list, replies: list,  # type: ignore[type-arg]
                             gauge_req: tuple[int, bytes]) -> None:
    """connect() against the scripted replies, then one gauge read: exactly the
    requests expected went out and the calibration matrix came out whole."""
    peer, sensor = connect_only(ch, base, replies + [gauge_frames(base, 0, (1,) * 6), []])
    try:
        sensor.connect()
    finally:
        sensor.close()
        peer.finish()
    assert peer.seen == requests + [gauge_req, gauge_req]
    np.testing.assert_array_equal(sensor.calibration, MATRIX)


def test_matrix_row_frames_are_read_in_any_arrival_order() -> None:
    """ATI answers a row read on three ids (base|2, |3, |4); the client places each
    frame by its id, whatever order the three arrive in."""
    ch, base = channel(), 0x24
    requests, replies = calibration_script(base)
    orders = [(0x4, 0x3, 0x2), (0x3, 0x2, 0x4), (0x2, 0x4, 0x3),
              (0x4, 0x2, 0x3), (0x3, 0x4, 0x2), (0x2, 0x3, 0x4)]
    replies[2:8] = [matrix_frames(base, r, order) for r, order in enumerate(orders)]
    gauge_req = (base << 4 | 0x0, b"")
    connect_reads_the_matrix(ch, base, requests, replies, gauge_req)


@pytest.mark.parametrize(("missing", "coefficients"),
                         [(0x2, "c[4][0], c[4][1]"), (0x3, "c[4][2], c[4][3]"),
                          (0x4, "c[4][4], c[4][5]")])
def test_a_missing_matrix_frame_is_named(missing: int, coefficients: str) -> None:
    """Row 4 (Ty) comes with one of its three frames missing: the error names the row,
    the missing frame's CAN id and coefficients, and the frames that did come."""
    ch, base = channel(), 0x25
    requests, replies = calibration_script(base)
    present = tuple(op for op in (0x2, 0x3, 0x4) if op != missing)
    replies[2 + 4] = matrix_frames(base, 4, present)
    peer, sensor = connect_only(ch, base, replies[:7], connect_timeout=1.0)
    try:
        with pytest.raises(TransportError) as info:
            sensor.connect()
    finally:
        sensor.close()
        peer.finish()
    assert peer.seen == requests[:7]
    msg = str(info.value)
    fid = (base << 4) | missing
    assert (f"calibration matrix row 4 (Ty) from the F/T sensor virtual:{ch}@0x25 is "
            f"incomplete: no frame on CAN id 0x{fid:03X} ({coefficients})") in msg, msg
    got = ", ".join(f"0x{(base << 4) | op:03X}" for op in present)
    assert f"within 1000 ms (got {got})" in msg, msg


def test_stray_frames_during_a_matrix_read_are_ignored() -> None:
    """Another master's row request, other opcodes' replies, a gauge frame and an exact
    repeat of a matrix frame come between the three frames of a row: all ignored."""
    ch, base = channel(), 0x26
    b = base << 4
    requests, replies = calibration_script(base)
    f2, f3, f4 = matrix_frames(base, 1)
    replies[3] = [(b | 0x2, b"\x05"), f3, (b | 0x5, b"SN012345"), (b | 0x0, bytes(8)), f3,
                  (b | 0x9, b"\x01\x02"), f2, f4]
    gauge_req = (b | 0x0, b"")
    connect_reads_the_matrix(ch, base, requests, replies, gauge_req)


@pytest.mark.parametrize(
    ("bad", "match"),
    [((0x3, struct.pack(">ff", 9.0, 9.0)), r"two different frames on CAN id 0x273"),
     ((0x4, bytes(4)), r"matrix frame on CAN id 0x274 has 4 data bytes, expected 8"),
     ((0x2, bytes(7)), r"matrix frame on CAN id 0x272 has 7 data bytes, expected 8")],
)
def test_malformed_matrix_frames_are_a_protocol_error(bad: tuple[int, bytes], match: str) -> None:
    ch, base = channel(), 0x27
    b = base << 4
    _, replies = calibration_script(base)
    f2, f3, f4 = matrix_frames(base, 0)
    replies[2] = [f2, f3, (b | bad[0], bad[1]), f4] if bad[0] == 0x3 else [(b | bad[0], bad[1])]
    peer, sensor = connect_only(ch, base, replies[:3])
    try:
        with pytest.raises(ProtocolError, match=match):
            sensor.connect()
    finally:
        sensor.close()
        peer.finish()


def test_fake_answers_a_matrix_row_in_atis_framing() -> None:
    """The simulated sensor, asked for row 3, puts exactly ATI's three frames on the bus."""
    ch, base = channel(), 0x2A
    with FakeFtCanSensor(ConstantWrench([0] * 6), channel=ch, base_id=base, calibration=MATRIX):
        bus = can.Bus(interface="virtual", channel=ch)
        try:
            bus.send(can.Message(arbitration_id=base << 4 | 0x2, data=b"\x03",
                                 is_extended_id=False))
            got = [bus.recv(timeout=10.0) for _ in range(3)]
        finally:
            bus.shutdown()
    assert [(m.arbitration_id, bytes(m.data), m.is_extended_id) for m in got if m] == [
        (aid, data, False) for aid, data in matrix_frames(base, 3)]


def fake_gauge_reply(fake: FakeFtCanSensor, ch: str) -> tuple[bytes, bytes]:
    """One gauge read from ``fake`` with a raw bus: the two reply frames' data."""
    bus = can.Bus(interface="virtual", channel=ch)
    try:
        bus.send(can.Message(arbitration_id=fake.base_id << 4, data=b"", is_extended_id=False))
        got = [bus.recv(timeout=10.0) for _ in range(2)]
    finally:
        bus.shutdown()
    assert all(m is not None for m in got)
    assert [m.arbitration_id for m in got] == [fake.base_id << 4, fake.base_id << 4 | 1]
    return bytes(got[0].data), bytes(got[1].data)


@pytest.mark.parametrize(
    ("bit", "word"),
    [(STATUS_WATCHDOG_RESET, 0x8001), (STATUS_DAC_ADC_TOO_HIGH, 0x8002),
     (STATUS_DAC_ADC_TOO_LOW, 0x8004), (STATUS_BUS_ERROR, 0xC000),
     (STATUS_DAC_ADC_TOO_HIGH | STATUS_BUS_ERROR, 0xC002), (0, 0x0000)],
)
def test_fake_sends_status_bits_as_the_sensor_does(bit: int, word: int) -> None:
    """Each status bit goes out as set, with bit 15 (any error) whenever another is set."""
    ch = channel()
    with FakeFtCanSensor(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), channel=ch) as fake:
        fake.status = bit
        first, _ = fake_gauge_reply(fake, ch)
    assert first[:2] == struct.pack(">H", word)


def test_fake_saturation_puts_a_gauge_on_the_rail_not_a_status_bit() -> None:
    ch = channel()
    with FakeFtCanSensor(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), channel=ch) as fake:
        fake.status = STATUS_SATURATION
        first, second = fake_gauge_reply(fake, ch)
    status, g = decode_gauges(first, second)
    assert status == 0
    assert g.max() == 32767 or g.min() == -32768


def test_caller_paced_requests_go_out_only_when_asked() -> None:
    """After the first request_next(), a decoded reply sends nothing by itself; each
    request_next() sends one request unless one is in flight; read() alone still works."""
    ch, base = channel(), 0x22
    requests, replies = calibration_script(base)
    sg = [(10 * k, 0, 0, 0, 0, 0) for k in range(1, 5)]
    gauge_req = (base << 4 | 0x0, b"")
    # connect's read, connect's pipelined request, one request_next(), read()'s own
    peer, sensor = scripted_sensor(ch, base, replies + [gauge_frames(base, 0, g) for g in sg])
    try:
        sensor.connect()
        sensor.request_next()  # the connect's pipelined request is still in flight: no-op
        w1 = sensor.read()  # its reply; nothing sent after it
        sensor.request_next()  # one request
        sensor.request_next()  # in flight: nothing
        w2 = sensor.read()
        w3 = sensor.read()  # no request in flight: read() sends one and waits
    finally:
        sensor.close()
        peer.finish()
    assert peer.seen == requests + [gauge_req] * 4
    assert (w1.sequence, w2.sequence, w3.sequence) == (2, 3, 4)
    assert w3.force[0] == pytest.approx(MATRIX[0, 0] * 40 / CPF)


def test_the_tail_of_an_abandoned_reply_is_skipped_not_a_fault() -> None:
    """A reply cut by a stall: its frame 1 comes, its frame 2 only after the client has
    given the request up and asked again.  That lone frame 2 is the old reply's tail
    (the daemon faulted on it, `sensor_link_lost`, in a 10-minute bench run); the new
    reply after it is read as usual."""
    import time

    ch, base = channel(), 0x23
    requests, replies = calibration_script(base)
    sg1, sg2, sg3 = (1, 2, 3, 4, 5, 6), (7, 8, 9, 10, 11, 12), (40, 0, 0, 0, 0, 0)
    gauge_req = (base << 4 | 0x0, b"")
    first2, second2 = gauge_frames(base, 0, sg2)
    script = replies + [
        gauge_frames(base, 0, sg1),  # connect's read
        [first2],  # the pipelined request: only frame 1 comes in time
        [],  # read() asked again at once: no answer
        [second2] + gauge_frames(base, 0, sg3),  # after the stall: the old tail, then a reply
    ]
    peer = ScriptedPeer(ch, script)
    peer.start()
    sensor = CanForceSensor(can_cfg(ch, base_id=base, timeout=0.2, connect_timeout=5.0),
                            stale_timeout=10.0)
    try:
        sensor.connect()
        w1 = sensor.read()  # frame 1 only: no new sample, the last one
        time.sleep(0.3)  # a stall longer than the reply timeout: the request is abandoned
        w2 = sensor.read()  # drops the queue, asks again: the tail, then the reply
    finally:
        sensor.close()
        peer.finish()
    assert peer.seen == requests + [gauge_req] * 4
    assert w1.sequence == 1 and w2.sequence == 2
    assert w2.force[0] == pytest.approx(MATRIX[0, 0] * 40 / CPF)
    assert sensor.stats().lost == 1


def test_non_si_units_are_refused_with_a_clear_message() -> None:
    ch = channel()
    _, replies = calibration_script(0x20, units=b"\x01\x01")
    peer = ScriptedPeer(ch, replies[:1])
    peer.start()
    sensor = CanForceSensor(can_cfg(ch, connect_timeout=5.0))
    try:
        with pytest.raises(ProtocolError, match="needs N"):
            sensor.connect()
    finally:
        sensor.close()
        peer.finish()


def test_nothing_answers_names_the_link() -> None:
    ch = channel()
    sensor = CanForceSensor(can_cfg(ch, connect_timeout=0.05))
    with pytest.raises(TransportError, match=f"virtual:{ch}@0x20.*within 50 ms"):
        sensor.connect()
    sensor.close()
    sensor.close()


def test_unknown_interface_is_a_transport_error() -> None:
    sensor = CanForceSensor(can_cfg("x", interface="no-such-interface"))
    with pytest.raises(TransportError, match="cannot open CAN bus no-such-interface:x"):
        sensor.connect()


def test_read_before_connect_is_a_transport_error() -> None:
    with pytest.raises(TransportError, match="not connected"):
        CanForceSensor(can_cfg("y")).read()


def test_another_masters_request_and_other_ids_are_ignored() -> None:
    ch = channel()
    with (FakeFtCanSensor(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), channel=ch) as fake,
          CanForceSensor(can_cfg(ch, timeout=1.0), stale_timeout=10.0) as sensor):
        other = can.Bus(interface="virtual", channel=ch)
        try:
            other.send(can.Message(arbitration_id=0x200, data=b"", is_extended_id=False))
            other.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
            w = sensor.read()
        finally:
            other.shutdown()
        bound = fake.quantisation_bound()
        assert np.all(np.abs(w.as_array() - [1, 2, 3, 0.1, 0.2, 0.3]) <= bound + 1e-12)


# -- decoders ---------------------------------------------------------------------------


def test_decode_gauges_is_big_endian_in_the_documented_order() -> None:
    first = bytes.fromhex("0000 0001 0002 FFFD".replace(" ", ""))
    second = bytes.fromhex("FFFF 7FFE 8001".replace(" ", ""))
    status, g = decode_gauges(first, second)
    assert status == 0
    np.testing.assert_array_equal(g, [1, -1, 2, 32766, -3, -32767])


def test_decode_small_replies() -> None:
    assert decode_counts(struct.pack(">II", 1_000_000, 1000)) == (1_000_000, 1000)
    assert decode_units(b"\x02\x03") == (2, 3)
    frames = [struct.pack(">ff", 1.0, -2.0), struct.pack(">ff", 0.5, 0.0),
              struct.pack(">ff", 3.0, 4.0)]
    assert decode_matrix_row(frames) == (1.0, -2.0, 0.5, 0.0, 3.0, 4.0)
    with pytest.raises(ProtocolError):
        decode_counts(struct.pack(">II", 0, 1))
    with pytest.raises(ProtocolError):
        decode_matrix_row(frames[:2])
    with pytest.raises(ProtocolError, match="not finite"):
        decode_matrix_row([struct.pack(">ff", float("nan"), 0.0)] + frames[1:])


@pytest.mark.parametrize(
    ("status", "bits"),
    [
        (0x0001, ("watchdog_reset",)),
        (0x8002, ("dac_adc_check_too_high", "any_error")),
        (0x8004, ("dac_adc_check_too_low", "any_error")),
        (0xC000, ("can_bus_error", "any_error")),
        (0x8000, ("any_error",)),
        (0x99F8, ("analog_ground_out_of_range", "supply_voltage_too_high",
                  "supply_voltage_too_low", "bad_active_calibration", "eeprom_failure",
                  "configuration_invalid", "temperature_too_high", "temperature_too_low",
                  "any_error")),
        (0x2600, ("reserved_bit9", "reserved_bit10", "reserved_bit13")),
    ],
)
def test_status_bits_are_named_as_ati_defines_them(status: int, bits: tuple[str, ...]) -> None:
    """Any set bit is a status fault (never "saturation"), each set bit named, bit 0 first."""
    assert status_bit_names(status) == bits
    with pytest.raises(SafetyFault) as info:
        check_status(status, np.zeros(6))
    assert info.value.cause is FaultCause.SENSOR_STATUS
    assert info.value.details["status"] == f"0x{status:04X}"
    assert info.value.details["bits"] == list(bits)


@pytest.mark.parametrize(("gauges", "at_rail"), [((0, 0, 32767, 0, 0, 0), ["sg2"]),
                                                 ((-32768, 0, 0, 0, 32767, 0), ["sg0", "sg4"])])
def test_a_gauge_at_the_int16_rail_is_saturation(gauges: tuple[int, ...],
                                                 at_rail: list[str]) -> None:
    with pytest.raises(SafetyFault) as info:
        check_status(0, np.array(gauges, dtype=float))
    assert info.value.cause is FaultCause.SENSOR_SATURATION
    assert info.value.details["gauges"] == at_rail


def test_healthy_status_passes() -> None:
    check_status(0, np.array([0, 1, -1, 32766, -32767, 5], dtype=float))


_frame = st.binary(min_size=0, max_size=8)


@settings(max_examples=300, deadline=None)
@given(first=_frame, second=_frame)
def test_fuzz_gauge_decoding_never_nan_never_foreign_exception(first: bytes, second: bytes) -> None:
    conv = conversion_matrix(MATRIX, CPF, CPT)
    try:
        status, g = decode_gauges(first, second)
        check_status(status, g)
    except (ProtocolError, SafetyFault):
        return
    w = conv @ g
    assert np.all(np.isfinite(w))


@settings(max_examples=200, deadline=None)
@given(frames=st.lists(st.binary(min_size=0, max_size=8), min_size=0, max_size=4))
def test_fuzz_matrix_row_decoding(frames: list[bytes]) -> None:
    try:
        row = decode_matrix_row(frames)
    except ProtocolError:
        return
    assert len(row) == 6 and all(np.isfinite(row))


def test_fuzz_client_against_random_frames_on_the_bus() -> None:
    """Random frames on the sensor's ids reach a connected client: it only ever raises
    its own errors and never returns a non-finite wrench."""
    ch = channel()
    with (FakeFtCanSensor(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), channel=ch) as fake,
          CanForceSensor(can_cfg(ch, timeout=0.001), stale_timeout=1e6) as sensor):
        fake.silent = True
        noise = can.Bus(interface="virtual", channel=ch)
        ids = st.sampled_from([0x200, 0x201, 0x202, 0x207, 0x208, 0x20F])

        @settings(max_examples=150, deadline=None,
                  suppress_health_check=[HealthCheck.function_scoped_fixture])
        @given(frames=st.lists(st.tuples(ids, _frame), max_size=5))
        def feed(frames: list[tuple[int, bytes]]) -> None:
            for aid, data in frames:
                noise.send(can.Message(arbitration_id=aid, data=data, is_extended_id=False))
            try:
                w = sensor.read()
            except (TransportError, SafetyFault):
                return
            assert np.all(np.isfinite(w.as_array()))

        try:
            feed()
        finally:
            noise.shutdown()
