"""What the simulated sensors measure: a :class:`WrenchSource` maps time to a wrench.

``t`` is the time since the fake sensor started [s]; the wrench is (fx, fy, fz, tx, ty,
tz) in the sensor frame [N, N m].  The daemon plugs the simulated human in through
:class:`CallableWrench`.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from mmctl.types import Vec


@runtime_checkable
class WrenchSource(Protocol):
    """Time [s] -> wrench (6,) [N, N m] in the sensor frame."""

    def wrench(self, t: float) -> Vec: ...


def as_wrench6(value: ArrayLike) -> Vec:
    """``value`` as a float (6,) array; ValueError for any other shape."""
    w = np.asarray(value, dtype=np.float64).reshape(-1)
    if w.shape != (6,):
        raise ValueError(f"a wrench has 6 components (fx, fy, fz, tx, ty, tz), got {w.shape[0]}")
    return w


class ConstantWrench:
    """The same wrench at every time."""

    def __init__(self, value: ArrayLike = (0.0,) * 6) -> None:
        self._w = as_wrench6(value)

    def wrench(self, t: float) -> Vec:
        return self._w.copy()


class ScriptedWrench:
    """A list of (t [s], wrench) points, held (step) or linearly interpolated.

    Before the first point the first wrench applies, after the last the last one.
    Times must increase strictly.
    """

    def __init__(self, points: Sequence[tuple[float, ArrayLike]], *, interpolate: bool = False):
        if not points:
            raise ValueError("a scripted wrench needs at least one (t, wrench) point")
        self._t = [float(t) for t, _ in points]
        if any(b <= a for a, b in zip(self._t, self._t[1:])):
            raise ValueError(f"scripted wrench times must increase strictly, got {self._t}")
        self._w = np.stack([as_wrench6(w) for _, w in points])
        self._interpolate = interpolate

    def wrench(self, t: float) -> Vec:
        i = bisect.bisect_right(self._t, t) - 1
        if i < 0:
            return self._row(0)
        if i >= len(self._t) - 1:
            return self._row(-1)
        if not self._interpolate:
            return self._row(i)
        s = (t - self._t[i]) / (self._t[i + 1] - self._t[i])
        w: Vec = (1.0 - s) * self._w[i] + s * self._w[i + 1]
        return w

    def _row(self, i: int) -> Vec:
        row: Vec = self._w[i].copy()
        return row


class CallableWrench:
    """Any function of time, e.g. the simulated human's hand force."""

    def __init__(self, fn: Callable[[float], ArrayLike]) -> None:
        self._fn = fn

    def wrench(self, t: float) -> Vec:
        return as_wrench6(self._fn(t))
