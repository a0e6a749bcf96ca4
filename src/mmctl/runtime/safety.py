"""The safety state machine as the runtime holds it: :class:`SafetyMonitor` keeps a
:class:`~mmctl.control.safety.Safety` value, applies the pure transitions of
:mod:`mmctl.control.safety` and logs their events (one structured ``fault`` event per
fault, each state change once, the conditions present while not armed, rate-limited).

The loop's own cycle does not go through this class: its pure update
(:mod:`mmctl.control.update`) owns the value, and the runtime logs the events with
:func:`log_events`.  This wrapper is for tools and tests that drive the machine alone.
"""

from __future__ import annotations

from collections.abc import Iterable

import structlog

from mmctl.control import safety as pure
from mmctl.control.safety import (
    Conditions,
    ConditionsChanged,
    EnableRefused,
    FaultRaised,
    Safety,
    SafetyState,
    StateChanged,
)
from mmctl.errors import FaultCause
from mmctl.runtime.logging import RateLimiter

__all__ = ["Conditions", "EnableRefused", "SafetyMonitor", "SafetyState", "log_events"]

log = structlog.get_logger("mmctl.safety")


def log_events(events: Iterable[object], limiter: RateLimiter) -> None:
    """Log the safety events of one transition (``fault_conditions`` rate-limited)."""
    for ev in events:
        if isinstance(ev, FaultRaised):
            log.error("fault", cause=ev.cause.value,
                      **{k: pure.plain(v) for k, v in ev.details.items()})
        elif isinstance(ev, StateChanged):
            log.info("safety_state", old=ev.old.value, new=ev.new.value, reason=ev.reason)
        elif isinstance(ev, ConditionsChanged):
            suppressed = limiter.allow("conditions")
            if suppressed is not None:
                log.info("fault_conditions", state=ev.state.value, present=list(ev.present),
                         suppressed=suppressed)


class SafetyMonitor:
    """DISARMED / ARMED / FAULT with a latched cause. Not thread-safe: one thread only."""

    def __init__(self, log_interval: float = 1.0):
        self.value = Safety()
        self._limiter = RateLimiter(log_interval)

    @property
    def state(self) -> SafetyState:
        return self.value.state

    @property
    def latched(self) -> FaultCause | None:
        return self.value.latched

    @property
    def latched_details(self) -> dict[str, object]:
        return dict(self.value.latched_details)

    @property
    def active(self) -> dict[FaultCause, dict[str, object]]:
        return {c: dict(d) for c, d in self.value.active.items()}

    @property
    def faults(self) -> int:
        return self.value.faults

    @property
    def armed(self) -> bool:
        return self.value.armed

    def update(self, conditions: Conditions) -> bool:
        """Feed this cycle's fault conditions; True when the stop must be sent now."""
        self.value, stop, events = pure.observe(self.value, conditions)
        log_events(events, self._limiter)
        return stop

    def trip(self, cause: FaultCause, **details: object) -> bool:
        """Fault right now (e.g. an exception in the cycle); True if newly ARMED -> FAULT."""
        self.value, stop, events = pure.trip(self.value, cause, details)
        log_events(events, self._limiter)
        return stop

    def enable(self, conditions: Conditions | None = None) -> None:
        """Operator re-arm; raises :class:`EnableRefused` while any condition is present.

        conditions: a fresh evaluation to use instead of the last cycle's."""
        if conditions is not None:  # judged and kept even when refused
            self.value = pure.Safety(self.value.state, self.value.latched,
                                     self.value.latched_details,
                                     {c: dict(d) for c, d in conditions.items()},
                                     self.value.faults)
        self.value, events = pure.enable(self.value)
        log_events(events, self._limiter)

    def disable(self) -> bool:
        """Operator disarm; True when the stop must be sent (we were ARMED)."""
        self.value, stop, events = pure.disable(self.value)
        log_events(events, self._limiter)
        return stop

    def as_dict(self) -> dict[str, object]:
        """Plain-JSON status."""
        return self.value.as_dict()
