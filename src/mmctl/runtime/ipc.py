"""The control socket: a Unix stream socket speaking one JSON object per line.

Request ``{"cmd": "status", ...}``; reply ``{"ok": true, "result": ...}`` or
``{"ok": false, "error": "one line"}``.  Several requests may share a connection.
A malformed line gets an error reply and the daemon carries on.

Access: the socket file gets mode 0660 (configurable) and every connection's peer
credentials (``SO_PEERCRED``) are checked: the daemon's own uid, root, or a member of
the socket file's group may talk to it.  A second daemon on a live socket refuses to
start (:class:`DaemonRunning`); a stale socket file left by a dead daemon is replaced.

What a client may cost (:class:`IpcLimits`; the daemon's loop shares the interpreter
with the server, so every request's work is time the loop may wait for): one selector
thread does all the socket I/O on non-blocking sockets, so a thousand clients are a
thousand buffers, not a thousand threads competing for the GIL; commands that may
block (``enable`` waits for the loop) run on a few worker threads, ``urgent`` ones
(``stop``, ``disable``) on one of their own, and non-blocking ``inline`` ones (the
daemon's ``status``, a snapshot rebuilt at most every 100 ms) on the selector thread.

* At most ``max_connections`` (64) connections: at the cap a new connection evicts an
  idle one (no request unanswered; of the client process holding the most
  connections, the one idle the longest), which gets one error line marked
  ``"evicted": true`` (:class:`ControlClient` then connects again and sends its
  request, which the daemon had not read); when every connection has a request in
  flight, new ones wait in the listen backlog (512) until one ends, and a client
  finding the backlog full retries within its timeout.
* A connection is dropped after ``idle_timeout`` (10 s) without a complete request
  line (idle, half-sent, or not reading its reply), with one error line.
* Rates: each client process (by peer pid) has a token bucket (50 requests/s, burst
  20); over it, its connections are not read until a token is due, so it is slowed by
  the kernel's socket buffers, never answered faster.  All clients together: 500
  requests and new connections per second (burst 100), the excess queued in order;
  urgent commands skip that queue.
* A request line is at most MAX_LINE bytes and nested at most ``max_depth`` (32)
  levels, checked by a byte scan before parsing; every bad line gets one error reply.
* ``accept`` failing for lack of descriptors (EMFILE, ENFILE, ENOBUFS, ENOMEM) closes
  the longest-idle connection, pauses accepting for 100 ms and goes on; other accept
  errors never end the server either.
"""

from __future__ import annotations

import collections
import errno
import json
import math
import os
import queue
import re
import selectors
import socket
import stat
import struct
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, NamedTuple, cast

import numpy as np
import structlog

from mmctl.errors import IpcError, MmctlError
from mmctl.runtime.logging import RateLimiter

log = structlog.get_logger("mmctl.ipc")

MAX_LINE = 65536
SOCKET_NAME = "mmctl.sock"


class DaemonRunning(MmctlError):
    """Another daemon already answers on the control socket."""


class Peer(NamedTuple):
    """Credentials of the process at the other end of a connection."""

    pid: int
    uid: int
    gid: int


#: A control-socket request's handler: the request (a JSON object whose ``cmd`` is a
#: string) and the client's credentials -> the result, any JSON-encodable value.
Handler = Callable[[Mapping[str, object], Peer], object]


def resolve_socket_path(configured: str = "", environ: Mapping[str, str] | None = None,
                        name: str = SOCKET_NAME) -> Path:
    """Where the control socket lives.

    configured path if given; else ``$RUNTIME_DIRECTORY/mmctl.sock`` (the systemd
    service), ``$XDG_RUNTIME_DIR/mmctl.sock`` (a user session) or
    ``/tmp/mmctl-$UID/mmctl.sock`` (``name``: another file in the same place, e.g. the
    simulated robot's ``mmctl-sim.sock``).
    """
    env = os.environ if environ is None else environ
    if configured:
        return Path(configured).expanduser()
    runtime_dir = env.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if runtime_dir:
        return Path(runtime_dir) / name
    xdg = env.get("XDG_RUNTIME_DIR")
    if xdg:
        return Path(xdg) / name
    return Path(f"/tmp/mmctl-{os.getuid()}") / name


def peer_credentials(conn: socket.socket) -> Peer:
    """SO_PEERCRED of a connected Unix socket."""
    raw = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return Peer(*struct.unpack("3i", raw))


def _groups_of(pid: int) -> set[int]:
    """Supplementary groups of a process, from /proc (empty if unreadable)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("Groups:"):
                return {int(g) for g in line.split()[1:]}
    except (OSError, ValueError):
        pass
    return set()


def peer_allowed(peer: Peer, socket_gid: int, own_uid: int | None = None) -> bool:
    """Same uid as the daemon, root, or a member of the socket's group."""
    own = os.getuid() if own_uid is None else own_uid
    if peer.uid in (own, 0) or peer.gid == socket_gid:
        return True
    return socket_gid in _groups_of(peer.pid)


def _probe(path: Path, timeout: float = 1.0) -> bool:
    """True if something accepts connections on ``path``."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout)
    try:
        s.connect(str(path))
        return True
    except (ConnectionRefusedError, FileNotFoundError):
        return False
    except OSError as exc:
        if exc.errno in (errno.ECONNREFUSED, errno.ENOENT):
            return False
        raise
    finally:
        s.close()


def bind_control_socket(path: Path, mode: int, backlog: int) -> socket.socket:
    """A listening Unix socket on ``path`` (mode bits ``mode``): refuses if a live daemon
    answers there (:class:`DaemonRunning`), replaces a stale file left by a dead one."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
    if path.exists() or path.is_symlink():
        st = path.lstat()
        if not stat.S_ISSOCK(st.st_mode):
            raise DaemonRunning(f"{path} exists and is not a socket; remove it or "
                                "choose another daemon.socket_path")
        if _probe(path):
            raise DaemonRunning(f"another mmctl daemon is already running on {path}")
        log.warning("ipc_stale_socket_replaced", path=str(path))
        path.unlink()
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    try:
        s.bind(str(path))
        os.chmod(path, mode)
        s.listen(backlog)
    except BaseException:
        s.close()
        raise
    return s


def call_handler(handler: Handler, req: Mapping[str, object], peer: Peer) -> dict[str, object]:
    """The reply to one parsed request: ``{"ok": true, "result": ...}``, or a one-line
    error for a :class:`MmctlError` (and, logged, for any other exception: a bad
    request must not kill the daemon)."""
    try:
        return {"ok": True, "result": handler(req, peer)}
    except MmctlError as exc:
        return {"ok": False, "error": str(exc)}
    except Exception as exc:  # noqa: BLE001 -- reply, log, carry on
        log.error("ipc_handler_failed", cmd=req.get("cmd"), error=repr(exc))
        return {"ok": False, "error": f"internal error: {exc!r}"}


@dataclass(frozen=True)
class IpcLimits:
    """What one control socket lets its clients cost (see the module docstring).

    max_connections: connections open at once; at the cap a new connection evicts the
    one idle the longest, or waits in the listen backlog while every connection has a
    request in flight.  backlog: the listen queue (the kernel caps it at
    ``net.core.somaxconn``).  idle_timeout [s]: a connection without a complete request
    line (idle, or half-sent) for this long is dropped.  client_rate [1/s] /
    client_burst: each client process's token bucket (by the peer's pid): over it, its
    connections are not read until a token is due (the kernel's buffers push back on
    it).  total_rate [1/s] / total_burst: the same for all clients together, one token
    per request and per accepted connection.  workers: threads for the commands that
    may block (e.g. ``enable`` waits for the loop); ``urgent`` commands have a thread of
    their own.  max_depth: nesting of a request's JSON.
    """

    max_connections: int = 64
    backlog: int = 512
    idle_timeout: float = 10.0
    client_rate: float = 50.0
    client_burst: float = 20.0
    total_rate: float = 500.0
    total_burst: float = 100.0
    workers: int = 4
    max_depth: int = 32


class _Bucket:
    """A token bucket: ``rate`` tokens per second, at most ``burst``."""

    __slots__ = ("burst", "rate", "stamp", "tokens")

    def __init__(self, rate: float, burst: float, now: float):
        self.rate, self.burst = rate, burst
        self.tokens, self.stamp = burst, now

    def refill(self, now: float) -> float:
        self.tokens = min(self.burst, self.tokens + (now - self.stamp) * self.rate)
        self.stamp = now
        return self.tokens

    def take(self, now: float) -> bool:
        if self.refill(now) >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def due(self, now: float) -> float:
        """When the next token is there (``now`` if it is)."""
        return now + max(0.0, 1.0 - self.refill(now)) / self.rate

    def full(self, now: float) -> bool:
        return self.refill(now) >= self.burst


class _Conn:
    """One client connection, owned by the server's selector thread."""

    __slots__ = ("busy", "closing", "eof", "events", "fd", "inbuf", "last", "out", "peer",
                 "pending", "sock")

    def __init__(self, sock: socket.socket, peer: Peer, now: float):
        self.sock = sock
        self.fd = sock.fileno()
        self.peer = peer
        self.inbuf = bytearray()
        self.out = bytearray()
        #: last complete request line, reply sent or accept [monotonic s]
        self.last = now
        #: a request is queued or running (nothing more is read until its reply is out)
        self.busy = False
        #: close once ``out`` is sent
        self.closing = False
        #: the client shut its side: answer what it sent, then close
        self.eof = False
        #: the request waiting for a token of the total rate
        self.pending: dict[str, object] | None = None
        self.events = 0


class _Workers:
    """A few daemon threads running jobs from a queue (the socket's blocking commands)."""

    def __init__(self, n: int, name: str):
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._threads = [threading.Thread(target=self._run, name=f"{name}-{i}", daemon=True)
                         for i in range(n)]
        for t in self._threads:
            t.start()

    def submit(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)

    def close(self) -> None:
        for _ in self._threads:
            self._jobs.put(None)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            job()


#: accept() errors after which the server backs off briefly and carries on
_ACCEPT_TRANSIENT = {errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM}
#: accept() errors about the one connection (it is gone): carry on at once
_ACCEPT_IGNORED = {errno.ECONNABORTED, errno.EPROTO, errno.EINTR, errno.EAGAIN,
                   errno.EPERM}
_ACCEPT_BACKOFF = 0.1
"""[s] without accepting after fd exhaustion (or an unexpected error: 10 times that)."""
_SWEEP = 0.25
"""[s] between the idle sweeps."""


class ControlServer:
    """Serves the control socket on one selector thread and dispatches requests to ``handler``.

    ``handler(request, peer)`` returns the result (JSON-serialisable) or raises
    :class:`MmctlError` for a one-line error reply.  Commands named in ``inline`` must
    not block (they run on the selector thread, e.g. a status snapshot); those in
    ``urgent`` (e.g. ``stop``) run on a thread of their own and skip the total rate;
    all others run on :attr:`IpcLimits.workers` threads.  Call :meth:`open` then
    :meth:`start`; :meth:`close` is idempotent and removes the socket file.
    """

    def __init__(self, path: Path | str, handler: Handler, mode: int = 0o660, *,
                 limits: IpcLimits | None = None, inline: Iterable[str] = (),
                 urgent: Iterable[str] = (), quick: Iterable[str] = ()):
        self.path = Path(path)
        self.mode = mode
        self.limits = limits if limits is not None else IpcLimits()
        self.inline = frozenset(inline)
        self.urgent = frozenset(urgent)
        self.quick = frozenset(quick)
        self._handler = handler
        self._sock: socket.socket | None = None
        self._inode: int | None = None
        self._wake_r, self._wake_w = -1, -1
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._done: queue.SimpleQueue[tuple[_Conn, bytes]] = queue.SimpleQueue()
        self._conns: dict[int, _Conn] = {}
        self._buckets: dict[int, _Bucket] = {}
        self._total = _Bucket(self.limits.total_rate, self.limits.total_burst, 0.0)
        self._waiting: collections.deque[_Conn] = collections.deque()
        self._throttled: dict[int, float] = {}
        self._listening = False
        self._sel: selectors.BaseSelector
        self._accept_at = 0.0
        self._limiter = RateLimiter(5.0)
        self._enc_obj: object = None
        self._enc_line = b""
        self._workers: _Workers | None = None
        self._urgent_worker: _Workers | None = None
        self._quick_worker: _Workers | None = None
        self.requests = 0
        self.errors = 0
        #: what the limits did: connections evicted at the cap, dropped idle, accept
        #: errors survived, requests held back by a rate
        self.counters = {"accepted": 0, "evicted": 0, "idle_dropped": 0,
                         "accept_errors": 0, "throttled": 0, "refused": 0}

    @property
    def connections(self) -> int:
        """Connections open now."""
        return len(self._conns)

    def open(self) -> None:
        """Bind the socket; refuse if a live daemon owns it, replace a stale file."""
        self.adopt(bind_control_socket(self.path, self.mode, self.limits.backlog), owned=True)

    def adopt(self, sock: socket.socket, owned: bool = False) -> None:
        """Serve ``sock``, a listening socket bound to :attr:`path` (another process's:
        the daemon's, for the socket's own process); ``owned``: :meth:`close` removes
        the socket file (else it is left to its owner)."""
        sock.setblocking(False)
        self._sock = sock
        self._inode = self.path.stat().st_ino if owned else None
        self._wake_r, self._wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)

    def start(self) -> None:
        """Start the selector thread and the workers."""
        if self._sock is None:
            self.open()
        self._workers = _Workers(max(1, self.limits.workers), "mmctl-ipc-worker")
        self._urgent_worker = _Workers(2, "mmctl-ipc-urgent")
        if self.quick:
            self._quick_worker = _Workers(4, "mmctl-ipc-quick")
        self._thread = threading.Thread(target=self._serve, name="mmctl-ipc", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop serving, close the connections and the socket, remove its file (if ours)."""
        if self._sock is None:
            return
        self._closing.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(2.0)
        for w in (self._workers, self._urgent_worker, self._quick_worker):
            if w is not None:
                w.close()
        if self._thread is None or not self._thread.is_alive():
            for conn in list(self._conns.values()):
                conn.sock.close()
            self._conns.clear()
        self._sock.close()
        self._sock = None
        wake_r, wake_w = self._wake_r, self._wake_w
        self._wake_r = self._wake_w = -1  # a worker finishing late writes nowhere
        for fd in (wake_r, wake_w):
            os.close(fd)
        try:
            if self.path.stat().st_ino == self._inode:
                self.path.unlink()
        except FileNotFoundError:
            pass

    def _wake(self) -> None:
        fd = self._wake_w
        if fd < 0:
            return
        try:
            os.write(fd, b"x")
        except (BlockingIOError, OSError):
            pass  # the pipe is full (a wake-up is pending anyway) or closed

    # -- the selector thread ------------------------------------------------------------
    def _serve(self) -> None:
        assert self._sock is not None
        sel = selectors.DefaultSelector()
        self._sel = sel
        sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._listen(True)
        next_sweep = time.monotonic() + _SWEEP
        try:
            while not self._closing.is_set():
                try:
                    now = time.monotonic()
                    wake_at = min([next_sweep, *self._throttled.values()])
                    if not self._listening:
                        wake_at = min(wake_at, self._accept_at)
                    if self._waiting:
                        wake_at = min(wake_at, self._total.due(now))
                    timeout = wake_at - now
                    for key, mask in sel.select(max(0.0, timeout)):
                        if key.data is None:
                            self._drain_wake()
                        elif key.data == "listen":
                            self._accept()
                        elif self._alive(key.data):  # (not closed earlier in this batch)
                            self._io(key.data, mask)
                    self._finish_done()
                    now = time.monotonic()
                    self._retry(now)
                    if now >= next_sweep:
                        self._sweep(now)
                        next_sweep = now + _SWEEP
                except Exception as exc:  # a bug here must not end control
                    if self._closing.is_set():
                        break
                    if (n := self._limiter.allow("serve")) is not None:
                        log.exception("ipc_serve_error", error=repr(exc), suppressed=n)
                    time.sleep(0.05)
        finally:
            for conn in list(self._conns.values()):
                self._drop(conn)
            sel.close()

    def _listen(self, on: bool) -> None:
        if on == self._listening or self._sock is None:
            return
        if on:
            self._sel.register(self._sock, selectors.EVENT_READ, "listen")
        else:
            self._sel.unregister(self._sock)
        self._listening = on

    def _drain_wake(self) -> None:
        try:
            while os.read(self._wake_r, 4096):
                pass
        except BlockingIOError:
            pass

    def _accept(self) -> None:
        assert self._sock is not None
        lim = self.limits
        for i in range(64):  # then let the others have their turn
            now = time.monotonic()
            if len(self._conns) >= lim.max_connections and i > 0:
                return  # (known to wait: only the first; the selector says if more do)
            if len(self._conns) >= lim.max_connections and not self._evict("cap"):
                self._listen(False)  # every connection busy: new ones wait in the backlog
                self._accept_at = math.inf
                return
            if not self._total.take(now):
                self._listen(False)
                self._accept_at = self._total.due(now)
                return
            try:
                sock, _addr = self._sock.accept()
            except BlockingIOError:
                self._total.tokens += 1.0
                return
            except OSError as exc:
                self._total.tokens += 1.0
                if self._accept_failed(exc, now):
                    continue
                return
            self._admit(sock, now)

    def _accept_failed(self, exc: OSError, now: float) -> bool:
        """Log (rate-limited) and recover; True: accept again at once."""
        self.counters["accept_errors"] += 1
        if exc.errno in _ACCEPT_IGNORED:
            return False
        transient = exc.errno in _ACCEPT_TRANSIENT
        freed = exc.errno in (errno.EMFILE, errno.ENFILE) and self._evict("fd_limit")
        if (n := self._limiter.allow(f"accept{exc.errno}")) is not None:
            log.error("ipc_accept_failed", error=str(exc), suppressed=n, connections=len(
                self._conns), action="closed the longest-idle connection" if freed else
                "backing off, then accepting again")
        if freed:
            return True  # a descriptor is free for the next client
        self._listen(False)
        self._accept_at = now + (_ACCEPT_BACKOFF if transient else 10 * _ACCEPT_BACKOFF)
        return False

    def _admit(self, sock: socket.socket, now: float) -> None:
        try:
            sock.setblocking(False)
            peer = peer_credentials(sock)
            if not peer_allowed(peer, self.path.stat().st_gid):
                self.counters["refused"] += 1
                log.warning("ipc_peer_refused", uid=peer.uid, pid=peer.pid)
                _send_now(sock, {"ok": False, "error": "permission denied: not the daemon's "
                                 "user, root, or a member of the socket's group"})
                sock.close()
                return
        except OSError as exc:
            log.warning("ipc_connection_error", error=str(exc))
            sock.close()
            return
        conn = _Conn(sock, peer, now)
        self._conns[conn.fd] = conn
        self.counters["accepted"] += 1
        self._update(conn)

    def _evict(self, why: str) -> bool:
        """Close the connection idle the longest (none with a request in flight)."""
        idle = [c for c in self._conns.values() if self._evictable(c)]
        if not idle:
            return False
        per_pid = collections.Counter(c.peer.pid for c in self._conns.values())
        # the client holding the most connections first, its longest idle one
        victim = max(idle, key=lambda c: (per_pid[c.peer.pid], -c.last))
        self.counters["evicted"] += 1
        if (n := self._limiter.allow(f"evict-{why}")) is not None:
            log.warning("ipc_connection_evicted", why=why, pid=victim.peer.pid,
                        connections=len(self._conns), suppressed=n)
        _send_now(victim.sock, {"ok": False, "evicted": True, "error": f"closed by the "
                                f"daemon: too many connections ({why}); this one was idle"})
        self._drop(victim)
        return True

    @staticmethod
    def _evictable(conn: _Conn) -> bool:
        """Nothing asked and unanswered: no request in flight, none complete and waiting."""
        return not conn.busy and b"\n" not in conn.inbuf

    def _drop(self, conn: _Conn) -> None:
        if not self._alive(conn):
            return
        del self._conns[conn.fd]
        if conn.events:
            self._sel.unregister(conn.sock)
            conn.events = 0
        self._throttled.pop(conn.fd, None)
        conn.sock.close()
        if not self._listening and self._accept_at == math.inf:
            self._accept_at = 0.0  # a slot is free: accept again
            self._listen(True)

    def _io(self, conn: _Conn, mask: int) -> None:
        try:
            if mask & selectors.EVENT_WRITE and conn.out:
                self._flush(conn)
            if mask & selectors.EVENT_READ:
                data = conn.sock.recv(65536)
                if not data:
                    conn.eof = True
                    if conn.inbuf and not conn.inbuf.endswith(b"\n"):
                        conn.inbuf += b"\n"  # its last request, unterminated
                else:
                    conn.inbuf += data
            self._advance(conn)
        except (BlockingIOError, InterruptedError):
            self._update(conn)
        except OSError as exc:
            if not isinstance(exc, (BrokenPipeError, ConnectionResetError)):
                log.warning("ipc_connection_error", error=str(exc))
            self._drop(conn)

    def _flush(self, conn: _Conn) -> None:
        n = conn.sock.send(conn.out)
        del conn.out[:n]
        if n:
            conn.last = time.monotonic()  # a long reply read slowly is not idle
        if not conn.out and conn.closing:
            self._drop(conn)

    def _advance(self, conn: _Conn) -> None:
        """Take the next complete line of ``conn`` if its turn has come; then (re)register."""
        if not self._alive(conn):
            return
        now = time.monotonic()
        while not (conn.busy or conn.closing or conn.out):
            end = conn.inbuf.find(b"\n")
            if end < 0:
                if len(conn.inbuf) > MAX_LINE:
                    self.errors += 1
                    # closing first: a reply that goes out at once drops the connection
                    conn.closing = True
                    self._reply(conn, {"ok": False,
                                       "error": f"request longer than {MAX_LINE} bytes"})
                break
            if end > MAX_LINE:
                self.errors += 1
                conn.closing = True
                self._reply(conn, {"ok": False, "error": f"request longer than {MAX_LINE} bytes"})
                break
            if not conn.inbuf[:end].strip():
                del conn.inbuf[:end + 1]
                continue
            bucket = self._buckets.get(conn.peer.pid)
            if bucket is None:
                bucket = self._buckets[conn.peer.pid] = _Bucket(
                    self.limits.client_rate, self.limits.client_burst, now)
            if not bucket.take(now):
                self.counters["throttled"] += 1
                self._throttled[conn.fd] = bucket.due(now)
                break
            self._throttled.pop(conn.fd, None)
            line = bytes(conn.inbuf[:end])
            del conn.inbuf[:end + 1]
            conn.last = now
            self.requests += 1
            req = self._parse(line)
            if "ok" in req:  # an error reply
                self._reply(conn, req)
                continue
            cmd = str(req["cmd"])  # (a string: _parse checked it)
            if cmd in self.urgent:
                self._run(conn, req, self._urgent_worker)
            elif self._waiting or not self._total.take(now):
                self.counters["throttled"] += 1
                conn.busy = True
                conn.pending = req
                self._waiting.append(conn)
            else:
                self._run(conn, req, self._lane(cmd))
        if (conn.eof and not (conn.busy or conn.out or conn.fd in self._throttled)
                and (conn.closing or b"\n" not in conn.inbuf)):
            self._drop(conn)  # all it sent is answered
            return
        self._update(conn)

    def _lane(self, cmd: str) -> _Workers | None:
        """Where a (non-urgent) command runs: None = on the selector thread."""
        if cmd in self.inline:
            return None
        if cmd in self.quick and self._quick_worker is not None:
            return self._quick_worker
        return self._workers

    def _run(self, conn: _Conn, req: dict[str, object], workers: _Workers | None) -> None:
        if workers is None:
            self._reply(conn, self._call(req, conn.peer), cache=True)
            return
        conn.busy = True

        def job() -> None:
            line = encode_reply(self._call(req, conn.peer))
            self._done.put((conn, line))
            self._wake()

        workers.submit(job)

    def _finish_done(self) -> None:
        while True:
            try:
                conn, line = self._done.get_nowait()
            except queue.Empty:
                return
            conn.busy = False
            if self._alive(conn):
                conn.out += line
                self._try_flush(conn)
                self._advance(conn)

    def _retry(self, now: float) -> None:
        """Requests waiting for the total rate, connections waiting for their client's."""
        while self._waiting and self._total.take(now):
            conn = self._waiting.popleft()
            req, conn.pending = conn.pending, None
            conn.busy = False
            if self._alive(conn) and req is not None:
                self._run(conn, req, self._lane(str(req["cmd"])))
                self._advance(conn)
        for fd, due in list(self._throttled.items()):
            if due <= now:
                del self._throttled[fd]
                throttled = self._conns.get(fd)
                if throttled is not None:
                    self._advance(throttled)
        if not self._listening and (self._accept_at <= now or (
                self._accept_at == math.inf
                and any(self._evictable(c) for c in self._conns.values()))):
            self._listen(True)  # (at the cap: one became idle, a new one may evict it)

    def _sweep(self, now: float) -> None:
        """Drop connections idle (or half-sent, or not reading their reply) too long;
        forget the buckets of clients that have been quiet long enough to be full."""
        limit = self.limits.idle_timeout
        for conn in list(self._conns.values()):
            if not conn.busy and now - conn.last > limit:
                self.counters["idle_dropped"] += 1
                if (n := self._limiter.allow("idle")) is not None:
                    log.info("ipc_idle_dropped", pid=conn.peer.pid, seconds=limit,
                             half_sent=bool(conn.inbuf), suppressed=n)
                _send_now(conn.sock, {"ok": False, "error": f"closed by the daemon: no "
                                      f"complete request for {limit:g} s"})
                self._drop(conn)
        live = {c.peer.pid for c in self._conns.values()}
        for pid in [p for p, b in self._buckets.items() if p not in live and b.full(now)]:
            del self._buckets[pid]

    def _alive(self, conn: _Conn) -> bool:
        return self._conns.get(conn.fd) is conn

    def _reply(self, conn: _Conn, reply: Mapping[str, object], cache: bool = False) -> None:
        """Queue one reply line; ``cache``: an inline command's result, encoded once per
        object (a snapshot returned again is the same bytes; inline results are never
        changed after they are returned)."""
        obj = reply.get("result")
        if cache and obj is not None and obj is self._enc_obj:
            line = self._enc_line
        else:
            line = encode_reply(reply)
            if cache and isinstance(obj, dict):
                self._enc_obj, self._enc_line = obj, line
        conn.out += line
        self._try_flush(conn)

    def _try_flush(self, conn: _Conn) -> None:
        try:
            self._flush(conn)
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            self._drop(conn)

    def _update(self, conn: _Conn) -> None:
        """Register for what ``conn`` waits for: its reply to go out, or more input."""
        if not self._alive(conn):
            return
        want = 0
        if conn.out:
            want = selectors.EVENT_WRITE
        elif not (conn.busy or conn.closing or conn.eof or conn.fd in self._throttled
                  or b"\n" in conn.inbuf or len(conn.inbuf) > MAX_LINE):
            want = selectors.EVENT_READ
        if want == conn.events:
            return
        if conn.events == 0:
            self._sel.register(conn.sock, want, conn)
        elif want == 0:
            self._sel.unregister(conn.sock)
        else:
            self._sel.modify(conn.sock, want, conn)
        conn.events = want

    # -- requests -----------------------------------------------------------------------
    def _parse(self, line: bytes) -> dict[str, object]:
        """The request of one line, or an error reply (has ``ok``)."""
        depth = json_depth(line, self.limits.max_depth)
        if depth > self.limits.max_depth:
            self.errors += 1
            return {"ok": False, "error": f"malformed request: nested deeper than "
                    f"{self.limits.max_depth} levels"}
        try:
            req = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            self.errors += 1
            return {"ok": False, "error": f"malformed request: {exc.msg if hasattr(exc, 'msg') else exc}"}
        except (RecursionError, ValueError) as exc:
            self.errors += 1
            return {"ok": False, "error": f"malformed request: {type(exc).__name__}"}
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            self.errors += 1
            return {"ok": False, "error": 'malformed request: expected {"cmd": "<name>", ...}'}
        return req

    def _call(self, req: Mapping[str, object], peer: Peer) -> dict[str, object]:
        reply = call_handler(self._handler, req, peer)
        if not reply["ok"]:
            self.errors += 1
        return reply

    def _dispatch(self, line: bytes, peer: Peer) -> dict[str, object]:
        """One request line to its reply, on the calling thread (no limits: tests, fuzz)."""
        self.requests += 1
        req = self._parse(line)
        return req if "ok" in req else self._call(req, peer)


_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def json_depth(line: bytes, limit: int = 32) -> int:
    """The nesting depth of one JSON text without parsing it (brackets inside strings do
    not count), or the count of its opening brackets when that is no more than
    ``limit``: scans at C speed, cheap for any line up to MAX_LINE."""
    opens = line.count(b"[") + line.count(b"{")
    if opens <= limit:
        return opens
    brackets = _STRING.sub(b"", line).translate(None, _NOT_BRACKETS)
    if not brackets:
        return 0
    steps = np.frombuffer(brackets, np.uint8)
    depth = np.cumsum(np.where((steps == 0x5B) | (steps == 0x7B), 1, -1), dtype=np.int64)
    return int(depth.max())


def encode_reply(reply: Mapping[str, object]) -> bytes:
    try:
        return json.dumps(reply, default=_json_default).encode() + b"\n"
    except (TypeError, ValueError, RecursionError) as exc:
        return json.dumps({"ok": False, "error": f"internal error: the reply is not JSON "
                           f"({type(exc).__name__})"}).encode() + b"\n"


def _send_now(sock: socket.socket, obj: Mapping[str, object]) -> None:
    """Best effort, never blocking: one line to a connection about to be closed."""
    try:
        sock.send(encode_reply(obj))
    except OSError:
        pass


def _send(conn: socket.socket, obj: Mapping[str, object]) -> None:
    conn.sendall(encode_reply(obj))


def _json_default(o: object) -> object:
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "value"):
        return o.value
    return repr(o)


class ControlClient:
    """A connection to the daemon; ``call(cmd, **args)`` returns the result or raises IpcError."""

    def __init__(self, path: Path | str, timeout: float = 10.0, absent: str | None = None,
                 max_reply: int = MAX_LINE):
        self.path = Path(path)
        self.timeout = timeout
        #: the longest reply line accepted [bytes] (the simulation's logs are long)
        self.max_reply = max_reply
        #: the error when nothing listens (default: no daemon, start `mmctl run`)
        self.absent = absent
        self._sock: socket.socket | None = None
        self._rfile: BinaryIO | None = None

    def connect(self) -> ControlClient:
        """Connect within :attr:`timeout`: a full listen backlog (EAGAIN: the daemon is
        busy, e.g. under a flood of clients) is retried with a growing pause; no daemon
        (no socket file, or nothing listening on it) is one clear error at once."""
        deadline = time.monotonic() + self.timeout
        pause = 0.002
        while True:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
            s.settimeout(max(deadline - time.monotonic(), 0.001))
            try:
                s.connect(str(self.path))
                break
            except (FileNotFoundError, ConnectionRefusedError):
                s.close()
                raise IpcError(self.absent or f"no mmctl daemon is running (nothing listens on "
                               f"{self.path}); start one with `mmctl run`") from None
            except PermissionError:
                s.close()
                raise IpcError(f"permission denied on {self.path}: join the socket's group "
                               "or run as the daemon's user") from None
            except (BlockingIOError, TimeoutError, InterruptedError) as exc:
                s.close()
                left = deadline - time.monotonic()
                if left <= 0:
                    why = ("its connection queue stayed full"
                           if isinstance(exc, BlockingIOError) else "it did not accept")
                    raise IpcError(f"the daemon on {self.path} is busy: {why} for "
                                   f"{self.timeout:g} s") from None
                time.sleep(min(pause, left))
                pause = min(2 * pause, 0.05)
            except OSError as exc:
                s.close()
                raise IpcError(f"cannot connect to {self.path}: {exc.strerror or exc}") from None
        s.settimeout(self.timeout)  # then each reply within the timeout
        self._sock = s
        self._rfile = s.makefile("rb")
        return self

    def close(self) -> None:
        if self._sock is not None:
            if self._rfile is not None:
                self._rfile.close()
            self._sock.close()
            self._sock = None

    def __enter__(self) -> ControlClient:  # noqa: PYI034
        return self.connect() if self._sock is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def raw(self, line: bytes) -> dict[str, object]:
        """Send raw bytes (one line) and return the decoded reply."""
        if self._sock is None:
            self.connect()
        assert self._sock is not None and self._rfile is not None
        try:
            try:
                self._sock.sendall(line if line.endswith(b"\n") else line + b"\n")
            except (BrokenPipeError, ConnectionResetError):
                pass  # closed before our request: its last line (if any) says why
            reply = self._rfile.readline(self.max_reply + 1)
        except TimeoutError:
            raise IpcError(f"the daemon on {self.path} did not answer within "
                           f"{self.timeout:g} s") from None
        except (BrokenPipeError, ConnectionResetError):
            raise IpcError(f"the daemon on {self.path} closed the connection") from None
        if not reply:
            raise IpcError(f"the daemon on {self.path} closed the connection")
        if not reply.endswith(b"\n"):
            self.close()  # the rest of that line would be read as the next reply
            raise IpcError(f"the reply from {self.path} is longer than {self.max_reply} bytes")
        try:
            return cast(dict[str, object], json.loads(reply))
        except ValueError:
            raise IpcError(f"the reply from {self.path} is not JSON: {reply[:80]!r}") from None

    def call(self, cmd: str, **args: object) -> Any:
        """One request; returns ``result`` or raises :class:`IpcError` with the daemon's error."""
        # timeout_s: the daemon finishes (or abandons) the command within this client's
        # patience, so a reply that never arrives never means "done later"
        line = json.dumps({"cmd": cmd, "timeout_s": self.timeout, **args}).encode()
        deadline = time.monotonic() + self.timeout
        reply = self.raw(line)
        while reply.get("evicted") and time.monotonic() < deadline:
            # closed at the daemon's connection cap before our request was read (never
            # after: then it is answered), so sending it again is safe
            self.close()
            time.sleep(0.01)
            self.connect()
            reply = self.raw(line)
        if not reply.get("ok"):
            raise IpcError(str(reply.get("error", "unknown error")))
        return reply.get("result")


def request(path: Path | str, cmd: str, timeout: float = 10.0, absent: str | None = None,
            max_reply: int = MAX_LINE, **args: object) -> Any:
    """Open, send one request, close (``absent``, ``max_reply``: see :class:`ControlClient`)."""
    with ControlClient(path, timeout, absent, max_reply) as c:
        return c.call(cmd, **args)
