"""The control socket served from a process of its own (mmctl.runtime.ipc_process):
the gateway is a real child process speaking to the daemon's side over a socket pair;
clients are real Unix-socket clients."""

from __future__ import annotations

import os
import signal
import socket
import threading
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from mmctl.errors import IpcError, MmctlError
from mmctl.runtime.ipc import ControlClient, DaemonRunning, IpcLimits, Peer, request
from mmctl.runtime.ipc_process import ProcessControlServer


class Backend:
    """A daemon's command table: counts what reaches it."""

    def __init__(self) -> None:
        self.calls: dict[str, int] = {}
        self.value = 0
        self.gate = threading.Event()
        self.lock = threading.Lock()

    def __call__(self, req: Mapping[str, Any], peer: Peer) -> Any:
        cmd = req["cmd"]
        with self.lock:
            self.calls[cmd] = self.calls.get(cmd, 0) + 1
        if cmd == "status":
            time.sleep(0.002)  # a snapshot costs something: requests arrive meanwhile
            return {"value": self.value}
        if cmd == "bump":
            self.value += 1
            return self.value
        if cmd == "whoami":
            return list(peer)
        if cmd == "block":  # an `enable` waiting for the loop
            self.gate.wait(10)
            return "unblocked"
        if cmd == "stop":
            return "stopped"
        if cmd == "crash":
            raise RuntimeError("bug")
        raise MmctlError(f"unknown command {cmd!r}")


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[ProcessControlServer, Backend]]:
    backend = Backend()
    srv = ProcessControlServer(tmp_path / "run" / "mmctl.sock", backend, inline=("status",),
                               urgent=("stop", "disable"))
    srv.start()
    yield srv, backend
    backend.gate.set()
    srv.close()


def test_requests_pass_through_the_gateway(served: tuple[ProcessControlServer, Backend]) -> None:
    srv, backend = served
    assert srv.pid is not None and srv.pid != os.getpid()
    assert request(srv.path, "status") == {"value": 0}
    assert request(srv.path, "bump") == 1
    # the client's own credentials reach the daemon's handler, not the gateway's
    assert request(srv.path, "whoami") == [os.getpid(), os.getuid(), os.getgid()]
    with pytest.raises(IpcError, match="unknown command 'nope'"):
        request(srv.path, "nope")
    with pytest.raises(IpcError, match="internal error: RuntimeError"):
        request(srv.path, "crash")
    with ControlClient(srv.path) as c:  # parsed and refused in the gateway
        assert "malformed" in c.raw(b"{not json")["error"]
        assert "nested deeper" in c.raw(b"[" * 5000)["error"]
        assert c.call("status") == {"value": 1}
    assert "nope" not in backend.calls or backend.calls["nope"] == 1
    assert srv.errors == 2


def test_status_right_after_a_command_shows_its_effect(
        served: tuple[ProcessControlServer, Backend]) -> None:
    srv, _ = served
    stop = threading.Event()

    def hammer() -> None:  # other clients keep a status round trip in flight
        with ControlClient(srv.path) as c:
            while not stop.is_set():
                c.call("status")

    threads = [threading.Thread(target=hammer) for _ in range(4)]
    for t in threads:
        t.start()
    try:
        with ControlClient(srv.path) as c:
            for _ in range(50):
                n = c.call("bump")
                assert c.call("status") == {"value": n}
    finally:
        stop.set()
        for t in threads:
            t.join()


def test_a_status_flood_costs_the_daemon_a_fraction_of_the_requests(tmp_path: Path) -> None:
    backend = Backend()
    # every client is this process: no per-client rate here, so they do arrive together
    srv = ProcessControlServer(tmp_path / "mmctl.sock", backend, inline=("status",),
                               limits=IpcLimits(client_rate=1e6, client_burst=1e6,
                                                total_burst=1000))
    srv.start()
    n = 120
    go = threading.Barrier(n)
    replies: list[Any] = []

    def client() -> None:
        with ControlClient(srv.path, timeout=30) as c:
            go.wait()
            replies.append(c.call("status"))

    threads = [threading.Thread(target=client) for _ in range(n)]
    for t in threads:
        t.start()
    t0 = time.monotonic()
    for t in threads:
        t.join()
    seconds = time.monotonic() - t0
    srv.close()
    assert replies == [{"value": 0}] * n
    # shared: at most one round trip per 20 ms, and one more for each window's start
    assert backend.calls["status"] <= 1 + seconds / 0.02, (backend.calls, seconds)
    assert backend.calls["status"] < n / 3, (backend.calls, seconds)


def test_a_blocking_command_blocks_neither_status_nor_stop(
        served: tuple[ProcessControlServer, Backend]) -> None:
    srv, backend = served
    blocked = [threading.Thread(target=request, args=(srv.path, "block")) for _ in range(6)]
    for t in blocked:
        t.start()
    try:
        while backend.calls.get("block", 0) < 4:  # the daemon's workers all wait
            time.sleep(0.01)
        assert request(srv.path, "status", timeout=5) == {"value": 0}
        assert request(srv.path, "stop", timeout=5) == "stopped"
    finally:
        backend.gate.set()
        for t in blocked:
            t.join()


def test_a_crashed_gateway_is_restarted_and_clients_wait_in_the_backlog(
        served: tuple[ProcessControlServer, Backend]) -> None:
    srv, _ = served
    first = srv.pid
    assert first is not None
    os.kill(first, signal.SIGKILL)
    # connecting right away succeeds (the daemon holds the listening socket); the reply
    # comes from the next gateway
    assert request(srv.path, "status", timeout=30) == {"value": 0}
    assert srv.started == 2 and srv.pid not in (None, first)


def test_the_gateway_ignores_stop_signals_and_ends_with_the_daemon(tmp_path: Path) -> None:
    srv = ProcessControlServer(tmp_path / "mmctl.sock", Backend(), inline=("status",))
    srv.start()
    pid = srv.pid
    assert pid is not None
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        os.kill(pid, sig)
    assert request(srv.path, "status") == {"value": 0}
    proc = srv._proc
    assert proc is not None
    srv.close()
    assert proc.poll() is not None  # ended when the daemon closed its end
    assert not srv.path.exists()
    with pytest.raises(IpcError, match="no mmctl daemon"):
        request(srv.path, "status")


def test_a_second_server_refuses_a_live_socket(
        served: tuple[ProcessControlServer, Backend], tmp_path: Path) -> None:
    srv, _ = served
    with pytest.raises(DaemonRunning):
        ProcessControlServer(srv.path, Backend()).open()
    assert request(srv.path, "status") == {"value": 0}


def test_a_daemon_killed_outright_ends_its_gateway(tmp_path: Path) -> None:
    """The daemon's end closes (as when SIGKILL ends the daemon): the gateway ends."""
    srv = ProcessControlServer(tmp_path / "mmctl.sock", Backend(), inline=("status",))
    srv.start()
    proc = srv._proc
    assert proc is not None
    backend = srv._backend
    assert backend is not None
    srv._closing.set()  # (so the reader does not start another one)
    backend.shutdown(socket.SHUT_RDWR)
    assert proc.wait(10) == 0
    srv.close()


def test_opened_but_never_started_closes_cleanly(tmp_path: Path) -> None:
    """A daemon whose devices fail to connect closes the socket it opened: the socket's
    process (started by open) ends, the file is gone."""
    srv = ProcessControlServer(tmp_path / "mmctl.sock", Backend(), inline=("status",))
    srv.open()
    proc = srv._proc
    assert proc is not None and proc.poll() is None
    srv.close()
    assert proc.poll() is not None
    assert not srv.path.exists()
