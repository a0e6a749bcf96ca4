"""The shared-memory mailbox: layout, seqlock semantics across real processes, wake-ups.

Conditions are asserted, never timing (tools/mailbox_bench.py prints the figures).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Iterator
from multiprocessing.connection import Connection

import numpy as np
import pytest

from mmctl.runtime.mailbox import (
    Mailbox,
    MailboxLayout,
    Sample,
    Wake,
    WakeKind,
    check_clocks,
    now_ns,
)

LAYOUT = MailboxLayout("test_box", (("a", 1), ("wrench", 6), ("code", 1)))
HAMMER = 20_000


def _segments() -> set[str]:
    return {f for f in os.listdir("/dev/shm") if f.startswith(f"mmctl-test_box-{os.getpid()}-")}


@pytest.fixture(autouse=True)
def _no_leaked_segments() -> Iterator[None]:
    before = _segments()
    yield
    assert _segments() == before, "a mailbox segment was left in /dev/shm"


@pytest.fixture
def box() -> Iterator[Mailbox]:
    with Mailbox.create(LAYOUT) as b:
        yield b


# -- layout --------------------------------------------------------------------------

def test_layout_places_fields_in_order() -> None:
    assert LAYOUT.width == 8
    assert LAYOUT.nbytes == 24 + 8 * 8
    assert LAYOUT.slice("wrench") == slice(1, 7)
    assert LAYOUT.index("code") == 7
    with pytest.raises(KeyError, match="has no field 'nope'.*'a', 'wrench', 'code'"):
        LAYOUT.slice("nope")
    with pytest.raises(KeyError, match="holds 6 values"):
        LAYOUT.index("wrench")


@pytest.mark.parametrize("fields", [(), (("a", 1), ("a", 2)), (("a", 0),), (("1x", 1),)])
def test_bad_layouts_are_refused(fields: tuple[tuple[str, int], ...]) -> None:
    with pytest.raises(ValueError, match="mailbox layout 'bad'"):
        MailboxLayout("bad", fields)


def test_the_clocks_compare_across_processes() -> None:
    check_clocks()  # Linux: monotonic and perf_counter are one CLOCK_MONOTONIC


# -- one process ---------------------------------------------------------------------

def test_a_read_copies_the_newest_record_once(box: Mailbox) -> None:
    reader = Mailbox.attach(box.name, LAYOUT)
    s = Sample(LAYOUT)
    assert not reader.read_into(s) and s.seq == 0  # nothing published yet
    box.staging[:] = np.arange(8.0)
    t = now_ns()
    box.publish(t)
    box.staging[:] = -1.0  # the record is a copy: the staging area is free again
    assert reader.read_into(s)
    assert s.seq == 2 and s.t_ns == t
    assert s["a"] == 0.0 and s.view("wrench").tolist() == [1, 2, 3, 4, 5, 6] and s["code"] == 7
    assert not reader.read_into(s)  # nothing new: False, the copy unchanged
    assert s.values.tolist() == list(range(8))
    box.publish(t + 1)
    box.publish(t + 2)  # a reader sees only the newest
    assert reader.read_into(s) and s.seq == 6 and s.t_ns == t + 2
    reader.close()
    reader.close()
    assert _segments() == {box.name}  # an attacher does not unlink


def test_a_writer_caught_mid_write_is_no_new_sample_never_a_wait(box: Mailbox) -> None:
    reader = Mailbox.attach(box.name, LAYOUT)
    s = Sample(LAYOUT)
    box.staging[:] = 5.0
    box.publish(1)
    assert reader.read_into(s)
    box._q[1] = box.seq() + 1  # a writer that died inside publish(): seq stays odd
    calls = sum(1 for _ in range(1000) if not reader.read_into(s, retries=4))
    assert calls == 1000 and reader.busy == 1000 and reader.torn == 4000
    assert s.seq == 2 and s.values.tolist() == [5.0] * 8  # the good copy kept
    reader.close()


def test_attach_checks_name_and_layout(box: Mailbox) -> None:
    other = MailboxLayout("test_box", (("a", 1), ("wrench", 6), ("other", 1)))
    with pytest.raises(ValueError, match="made for another layout"):
        Mailbox.attach(box.name, other)
    bigger = MailboxLayout("test_box", (("a", 100),))
    with pytest.raises(ValueError, match="needs"):
        Mailbox.attach(box.name, bigger)
    with pytest.raises(FileNotFoundError):
        Mailbox.attach("mmctl-test_box-no-such-segment", LAYOUT)


def test_the_owner_unlinks_at_close() -> None:
    box = Mailbox.create(LAYOUT)
    name = box.name
    assert name in _segments()
    box.close()
    box.close()
    assert name not in _segments() and box.closed
    with pytest.raises(ValueError, match="closed"):
        _ = box.name


# -- across processes ----------------------------------------------------------------

def _hammer(name: str, n: int) -> None:
    """Spawned writer: record k has every field = k and t_ns = k, as fast as it goes."""
    box = Mailbox.attach(name, LAYOUT)
    for k in range(1, n + 1):
        box.staging[:] = k
        box.publish(k)
    box.close()


def test_every_read_is_consistent_while_a_writer_hammers(box: Mailbox) -> None:
    ctx = multiprocessing.get_context("spawn")
    writer = ctx.Process(target=_hammer, args=(box.name, HAMMER), daemon=True)
    s = Sample(LAYOUT)
    seen: list[int] = []
    writer.start()
    while s.t_ns != HAMMER:
        if box.read_into(s):
            k = s.t_ns
            assert np.all(s.values == k), (k, s.values)  # never a mix of two records
            assert s.seq == 2 * k  # seq: +2 per record
            seen.append(k)
        elif not writer.is_alive() and box.seq() != 2 * HAMMER:
            pytest.fail(f"the writer ended ({writer.exitcode}) before its last record")
    writer.join(30.0)
    assert writer.exitcode == 0
    assert seen == sorted(set(seen)) and seen[-1] == HAMMER  # newer each time, the last one
    print(f"reads {len(seen)} of {HAMMER} records, writer caught mid-write {box.torn} times")


def _echo(request: str, reply: str, wake: Wake, back: Wake, n: int) -> None:
    """Spawned device side: wait for a command, answer with its value + 1."""
    inbox, outbox = Mailbox.attach(request, LAYOUT), Mailbox.attach(reply, LAYOUT)
    s = Sample(LAYOUT)
    answered = 0
    while answered < n:
        if not wake.wait(30.0):
            break
        if inbox.read_into(s):
            outbox.staging[:] = s.values + 1
            outbox.publish(now_ns())
            back.notify()
            answered += 1
    inbox.close()
    outbox.close()


@pytest.mark.parametrize("kind", list(WakeKind))
def test_commands_wake_the_other_process(kind: WakeKind) -> None:
    ctx = multiprocessing.get_context("spawn")
    n = 200
    with Mailbox.create(LAYOUT) as request, Mailbox.create(LAYOUT) as reply:
        wake, back = Wake(kind), Wake(kind)
        device = ctx.Process(target=_echo, args=(request.name, reply.name, wake, back, n),
                             daemon=True)
        device.start()
        s = Sample(LAYOUT)
        try:
            for k in range(n):
                request.staging[:] = k
                request.publish(now_ns())
                wake.notify()
                while not reply.read_into(s):  # the answer to this command, not an old one
                    assert back.wait(30.0), f"no answer to command {k}"
                assert s.values.tolist() == [k + 1] * 8
        finally:
            device.join(30.0)
            wake.close()
            back.close()
    assert device.exitcode == 0


@pytest.mark.parametrize("kind", list(WakeKind))
def test_notifications_coalesce_and_a_wait_can_poll(kind: WakeKind) -> None:
    wake = Wake(kind)
    assert not wake.wait(0.0)
    for _ in range(10):
        wake.notify()
    assert wake.wait(0.0)
    assert not wake.wait(0.0)  # all ten consumed by one wait
    wake.close()
    wake.close()


def _reader_of(conn: Connection, name: str) -> None:
    box = Mailbox.attach(name, LAYOUT)
    s = Sample(LAYOUT)
    got = box.read_into(s)
    conn.send((got, s.t_ns, s.values.tolist()))
    box.close()


def test_many_readers_each_see_the_record(box: Mailbox) -> None:
    ctx = multiprocessing.get_context("spawn")
    box.staging[:] = 7.0
    box.publish(42)
    results = []
    for _ in range(2):
        parent, child = ctx.Pipe()
        p = ctx.Process(target=_reader_of, args=(child, box.name), daemon=True)
        p.start()
        results.append(parent.recv())
        p.join(30.0)
    assert results == [(True, 42, [7.0] * 8)] * 2
