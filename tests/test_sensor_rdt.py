"""RDT transport: exact bytes (scripted UDP peer), sequence counters, fuzz."""

from __future__ import annotations

import dataclasses
import select
import socket
import struct
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mmctl.config import default_config
from mmctl.errors import FaultCause, ProtocolError, SafetyFault, TransportError
from mmctl.sim.fake_rdt import FakeRdtServer
from mmctl.sim.wrench_source import ConstantWrench
from mmctl.transports.sensor.rdt import (
    RdtForceSensor,
    SequenceTracker,
    decode_record,
    encode_request,
)

WAIT = 10.0  # generous bound when waiting for an event on a loaded machine


def rdt_cfg(host: str, port: int, **over: object):
    base = default_config().sensor.rdt
    return dataclasses.replace(base, host=host, port=port, **over)


def record(seq: int, ft_seq: int, status: int, counts: tuple[int, ...]) -> bytes:
    return struct.pack(">III6i", seq, ft_seq, status, *counts)


class Peer:
    """A hand-driven RDT peer: a bound UDP socket the test reads and writes."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.client: tuple[str, int] | None = None

    def recv(self) -> bytes:
        ready, _, _ = select.select([self.sock], [], [], WAIT)
        assert ready, "the client sent nothing"
        data, self.client = self.sock.recvfrom(64)
        return data

    def send(self, data: bytes) -> None:
        assert self.client is not None
        self.sock.sendto(data, self.client)

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def peer():
    p = Peer()
    yield p
    p.close()


def connect_against(peer: Peer, first: bytes, **over: object) -> RdtForceSensor:
    """Connect a client to ``peer`` from a helper thread-free dance: the client's start
    request is answered with ``first`` as soon as it arrives."""
    sensor = RdtForceSensor(rdt_cfg("127.0.0.1", peer.port, connect_timeout=WAIT, **over),
                            stale_timeout=1e6)
    seen: list[bytes] = []

    def answer() -> None:
        seen.append(peer.recv())
        peer.send(first)

    t = threading.Thread(target=answer, daemon=True)
    t.start()
    sensor.connect()
    t.join(WAIT)
    assert seen == [bytes.fromhex("1234 0002 00000000".replace(" ", ""))]
    return sensor


def test_request_bytes() -> None:
    assert encode_request(0x0002, 0) == b"\x12\x34\x00\x02\x00\x00\x00\x00"
    assert encode_request(0x0042) == b"\x12\x34\x00\x42\x00\x00\x00\x00"
    assert encode_request(0x0000, 7) == b"\x12\x34\x00\x00\x00\x00\x00\x07"


def test_exact_exchange_start_records_stop(peer: Peer) -> None:
    counts = (1_500_000, -2_000_000, 30_000_000, 100_000, -250_000, 5)
    sensor = connect_against(peer, record(1, 11, 0, counts),
                             counts_per_force=1e6, counts_per_torque=2e6)
    w = sensor.read()
    np.testing.assert_allclose(w.force, [1.5, -2.0, 30.0], rtol=1e-15)
    np.testing.assert_allclose(w.torque, [0.05, -0.125, 2.5e-6], rtol=1e-15)
    assert (w.sequence, w.status) == (1, 0)
    # newest record wins; both are counted
    peer.send(record(2, 12, 0, (0,) * 6))
    peer.send(record(3, 13, 0x10, (1,) * 6))
    deadline = time.monotonic() + WAIT
    while sensor.read().sequence != 3 and time.monotonic() < deadline:
        time.sleep(0.001)
    w = sensor.read()
    assert (w.sequence, w.status) == (3, 0x10)  # bit 4 is not in the fault masks
    assert sensor.stats() == (3, 0, 0)
    sensor.close()
    assert peer.recv() == b"\x12\x34\x00\x00\x00\x00\x00\x00"
    sensor.close()


def test_status_masks(peer: Peer) -> None:
    sensor = connect_against(peer, record(1, 1, 0, (0,) * 6))
    peer.send(record(2, 2, 0x80000000, (0,) * 6))
    with pytest.raises(SafetyFault) as info:
        _read_until_raises(sensor)
    assert info.value.cause is FaultCause.SENSOR_STATUS
    peer.send(record(3, 3, 0x80020000, (0,) * 6))
    with pytest.raises(SafetyFault) as info:
        _read_until_raises(sensor)
    assert info.value.cause is FaultCause.SENSOR_SATURATION
    sensor.close()


def test_short_datagram_is_a_protocol_error(peer: Peer) -> None:
    sensor = connect_against(peer, record(1, 1, 0, (0,) * 6))
    peer.send(b"\x00" * 35)
    with pytest.raises(ProtocolError, match="35 bytes"):
        _read_until_raises(sensor)
    sensor.close()


def _read_until_raises(sensor: RdtForceSensor) -> None:
    deadline = time.monotonic() + WAIT
    while time.monotonic() < deadline:
        sensor.read()
        time.sleep(0.0005)
    raise AssertionError("no error within the wait")


def test_nothing_listening_is_connection_refused() -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    sensor = RdtForceSensor(rdt_cfg("127.0.0.1", port, connect_timeout=WAIT))
    with pytest.raises(TransportError, match="nothing answers at udp://127.0.0.1:.*refused"):
        sensor.connect()
    sensor.close()


def test_silent_peer_times_out(peer: Peer) -> None:
    sensor = RdtForceSensor(rdt_cfg("127.0.0.1", peer.port, connect_timeout=0.2))
    with pytest.raises(TransportError, match=r"nothing answers at .*0/1 RDT records within 200 ms"):
        sensor.connect()


# -- sequence counters -------------------------------------------------------------------


def test_tracker_counts_gaps_and_late_records() -> None:
    t = SequenceTracker()
    for s in (1, 2, 4, 3, 5, 8, 8, 6):
        t.observe(s)
    # 3 late (fills its gap), 7 never came, 6 late; 8 duplicated
    assert t.newest == 8
    assert t.lost == 1
    assert t.out_of_order == 3


def test_tracker_wraps_at_32_bits() -> None:
    t = SequenceTracker()
    assert t.observe(0xFFFFFFFE)
    assert t.observe(0xFFFFFFFF)
    assert t.observe(1)  # 0 skipped across the wrap
    assert (t.lost, t.out_of_order) == (1, 0)
    assert not t.observe(0)  # late, fills the gap
    assert (t.lost, t.out_of_order) == (0, 1)


@settings(max_examples=200, deadline=None)
@given(st.permutations(list(range(1, 40))), st.sets(st.integers(1, 39), max_size=10))
def test_tracker_lost_is_exactly_the_missing_records(order: list[int], dropped: set[int]) -> None:
    """Whatever the arrival order, once everything sent has arrived, lost counts exactly
    the records never sent (gaps below the newest)."""
    t = SequenceTracker()
    sent = [s for s in order if s not in dropped]
    for s in sent:
        t.observe(s)
    newest = max(sent) if sent else None
    if newest is None:
        return
    first = sent[0]
    expected = sum(1 for s in dropped if first < s < newest)
    # records below the first one seen are late, never "lost"
    assert t.lost == expected


def test_fake_drops_and_swaps_are_counted() -> None:
    with FakeRdtServer(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), rate_hz=500.0) as fake:
        fake.drop = {5, 9}
        fake.swap = {12}
        host, port = fake.address
        with RdtForceSensor(rdt_cfg(host, port, connect_timeout=WAIT), stale_timeout=1e6) as s:
            deadline = time.monotonic() + WAIT
            while s.read().sequence < 25 and time.monotonic() < deadline:
                time.sleep(0.001)
            stats = s.stats()
    assert stats.lost == 2
    assert stats.out_of_order == 1
    assert stats.received >= 22


# -- fuzz -------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(min_size=36, max_size=36), st.binary(max_size=80)))
def test_fuzz_decode_record(data: bytes) -> None:
    try:
        rec = decode_record(data)
    except ProtocolError:
        assert len(data) != 36
        return
    assert len(rec.counts) == 6
    assert all(-(2**31) <= c < 2**31 for c in rec.counts)


def test_fuzz_client_against_random_datagrams(peer: Peer) -> None:
    sensor = connect_against(peer, record(1, 1, 0, (0,) * 6))
    datagrams = st.lists(st.one_of(st.binary(min_size=36, max_size=36), st.binary(max_size=64)),
                         max_size=4)

    @settings(max_examples=150, deadline=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(batch=datagrams)
    def feed(batch: list[bytes]) -> None:
        for d in batch:
            peer.send(d)
        if batch:
            select.select([sensor._sock], [], [], 0.05)  # let them land (test-only peek)
        try:
            w = sensor.read()
        except (TransportError, SafetyFault):
            return
        assert np.all(np.isfinite(w.as_array()))

    try:
        feed()
    finally:
        sensor.close()
