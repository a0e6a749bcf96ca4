"""What every device link's child process does first (the arm's, the sensor's, the
base's): leave the terminal's session, so that a terminal's Ctrl-C reaches the daemon
only; ignore the terminating signals, since the daemon sends its stop commands through
the child and then ends it; log as the daemon does; take the loop's real-time
priority and CPUs (before the transport connects: its threads inherit them)."""

from __future__ import annotations

import os
import signal
from collections.abc import Sequence


def start_device_child(log_setup: tuple[str, bool | None],
                       realtime: tuple[int, Sequence[int]] | None = None) -> None:
    """In a device link's child, before anything else (see the module doc)."""
    try:
        os.setsid()
    except OSError:
        pass
    for name in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"):
        signal.signal(getattr(signal, name), signal.SIG_IGN)
    from mmctl.runtime.logging import setup_logging

    setup_logging(log_setup[0], json=log_setup[1])
    if realtime is not None:
        from mmctl.runtime.loop import apply_realtime

        apply_realtime(realtime[0], tuple(realtime[1]))
