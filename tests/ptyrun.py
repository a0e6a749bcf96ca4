"""A command run with its stdout (and stderr if asked) on a fresh pty, everything the
terminal received read back (the live view's tests, `mmctl run`'s first-run tests)."""

from __future__ import annotations

import fcntl
import os
import struct
import subprocess
import termios
import threading
from collections.abc import Mapping


def run_on_pty(cmd: list[str], *, columns: int = 100, rows: int = 30,
               env: Mapping[str, str] | None = None, stderr_on_pty: bool = True,
               cwd: str | None = None, timeout: float = 300.0) -> tuple[int, str, str]:
    """Run ``cmd`` on a pty of ``columns`` x ``rows``: (exit code, what the terminal
    received, stderr when not on the pty).  The read ends when every holder of the
    pty (the command and its children) has closed it."""
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, columns, 0, 0))
    received = bytearray()

    def read_all() -> None:
        while True:
            try:
                chunk = os.read(master, 1 << 16)
            except OSError:  # EIO: every slave fd is closed (the program and its children)
                return
            if not chunk:
                return
            received.extend(chunk)

    reader = threading.Thread(target=read_all, daemon=True)
    reader.start()
    try:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=slave,
                                stderr=slave if stderr_on_pty else subprocess.PIPE,
                                env=dict(env) if env is not None else None, cwd=cwd)
    finally:
        os.close(slave)
    try:
        _, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(timeout=60)
    os.close(master)
    assert not reader.is_alive()
    return (proc.returncode, received.decode("utf-8", errors="replace"),
            (err or b"").decode(errors="replace"))
