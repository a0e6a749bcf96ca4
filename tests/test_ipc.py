"""The control socket: JSON lines, errors for bad requests, 0660, peer check, one daemon."""

from __future__ import annotations

import os
import socket
import stat
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import pytest

from mmctl.errors import IpcError, MmctlError
from mmctl.runtime.ipc import (
    ControlClient,
    ControlServer,
    DaemonRunning,
    Peer,
    peer_allowed,
    request,
    resolve_socket_path,
)


def handler(req: Mapping[str, Any], peer: Peer) -> Any:
    if req["cmd"] == "status":
        return {"state": "disarmed", "peer_uid": peer.uid, "peer_pid": peer.pid}
    if req["cmd"] == "crash":
        raise RuntimeError("bug")
    raise MmctlError(f"unknown command {req['cmd']!r}; known: status")


@pytest.fixture
def server(tmp_path: Path) -> Iterator[ControlServer]:
    srv = ControlServer(tmp_path / "run" / "mmctl.sock", handler)
    srv.start()
    yield srv
    srv.close()


def test_status_roundtrip_mode_and_peer(server: ControlServer) -> None:
    res = request(server.path, "status")
    assert res == {"state": "disarmed", "peer_uid": os.getuid(), "peer_pid": os.getpid()}
    assert stat.S_IMODE(server.path.stat().st_mode) == 0o660
    assert stat.S_ISSOCK(server.path.stat().st_mode)


def test_malformed_and_unknown_get_errors_and_the_server_carries_on(server: ControlServer) -> None:
    with ControlClient(server.path) as c:
        bad = c.raw(b"{not json")
        assert bad["ok"] is False and bad["error"].startswith("malformed request")
        assert c.raw(b'["status"]')["error"].startswith("malformed request")
        assert c.raw(b'{"command": "status"}')["ok"] is False
        unknown = c.raw(b'{"cmd": "fly"}')
        assert unknown == {"ok": False, "error": "unknown command 'fly'; known: status"}
        crash = c.raw(b'{"cmd": "crash"}')
        assert crash["ok"] is False and "internal error" in crash["error"]
        with pytest.raises(IpcError, match="unknown command"):
            c.call("jump")
        assert c.call("status")["state"] == "disarmed"  # same connection still served
    # Binary garbage on a fresh connection.
    with ControlClient(server.path) as c:
        assert c.raw(b"\xff\xfe\x00")["ok"] is False
    assert request(server.path, "status")["state"] == "disarmed"
    assert server.errors == 7


def test_second_server_refused_and_stale_socket_replaced(server: ControlServer,
                                                         tmp_path: Path) -> None:
    with pytest.raises(DaemonRunning, match="already running"):
        ControlServer(server.path, handler).open()
    assert request(server.path, "status")["state"] == "disarmed"
    # A socket file nobody listens on (a daemon that died without cleaning up).
    stale = tmp_path / "stale.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(stale))
    s.close()
    srv = ControlServer(stale, handler)
    srv.start()
    try:
        assert request(stale, "status")["state"] == "disarmed"
    finally:
        srv.close()
    assert not stale.exists()
    # A regular file in the way.
    blocker = tmp_path / "file.sock"
    blocker.write_text("x")
    with pytest.raises(DaemonRunning, match="not a socket"):
        ControlServer(blocker, handler).open()


def test_no_daemon_is_one_clear_error(tmp_path: Path) -> None:
    with pytest.raises(IpcError, match="no mmctl daemon is running") as info:
        request(tmp_path / "none.sock", "status")
    assert "\n" not in str(info.value)


def test_peer_policy() -> None:
    me = os.getuid()
    assert peer_allowed(Peer(1, me, 12345), socket_gid=999, own_uid=me)
    assert peer_allowed(Peer(1, 0, 0), socket_gid=999, own_uid=1000)
    assert peer_allowed(Peer(1, 4242, 999), socket_gid=999, own_uid=1000)
    # Supplementary groups come from /proc/<pid>/status: our own process's groups.
    groups = os.getgroups()
    if groups:
        assert peer_allowed(Peer(os.getpid(), 4242, 4242), socket_gid=groups[0], own_uid=1000)
    assert not peer_allowed(Peer(2**22 + 7, 4242, 4242), socket_gid=999, own_uid=1000)


def test_socket_path_resolution() -> None:
    assert resolve_socket_path("/x/y.sock", {}) == Path("/x/y.sock")
    assert resolve_socket_path("", {"RUNTIME_DIRECTORY": "/run/mmctl", "XDG_RUNTIME_DIR": "/r"}) \
        == Path("/run/mmctl/mmctl.sock")
    assert resolve_socket_path("", {"XDG_RUNTIME_DIR": "/run/user/7"}) == \
        Path("/run/user/7/mmctl.sock")
    assert resolve_socket_path("", {}) == Path(f"/tmp/mmctl-{os.getuid()}/mmctl.sock")
