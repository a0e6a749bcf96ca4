"""Turn a list of per-cycle samples into columns (pure numpy, no rerun).

The publisher stacks the samples it drained into one :class:`Columns` per rate: the
full-rate series (every sample: the trial-metric inputs) and the plot-rate series
(every ``stride``-th cycle).  The same row functions (:func:`force_norm`,
:func:`ee_speed`) are used by the trial tracker, so metrics computed live and metrics
recomputed from a recording see bit-identical inputs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.telemetry import layout
from mmctl.telemetry.sample import TelemetrySample

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


def norm3(x: F64) -> float:
    """‖x[:3]‖ of one vector, evaluated as ``sqrt((x0 x0 + x1 x1) + x2 x2)``.

    The loop-side trial tracker uses this scalar form; :func:`norm3_rows` is the same
    expression on columns, so both give bit-identical results (IEEE-754, no fusing).
    """
    x0, x1, x2 = float(x[0]), float(x[1]), float(x[2])
    return math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)


def norm3_rows(a: F64) -> F64:
    """:func:`norm3` of every row of an (n, >=3) array."""
    return np.sqrt(a[:, 0] * a[:, 0] + a[:, 1] * a[:, 1] + a[:, 2] * a[:, 2])


def force_norm(f_h: F64) -> F64:
    """‖f_h‖ per row of an (n, 6) wrench array: the norm of the force part [N]
    (the paper keeps the rotations fixed; ``mmctl.control.metrics`` does the same)."""
    return norm3_rows(f_h)


def ee_speed(twist: F64) -> F64:
    """‖v‖ per row of an (n, 6) twist array: the linear speed [m/s]."""
    return norm3_rows(twist)


def time_ns(t: F64) -> I64:
    """Seconds -> integer nanoseconds, as the ``time`` timeline stores them."""
    return np.round(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)


class Columns(NamedTuple):
    """Rows of several series sharing the same index.

    cycle: (n,) loop cycle indices; time_ns: (n,) deadline since the origin [ns];
    values: series path -> (n, k) float64 array (k = len(series.names)).
    """

    cycle: I64
    time_ns: I64
    values: dict[str, F64]

    def __len__(self) -> int:  # type: ignore[override]
        return int(self.cycle.shape[0])


def _stack(samples: Sequence[TelemetrySample], field: str) -> F64:
    return np.array([getattr(s, field) for s in samples], dtype=np.float64)


def _index(samples: Sequence[TelemetrySample]) -> tuple[I64, I64]:
    cycle = np.fromiter((s.cycle for s in samples), np.int64, len(samples))
    t = np.fromiter((s.t for s in samples), np.float64, len(samples))
    return cycle, time_ns(t)


def full_rate(samples: Sequence[TelemetrySample]) -> Columns:
    """The full-rate series of every sample (E_K, ‖f_h‖, speeds, p, p_des)."""
    cycle, t_ns = _index(samples)
    n = len(samples)
    energy = np.empty((n, 3))
    for i, s in enumerate(samples):
        energy[i, 0] = s.e_total
        energy[i, 1] = s.e_arm
        energy[i, 2] = s.e_base
    speed = np.empty((n, 2))
    speed[:, 0] = ee_speed(_stack(samples, "v_d").reshape(n, 6))
    speed[:, 1] = ee_speed(_stack(samples, "v").reshape(n, 6))
    return Columns(cycle, t_ns, {
        layout.ENERGY.path: energy,
        layout.FORCE_NORM.path: force_norm(_stack(samples, "f_h").reshape(n, 6))[:, None],
        layout.SPEED.path: speed,
        layout.EE_POSITION.path: _stack(samples, "p").reshape(n, 3),
        layout.EE_POSITION_DES.path: _stack(samples, "p_des").reshape(n, 3),
    })


def plot_rate(samples: Sequence[TelemetrySample], stride: int) -> Columns:
    """The plot-rate series of the samples whose cycle is a multiple of ``stride``."""
    picked = [s for s in samples if s.cycle % stride == 0]
    cycle, t_ns = _index(picked)
    n = len(picked)
    qd = _stack(picked, "qd_cmd").reshape(n, 9)
    return Columns(cycle, t_ns, {
        layout.FORCE.path: _stack(picked, "f_h").reshape(n, 6),
        layout.ARM_QD.path: qd[:, :6],
        layout.BASE_TWIST.path: qd[:, 6:],
        layout.WHEELS.path: _stack(picked, "wheels_cmd").reshape(n, 4),
    })


def plot_stride(loop_rate_hz: float, plot_rate_hz: float) -> int:
    """Cycles between two plot rows: round(loop rate / plot rate), at least 1."""
    return max(1, round(loop_rate_hz / plot_rate_hz))
