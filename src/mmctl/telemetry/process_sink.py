"""The rerun sink in a child process, so rerun's work leaves the loop's interpreter.

``Chunk.from_record_batch`` and ``send_chunks`` hold the GIL for 20-400 us per call,
and rerun's encoder threads share the caches of the process; in the daemon's process
they slowed the control loop measurably (`mmctl bench loop --telemetry`).  With
:class:`ProcessSink` the publisher thread only batches the samples into numpy columns
and 3-D frames and pickles them down a pipe; a child process (``spawn``: a fresh
interpreter) owns a :class:`~mmctl.telemetry.rerun_sink.RerunSink` and does the Arrow
encoding and every rerun call.

Protocol on the pipe (parent -> child): ``("write", columns, scene)``,
``("event", event)``, ``("close",)``; child -> parent: ``("ready",)`` after the
destinations are open, ``("closed",)`` after the last flush, or ``("error", text)``
(then the child exits).  The child ignores SIGINT/SIGTERM (a Ctrl-C or systemd's stop
reaches the whole process group): the daemon closes it after its own stop commands,
so the recording is complete; it exits by itself when the parent goes away.  It runs
at ``nice +10``: on a machine with few cores the loop thread, waking up for its next
cycle, then takes the CPU from it at once.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any

import structlog

from mmctl.config.base import MecanumConfig
from mmctl.telemetry.batch import Columns
from mmctl.telemetry.events import Event
from mmctl.telemetry.rerun_sink import Destinations, TelemetryError
from mmctl.telemetry.scene import SceneFrame

log = structlog.get_logger("mmctl.telemetry")

NICE = 10  #: the child's niceness increment (a process may always lower its priority)


class ProcessSink:
    """A :class:`~mmctl.telemetry.publisher.Sink` whose rerun side runs in a child process.

    Same arguments as :class:`~mmctl.telemetry.rerun_sink.RerunSink`; start_timeout:
    how long :meth:`open` waits for the child to open the destinations [s];
    close_timeout: how long :meth:`close` waits for the last flush [s].
    """

    def __init__(self, destinations: Destinations, recording_name: str = "mmctl",
                 static: dict[str, float | int | str] | None = None,
                 mecanum: MecanumConfig | None = None, start_timeout: float = 60.0,
                 close_timeout: float = 30.0):
        self.destinations = destinations
        self._args = (destinations, recording_name, dict(static or {}), mecanum)
        self.start_timeout = start_timeout
        self.close_timeout = close_timeout
        self._conn: Connection | None = None
        self._proc: Any = None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    # -- lifecycle ------------------------------------------------------------------
    def open(self) -> None:
        """Start the child and wait until it has opened the destinations."""
        if self._proc is not None:
            return
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=_serve, args=(child, *self._args), name="mmctl-telemetry",
                           daemon=True)
        proc.start()
        child.close()
        self._conn, self._proc = parent, proc
        try:
            if not parent.poll(self.start_timeout):
                raise TelemetryError(f"the telemetry process did not start within "
                                     f"{self.start_timeout:g} s")
            reply = parent.recv()
        except (EOFError, OSError) as exc:
            self._kill()
            raise TelemetryError(f"the telemetry process exited at start "
                                 f"(code {proc.exitcode})") from exc
        except TelemetryError:
            self._kill()
            raise
        if reply[0] != "ready":
            self._kill()
            raise TelemetryError(str(reply[1]) if len(reply) > 1 else repr(reply))

    def close(self) -> None:
        """Last flush in the child, then end it (idempotent); a child error re-raised."""
        conn, proc = self._conn, self._proc
        if proc is None or conn is None:
            return
        error = None
        try:
            conn.send(("close",))
            while True:
                if not conn.poll(self.close_timeout):
                    error = f"no flush within {self.close_timeout:g} s"
                    break
                reply = conn.recv()
                if reply[0] == "closed":
                    break
                if reply[0] == "error":
                    error = str(reply[1])
                    break
        except (EOFError, OSError) as exc:
            error = f"the telemetry process went away ({exc!r}, code {proc.exitcode})"
        finally:
            proc.join(5.0)
            self._kill()
        if error is not None:
            raise TelemetryError(f"telemetry process: {error}")

    def _kill(self) -> None:
        proc, self._proc = self._proc, None
        conn, self._conn = self._conn, None
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(5.0)
        if conn is not None:
            conn.close()

    # -- what the publisher calls -------------------------------------------------------
    def write(self, columns: Sequence[Columns],
              scene: tuple[int, float, SceneFrame] | None = None,
              pace: Callable[[], None] | None = None) -> None:
        """Hand column batches and an optional 3-D frame to the child (one pickle)."""
        if pace is not None:
            pace()
        self._send(("write", list(columns), scene))

    def write_event(self, event: Event) -> None:
        self._send(("event", event))

    def _send(self, msg: tuple[Any, ...]) -> None:
        conn = self._conn
        if conn is None:
            raise TelemetryError("the telemetry process is not running")
        try:
            if conn.poll():  # the child only speaks when it fails (or, at EOF, is gone)
                reply = conn.recv()
                raise TelemetryError(
                    f"telemetry process: {reply[1] if len(reply) > 1 else reply}")
            conn.send(msg)
        except (EOFError, OSError) as exc:
            raise TelemetryError(f"the telemetry process went away ({exc!r})") from exc


def _serve(conn: Connection, destinations: Destinations, recording_name: str,
           static: dict[str, float | int | str], mecanum: MecanumConfig | None) -> None:
    """The child: a RerunSink driven by the pipe."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.nice(NICE)  # background work: the control loop wins the CPU when it wakes up
    from mmctl.telemetry.rerun_sink import RerunSink

    sink = RerunSink(destinations, recording_name=recording_name, static=static,
                     mecanum=mecanum)
    try:
        sink.open()
        conn.send(("ready",))
        while True:
            try:
                msg = conn.recv()
            except EOFError:  # the parent is gone: flush what we have and leave
                sink.close()
                return
            kind = msg[0]
            if kind == "write":
                sink.write(msg[1], msg[2])
            elif kind == "event":
                sink.write_event(msg[1])
            elif kind == "close":
                sink.close()
                conn.send(("closed",))
                return
            else:
                raise TelemetryError(f"unknown telemetry message {kind!r}")
    except Exception as exc:  # noqa: BLE001 -- reported to the parent, then exit
        try:
            conn.send(("error", repr(exc)))
        except OSError:
            pass
        try:
            sink.close()
        except Exception as close_exc:  # noqa: BLE001 -- the error above is the news
            log.warning("telemetry_child_close_failed", error=repr(close_exc))
    finally:
        conn.close()
