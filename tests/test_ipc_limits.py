"""The control socket under floods and bad clients (issue 17): a connection cap, idle
and half-sent clients dropped, accept surviving fd exhaustion, rates that slow a client
instead of refusing it, nesting bounded before parsing, the CLI retrying a full backlog.

Real sockets and a real :class:`ControlServer` with a handler; no timing assertions
(every wait is bounded by a generous timeout and only its outcome is checked).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from mmctl.errors import IpcError, MmctlError
from mmctl.runtime.ipc import (
    ControlClient,
    ControlServer,
    IpcLimits,
    Peer,
    json_depth,
    request,
)

PATIENCE = 60.0
"""[s] the longest any one step may take on a loaded machine (never reached when it works)."""


class Handler:
    """status, stop (recorded), and wait (blocks until released: a command like enable)."""

    def __init__(self) -> None:
        self.stops = 0
        self.release = threading.Event()
        self.entered = threading.Semaphore(0)

    def __call__(self, req: Mapping[str, Any], peer: Peer) -> Any:
        if req["cmd"] == "status":
            return {"state": "disarmed"}
        if req["cmd"] == "stop":
            self.stops += 1
            return {"stopping": True}
        if req["cmd"] == "wait":
            self.entered.release()
            self.release.wait(PATIENCE)
            return {"waited": True}
        raise MmctlError(f"unknown command {req['cmd']!r}")


@pytest.fixture
def handler() -> Handler:
    return Handler()


def serve(tmp_path: Path, handler: Handler, **limits: Any) -> ControlServer:
    srv = ControlServer(tmp_path / "mmctl.sock", handler, limits=IpcLimits(**limits),
                        inline=("status",), urgent=("stop",))
    srv.start()
    return srv


@pytest.fixture
def server(tmp_path: Path, handler: Handler) -> Iterator[ControlServer]:
    srv = serve(tmp_path, handler)
    yield srv
    handler.release.set()
    srv.close()


def connect(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(PATIENCE)
    s.connect(str(path))
    return s


def read_line(s: socket.socket) -> bytes:
    """The first line, or what came before the connection closed (b"" when nothing)."""
    buf = b""
    while b"\n" not in buf:
        chunk = s.recv(65536)
        if not chunk:
            break
        buf += chunk
    return buf.partition(b"\n")[0]


def test_a_flood_of_concurrent_clients_and_held_connections_beyond_the_cap(
        server: ControlServer, handler: Handler) -> None:
    cap = server.limits.max_connections
    # 200 clients connecting at once, each then asking for the status and holding on.
    flood = [connect(server.path) for _ in range(200)]
    for s in flood:
        try:
            s.sendall(b'{"cmd": "status"}\n')
        except BrokenPipeError:
            pass  # evicted at the cap before it asked (its one line says so)
    replies = [json.loads(read_line(s)) for s in flood]
    # Every one got exactly one line: its status, or that it was evicted (idle, nothing
    # asked yet) at the connection cap.
    for reply in replies:
        assert reply == {"ok": True, "result": {"state": "disarmed"}} or (
            reply["ok"] is False and reply["evicted"] is True
            and "too many connections" in reply["error"]), reply
    assert any(r["ok"] for r in replies)
    # 300 more held open without a word: the server never holds more than the cap.
    held = [connect(server.path) for _ in range(300)]
    assert request(server.path, "status", timeout=PATIENCE) == {"state": "disarmed"}
    assert server.connections <= cap
    assert server.counters["evicted"] > 0
    assert request(server.path, "stop", timeout=PATIENCE) == {"stopping": True}
    assert handler.stops == 1
    for s in flood + held:
        s.close()
    assert request(server.path, "status", timeout=PATIENCE) == {"state": "disarmed"}


def test_at_the_cap_with_every_connection_busy_new_ones_wait_in_the_backlog(
        tmp_path: Path, handler: Handler) -> None:
    srv = serve(tmp_path, handler, max_connections=2, workers=2)
    try:
        busy = [connect(srv.path) for _ in range(2)]
        for s in busy:
            s.sendall(b'{"cmd": "wait"}\n')
        for _ in busy:  # both requests running: no connection left to evict
            assert handler.entered.acquire(timeout=PATIENCE)
        result: dict[str, Any] = {}

        def later() -> None:
            result["status"] = request(srv.path, "status", timeout=PATIENCE)

        t = threading.Thread(target=later)
        t.start()
        t.join(0.5)  # (either way: the outcome below does not depend on it)
        handler.release.set()
        t.join(PATIENCE)
        assert result["status"] == {"state": "disarmed"}
        for s in busy:
            assert json.loads(read_line(s)) == {"ok": True, "result": {"waited": True}}
            s.close()
    finally:
        handler.release.set()
        srv.close()


def test_stop_and_status_are_answered_while_the_workers_are_blocked(
        tmp_path: Path, handler: Handler) -> None:
    srv = serve(tmp_path, handler, workers=1)
    try:
        blocked = connect(srv.path)
        blocked.sendall(b'{"cmd": "wait"}\n')
        assert request(srv.path, "status", timeout=PATIENCE) == {"state": "disarmed"}
        assert request(srv.path, "stop", timeout=PATIENCE) == {"stopping": True}
        handler.release.set()
        assert json.loads(read_line(blocked))["result"] == {"waited": True}
        blocked.close()
    finally:
        handler.release.set()
        srv.close()


def test_idle_and_half_sent_clients_are_dropped(tmp_path: Path, handler: Handler) -> None:
    srv = serve(tmp_path, handler, idle_timeout=0.3)
    try:
        idle = connect(srv.path)
        half = connect(srv.path)
        half.sendall(b'{"cmd": "sta')
        for s in (idle, half):
            reply = json.loads(read_line(s))
            assert reply["ok"] is False and "no complete request" in reply["error"]
            assert s.recv(1) == b""  # then closed
            s.close()
        assert srv.counters["idle_dropped"] == 2
        # A client sending its requests keeps its connection.
        with ControlClient(srv.path, timeout=PATIENCE) as c:
            for _ in range(3):
                assert c.call("status") == {"state": "disarmed"}
    finally:
        srv.close()


def test_a_client_over_its_rate_is_slowed_not_refused(tmp_path: Path, handler: Handler) -> None:
    srv = serve(tmp_path, handler, client_rate=4.0, client_burst=1.0)
    try:
        s = connect(srv.path)
        s.sendall(b'{"cmd": "status"}\n' * 5)  # pipelined, beyond the burst
        f = s.makefile("rb")
        for _ in range(5):
            assert json.loads(f.readline()) == {"ok": True, "result": {"state": "disarmed"}}
        assert srv.counters["throttled"] > 0
        s.close()
    finally:
        srv.close()


def test_a_request_and_shutdown_of_the_sending_side_is_answered(server: ControlServer) -> None:
    s = connect(server.path)
    s.sendall(b'{"cmd": "status"}')  # no newline: the end of its input ends the line
    s.shutdown(socket.SHUT_WR)
    assert json.loads(read_line(s))["result"] == {"state": "disarmed"}
    assert s.recv(1) == b""
    s.close()


def test_an_over_long_line_gets_its_error_and_the_connection_closes_at_once(
        tmp_path: Path, handler: Handler) -> None:
    """A client still sending a 300 kB line: the server answers after MAX_LINE bytes and
    closes, so the client's blocked send ends.  The fuzzer found the close missing when
    the error reply went out at once (the connection then waited, unread and unwritten,
    for the idle sweep: 10 s without a reply).  The idle timeout here is beyond the
    test's patience: only the close itself can end the client's send."""
    srv = serve(tmp_path, handler, idle_timeout=10 * PATIENCE)
    try:
        for _ in range(20):  # the reply went out at once in some runs, not in others
            s = connect(srv.path)
            sent: list[BaseException | None] = []

            def send(s: socket.socket = s, sent: list[BaseException | None] = sent) -> None:
                try:
                    s.sendall(b'{"cmd": "status", "y": ' * 15_000 + b"\n")
                    sent.append(None)
                except OSError as exc:  # the server closed under the send: expected
                    sent.append(exc)

            sender = threading.Thread(target=send)
            sender.start()
            reply = json.loads(read_line(s))
            assert reply == {"ok": False, "error": "request longer than 65536 bytes"}
            sender.join(PATIENCE)
            assert not sender.is_alive(), "the client's send still blocked: not closed"
            assert isinstance(sent[0], (BrokenPipeError, ConnectionResetError))
            s.close()
        with ControlClient(srv.path, timeout=PATIENCE) as c:
            assert c.call("status") == {"state": "disarmed"}
    finally:
        handler.release.set()
        srv.close()


def test_deep_nesting_gets_one_error_reply(server: ControlServer) -> None:
    with ControlClient(server.path, timeout=PATIENCE) as c:
        deep = c.raw(b"[" * 5000)
        assert deep["ok"] is False and "nested deeper than 32" in deep["error"]
        wrapped = c.raw(b'{"cmd": "status", "x": ' + b"[" * 40 + b"]" * 40 + b"}")
        assert wrapped["ok"] is False and "nested deeper" in wrapped["error"]
        # brackets inside strings are not nesting
        fine = c.raw(json.dumps({"cmd": "status", "x": "[{" * 100 + '"\\'}).encode())
        assert fine == {"ok": True, "result": {"state": "disarmed"}}
        assert c.call("status") == {"state": "disarmed"}


def test_recursion_error_is_an_error_reply_even_without_the_depth_check(
        tmp_path: Path, handler: Handler) -> None:
    srv = ControlServer(tmp_path / "x.sock", handler, limits=IpcLimits(max_depth=10**9))
    reply = srv._dispatch(b"[" * 200_000 + b"]" * 200_000, Peer(0, 0, 0))
    assert reply["ok"] is False and reply["error"].startswith("malformed request")


def test_json_depth() -> None:
    assert json_depth(b'{"cmd": "status"}') == 1
    assert json_depth(b"[" * 100) == 100
    assert json_depth(b"[]" * 100) == 1
    assert json_depth(b'[' * 20 + b'"' + b"[" * 100 + b'"' + b"]" * 20) == 20
    assert json_depth(b'"\\"' + b"[" * 50 + b'"') == 0
    assert json_depth(b"") == 0


def test_the_client_retries_a_full_backlog_within_its_timeout(tmp_path: Path) -> None:
    path = tmp_path / "slow.sock"
    lsock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    lsock.bind(str(path))
    lsock.listen(1)
    filler = []
    try:
        while True:  # fill the backlog: the next connect gets EAGAIN
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.setblocking(False)
            try:
                s.connect(str(path))
            except BlockingIOError:
                s.close()
                break
            filler.append(s)
            assert len(filler) < 1000
        # Nobody accepts: a clear one-line error once the timeout is spent.
        with pytest.raises(IpcError, match="busy: its connection queue stayed full") as info:
            request(path, "status", timeout=0.2)
        assert "\n" not in str(info.value)

        # A peer that starts accepting while the client retries: the request gets through.
        def accept_and_answer() -> None:
            while True:
                try:
                    conn, _ = lsock.accept()
                except OSError:
                    return
                with conn:
                    conn.settimeout(PATIENCE)
                    line = conn.makefile("rb").readline()
                    if line:
                        conn.sendall(b'{"ok": true, "result": "served"}\n')

        peer = threading.Thread(target=accept_and_answer, daemon=True)
        result: dict[str, Any] = {}

        def client() -> None:
            result["r"] = request(path, "status", timeout=PATIENCE)

        c = threading.Thread(target=client)
        c.start()
        c.join(0.2)
        peer.start()
        for s in filler:
            s.close()
        c.join(PATIENCE)
        assert result["r"] == "served"
    finally:
        lsock.close()
        for s in filler:
            s.close()


def test_no_daemon_with_a_stale_socket_file_is_one_clear_error_at_once(tmp_path: Path) -> None:
    stale = tmp_path / "stale.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(stale))
    s.close()
    with pytest.raises(IpcError, match="no mmctl daemon is running"):
        request(stale, "status", timeout=PATIENCE)


_FD_LIMITED_SERVER = textwrap.dedent("""
    import resource, sys
    from mmctl.runtime.ipc import ControlServer, IpcLimits
    srv = ControlServer(sys.argv[1], lambda req, peer: {"state": "disarmed", **srv.counters},
                        limits=IpcLimits(max_connections=10_000, client_rate=1e6,
                                         client_burst=1e6, total_rate=1e6, total_burst=1e6))
    srv.start()
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (int(sys.argv[2]), hard))
    print("ready", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    srv.close()
""")


def test_fd_exhaustion_does_not_end_the_control_socket(tmp_path: Path) -> None:
    path = tmp_path / "fd.sock"
    nofile = 64  # far below the connections held (the cap is lifted in the child)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    child = subprocess.Popen([sys.executable, "-c", _FD_LIMITED_SERVER, str(path), str(nofile)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
    held: list[socket.socket] = []
    try:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.readline() == b"ready\n"
        for _ in range(150):  # beyond the child's descriptors
            try:
                held.append(connect(path))
            except BlockingIOError:  # (the backlog is full: enough)
                break
        # The server hits EMFILE, frees the longest-idle connection and goes on.
        st = request(path, "status", timeout=PATIENCE)
        assert st["state"] == "disarmed" and st["accept_errors"] > 0
        for s in held:
            s.close()
        held.clear()
        for _ in range(3):
            assert request(path, "status", timeout=PATIENCE)["state"] == "disarmed"
        assert child.poll() is None
    finally:
        for s in held:
            s.close()
        if child.stdin is not None:
            child.stdin.close()
        try:
            child.wait(PATIENCE)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait()
    assert child.returncode == 0
