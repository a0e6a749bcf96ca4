"""Wrench sources that feed the simulated sensors."""

from __future__ import annotations

import numpy as np
import pytest

from mmctl.sim.wrench_source import (
    CallableWrench,
    ConstantWrench,
    ScriptedWrench,
    WrenchSource,
)


def test_constant() -> None:
    src = ConstantWrench([1, 2, 3, 4, 5, 6])
    assert isinstance(src, WrenchSource)
    out = src.wrench(12.0)
    out[0] = 99.0  # callers may not mutate the source through the result
    np.testing.assert_array_equal(src.wrench(0.0), [1, 2, 3, 4, 5, 6])


def test_scripted_hold_and_interpolate() -> None:
    pts = [(0.0, [0] * 6), (1.0, [10, 0, 0, 0, 0, 1]), (2.0, [0, 20, 0, 0, 0, 0])]
    hold = ScriptedWrench(pts)
    lerp = ScriptedWrench(pts, interpolate=True)
    assert hold.wrench(-1.0)[0] == 0.0
    assert hold.wrench(0.5)[0] == 0.0
    assert hold.wrench(1.0)[0] == 10.0
    assert hold.wrench(1.99)[5] == 1.0
    assert hold.wrench(5.0)[1] == 20.0
    np.testing.assert_allclose(lerp.wrench(0.5), [5, 0, 0, 0, 0, 0.5])
    np.testing.assert_allclose(lerp.wrench(1.5), [5, 10, 0, 0, 0, 0.5])
    np.testing.assert_allclose(lerp.wrench(3.0), [0, 20, 0, 0, 0, 0])


def test_callable() -> None:
    src = CallableWrench(lambda t: [t, 0, 0, 0, 0, -t])
    np.testing.assert_array_equal(src.wrench(2.0), [2, 0, 0, 0, 0, -2])


@pytest.mark.parametrize(
    "make",
    [lambda: ConstantWrench([1, 2, 3]), lambda: ScriptedWrench([]),
     lambda: ScriptedWrench([(1.0, [0] * 6), (1.0, [0] * 6)]),
     lambda: CallableWrench(lambda t: [0] * 5).wrench(0.0)],
)
def test_bad_sources_are_refused(make) -> None:
    with pytest.raises(ValueError):
        make()
