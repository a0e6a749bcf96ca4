"""The safety state machine (SPEC §5).

::

    DISARMED --enable (healthy)--> ARMED --any fault--> FAULT
        ^                            |                    |
        +---------- disable ---------+                    |
        +<--------- disable ----------------------------- +
    FAULT --enable (every cause gone)--> ARMED

The loop thread owns the machine: each cycle it calls :meth:`SafetyMonitor.update`
with the fault conditions present in that cycle; the return value says whether the
stop commands must go out *this* cycle.  Only ARMED commands motion.  A fault latches:
the machine stays in FAULT, even after the condition clears, until an operator enables
again, and enabling is refused while any condition is still present.  The daemon always
starts DISARMED.  One structured event names each fault; state changes are logged once.
"""

from __future__ import annotations

from collections.abc import Mapping
from enum import Enum
from typing import Any

import structlog

from mmctl.errors import FaultCause, MmctlError
from mmctl.runtime.logging import RateLimiter

log = structlog.get_logger("mmctl.safety")


class SafetyState(str, Enum):
    """Where the robot stands; only ARMED sends motion commands."""

    DISARMED = "disarmed"
    ARMED = "armed"
    FAULT = "fault"


class EnableRefused(MmctlError):
    """``enable`` was asked while a fault condition is present (or a device is unhealthy)."""

    def __init__(self, causes: list[FaultCause], details: Mapping[FaultCause, Mapping[str, Any]]):
        self.causes = causes
        names = ", ".join(c.value for c in causes)
        super().__init__(f"refused to enable: fault condition present ({names})")
        self.details = {c.value: dict(details.get(c, {})) for c in causes}


Conditions = Mapping[FaultCause, Mapping[str, Any]]


class SafetyMonitor:
    """DISARMED / ARMED / FAULT with a latched cause. Not thread-safe: loop thread only."""

    def __init__(self, log_interval: float = 1.0):
        self.state = SafetyState.DISARMED
        self.latched: FaultCause | None = None
        self.latched_details: dict[str, Any] = {}
        self.active: dict[FaultCause, dict[str, Any]] = {}
        self.faults = 0
        self._limiter = RateLimiter(log_interval)

    @property
    def armed(self) -> bool:
        return self.state is SafetyState.ARMED

    def update(self, conditions: Conditions) -> bool:
        """Feed this cycle's fault conditions; True when the stop must be sent now."""
        before = set(self.active)
        self.active = {c: dict(d) for c, d in conditions.items()}
        if self.state is SafetyState.ARMED and self.active:
            cause, details = next(iter(self.active.items()))
            self._to_fault(cause, details)
            return True
        if set(self.active) != before and self.state is not SafetyState.ARMED:
            suppressed = self._limiter.allow("conditions")
            if suppressed is not None:
                log.info("fault_conditions", state=self.state.value,
                         present=sorted(c.value for c in self.active),
                         suppressed=suppressed)
        return False

    def trip(self, cause: FaultCause, **details: Any) -> bool:
        """Fault right now (e.g. an exception in the cycle); True if newly ARMED -> FAULT."""
        if self.state is SafetyState.ARMED:
            self._to_fault(cause, details)
            return True
        return False

    def enable(self, conditions: Conditions | None = None) -> None:
        """Operator re-arm; raises :class:`EnableRefused` while any condition is present.

        conditions: a fresh evaluation to use instead of the last cycle's (e.g. after
        the caller reset a device's latched fault).
        """
        if conditions is not None:
            self.active = {c: dict(d) for c, d in conditions.items()}
        if self.active:
            raise EnableRefused(list(self.active), self.active)
        if self.state is not SafetyState.ARMED:
            self._set(SafetyState.ARMED, reason="enable")
            self.latched = None
            self.latched_details = {}

    def disable(self) -> bool:
        """Operator disarm; True when the stop must be sent (we were ARMED)."""
        was_armed = self.state is SafetyState.ARMED
        if self.state is not SafetyState.DISARMED:
            self._set(SafetyState.DISARMED, reason="disable")
            self.latched = None
            self.latched_details = {}
        return was_armed

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON status."""
        return {
            "state": self.state.value,
            "fault": self.latched.value if self.latched else None,
            "fault_details": {k: _plain(v) for k, v in self.latched_details.items()},
            "conditions": sorted(c.value for c in self.active),
            "faults": self.faults,
        }

    def _to_fault(self, cause: FaultCause, details: Mapping[str, Any]) -> None:
        self.latched = cause
        self.latched_details = dict(details)
        self.faults += 1
        log.error("fault", cause=cause.value, **{k: _plain(v) for k, v in details.items()})
        self._set(SafetyState.FAULT, reason=cause.value)

    def _set(self, new: SafetyState, reason: str) -> None:
        old, self.state = self.state, new
        log.info("safety_state", old=old.value, new=new.value, reason=reason)


def _plain(v: Any) -> Any:
    """A JSON-friendly version of a detail value."""
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    if isinstance(v, Enum):
        return v.value
    try:
        return [float(x) for x in v]
    except (TypeError, ValueError):
        return repr(v)
