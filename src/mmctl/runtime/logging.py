"""structlog set-up: key-value events on stdout, console renderer on a TTY, JSON otherwise.

journald (or whatever collects stdout) does the rest.  The hot path logs only faults
and state changes, through a :class:`RateLimiter` so a flapping condition cannot
flood the log.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import TextIO

import structlog

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
           "error": logging.ERROR}


CURRENT: tuple[str, bool | None] = ("info", None)
"""(level, json) of the newest :func:`setup_logging`: what a child process of the daemon
(the arm's, the simulated robot's) sets up in turn on the stdout it inherits, so its
events join the daemon's stream."""


def setup_logging(level: str = "info", stream: TextIO | None = None,
                  json: bool | None = None) -> None:
    """Configure structlog for the process.

    level: "debug" | "info" | "warning" | "error"; stream: default sys.stdout;
    json: force the renderer (None = JSON unless the stream is a TTY).
    """
    out = stream if stream is not None else sys.stdout
    if json is None:
        json = not (hasattr(out, "isatty") and out.isatty())
    global CURRENT
    CURRENT = (level, json)
    renderer: structlog.typing.Processor = (structlog.processors.JSONRenderer() if json
                     else structlog.dev.ConsoleRenderer(colors=False))
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.format_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(_LEVELS.get(level, logging.INFO)),
        # one write() per event, its newline included: the arm's process writes to the
        # same stdout, and print()'s separate newline let their lines interleave
        logger_factory=structlog.WriteLoggerFactory(out),
        cache_logger_on_first_use=False,
    )


class RateLimiter:
    """At most one event per key per ``interval`` seconds; counts what it suppressed.

    ``allow(key)`` returns ``None`` when the event must be dropped, else the number of
    events suppressed since the last one let through (to log as ``suppressed=n``).
    """

    def __init__(self, interval: float = 1.0, clock: Callable[[], float] = time.monotonic):
        self.interval = interval
        self._clock = clock
        self._last: dict[str, float] = {}
        self._dropped: dict[str, int] = {}

    def allow(self, key: str) -> int | None:
        now = self._clock()
        last = self._last.get(key)
        if last is not None and now - last < self.interval:
            self._dropped[key] = self._dropped.get(key, 0) + 1
            return None
        self._last[key] = now
        return self._dropped.pop(key, 0)
