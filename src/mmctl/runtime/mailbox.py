"""A lock-free, shared-memory mailbox: one writer leaves its newest record, readers copy it.

The loop never waits on a device (SPEC §7): each device link, in a process of its own,
publishes its newest time-stamped sample here, and the loop copies it out; commands go
the other way through a second mailbox and a :class:`Wake`.

Segment layout (``multiprocessing.shared_memory``, native byte order, 8-byte aligned)::

    offset 0    int64    layout fingerprint (crc32 of the field list; checked at attach)
    offset 8    int64    seq: even = stable, odd = the writer is writing
    offset 16   int64    t_ns: the record's own time stamp [ns of CLOCK_MONOTONIC]
    offset 24   float64  the layout's fields, in order (MailboxLayout.fields)

Clock: ``t_ns`` is ``time.monotonic_ns()`` — on Linux ``time.monotonic`` and
``time.perf_counter`` are both ``clock_gettime(CLOCK_MONOTONIC)`` (the loop's deadlines
are ``perf_counter_ns``), one clock for every process of the machine, so a time stamp
taken in a device's process compares with the loop's ``perf_counter_ns()`` directly.
:func:`check_clocks` says so or raises.

Seqlock (single writer; any number of readers, each with its own :class:`Sample`):

* the writer stores seq + 1 (odd), copies the fields, stores ``t_ns``, stores seq + 2;
* a reader loads seq; equal to the one it holds: nothing new, it returns False at once;
  odd: the writer is inside, retry; else it copies seq..end into a scratch buffer,
  loads seq again, and keeps the copy only if seq did not move (then one more copy into
  its :class:`Sample`, whose previous contents stay intact on failure).  After
  ``retries`` failed attempts (a writer that keeps writing, or a dead writer that left
  seq odd) it returns False, "no new sample": never spins forever, never blocks.

Memory model: numpy/memoryview stores to the segment are plain 8-byte aligned stores
(seq is never torn itself).  On x86-64 (TSO: stores are seen in program order, loads
are not reordered with older loads) the protocol above is correct as written.  On
aarch64 a real seqlock needs barriers (``dmb ishst`` between the writer's stores,
``dmb ishld`` between the reader's loads); pure Python has no fence instruction, so
there the seq re-check is a strong mitigation, not a proof: between two stores of the
writer (or loads of the reader) the interpreter runs hundreds of instructions,
including the atomic operations of its own bookkeeping, so the window in which the
CPU could reorder across them is tiny, and a torn copy that the re-check does catch
costs one retry (a few hundred ns).  A reader that still cannot get a stable copy after
``retries`` attempts reports "no new sample" and the caller judges freshness by the
time stamp of the sample it has, exactly as for a late device.  Where an undetected
tear would matter, put a fence in C (a one-line cffi/ctypes helper calling
``atomic_thread_fence``) into :meth:`Mailbox.publish` and :meth:`Mailbox.read_into`.

Allocation: the read path copies with memoryview slice assignment (memcpy) between
buffers made at construction; nothing numpy is allocated per read.  (Python itself
still creates int objects for seq values above 256; that is the interpreter's, not
ours, and costs tens of ns.)

The owner (:meth:`Mailbox.create`) unlinks the segment at :meth:`Mailbox.close`; a
process that attaches (:meth:`Mailbox.attach`) only unmaps it.  Segment names start with
``mmctl-`` so a leak is easy to find in ``/dev/shm``.
"""

from __future__ import annotations

import os
import secrets
import select
import sys
import time
import zlib
from dataclasses import dataclass
from enum import Enum
from multiprocessing import shared_memory
from multiprocessing.reduction import DupFd
from types import TracebackType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self

__all__ = ["HEADER_BYTES", "Mailbox", "MailboxLayout", "Sample", "Wake", "WakeKind",
           "check_clocks", "now_ns"]

HEADER_BYTES = 24
"""fingerprint, seq, t_ns: three int64 before the fields."""
DEFAULT_RETRIES = 8
"""Attempts of one read before it reports "no new sample" (see the module doc)."""
NAME_PREFIX = "mmctl-"

now_ns = time.monotonic_ns
"""The mailbox clock: CLOCK_MONOTONIC [ns], the same as ``time.perf_counter_ns`` on Linux."""


def check_clocks() -> None:
    """Raise RuntimeError unless ``monotonic`` and ``perf_counter`` are one system-wide
    clock (Linux: both ``clock_gettime(CLOCK_MONOTONIC)``), as the time stamps need."""
    mono = time.get_clock_info("monotonic").implementation
    perf = time.get_clock_info("perf_counter").implementation
    if mono != perf or "CLOCK_MONOTONIC" not in mono:
        raise RuntimeError(f"mailbox time stamps need one CLOCK_MONOTONIC for monotonic and "
                           f"perf_counter; this platform has {mono!r} and {perf!r}")


@dataclass(frozen=True)
class MailboxLayout:
    """The fields of one mailbox record, float64 each: ``((name, count), ...)``.

    name: what the record is (in messages and the fingerprint); fields: ``(name, n)``
    pairs, n >= 1 float64 values each, in memory order.  Integers up to 2**53 (device
    sequence numbers, status words, error codes) are exact in a float64.
    """

    name: str
    fields: tuple[tuple[str, int], ...]

    def __post_init__(self) -> None:
        names = [f for f, _ in self.fields]
        if not self.fields:
            raise ValueError(f"mailbox layout {self.name!r} has no fields")
        if len(set(names)) != len(names):
            raise ValueError(f"mailbox layout {self.name!r}: field names repeat: {names}")
        for field, n in self.fields:
            if not field.isidentifier() or not (isinstance(n, int) and n >= 1):
                raise ValueError(f"mailbox layout {self.name!r}: field ({field!r}, {n!r}) must "
                                 "be an identifier and a count >= 1")

    @property
    def width(self) -> int:
        """How many float64 values a record holds."""
        return sum(n for _, n in self.fields)

    @property
    def nbytes(self) -> int:
        """Size of the shared segment [bytes]: header + fields."""
        return HEADER_BYTES + 8 * self.width

    @property
    def fingerprint(self) -> int:
        """crc32 of the name and fields: a reader of another layout is refused at attach."""
        return zlib.crc32(repr((self.name, self.fields)).encode())

    def slice(self, field: str) -> slice:
        """Where ``field`` sits among the values (index into ``Sample.values``)."""
        start = 0
        for name, n in self.fields:
            if name == field:
                return slice(start, start + n)
            start += n
        raise KeyError(f"mailbox layout {self.name!r} has no field {field!r}; it has "
                       f"{[f for f, _ in self.fields]}")

    def index(self, field: str) -> int:
        """The index of a one-value field among the values."""
        s = self.slice(field)
        if s.stop - s.start != 1:
            raise KeyError(f"field {field!r} of {self.name!r} holds {s.stop - s.start} values")
        return int(s.start)


class Sample:
    """A reader's own copy of one record (preallocated; :meth:`Mailbox.read_into` fills it).

    ``values``: (layout.width,) float64 view of the fields; ``view(name)`` one field's
    view (both stay valid: reads copy into them); ``fields``: the same values as a
    memoryview of doubles, whose items are plain floats (on a path that must be cheap
    when the caches are cold, numpy's scalar indexing costs tens of us, this does not).
    seq 0 means "nothing read yet".
    """

    __slots__ = ("_buf", "_mv", "_q", "_views", "fields", "layout", "values")

    def __init__(self, layout: MailboxLayout) -> None:
        self.layout = layout
        self._buf = bytearray(layout.nbytes - 8)  # seq, t_ns, fields
        self._mv = memoryview(self._buf)
        self._q = self._mv[:16].cast("q")
        self.values: NDArray[np.float64] = np.frombuffer(self._buf, np.float64, offset=16)
        self.fields = self._mv[16:].cast("d")
        self._views = {name: self.values[layout.slice(name)] for name, _ in layout.fields}

    @property
    def seq(self) -> int:
        """The writer's sequence of this copy (even; 0: nothing read yet)."""
        return int(self._q[0])

    @property
    def t_ns(self) -> int:
        """The record's time stamp [ns, CLOCK_MONOTONIC]."""
        return int(self._q[1])

    def view(self, field: str) -> NDArray[np.float64]:
        """The (n,) view of ``field`` inside :attr:`values`."""
        return self._views[field]

    def __getitem__(self, field: str) -> float:
        """A one-value field as a float."""
        return float(self.values[self.layout.index(field)])


class Mailbox:
    """One record in shared memory, one writer (see module doc).

    Build with :meth:`create` (the owner: unlinks at close) or :meth:`attach` (another
    process, by :attr:`name`).  Writer: fill :attr:`staging`, call :meth:`publish`.
    Reader: :meth:`read_into` a :class:`Sample` of its own.
    """

    def __init__(self, shm: shared_memory.SharedMemory, layout: MailboxLayout,
                 owner: bool) -> None:
        self.layout = layout
        self._shm: shared_memory.SharedMemory | None = shm
        self._owner = owner
        n = layout.nbytes
        buf = shm.buf
        assert buf is not None
        self._whole = buf[:n]
        self._q = self._whole.cast("q")  # [fingerprint, seq, t_ns, ...]
        self._src = self._whole[8:]  # seq, t_ns, fields: what a reader copies
        self._dst = self._whole[HEADER_BYTES:]  # the fields: where a writer copies
        self.staging: NDArray[np.float64] = np.zeros(layout.width)
        """The writer's next record: fill it, then :meth:`publish` copies it in."""
        self._stage = memoryview(self.staging.data).cast("B")
        self._scratch = bytearray(n - 8)
        self._scratch_mv = memoryview(self._scratch)
        self._scratch_q = self._scratch_mv[:8].cast("q")
        self._seq = int(self._q[1])
        self.torn = 0
        """Reads that found the writer inside (retried): a figure for benchmarks."""
        self.busy = 0
        """Reads that gave up after ``retries`` attempts."""

    @classmethod
    def create(cls, layout: MailboxLayout) -> Mailbox:
        """A new zeroed segment ``mmctl-<layout>-<pid>-<random>``; this object owns it."""
        name = f"{NAME_PREFIX}{layout.name}-{os.getpid()}-{secrets.token_hex(4)}"
        shm = shared_memory.SharedMemory(name=name, create=True, size=layout.nbytes)
        box = cls(shm, layout, owner=True)
        box._whole[:] = bytes(layout.nbytes)
        box._q[0] = layout.fingerprint
        return box

    @classmethod
    def attach(cls, name: str, layout: MailboxLayout) -> Mailbox:
        """Map the segment ``name`` made by another process with the same ``layout``.

        Raises FileNotFoundError when there is no such segment and ValueError when it is
        too small or was made for another layout."""
        if sys.version_info >= (3, 13):  # the owner's resource tracker entry is enough
            shm = shared_memory.SharedMemory(name=name, track=False)
        else:  # registers the name again: harmless, the tracker keeps a set
            shm = shared_memory.SharedMemory(name=name)
        if shm.size < layout.nbytes:
            shm.close()
            raise ValueError(f"mailbox {name} has {shm.size} bytes, layout {layout.name!r} "
                             f"needs {layout.nbytes}")
        box = cls(shm, layout, owner=False)
        if int(box._q[0]) != layout.fingerprint:
            found = int(box._q[0])
            box.close()
            raise ValueError(f"mailbox {name} was made for another layout (fingerprint "
                             f"{found:#x}, {layout.name!r} is {layout.fingerprint:#x})")
        return box

    @property
    def name(self) -> str:
        """The segment's name (what :meth:`attach` takes)."""
        if self._shm is None:
            raise ValueError(f"mailbox {self.layout.name!r} is closed")
        return str(self._shm.name)

    @property
    def closed(self) -> bool:
        return self._shm is None

    # -- writer ------------------------------------------------------------------------

    def publish(self, t_ns: int) -> int:
        """Copy :attr:`staging` in, time-stamped ``t_ns`` [ns, CLOCK_MONOTONIC]; returns
        the new seq.  Never blocks.  One writer per mailbox."""
        q = self._q
        seq = self._seq
        q[1] = seq + 1  # odd: readers retry
        self._dst[:] = self._stage
        q[2] = t_ns
        q[1] = seq + 2  # stable again, the new record
        self._seq = seq + 2
        return seq + 2

    # -- reader ------------------------------------------------------------------------

    def seq(self) -> int:
        """The writer's current seq (odd while it writes); no copy."""
        return int(self._q[1])

    def read_into(self, out: Sample, retries: int = DEFAULT_RETRIES) -> bool:
        """Copy the newest record into ``out`` if it is newer than ``out``'s.

        True: ``out`` holds a new, consistent record.  False: nothing new, or no stable
        copy in ``retries`` attempts; ``out`` is unchanged.  Never blocks.
        """
        q = self._q
        have = out._q[0]
        for _ in range(retries):
            seq = q[1]
            if seq == have:
                return False
            if seq & 1:
                self.torn += 1
                continue
            self._scratch_mv[:] = self._src
            if q[1] == seq and self._scratch_q[0] == seq:
                out._mv[:] = self._scratch_mv
                return True
            self.torn += 1
        self.busy += 1
        return False

    # -- lifecycle ---------------------------------------------------------------------

    def close(self) -> None:
        """Unmap; the owner also unlinks the segment.  Safe to call twice."""
        shm, self._shm = self._shm, None
        if shm is None:
            return
        for mv in (self._q, self._src, self._dst, self._whole):
            mv.release()
        shm.close()
        if self._owner:
            try:
                shm.unlink()
            except FileNotFoundError:  # someone else removed it: the goal is met
                pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


class WakeKind(Enum):
    """How a writer wakes the process that waits for its commands (see docs/mailbox.md)."""

    EVENTFD = "eventfd"
    PIPE = "pipe"


class Wake:
    """A wake-up from one process to another: ``notify()`` here, ``wait()`` there.

    EVENTFD (the default; chosen in docs/mailbox.md): one non-blocking eventfd, whose
    8-byte counter coalesces notifications (a waiter that was slow sees one wake-up,
    never a full buffer).  PIPE: a non-blocking pipe, one byte per notify (a full pipe
    drops the byte: the waiter is awake anyway).  The object pickles into a ``spawn``
    child's arguments (the fds are passed as the child's own).  The notifier publishes
    into the mailbox first, then notifies; the waiter reads the mailbox after ``wait``.
    """

    def __init__(self, kind: WakeKind = WakeKind.EVENTFD,
                 fds: tuple[int, int] | None = None) -> None:
        self.kind = kind
        if fds is not None:
            self._r, self._w = fds
        elif kind is WakeKind.EVENTFD:
            fd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
            self._r = self._w = fd
        else:
            self._r, self._w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._open = True

    def fileno(self) -> int:
        """The fd a waiter may put in its own select/poll (readable = woken)."""
        return self._r

    def notify(self) -> None:
        """Wake the waiter; never blocks."""
        try:
            if self.kind is WakeKind.EVENTFD:
                os.eventfd_write(self._w, 1)
            else:
                os.write(self._w, b"\x01")
        except BlockingIOError:  # counter/pipe full: the waiter has a wake-up pending
            pass

    def wait(self, timeout: float | None) -> bool:
        """Block up to ``timeout`` [s] (None: forever) for a notify; True if woken (the
        pending wake-ups are consumed)."""
        ready, _, _ = select.select([self._r], [], [], timeout)
        if not ready:
            return False
        self.clear()
        return True

    def clear(self) -> None:
        """Consume pending wake-ups without waiting."""
        try:
            if self.kind is WakeKind.EVENTFD:
                os.eventfd_read(self._r)
            else:
                while os.read(self._r, 4096):
                    pass
        except BlockingIOError:
            pass

    def close(self) -> None:
        """Close the fds; safe to call twice."""
        if not self._open:
            return
        self._open = False
        os.close(self._r)
        if self._w != self._r:
            os.close(self._w)

    def __reduce__(self) -> tuple[Any, ...]:
        if self.kind is WakeKind.EVENTFD:
            return (_rebuild_wake, (self.kind.value, DupFd(self._r), None))
        return (_rebuild_wake, (self.kind.value, DupFd(self._r), DupFd(self._w)))


def _rebuild_wake(kind: str, r: Any, w: Any) -> Wake:
    rfd = r.detach()
    wfd = rfd if w is None else w.detach()
    return Wake(WakeKind(kind), fds=(rfd, wfd))
