"""The safety state machine (SPEC §5) as a value and pure transitions.

::

    DISARMED --enable (healthy)--> ARMED --any fault--> FAULT
        ^                            |                    |
        +---------- disable ---------+                    |
        +<--------- disable ----------------------------- +
    FAULT --enable (every cause gone)--> ARMED

:class:`Safety` is frozen; each transition returns the next value and the events it
raised (:class:`FaultRaised`, :class:`StateChanged`, :class:`ConditionsChanged`), which
the runtime logs.  No I/O, no clock, no logging here.  Each cycle
:func:`observe` takes the fault conditions present in that cycle and says whether the
stop commands must go out *this* cycle.  Only ARMED commands motion.  A fault latches:
FAULT stays, even after the condition clears, until an operator enables again, and
enabling is refused while any condition is still present.  The daemon always starts
DISARMED.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, NamedTuple

from mmctl.errors import FaultCause, MmctlError

Conditions = Mapping[FaultCause, Mapping[str, Any]]
"""The fault conditions present in one cycle: cause -> details (for the fault event)."""


class SafetyState(str, Enum):
    """Where the robot stands; only ARMED sends motion commands."""

    DISARMED = "disarmed"
    ARMED = "armed"
    FAULT = "fault"


class EnableRefused(MmctlError):
    """``enable`` was asked while a fault condition is present (or a device is unhealthy)."""

    def __init__(self, causes: list[FaultCause], details: Conditions):
        self.causes = causes
        names = ", ".join(c.value for c in causes)
        super().__init__(f"refused to enable: fault condition present ({names})")
        self.details = {c.value: dict(details.get(c, {})) for c in causes}


class FaultRaised(NamedTuple):
    """ARMED -> FAULT: the cause and its details (one event per fault)."""

    cause: FaultCause
    details: Mapping[str, Any]


class StateChanged(NamedTuple):
    """The safety state changed (``reason``: ``enable``, ``disable`` or the cause)."""

    old: SafetyState
    new: SafetyState
    reason: str


class ConditionsChanged(NamedTuple):
    """Not armed: the set of conditions present changed (``present``: their names)."""

    state: SafetyState
    present: tuple[str, ...]


SafetyEvent = FaultRaised | StateChanged | ConditionsChanged
_NONE: tuple[SafetyEvent, ...] = ()


@dataclass(frozen=True)
class Safety:
    """The machine's value: state, the latched cause (and its details), the conditions
    present in the last cycle, and how many faults so far."""

    state: SafetyState = SafetyState.DISARMED
    latched: FaultCause | None = None
    latched_details: Mapping[str, Any] = field(default_factory=dict)
    active: Mapping[FaultCause, Mapping[str, Any]] = field(default_factory=dict)
    faults: int = 0

    @property
    def armed(self) -> bool:
        return self.state is SafetyState.ARMED

    def as_dict(self) -> dict[str, Any]:
        """Plain-JSON status."""
        return {
            "state": self.state.value,
            "fault": self.latched.value if self.latched else None,
            "fault_details": {k: plain(v) for k, v in self.latched_details.items()},
            "conditions": sorted(c.value for c in self.active),
            "faults": self.faults,
        }


def _copy(conditions: Conditions) -> dict[FaultCause, Mapping[str, Any]]:
    return {c: dict(d) for c, d in conditions.items()}


def observe(s: Safety, conditions: Conditions) -> tuple[Safety, bool, tuple[SafetyEvent, ...]]:
    """This cycle's conditions: the next value, whether the stop goes out now, events."""
    if not conditions and not s.active:  # the common case: nothing to copy
        return s, False, _NONE
    active = _copy(conditions)
    if s.state is SafetyState.ARMED and active:
        cause, details = next(iter(active.items()))
        nxt, events = _to_fault(s, cause, details)
        return _replace(nxt, active=active), True, events
    changed = active.keys() != s.active.keys()
    nxt = _replace(s, active=active)
    if changed:
        return nxt, False, (ConditionsChanged(s.state, tuple(sorted(c.value for c in active))),)
    return nxt, False, _NONE


def trip(s: Safety, cause: FaultCause, details: Mapping[str, Any]
         ) -> tuple[Safety, bool, tuple[SafetyEvent, ...]]:
    """Fault right now (e.g. a command that failed); True if newly ARMED -> FAULT."""
    if s.state is SafetyState.ARMED:
        nxt, events = _to_fault(s, cause, details)
        return nxt, True, events
    return s, False, _NONE


def enable(s: Safety, conditions: Conditions | None = None
           ) -> tuple[Safety, tuple[SafetyEvent, ...]]:
    """Operator re-arm; raises :class:`EnableRefused` while any condition is present.

    conditions: a fresh evaluation to judge instead of the last cycle's."""
    active = s.active if conditions is None else _copy(conditions)
    if active:
        raise EnableRefused(list(active), active)
    if s.state is SafetyState.ARMED:
        return _replace(s, active=active), _NONE
    return (Safety(SafetyState.ARMED, None, {}, active, s.faults),
            (StateChanged(s.state, SafetyState.ARMED, "enable"),))


def disable(s: Safety) -> tuple[Safety, bool, tuple[SafetyEvent, ...]]:
    """Operator disarm; True when the stop must be sent (we were ARMED)."""
    if s.state is SafetyState.DISARMED:
        return s, False, _NONE
    return (Safety(SafetyState.DISARMED, None, {}, s.active, s.faults), s.armed,
            (StateChanged(s.state, SafetyState.DISARMED, "disable"),))


def _to_fault(s: Safety, cause: FaultCause, details: Mapping[str, Any]
              ) -> tuple[Safety, tuple[SafetyEvent, ...]]:
    nxt = Safety(SafetyState.FAULT, cause, dict(details), s.active, s.faults + 1)
    return nxt, (FaultRaised(cause, dict(details)),
                 StateChanged(s.state, SafetyState.FAULT, cause.value))


def _replace(s: Safety, **kw: Any) -> Safety:
    return Safety(**{"state": s.state, "latched": s.latched,
                     "latched_details": s.latched_details, "active": s.active,
                     "faults": s.faults, **kw})


def plain(v: Any) -> Any:
    """A JSON-friendly version of a detail value."""
    if isinstance(v, (str, int, float, bool)) or v is None:
        return v
    if isinstance(v, Enum):
        return v.value
    try:
        return [float(x) for x in v]
    except (TypeError, ValueError):
        return repr(v)
