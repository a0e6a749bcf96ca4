"""Rare, discrete telemetry items: text events and named values at one cycle."""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

from mmctl.telemetry import layout


class Event(NamedTuple):
    """Something that happened at one cycle.

    cycle: loop cycle index; t: time since the loop's origin [s]; text: one line for
    the viewer's text log (empty: none); level: "INFO" | "WARN" | "ERROR";
    entity: where ``values`` go; values: named numbers/strings logged as one row
    (e.g. a trial's metrics), or None.
    """

    cycle: int
    t: float
    text: str
    level: str = "INFO"
    entity: str = layout.EVENTS
    values: Mapping[str, float | int | str] | None = None
