"""The control socket served from a process of its own (``daemon.socket_process``).

Measured with ``tools/ipc_flood.py`` (issue 17), a thousand clients connecting at once
cost the loop deadlines even with every limit of :mod:`mmctl.runtime.ipc` in place:
accepting, reading, evicting and answering them is Python work on the interpreter the
500 Hz loop runs on, and each of its slices is a slice the loop waits for the GIL.  So
the daemon keeps only the listening socket's file and hands the socket to a child
process, the *gateway*, which runs the whole :class:`~mmctl.runtime.ipc.ControlServer`
(connections, credentials, limits, rates, parsing, evictions) on its own interpreter
and passes the daemon complete, parsed, rate-limited requests over one private
connection (a socket pair), one JSON line each, answered by id:

* the daemon's side (:class:`ProcessControlServer`) is one reader thread: ``status``
  is answered on it from the daemon's snapshot (``inline``), ``stop`` and ``disable`` on
  two threads of their own (``urgent``), everything else on the worker threads, as in
  the socket's own process-less form;
* the gateway runs ``status`` on a small pool of its own (never behind a blocking
  ``enable``) and *shares* it: a reply from a round trip started at most
  :data:`STATUS_SHARE` (20 ms) before a request arrived answers it too, unless another
  command's reply came in between (so a status right after a command shows its
  effect); however many clients ask, the daemon answers at most 50 ``status`` a second
  from the gateway (its own snapshot is at most 100 ms old, and rebuilt at once on a
  change of state);
* the daemon holds the listening socket: a gateway that dies (a crash included) leaves
  new clients waiting in the listen backlog while the daemon starts another one
  (``ipc_process_restarted``); the daemon never stops serving;
* the gateway ignores the terminal's and the service manager's stop signals and ends
  when the daemon closes its end (a daemon killed outright included), so the daemon
  answers ``stop`` until it has stopped the robot.

Its CPU is not the loop's: on the robot it runs off the loop's CPUs
(``loop.cpu_affinity``), like the simulated robot.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import structlog

from mmctl.errors import MmctlError
from mmctl.runtime.ipc import (
    ControlServer,
    Handler,
    IpcLimits,
    Peer,
    _Workers,
    bind_control_socket,
    call_handler,
    encode_reply,
)

log = structlog.get_logger("mmctl.ipc")

START_TIMEOUT = 30.0
"""[s] for a gateway to report (a Python start on a loaded machine)."""
RESTART_PAUSE = (0.2, 5.0)
"""[s] before starting a gateway again after one ended: the first pause, the longest
(doubling while each lives less than 10 s)."""
STATUS_SHARE = 0.02
"""[s] a status reply is shared with the requests arriving this long after its round trip
started (unless a command's reply came in between): however many clients ask, the
daemon answers at most 1 / STATUS_SHARE status requests a second from the gateway."""
REPLY_WAIT = 30.0
"""[s] the gateway waits for the daemon's reply to a request without ``timeout_s``."""
SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT")
                if hasattr(signal, n))


class ProcessControlServer:
    """The daemon's side of a control socket served by a gateway process.

    The same interface as :class:`~mmctl.runtime.ipc.ControlServer` (``open``,
    ``start``, ``close``, ``path``): ``handler``, ``inline``, ``urgent``, ``limits`` and
    ``mode`` mean what they mean there; ``log_setup``: (level, json) for the gateway's
    structlog (the daemon's own); ``cpus``: the CPUs the gateway may run on (empty:
    any).
    """

    def __init__(self, path: Path | str, handler: Handler, mode: int = 0o660, *,
                 limits: IpcLimits | None = None, inline: Iterable[str] = (),
                 urgent: Iterable[str] = (), log_setup: tuple[str, bool | None] = ("info", None),
                 cpus: Sequence[int] = ()):
        self.path = Path(path)
        self.mode = mode
        self.limits = limits if limits is not None else IpcLimits()
        self.inline = frozenset(inline)
        self.urgent = frozenset(urgent)
        self.log_setup = log_setup
        self.cpus = tuple(cpus)
        self._handler = handler
        self._listen: socket.socket | None = None
        self._inode: int | None = None
        self._closing = threading.Event()
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._workers: _Workers | None = None
        self._urgent_worker: _Workers | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._backend: socket.socket | None = None
        self._first: socket.socket | None = None
        """the connection to the process :meth:`open` started (taken by the reader)"""
        self._send_lock = threading.Lock()
        self._enc_obj: object = None
        self._enc_line = b""
        self.requests = 0
        self.errors = 0
        #: gateways started (1 + restarts)
        self.started = 0

    @property
    def pid(self) -> int | None:
        """The gateway's process id (None when none runs)."""
        proc = self._proc
        return None if proc is None or proc.poll() is not None else proc.pid

    def open(self) -> None:
        """Bind the socket (refuse if a live daemon owns it, replace a stale file) and
        start the socket's process: its start-up (an interpreter, its imports) then
        overlaps the devices' connection, not the loop's first cycles.  Requests wait
        in the private connection until :meth:`start`."""
        self._listen = bind_control_socket(self.path, self.mode, self.limits.backlog)
        self._inode = self.path.stat().st_ino
        try:
            self._first = self._spawn()
        except OSError as exc:
            log.error("ipc_process_start_failed", error=str(exc), why="started again by start()")

    def start(self, timeout: float = START_TIMEOUT) -> None:
        """Start the gateway, the reader thread and the workers; wait (at most
        ``timeout``) until the gateway serves (clients connecting earlier wait in the
        listen backlog)."""
        if self._listen is None:
            self.open()
        self._workers = _Workers(max(1, self.limits.workers), "mmctl-ipc-worker")
        self._urgent_worker = _Workers(2, "mmctl-ipc-urgent")
        self._thread = threading.Thread(target=self._serve, name="mmctl-ipc", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            log.error("ipc_process_slow", seconds=timeout,
                      why="clients wait in the listen backlog until it serves")

    def close(self) -> None:
        """End the gateway (it ends when its connection closes; killed if it does not
        within 2 s), stop the reader, close the socket and remove its file (if ours)."""
        if self._listen is None:
            return
        self._closing.set()
        backend = self._backend
        if backend is not None:
            try:
                backend.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        _end(self._proc)
        if self._first is not None:  # started by open(), never taken by a reader
            self._first.close()
            self._first = None
        if self._thread is not None:
            self._thread.join(2.0)
        for w in (self._workers, self._urgent_worker):
            if w is not None:
                w.close()
        self._listen.close()
        self._listen = None
        try:
            if self.path.stat().st_ino == self._inode:
                self.path.unlink()
        except FileNotFoundError:
            pass

    # -- the reader thread -----------------------------------------------------------------
    def _serve(self) -> None:
        pause = RESTART_PAUSE[0]
        while not self._closing.is_set():
            began = time.monotonic()
            try:
                backend, self._first = self._first or self._spawn(), None
            except OSError as exc:
                log.error("ipc_process_start_failed", error=str(exc))
            else:
                try:
                    self._read(backend)
                except Exception as exc:  # a bug here must not end control
                    log.exception("ipc_process_link_error", error=repr(exc))
                finally:
                    self._backend = None
                    backend.close()
            if self._closing.is_set():
                break
            code = _end(self._proc)
            pause = RESTART_PAUSE[0] if time.monotonic() - began > 10.0 else min(
                2 * pause, RESTART_PAUSE[1])
            log.error("ipc_process_ended", exit_code=code, restart_in_s=pause,
                      why="clients wait in the listen backlog meanwhile")
            self._closing.wait(pause)

    def _spawn(self) -> socket.socket:
        assert self._listen is not None
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            level, json_logs = self.log_setup
            cmd = [sys.executable, "-m", "mmctl.runtime.ipc_process",
                   "--listen-fd", str(self._listen.fileno()), "--backend-fd", str(theirs.fileno()),
                   "--path", str(self.path), "--limits", json.dumps(dataclasses.asdict(self.limits)),
                   "--log-level", level,
                   "--log-format", {True: "json", False: "console", None: "auto"}[json_logs]]
            if self.cpus:
                cmd += ["--cpus", ",".join(map(str, self.cpus))]
            sys.stdout.flush()
            # its own session: a terminal's Ctrl-C reaches only the daemon
            self._proc = subprocess.Popen(cmd, pass_fds=(self._listen.fileno(), theirs.fileno()),
                                          start_new_session=True, stdin=subprocess.DEVNULL)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self.started += 1
        self._backend = ours
        return ours

    def _read(self, backend: socket.socket) -> None:
        rfile = backend.makefile("rb")
        try:
            hello = rfile.readline()
            if not hello:
                return
            if self.started > 1:
                log.warning("ipc_process_restarted", pid=self.pid, starts=self.started)
            else:
                log.info("ipc_process_started", pid=self.pid, socket=str(self.path))
            self._ready.set()
            for line in rfile:
                self._dispatch(backend, line)
        finally:
            rfile.close()

    def _dispatch(self, backend: socket.socket, line: bytes) -> None:
        try:
            msg = json.loads(line)
            rid, peer, req = int(msg["id"]), Peer(*msg["peer"]), msg["req"]
            cmd = req["cmd"]
        except (ValueError, KeyError, TypeError) as exc:  # the gateway is ours: a bug
            log.error("ipc_process_bad_message", error=repr(exc), line=line[:80])
            return
        self.requests += 1
        if cmd in self.inline:
            self._answer(backend, rid, call_handler(self._handler, req, peer), cache=True)
            return
        workers = self._urgent_worker if cmd in self.urgent else self._workers
        assert workers is not None

        def job() -> None:
            self._answer(backend, rid, call_handler(self._handler, req, peer))

        workers.submit(job)

    def _answer(self, backend: socket.socket, rid: int, reply: Mapping[str, object],
                cache: bool = False) -> None:
        """Send one reply (any thread); ``cache``: an inline result, encoded once per
        object (a snapshot returned again is the same bytes)."""
        if not reply.get("ok"):
            self.errors += 1
        obj = reply.get("result")
        if cache and obj is not None and obj is self._enc_obj:
            body = self._enc_line
        else:
            body = encode_reply(reply)
            if cache and isinstance(obj, dict):
                self._enc_obj, self._enc_line = obj, body
        data = b'{"id": %d, "reply": ' % rid + body[:-1] + b"}\n"
        try:
            with self._send_lock:
                backend.sendall(data)
        except OSError:
            pass  # the gateway is gone: its clients see their connection closed


def _end(proc: subprocess.Popen[bytes] | None, timeout: float = 2.0) -> int | None:
    """Wait for a gateway to end (its connection is closed), kill it if it does not."""
    if proc is None:
        return None
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait(timeout)


# -- the gateway (child process) -----------------------------------------------------------
class _Remote(MmctlError):
    """The daemon's error reply to a forwarded request."""


class _Slot:
    __slots__ = ("event", "reply", "status")

    def __init__(self, status: bool) -> None:
        self.event = threading.Event()
        self.reply: dict[str, object] = {}
        self.status = status


class Forwarder:
    """The gateway's handler: passes each request to the daemon and waits for its reply;
    ``status`` coalesced (see the module docstring).  ``sock``: the connection to the
    daemon (blocking); :meth:`run` reads the replies until the daemon closes it."""

    def __init__(self, sock: socket.socket):
        self._sock = sock
        self._send_lock = threading.Lock()
        self._pending: dict[int, _Slot] = {}
        self._ids = itertools.count(1)
        self._own = Peer(os.getpid(), os.getuid(), os.getgid())
        self._cv = threading.Condition()
        self._status_running = False
        self._status: tuple[float, dict[str, object]] = (-math.inf, {})
        """(start [monotonic s], reply) of the newest status round trip finished"""
        self._command_done = -math.inf
        """[monotonic s] the newest reply to another command arrived"""
        #: status requests answered / status round trips to the daemon
        self.status_asked = 0
        self.status_sent = 0

    def send(self, line: bytes) -> None:
        with self._send_lock:
            self._sock.sendall(line)

    def handle(self, req: Mapping[str, object], peer: Peer) -> object:
        wait = req.get("timeout_s")
        wait = (float(wait) if isinstance(wait, int | float) and not isinstance(wait, bool)
                and math.isfinite(wait) and 0 < wait <= 600 else REPLY_WAIT) + 2.0
        if req.get("cmd") == "status" and set(req) <= {"cmd", "timeout_s"}:
            reply = self._coalesced_status(wait)
        else:
            reply = self._round_trip(req, peer, wait)
        if not reply.get("ok"):
            raise _Remote(str(reply.get("error", "unknown error")))
        return reply.get("result")

    def _coalesced_status(self, wait: float) -> dict[str, object]:
        """A status reply from a round trip that started after this request arrived, or
        at most :data:`STATUS_SHARE` before it and after the newest command's reply."""
        arrived = time.monotonic()
        deadline = arrived + wait
        with self._cv:
            self.status_asked += 1
            while True:
                started, reply = self._status
                if reply and (started >= arrived or (
                        arrived - started <= STATUS_SHARE and started > self._command_done)):
                    return reply
                if not self._status_running:
                    break  # start one here
                left = deadline - time.monotonic()
                if left <= 0:
                    raise MmctlError(f"the daemon did not answer status within {wait:g} s")
                self._cv.wait(left)
            self._status_running = True
            self.status_sent += 1
        began = time.monotonic()
        try:
            reply = self._round_trip({"cmd": "status"}, self._own,
                                     max(deadline - began, 0.1), status=True)
            with self._cv:
                self._status = (began, reply)
        finally:
            with self._cv:
                self._status_running = False
                self._cv.notify_all()
        return reply

    def _round_trip(self, req: Mapping[str, object], peer: Peer, wait: float,
                    status: bool = False) -> dict[str, object]:
        rid = next(self._ids)
        slot = _Slot(status)
        self._pending[rid] = slot
        try:
            line = json.dumps({"id": rid, "peer": list(peer), "req": req}).encode() + b"\n"
            try:
                self.send(line)
            except OSError:
                raise MmctlError("the daemon is shutting down") from None
            if not slot.event.wait(wait):
                raise MmctlError(f"the daemon did not answer within {wait:g} s")
            return slot.reply
        finally:
            self._pending.pop(rid, None)

    def run(self) -> None:
        """Read the daemon's replies until it closes the connection."""
        rfile = self._sock.makefile("rb")
        try:
            for line in rfile:
                msg = json.loads(line)
                slot = self._pending.get(int(msg["id"]))
                if slot is not None:
                    slot.reply = msg["reply"]
                    if not slot.status:  # a status from before this is not shared again
                        self._command_done = time.monotonic()
                    slot.event.set()
        except OSError:
            pass
        finally:
            rfile.close()


def main(argv: Sequence[str] | None = None) -> int:
    """The gateway process: ``python -m mmctl.runtime.ipc_process`` (started by the
    daemon, with its listening socket and its end of the private connection)."""
    p = argparse.ArgumentParser(prog="mmctl-ipc", description="the mmctl daemon's control "
                                "socket, served for it (started by the daemon)")
    p.add_argument("--listen-fd", type=int, required=True)
    p.add_argument("--backend-fd", type=int, required=True)
    p.add_argument("--path", required=True)
    p.add_argument("--limits", default="{}")
    p.add_argument("--log-level", default="info")
    p.add_argument("--log-format", choices=("json", "console", "auto"), default="auto")
    p.add_argument("--cpus", default="")
    args = p.parse_args(argv)
    for sig in SIGNALS:  # the daemon ends it, after it has stopped the robot
        signal.signal(sig, signal.SIG_IGN)
    from mmctl.runtime.logging import setup_logging

    setup_logging(args.log_level, json={"json": True, "console": False, "auto": None}[
        args.log_format])
    if args.cpus and hasattr(os, "sched_setaffinity"):
        try:
            os.sched_setaffinity(0, {int(c) for c in args.cpus.split(",")})
        except (OSError, ValueError) as exc:
            log.warning("ipc_process_affinity_failed", error=str(exc))
    listen = socket.socket(fileno=args.listen_fd)
    backend = socket.socket(fileno=args.backend_fd)
    backend.setblocking(True)
    fwd = Forwarder(backend)
    server = ControlServer(args.path, fwd.handle, limits=IpcLimits(**json.loads(args.limits)),
                           urgent=("stop", "disable"), quick=("status",))
    # (a status waiting for the daemon's answer holds a quick thread: 4 of them)
    server.adopt(listen)
    fwd.send(json.dumps({"hello": os.getpid()}).encode() + b"\n")  # before any request
    server.start()
    fwd.run()  # until the daemon closes its end
    server.close()  # (the socket file is the daemon's)
    sys.stdout.flush()
    os._exit(0)  # no interpreter teardown under the server's threads


if __name__ == "__main__":
    sys.exit(main())
