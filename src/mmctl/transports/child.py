"""A device link's child process, both sides (the arm's, the sensor's, the base's).

In the child, :func:`start_device_child` comes first: leave the terminal's session, so
that a terminal's Ctrl-C reaches the daemon only; ignore the terminating signals, since
the daemon sends its stop commands through the child and then ends it; log as the
daemon does; take the loop's real-time priority and CPUs (before the transport
connects: its threads inherit them).

In the parent, :class:`LinkProcess` is what the three links share: the ``spawn`` child
with its duplex pipe (and a side pipe for the details of errors, if the link has one),
the connect handshake, the exit handler, the child's end, the details messages."""

from __future__ import annotations

import atexit
import multiprocessing
import os
import select
import signal
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from mmctl.errors import FaultCause, LinkLost, MmctlError, TransportError

if TYPE_CHECKING:
    from types import TracebackType

    from typing_extensions import Self

Described = tuple[str, str | None, dict[str, Any], str]
"""An exception as plain data for the pipe: (kind, cause, details, message)."""

GoneT = TypeVar("GoneT", bound=MmctlError)


def start_device_child(log_setup: tuple[str, bool | None],
                       realtime: tuple[int, Sequence[int]] | None = None) -> None:
    """In a device link's child, before anything else (see the module doc)."""
    try:
        os.setsid()
    except OSError:
        pass
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"):
        signal.signal(getattr(signal, name), signal.SIG_IGN)
    from mmctl.runtime.logging import setup_logging

    setup_logging(log_setup[0], json=log_setup[1])
    if realtime is not None:
        from mmctl.runtime.loop import apply_realtime

        apply_realtime(realtime[0], tuple(realtime[1]))


class _Part(Protocol):
    """What the parent owns beside the child and unlinks or closes at the end (a
    :class:`~mmctl.runtime.mailbox.Mailbox`, a :class:`~mmctl.runtime.mailbox.Wake`)."""

    def close(self) -> None: ...


def end_child(proc: Any, conn: Any, timeout: float, kill_wait: float) -> None:
    """Wait ``timeout`` [s] for the child to end, else kill it (and wait ``kill_wait``);
    close the parent's end of its pipe."""
    proc.join(timeout)
    if proc.is_alive():
        proc.kill()
        proc.join(kill_wait)
    conn.close()


class LinkProcess(ABC, Generic[GoneT]):
    """The parent's side of a device link's child process (see the module doc).

    A subclass creates its shared-memory parts and calls :meth:`_start`, whose
    ``install`` takes the child's "connected" reply under ``_lock``; its ``close`` calls
    :meth:`_close_child`.  ``_gone`` is the exception of a child that ended (GoneT);
    ``_details`` the details messages taken from the child, by id.

    close_timeout: [s] for the child to end after ``close`` or a failed connect (and to
    die once killed)."""

    _ENDED_EARLY = " before it connected"
    """Said after "ended (exit code N)" of a child that ended before its answer."""

    def __init__(self, close_timeout: float) -> None:
        self._close_timeout = close_timeout
        self._proc: Any = None
        self._conn: Any = None  # the duplex pipe: connect's answer, requests, "close"
        self._events: Any = None  # where the details come: _conn, or a pipe of their own
        self._parts: tuple[_Part, ...] = ()
        self._poller = select.poll()
        self._details: dict[int, tuple[int, Described]] = {}
        self._gone: GoneT | None = None
        self._lock = threading.Lock()

    @property
    def pid(self) -> int | None:
        """The child's process id (None before connect)."""
        return None if self._proc is None else int(self._proc.pid)

    @abstractmethod
    def connect(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    # -- what a link says of itself --------------------------------------------------------

    @abstractmethod
    def _who(self) -> str:
        """The child as its start's errors name it ("F/T sensor <link>: the link process")."""

    @abstractmethod
    def _refused(self, reply: tuple[Any, ...]) -> MmctlError:
        """The exception of the child's ("error", ...) reply to connect."""

    @abstractmethod
    def _child_ended(self, exit_code: int | None) -> GoneT:
        """The exception of a child that ended (its pipe closed); logs it if the link does."""

    @abstractmethod
    def _detach(self) -> None:
        """Forget the shared-memory parts (under ``_lock``, at close)."""

    # -- lifecycle ---------------------------------------------------------------------

    def _start(self, target: Callable[..., None], args: tuple[Any, ...], name: str,
               parts: tuple[_Part, ...], wait: float,
               install: Callable[[tuple[Any, ...]], None], *,
               side_pipe: bool = False) -> None:
        """Start ``target(conn, [events,] *args)`` in a ``spawn`` child named ``name``;
        take the details messages it sends first, then wait up to ``wait`` [s] in all
        for its ("connected", ...) reply, which ``install`` takes under ``_lock``.  On
        ("error", ...), silence or its end, the child is ended, ``parts`` are closed, and
        :meth:`_refused` or TransportError raised.  side_pipe: the details come on a
        pipe of their own (else on the duplex pipe)."""
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe(duplex=True)
        events: Any = parent
        ends: tuple[Any, ...] = (child,)
        if side_pipe:
            events, events_w = ctx.Pipe(duplex=False)
            ends = (child, events_w)
        proc = ctx.Process(target=target, args=(*ends, *args), name=name, daemon=True)

        def discard() -> None:
            end_child(proc, parent, self._close_timeout, self._close_timeout)
            if events is not parent:
                events.close()
            _close_all(parts)

        try:
            proc.start()
        except BaseException:
            _close_all(parts)
            raise
        for end in ends:
            end.close()
        self._details.clear()
        ended: str | None = None
        try:
            reply: tuple[Any, ...] = ("detail",)
            while reply[0] == "detail":  # details of a first sample's fault come first
                if not parent.poll(wait):
                    raise TransportError(f"{self._who()} did not report within {wait:g} s")
                reply = parent.recv()
                self._take(reply)
        except (EOFError, OSError):
            ended = f"{self._who()} ended (exit code {proc.exitcode}){self._ENDED_EARLY}"
            reply = ("error",)
        except BaseException:
            discard()
            raise
        if reply[0] != "connected":
            discard()
            raise TransportError(ended) if ended is not None else self._refused(reply)
        poller = select.poll()
        poller.register(events.fileno(), select.POLLIN)
        with self._lock:  # a read on another thread sees all of it or none
            self._proc, self._conn, self._events, self._parts = proc, parent, events, parts
            self._poller = poller
            self._gone = None
            install(reply)
        # before multiprocessing's own exit handler, which joins daemonic children
        # without a timeout (the child ignores SIGTERM): a process that never closed the
        # link still exits, and its segments go
        atexit.register(self.close)

    def _close_child(self, wait: float | None = None, answer: float = 0.0) -> Any:
        """Ask the child to end (("close",); then wait up to ``answer`` [s] for its reply
        if > 0); kill it if it has not ended within ``wait`` [s] (default: the close
        timeout); close the parts, also after the child died.  Returns the ended process
        (None: there was none).  Safe to call twice."""
        with self._lock:  # not under a read on another thread
            proc, conn, events, parts = self._proc, self._conn, self._events, self._parts
            self._proc = self._conn = self._events = None
            self._parts = ()
            self._detach()
        if proc is None:
            return None
        atexit.unregister(self.close)
        try:
            try:
                conn.send(("close",))
                if answer > 0:
                    conn.poll(answer)  # its "closed", or the pipe closing, or nothing
            except (EOFError, OSError):
                pass
            end_child(proc, conn, self._close_timeout if wait is None else wait,
                      self._close_timeout)
            if events is not conn:
                events.close()
        finally:
            _close_all(parts)
        return proc

    def _restart(self, link: str, cause: FaultCause,
                 then: Callable[[], object] | None = None) -> None:
        """End the child, start a new one (and run ``then``); a TransportError but a
        LinkLost is raised as LinkLost(``link``, ``cause``, "reconnect failed: ...")."""
        self.close()
        try:
            self.connect()
            if then is not None:
                then()
        except LinkLost:
            raise
        except TransportError as exc:
            raise LinkLost(link, cause, f"reconnect failed: {exc}") from exc

    # -- the child's messages --------------------------------------------------------------

    def _check_child(self) -> None:
        """Take the details messages; a closed pipe is a child that ended."""
        if self._gone is not None or self._events is None:
            return
        try:
            while self._poller.poll(0):  # (Connection.poll builds a selector per call)
                self._take(self._events.recv())
        except (EOFError, OSError):
            proc = self._proc
            if proc is not None:
                proc.join(0)  # reap it if it has ended (never waits), for its exit code
            self._gone = self._child_ended(None if proc is None else proc.exitcode)

    def _take(self, msg: tuple[Any, ...]) -> None:
        if msg[0] == "detail":
            _, ident, code, data = msg
            self._details[ident] = (code, data)
            for old in [k for k in self._details if k < ident - 8]:
                del self._details[old]


def _close_all(parts: tuple[_Part, ...]) -> None:
    for part in parts:
        part.close()
