"""sd_notify over the raw datagram socket: path and abstract addresses, watchdog pacing."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from mmctl.runtime.notify import Notifier


def _listener(addr: str | bytes) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(addr)
    s.settimeout(10.0)
    return s


def test_ready_status_stopping_to_a_path(tmp_path: Path) -> None:
    path = str(tmp_path / "notify")
    srv = _listener(path)
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("state=disarmed")
    assert srv.recv(4096) == b"READY=1\nSTATUS=state=disarmed"
    assert n.status("mode=min-energy")
    assert srv.recv(4096) == b"STATUS=mode=min-energy"
    assert n.stopping()
    assert srv.recv(4096) == b"STOPPING=1"
    n.close()
    n.close()
    srv.close()


def test_abstract_address_and_watchdog_pacing() -> None:
    name = f"mmctl-test-notify-{os.getpid()}"
    srv = _listener(b"\0" + name.encode())
    n = Notifier({"NOTIFY_SOCKET": "@" + name, "WATCHDOG_USEC": "2000000",
                  "WATCHDOG_PID": str(os.getpid())})
    assert n.watchdog_interval == 1.0
    assert n.watchdog_tick(10_000_000_000)
    assert srv.recv(64) == b"WATCHDOG=1"
    assert not n.watchdog_tick(10_500_000_000)  # not due yet: half interval is 1 s
    assert n.watchdog_tick(11_000_000_000)
    assert srv.recv(64) == b"WATCHDOG=1"
    srv.close()


def test_noop_without_systemd_and_other_pids_watchdog() -> None:
    n = Notifier({})
    assert not n.enabled and not n.ready() and not n.watchdog_tick(0)
    other = Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"})
    assert other.watchdog_interval is None or os.getpid() == 1


def test_missing_listener_is_counted_not_raised(tmp_path: Path) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "nobody")})
    assert not n.ready()
    assert n.dropped == 1
