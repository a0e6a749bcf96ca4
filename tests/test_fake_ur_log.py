"""The fake UR's command log stays small: in the controller's process, and in the copy
the simulation keeps of it (it outlives a killed controller).

`mmctl bench soak` saw the simulation's process grow by ~270 MB over an hour: each
injected ``arm_disconnected`` copied the controller's whole log (up to 200 000 entries,
as 13 Python objects and ~500 bytes each) into it in one message.  These tests count
the objects a log holds and check that a fetch comes in chunks and keeps every entry.
"""

from __future__ import annotations

import gc
import socket
import types
from typing import Any

import pytest

from mmctl.sim.fake_ur import CommandKind, FakeURController
from mmctl.sim.fake_ur.log import CommandLog

QD = (0.1, -0.2, 0.3, 1e-9, 5.0, -6.0)


def _objects_held(root: object) -> int:
    """Distinct objects reachable from ``root`` (not through types, modules or functions,
    nor the shared singletons: None, bools, enum members)."""
    seen: set[int] = set()
    todo: list[Any] = [root]
    skip = (type, types.ModuleType, types.FunctionType, types.BuiltinFunctionType)
    while todo:
        obj = todo.pop()
        if id(obj) in seen or obj is None or isinstance(obj, (bool, CommandKind, *skip)):
            continue
        seen.add(id(obj))
        todo.extend(gc.get_referents(obj))
    return len(seen)


def _fill(log: CommandLog, n: int) -> None:
    for i in range(n):
        if i % 10:
            log.add(0.002 * i, CommandKind.SPEEDJ, qd=QD, acceleration=2.0, time=0.008)
        else:
            log.add(0.002 * i, CommandKind.DASHBOARD, text="robotmode",
                    reply="Robotmode: RUNNING")


def test_a_log_entry_is_one_object_untracked_by_the_gc() -> None:
    log = CommandLog(capacity=2000)
    _fill(log, 2500)
    assert len(log.since(0)) == 2000
    # the log, its ring, its counter and one bytes per entry (the old tuples: 13 each)
    assert _objects_held(log) <= 2000 + 10
    assert not any(gc.is_tracked(e) for e in log.rows(0))


def test_entries_round_trip_through_rows_and_extend() -> None:
    src = CommandLog(capacity=100)
    src.add(0.5, CommandKind.SPEEDJ, qd=QD, acceleration=2.0, time=0.008)
    src.add(0.6, CommandKind.DASHBOARD, text="is in remote control", reply="fälse")
    src.add(0.7, CommandKind.SCRIPT, text="rtde_control", code=1234)
    src.add(0.8, CommandKind.SPEED_STOP, deceleration=10)
    src.add(0.9, CommandKind.CONNECTION, code=30004, text="closed: peer closed")
    src.add(1.0, CommandKind.STOP_SCRIPT)
    want = src.since(0)
    assert want[0].qd == QD and (want[0].acceleration, want[0].time) == (2.0, 0.008)
    assert (want[1].text, want[1].reply, want[1].qd) == ("is in remote control", "fälse", None)
    assert (want[2].code, want[3].deceleration, want[5].text) == (1234, 10.0, None)
    assert all(e.received is not None for e in want)
    copy = CommandLog(capacity=100)
    copy.extend(src.rows(0, 2))
    copy.extend(src.rows(copy.next_seq, 100))
    assert copy.since(0) == want and copy.next_seq == 6
    assert copy.since(4) == want[4:] and copy.since(6) == []
    with pytest.raises(ValueError, match="do not follow"):
        copy.extend(src.rows(0))


def test_a_copy_with_dropped_entries_finds_seqs_across_the_gap() -> None:
    src = CommandLog(capacity=100)
    for i in range(10):
        src.add(float(i), CommandKind.STOP_SCRIPT)
    copy = CommandLog(capacity=100)
    for seq, limit in ((1, 2), (5, 3), (9, 5)):
        copy.extend(src.rows(seq, limit))
    assert [e.seq for e in copy.since(0)] == [1, 2, 5, 6, 7, 9]
    assert [e.seq for e in copy.since(3)] == [5, 6, 7, 9]
    assert [e.seq for e in copy.since(8)] == [9]


def _dashboard(host: str, lines: int) -> None:
    with socket.create_connection((host, 29999), timeout=30.0) as s, s.makefile("rb") as f:
        f.readline()
        s.sendall(b"robotmode\n" * lines)
        for _ in range(lines):
            assert f.readline() == b"Robotmode: RUNNING\n"


@pytest.mark.timeout(120)
def test_a_killed_controllers_log_is_fetched_in_chunks_and_kept_compact(
        loopback_host: str) -> None:
    fake = FakeURController(loopback_host, log_capacity=1000, log_chunk=100).start()
    try:
        _dashboard(fake.host, 1500)
        fake.kill()  # fetches the process's log first: 1000 entries, 100 per request
        kept = fake.commands()
        assert len(kept) == 1000
        assert [e.seq for e in kept] == list(range(kept[0].seq, kept[0].seq + 1000))
        assert sum(e.kind is CommandKind.DASHBOARD for e in kept) >= 998
        assert _objects_held(fake._log) <= 1000 + 10  # one bytes per entry
        fake.restart()
        _dashboard(fake.host, 5)
        fake.stop()
        after = fake.commands()
        assert len(after) == 1000  # the copy is bounded by log_capacity
        # the restarted process numbers on: nothing lost, nothing twice
        assert [e.seq for e in after] == list(range(after[0].seq, after[0].seq + 1000))
        new = [e for e in after if e.seq > kept[-1].seq]
        assert [e.text for e in new if e.kind is CommandKind.DASHBOARD] == ["robotmode"] * 5
    finally:
        fake.stop()
