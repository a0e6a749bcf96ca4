"""Polling helper shared by the daemon tests (conditions, never timing, are asserted)."""

from __future__ import annotations

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
