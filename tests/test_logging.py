"""structlog set-up: JSON lines off a TTY, the console renderer on one; the rate limiter."""

from __future__ import annotations

import io
import json

import structlog

from mmctl.runtime.logging import RateLimiter, setup_logging


class FakeTty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_json_lines_when_not_a_tty() -> None:
    out = io.StringIO()
    setup_logging("info", stream=out)
    structlog.get_logger("t").info("fault", cause="sensor_stale", age_ms=12.5)
    structlog.get_logger("t").debug("hidden")  # below the level
    (line,) = out.getvalue().splitlines()
    event = json.loads(line)
    assert event["event"] == "fault" and event["cause"] == "sensor_stale"
    assert event["age_ms"] == 12.5 and event["level"] == "info" and "timestamp" in event


def test_console_renderer_on_a_tty() -> None:
    out = FakeTty()
    setup_logging("warning", stream=out)
    structlog.get_logger("t").info("quiet")
    structlog.get_logger("t").warning("arm_stop_not_sent", why="not connected")
    text = out.getvalue()
    assert "quiet" not in text
    assert "arm_stop_not_sent" in text and "why='not connected'" in text
    assert not text.lstrip().startswith("{")


def test_rate_limiter_lets_one_event_per_interval_and_counts_the_rest() -> None:
    now = [0.0]
    lim = RateLimiter(1.0, clock=lambda: now[0])
    assert lim.allow("a") == 0
    assert lim.allow("a") is None and lim.allow("a") is None
    assert lim.allow("b") == 0  # keys are independent
    now[0] = 1.5
    assert lim.allow("a") == 2  # two suppressed since the last one let through
    assert lim.allow("a") is None
