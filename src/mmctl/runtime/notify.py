"""sd_notify over the raw ``NOTIFY_SOCKET`` datagram socket (no libsystemd needed).

systemd sets ``NOTIFY_SOCKET`` (a path, or ``@name`` for an abstract socket) and, with
``WatchdogSec=``, ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``).  The daemon sends
``READY=1`` once its devices are connected and one healthy cycle ran, ``WATCHDOG=1``
from the loop thread at half the watchdog interval (so a stalled loop gets killed),
``STATUS=...`` on state/mode changes and ``STOPPING=1`` on shutdown.  Every send is
non-blocking: a full socket drops the datagram instead of stalling the loop.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Mapping

import structlog

log = structlog.get_logger("mmctl.notify")


def _address(raw: str) -> str | bytes:
    """'@name' -> abstract address (leading NUL); a path stays a path."""
    if raw.startswith("@"):
        return b"\0" + raw[1:].encode()
    return raw


class Notifier:
    """Client end of the systemd notify protocol; a no-op when not under systemd."""

    def __init__(self, environ: Mapping[str, str] | None = None):
        env = os.environ if environ is None else environ
        self.address = env.get("NOTIFY_SOCKET") or None
        self.watchdog_interval: float | None = None  # [s] between WATCHDOG=1 pings
        usec = env.get("WATCHDOG_USEC")
        pid = env.get("WATCHDOG_PID")
        if usec and (not pid or pid == str(os.getpid())):
            try:
                if int(usec) > 0:
                    self.watchdog_interval = int(usec) / 2e6
            except ValueError:
                log.warning("notify_bad_watchdog_usec", value=usec)
        self._sock: socket.socket | None = None
        self._next_ping_ns = 0
        self.dropped = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def connect(self) -> None:
        """Open the datagram socket (idempotent; nothing to do without NOTIFY_SOCKET)."""
        if self.address is None or self._sock is not None:
            return
        s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        s.setblocking(False)
        self._sock = s

    def close(self) -> None:
        """Close the socket (idempotent)."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def send(self, *fields: str) -> bool:
        """Send ``KEY=value`` lines as one datagram; False if dropped or not under systemd."""
        if self.address is None:
            return False
        if self._sock is None:
            self.connect()
        assert self._sock is not None
        try:
            self._sock.sendto("\n".join(fields).encode(), _address(self.address))
            return True
        except (BlockingIOError, InterruptedError):
            self.dropped += 1
            return False
        except OSError as exc:
            self.dropped += 1
            if self.dropped == 1 or self.dropped % 1000 == 0:
                log.warning("notify_send_failed", error=str(exc), dropped=self.dropped)
            return False

    def ready(self, status: str = "") -> bool:
        return self.send("READY=1", *((f"STATUS={status}",) if status else ()))

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def stopping(self, status: str = "") -> bool:
        return self.send("STOPPING=1", *((f"STATUS={status}",) if status else ()))

    def watchdog_tick(self, now_ns: int) -> bool:
        """Ping the watchdog if half its interval has passed since the last ping.

        Called every cycle from the loop thread; cheap when not due or not configured.
        """
        if self.watchdog_interval is None or now_ns < self._next_ping_ns:
            return False
        self._next_ping_ns = now_ns + int(self.watchdog_interval * 1e9)
        return self.send("WATCHDOG=1")
