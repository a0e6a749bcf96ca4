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
from structlog.testing import capture_logs

from mmctl.config import default_config
from mmctl.errors import FaultCause, LinkLost, ProtocolError, SafetyFault, TransportError
from mmctl.sim.fake_rdt import FakeRdtServer
from mmctl.sim.wrench_source import ConstantWrench
from mmctl.transports.sensor.rdt import (
    CMD_START,
    RdtForceSensor,
    SequenceTracker,
    decode_record,
    encode_request,
    restart_interval,
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


def connect_against(peer: Peer, first: bytes, stale_timeout: float = 1e6,
                    **over: object) -> RdtForceSensor:
    """Connect a client to ``peer`` from a helper thread-free dance: the client's start
    request is answered with ``first`` as soon as it arrives."""
    sensor = RdtForceSensor(rdt_cfg("127.0.0.1", peer.port, connect_timeout=WAIT, **over),
                            stale_timeout=stale_timeout)
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
    assert sensor.stats() == (3, 0, 0, 0, 0)
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
@given(st.permutations(list(range(2, 40))), st.sets(st.integers(2, 39), max_size=10))
def test_tracker_lost_is_exactly_the_missing_records(order: list[int], dropped: set[int]) -> None:
    """The stream's first record first, then whatever the arrival order: once everything
    sent has arrived, lost counts exactly the records never sent (gaps below the newest),
    out-of-order every record that came after a newer one, and nothing is a reset."""
    t = SequenceTracker()
    sent = [1] + [s for s in order if s not in dropped]
    late = 0
    for i, s in enumerate(sent):
        newer = s > max(sent[:i], default=0)
        assert t.observe(s) is newer
        late += not newer
    newest = max(sent)
    assert t.newest == newest
    assert t.lost == sum(1 for s in dropped if s < newest)
    assert t.out_of_order == late
    assert t.resets == 0


@pytest.mark.parametrize("ran", [5, 200, 5000])
@pytest.mark.parametrize("start", [0, 1, 2, 3, 4, 100, 4000, 4999, 5000, 2**31, 2**32 - 2])
def test_tracker_takes_a_restarted_stream_by_its_third_record(ran: int, start: int) -> None:
    """However long the old stream ran and wherever the new one starts, the new stream's
    third record is taken at the latest, and every record after it."""
    t = SequenceTracker()
    for s in range(1, ran + 1):
        assert t.observe(s)
    taken = [t.observe((start + i) % 2**32) for i in range(50)]
    assert True in taken[:3], taken
    first = taken.index(True)
    assert all(taken[first:]), taken
    assert t.newest == (start + 49) % 2**32
    # what the old stream's tail decides: ahead of it (a gap), or a reset of the counts
    behind = (ran - start) % 2**32
    if 0 < (start - ran) % 2**32 < 2**31:
        assert (t.resets, first) == (0, 0)
    elif start <= 1 or behind > 256:
        assert (t.resets, first, t.out_of_order) == (1, 0, 0)
    else:  # a short step back: the third record, or the stream passed the old newest
        assert first == min(2, behind + 1)
        assert t.resets == (1 if behind >= 2 else 0)


@settings(max_examples=300, deadline=None)
@given(old=st.integers(1, 20_000), start=st.integers(0, 2**32 - 1),
       n=st.integers(3, 40))
def test_tracker_never_locks_a_new_stream_out(old: int, start: int, n: int) -> None:
    t = SequenceTracker()
    for s in range(max(1, old - 300), old + 1):
        t.observe(s)
    taken = [t.observe((start + i) % 2**32) for i in range(n)]
    assert True in taken[:3]
    assert all(taken[taken.index(True):])
    assert t.lost >= 0 and t.out_of_order >= 0


def test_tracker_a_duplicate_is_not_a_reset() -> None:
    t = SequenceTracker()
    for s in range(1, 1001):
        t.observe(s)
    assert not t.observe(1000)  # the newest again
    assert not t.observe(998)  # an old one again (already seen, fills no gap)
    assert (t.resets, t.out_of_order, t.newest) == (0, 2, 1000)
    assert t.observe(1001)


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


# -- recovery: sequence restarts, re-start on silence -------------------------------------

START = encode_request(CMD_START)


def feed(sensor: RdtForceSensor, peer: Peer, seqs: list[int]) -> None:
    """Send records numbered ``seqs`` (counts = the number), 64 at a time (what the
    socket buffer surely holds), each batch read before the next: its last record must
    be taken (the read returns it) within the wait."""
    for i in range(0, len(seqs), 64):
        batch = seqs[i:i + 64]
        for s in batch:
            peer.send(record(s, s, 0, (s,) * 6))
        deadline = time.monotonic() + WAIT
        while sensor.read().sequence != batch[-1]:
            assert time.monotonic() < deadline, (
                f"record {batch[-1]} never taken: {sensor.stats()}")
            time.sleep(0.0005)


@pytest.mark.parametrize(("start", "taken"), [(1, 20), (0, 20), (3000, 20), (4900, 18)])
def test_a_restarted_sequence_is_taken_again(peer: Peer, start: int, taken: int) -> None:
    """Issue 17: after 5000 records the sensor's sequence restarts (a reboot, a start
    request): every record of the new stream is taken (from its third one at the latest,
    when it steps back only a little), counted as one reset, logged once."""
    sensor = connect_against(peer, record(1, 1, 0, (1,) * 6), counts_per_force=1.0,
                             counts_per_torque=1.0)
    feed(sensor, peer, list(range(2, 5001)))
    before = sensor.stats()
    assert before == (5000, 0, 0, 0, 0)
    with capture_logs() as logs:
        feed(sensor, peer, list(range(start, start + 20)))
    after = sensor.stats()
    assert after.received - before.received == taken
    assert (after.resets, after.lost, after.out_of_order, after.restarts) == (1, 0, 0, 0)
    w = sensor.read()
    assert w.sequence == start + 19 and w.force[0] == start + 19
    resets = [e for e in logs if e["event"] == "rdt_sequence_reset"]
    assert len(resets) == 1 and (resets[0]["previous"], resets[0]["first"]) == (
        5000, start + 20 - taken), resets
    sensor.close()


def restart_times(restart_after: float, silent_for: float) -> int:
    """How many start requests the backoff allows within ``silent_for`` of silence: the
    first at ``restart_after``, then after restart_after x 1, 2, 4, ... (at most 1 s)."""
    t, n = restart_after, 0
    while t <= silent_for:
        n += 1
        t += restart_interval(restart_after, n)
    return n


def test_the_restart_interval_doubles_up_to_a_second_and_never_overflows() -> None:
    assert [restart_interval(0.1, n) for n in range(1, 7)] == pytest.approx(
        [0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    assert restart_interval(0.1, 10**9) == 1.0  # a sensor gone for years
    assert restart_interval(5.0, 1) == restart_interval(5.0, 10**6) == 5.0


def test_a_silent_sensor_is_sent_start_again_rate_limited_and_still_stale(peer: Peer) -> None:
    """No record for ``restart_after``: the start request goes out again, then at
    doubling intervals; every read past the stale timeout still raises SENSOR_STALE; the
    first record after that is taken (a new stream) and the recovery is logged."""
    t0 = time.monotonic()  # before the last record: the silence is shorter than from here
    sensor = connect_against(peer, record(7, 7, 0, (0,) * 6), stale_timeout=0.01,
                             restart_after=0.02)
    stale = 0
    with capture_logs() as logs:
        while time.monotonic() - t0 < 0.5:
            try:
                sensor.read()
            except SafetyFault as exc:
                assert exc.cause is FaultCause.SENSOR_STALE
                stale += 1
            time.sleep(0.001)
        silent_for = time.monotonic() - t0
    requests = []
    while select.select([peer.sock], [], [], 0)[0]:
        requests.append(peer.recv())
    assert stale > 0
    assert requests and set(requests) == {START}
    assert len(requests) == sensor.stats().restarts <= restart_times(0.02, silent_for)
    attempts = [e["attempt"] for e in logs if e["event"] == "rdt_restart_sent"]
    assert attempts == [2**k for k in range(12) if 2**k <= len(requests)]
    # the sensor answers the last request: its new stream is taken at once
    with capture_logs() as logs:
        feed(sensor, peer, [1, 2, 3])
    assert sensor.stats().resets == 1
    recovered = [e for e in logs if e["event"] == "rdt_stream_recovered"]
    assert len(recovered) == 1 and recovered[0]["attempts"] == len(requests)
    sensor.close()


def test_a_rebooted_fake_streams_again_after_the_clients_new_start() -> None:
    """The fake's reboot: streaming stops, sequences restart, requests are ignored while
    it boots; the client sends start again until one is obeyed, the stale fault is
    raised meanwhile, then fresh samples flow as before."""
    with FakeRdtServer(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), rate_hz=500.0) as fake:
        host, port = fake.address
        cfg = rdt_cfg(host, port, connect_timeout=WAIT, restart_after=0.02)
        with RdtForceSensor(cfg, stale_timeout=0.05) as s:
            deadline = time.monotonic() + WAIT
            while s.read().sequence < 20:
                assert time.monotonic() < deadline
                time.sleep(0.001)
            assert fake.starts == 1
            fake.reboot(down_for=0.3)
            stale = 0
            deadline = time.monotonic() + WAIT
            while True:  # until ten fresh records of the new stream
                assert time.monotonic() < deadline, (s.stats(), fake.starts)
                try:
                    w = s.read()
                except SafetyFault as exc:
                    assert exc.cause is FaultCause.SENSOR_STALE
                    stale += 1
                else:
                    if s.stats().resets and w.sequence >= 10:
                        break
                time.sleep(0.001)
            stats = s.stats()
    assert stale > 0
    assert fake.reboots == 1 and fake.starts >= 2
    assert stats.restarts >= fake.starts - 1 >= 1  # all re-sent; the obeyed one among them
    assert stats.resets == 1
    np.testing.assert_allclose(w.force, [1, 2, 3], atol=1e-6)


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


def test_link_lost_then_reconnected() -> None:
    """The sensor goes away (nothing listens: the restart request is refused): the read
    raises LinkLost naming the link, reconnect() fails while nothing answers, and opens a
    new stream once the sensor is back (issue 28, point 4)."""
    fake = FakeRdtServer(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), rate_hz=500.0).start()
    host, port = fake.address
    sensor = RdtForceSensor(rdt_cfg(host, port, connect_timeout=0.3, restart_after=0.01),
                            stale_timeout=1e6)
    try:
        sensor.connect()
        sensor.reconnect()  # the link works: nothing to do
        assert fake.starts == 1
        fake.stop()
        deadline = time.monotonic() + WAIT
        with pytest.raises(LinkLost) as lost:
            while time.monotonic() < deadline:
                sensor.read()
                time.sleep(0.002)
        assert lost.value.cause is FaultCause.SENSOR_LINK and sensor.link in str(lost.value)
        with pytest.raises(LinkLost, match="reconnect failed"):
            sensor.reconnect()
        fake = FakeRdtServer(ConstantWrench([1, 2, 3, 0.1, 0.2, 0.3]), host=host, port=port,
                             rate_hz=500.0).start()
        sensor.reconnect()
        assert sensor.read().force[2] == pytest.approx(3.0)
    finally:
        sensor.close()
        fake.stop()
