"""The control socket: a Unix stream socket speaking one JSON object per line.

Request ``{"cmd": "status", ...}``; reply ``{"ok": true, "result": ...}`` or
``{"ok": false, "error": "one line"}``.  Several requests may share a connection.
A malformed line gets an error reply and the daemon carries on.

Access: the socket file gets mode 0660 (configurable) and every connection's peer
credentials (``SO_PEERCRED``) are checked: the daemon's own uid, root, or a member of
the socket file's group may talk to it.  A second daemon on a live socket refuses to
start (:class:`DaemonRunning`); a stale socket file left by a dead daemon is replaced.
"""

from __future__ import annotations

import errno
import json
import os
import selectors
import socket
import stat
import struct
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple, cast

import structlog

from mmctl.errors import IpcError, MmctlError

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


Handler = Callable[[Mapping[str, Any], Peer], Any]


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


class ControlServer:
    """Accepts connections on the control socket and dispatches requests to ``handler``.

    ``handler(request, peer)`` returns the result (JSON-serialisable) or raises
    :class:`MmctlError` for a one-line error reply.  Call :meth:`open` then
    :meth:`start`; :meth:`close` is idempotent and removes the socket file.
    """

    def __init__(self, path: Path | str, handler: Handler, mode: int = 0o660):
        self.path = Path(path)
        self.mode = mode
        self._handler = handler
        self._sock: socket.socket | None = None
        self._inode: int | None = None
        self._wake_r, self._wake_w = -1, -1
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self.requests = 0
        self.errors = 0

    def open(self) -> None:
        """Bind the socket; refuse if a live daemon owns it, replace a stale file."""
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        if self.path.exists() or self.path.is_symlink():
            st = self.path.lstat()
            if not stat.S_ISSOCK(st.st_mode):
                raise DaemonRunning(f"{self.path} exists and is not a socket; remove it or "
                                    "choose another daemon.socket_path")
            if _probe(self.path):
                raise DaemonRunning(f"another mmctl daemon is already running on {self.path}")
            log.warning("ipc_stale_socket_replaced", path=str(self.path))
            self.path.unlink()
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        s.bind(str(self.path))
        os.chmod(self.path, self.mode)
        s.listen(16)
        s.setblocking(False)
        self._sock = s
        self._inode = self.path.stat().st_ino
        self._wake_r, self._wake_w = os.pipe()

    def start(self) -> None:
        """Start the accept thread."""
        if self._sock is None:
            self.open()
        self._thread = threading.Thread(target=self._serve, name="mmctl-ipc", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop accepting, close the socket and remove its file (if still ours)."""
        if self._sock is None:
            return
        self._closing.set()
        os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(2.0)
        self._sock.close()
        self._sock = None
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)
        try:
            if self.path.stat().st_ino == self._inode:
                self.path.unlink()
        except FileNotFoundError:
            pass

    def _serve(self) -> None:
        assert self._sock is not None
        sel = selectors.DefaultSelector()
        sel.register(self._sock, selectors.EVENT_READ)
        sel.register(self._wake_r, selectors.EVENT_READ)
        try:
            while not self._closing.is_set():
                for key, _ in sel.select():
                    if key.fileobj is not self._sock or self._closing.is_set():
                        continue
                    try:
                        conn, _addr = self._sock.accept()
                    except BlockingIOError:
                        continue
                    threading.Thread(target=self._client, args=(conn,), name="mmctl-ipc-conn",
                                     daemon=True).start()
        except OSError as exc:
            if not self._closing.is_set():
                log.error("ipc_accept_failed", error=str(exc))
        finally:
            sel.close()

    def _client(self, conn: socket.socket) -> None:
        try:
            conn.setblocking(True)
            peer = peer_credentials(conn)
            if not peer_allowed(peer, self.path.stat().st_gid):
                log.warning("ipc_peer_refused", uid=peer.uid, pid=peer.pid)
                _send(conn, {"ok": False, "error": "permission denied: not the daemon's user, "
                             "root, or a member of the socket's group"})
                return
            rfile = conn.makefile("rb")
            while True:
                line = rfile.readline(MAX_LINE + 1)
                if not line:
                    return
                if len(line) > MAX_LINE:
                    _send(conn, {"ok": False, "error": f"request longer than {MAX_LINE} bytes"})
                    return
                if not line.strip():
                    continue
                _send(conn, self._dispatch(line, peer))
        except (BrokenPipeError, ConnectionResetError):
            return
        except OSError as exc:
            log.warning("ipc_connection_error", error=str(exc))
        finally:
            conn.close()

    def _dispatch(self, line: bytes, peer: Peer) -> dict[str, Any]:
        self.requests += 1
        try:
            req = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            self.errors += 1
            return {"ok": False, "error": f"malformed request: {exc.msg if hasattr(exc, 'msg') else exc}"}
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            self.errors += 1
            return {"ok": False, "error": 'malformed request: expected {"cmd": "<name>", ...}'}
        try:
            return {"ok": True, "result": self._handler(req, peer)}
        except MmctlError as exc:
            self.errors += 1
            return {"ok": False, "error": str(exc)}
        except Exception as exc:  # noqa: BLE001 -- reply, log, carry on: a bad request must not kill the daemon
            self.errors += 1
            log.error("ipc_handler_failed", cmd=req.get("cmd"), error=repr(exc))
            return {"ok": False, "error": f"internal error: {exc!r}"}


def _send(conn: socket.socket, obj: Mapping[str, Any]) -> None:
    conn.sendall(json.dumps(obj, default=_json_default).encode() + b"\n")


def _json_default(o: Any) -> Any:
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
        self._rfile: Any = None

    def connect(self) -> ControlClient:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        s.settimeout(self.timeout)
        try:
            s.connect(str(self.path))
        except (FileNotFoundError, ConnectionRefusedError):
            s.close()
            raise IpcError(self.absent or f"no mmctl daemon is running (nothing listens on "
                           f"{self.path}); start one with `mmctl run`") from None
        except PermissionError:
            s.close()
            raise IpcError(f"permission denied on {self.path}: join the socket's group "
                           "or run as the daemon's user") from None
        self._sock = s
        self._rfile = s.makefile("rb")
        return self

    def close(self) -> None:
        if self._sock is not None:
            self._rfile.close()
            self._sock.close()
            self._sock = None

    def __enter__(self) -> ControlClient:  # noqa: PYI034
        return self.connect() if self._sock is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def raw(self, line: bytes) -> dict[str, Any]:
        """Send raw bytes (one line) and return the decoded reply."""
        if self._sock is None:
            self.connect()
        assert self._sock is not None
        try:
            self._sock.sendall(line if line.endswith(b"\n") else line + b"\n")
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
            return cast(dict[str, Any], json.loads(reply))
        except ValueError:
            raise IpcError(f"the reply from {self.path} is not JSON: {reply[:80]!r}") from None

    def call(self, cmd: str, **args: Any) -> Any:
        """One request; returns ``result`` or raises :class:`IpcError` with the daemon's error."""
        # timeout_s: the daemon finishes (or abandons) the command within this client's
        # patience, so a reply that never arrives never means "done later"
        reply = self.raw(json.dumps({"cmd": cmd, "timeout_s": self.timeout, **args}).encode())
        if not reply.get("ok"):
            raise IpcError(str(reply.get("error", "unknown error")))
        return reply.get("result")


def request(path: Path | str, cmd: str, timeout: float = 10.0, absent: str | None = None,
            max_reply: int = MAX_LINE, **args: Any) -> Any:
    """Open, send one request, close (``absent``, ``max_reply``: see :class:`ControlClient`)."""
    with ControlClient(path, timeout, absent, max_reply) as c:
        return c.call(cmd, **args)
