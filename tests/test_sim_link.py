"""The daemon's link to the simulated robot: attach to one that runs, even a slow one."""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest
import structlog

from mmctl.config import config_from_dict
from mmctl.errors import MmctlError
from mmctl.runtime.ipc import ControlServer, Peer
from mmctl.runtime.sim_link import SimLink


class _SlowSim:
    """A control socket that answers ``status`` only after ``delay`` [s] (a starved
    simulation), counting the requests."""

    def __init__(self, delay: float) -> None:
        self.delay = delay
        self.calls = 0
        self.lock = threading.Lock()

    def __call__(self, req: Mapping[str, Any], _peer: Peer) -> Any:
        with self.lock:
            self.calls += 1
        time.sleep(self.delay)
        return {"pid": 4242, "answered_after_s": self.delay}


def _link(path: Path, ready_timeout: float) -> SimLink:
    cfg = config_from_dict({"sim": {"socket_path": str(path), "ready_timeout": ready_timeout}})
    return SimLink(cfg)


def test_a_simulation_slow_to_answer_is_attached_not_replaced(tmp_path: Path) -> None:
    """The first status request times out (2 s) on a simulation that answers after 3 s:
    the daemon waits for it and attaches, and starts no second one (which could only
    fail on the socket in use: seen in CI with both cores busy)."""
    slow = _SlowSim(3.0)
    srv = ControlServer(tmp_path / "sim.sock", slow)
    srv.start()
    try:
        link = _link(srv.path, 30.0)
        with structlog.testing.capture_logs() as logs:
            link.start()
        assert link.pid == 4242 and not link.owned and link.proc is None
        events = [e["event"] for e in logs]
        assert "sim_slow_to_answer" in events and "sim_attached" in events, events
        assert slow.calls >= 2
    finally:
        srv.close()


def test_a_simulation_that_never_answers_is_an_error_naming_the_socket(tmp_path: Path) -> None:
    slow = _SlowSim(8.0)
    srv = ControlServer(tmp_path / "sim.sock", slow)
    srv.start()
    try:
        link = _link(srv.path, 1.0)
        with pytest.raises(MmctlError, match="accepts connections but did not answer within "
                                             "sim.ready_timeout = 1 s"):
            link.start()
        assert link.proc is None
    finally:
        srv.close()


def test_a_stale_socket_file_is_no_simulation(tmp_path: Path) -> None:
    """A socket file nothing listens on: no wait (a simulation would be started)."""
    import socket

    path = tmp_path / "sim.sock"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(str(path))
    s.close()  # the file stays, nothing listens
    link = _link(path, 1.0)  # (a wait would end in MmctlError after 1 s)
    assert link._wait_for_a_slow_one(lambda: False) is None
