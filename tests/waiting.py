"""Polling helper shared by the daemon tests (conditions, never timing, are asserted)."""

from __future__ import annotations

import subprocess
import time
from collections.abc import Callable
from typing import Any


def wait_for(pred: Callable[[], Any], what: str, timeout: float = 60.0,
             interval: float = 0.01) -> Any:
    """Poll ``pred()`` until it returns something truthy (returned); fail after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out waiting for {what}")


def wait_while_alive(pred: Callable[[], Any], what: str, proc: subprocess.Popen[bytes],
                     name: str, log_text: Callable[[], str], timeout: float = 180.0) -> Any:
    """Poll ``pred()`` (an IpcError or OSError counts as not yet) while ``proc`` (the
    ``name``d process) lives; fail with the tail of its log when it exits or on timeout."""
    from mmctl.errors import IpcError

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = pred()
        except (IpcError, OSError):
            value = None
        if value:
            return value
        if proc.poll() is not None:
            raise AssertionError(f"{name} exited ({proc.returncode}) while waiting for "
                                 f"{what}:\n{log_text()[-4000:]}")
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}\n{log_text()[-4000:]}")


def with_ur_program(log_text: Callable[[], str], sim_socket: Any) -> Callable[[], str]:
    """``log_text`` followed by the simulated UR's program events (started, stopped or
    paused, and why: its RTDE watchdog, a joint limit) and where the robot is, asked of
    the simulation at ``sim_socket``: what a failed wait most needs and the daemon's log
    cannot say."""
    from mmctl.errors import IpcError
    from mmctl.runtime.ipc import request

    def text() -> str:
        try:
            # (since now: no commands, which can be too many for one reply; the program
            # events come whole)
            events = request(sim_socket, "log", timeout=10.0,
                             since=time.monotonic())["program"]
            st = request(sim_socket, "status", timeout=10.0)
            where = {k: st.get(k) for k in ("arm_q", "arm_qd", "base_pose", "handle_world",
                                            "wheel_velocities", "push", "faults")}
        except (IpcError, OSError, KeyError) as exc:
            events, where = f"(not known: {exc})", {}
        return (f"{log_text()}\nthe UR's program events [controller time, text]: {events}"
                f"\nthe simulation now: {where}")
    return text
