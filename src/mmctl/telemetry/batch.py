"""Turn the sample rows the publisher took from the ring into columns (pure numpy).

The publisher slices the rows (:mod:`mmctl.telemetry.ring`) into one :class:`Columns`
per rate: the full-rate series (every sample: the trial-metric inputs), the plot-rate
series (every ``stride``-th cycle) and the loop timing.  What the loop leaves out of a
row to keep its work small is derived here: positions in the mobile base frame
(:func:`base_frame`) and the wheel speeds (:func:`wheel_speeds`).  The same row
functions (:func:`force_norm`, :func:`ee_speed`, :func:`base_frame`) are used by the
trial tracker, so metrics computed live and metrics recomputed from a recording see
bit-identical inputs.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.telemetry import layout, ring

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

    def __len__(self) -> int:
        return int(self.cycle.shape[0])


def _index(rows: F64) -> tuple[I64, I64]:
    return rows[:, ring.CYCLE].astype(np.int64), time_ns(rows[:, ring.T])


def base_frame(rows: F64, cols: slice) -> F64:
    """World positions (columns ``cols`` of the rows) in the mobile base frame: the
    offset from the base origin rotated by -yaw [m].

    Row by row the same expressions (``math.cos``/``math.sin`` of each yaw, then
    elementwise products and sums), so one row alone gives bit-identical results
    to the same row among many: the trial tracker relies on that for x_f.
    """
    yaw = rows[:, ring.BASE_YAW].tolist()
    c = np.array([math.cos(a) for a in yaw])
    s = np.array([math.sin(a) for a in yaw])
    dx = rows[:, cols.start] - rows[:, ring.BASE_X]
    dy = rows[:, cols.start + 1] - rows[:, ring.BASE_Y]
    out = np.empty((len(rows), 3))
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    out[:, 2] = rows[:, cols.start + 2]
    return out


def wheel_speeds(rows: F64, wheels: F64) -> F64:
    """Commanded wheel speeds (n, 4) [rad/s] from the rows' base twist command and the
    (4, 3) wheel matrix (:func:`mmctl.control.mecanum.wheel_matrix`)."""
    return rows[:, ring.BASE_TWIST] @ wheels.T


def full_rate(rows: F64) -> Columns:
    """The full-rate series of every row (E_K, ‖f_h‖, speeds, p, p_des in the base
    frame) of an (n, ring.WIDTH) array of sample rows (:mod:`mmctl.telemetry.ring`)."""
    cycle, t_ns = _index(rows)
    speed = np.empty((len(rows), 2))
    speed[:, 0] = ee_speed(rows[:, ring.V_D])
    speed[:, 1] = ee_speed(rows[:, ring.V])
    return Columns(cycle, t_ns, {
        layout.ENERGY.path: rows[:, ring.ENERGY].copy(),
        layout.FORCE_NORM.path: force_norm(rows[:, ring.F_H])[:, None],
        layout.SPEED.path: speed,
        layout.EE_POSITION.path: base_frame(rows, ring.P),
        layout.EE_POSITION_DES.path: base_frame(rows, ring.P_DES),
    })


def plot_rate(rows: F64, stride: int, wheels: F64) -> Columns:
    """The plot-rate series of the rows whose cycle is a multiple of ``stride``;
    wheels: the (4, 3) wheel matrix."""
    picked = rows[rows[:, ring.CYCLE].astype(np.int64) % stride == 0]
    cycle, t_ns = _index(picked)
    qd = picked[:, ring.QD_CMD]
    return Columns(cycle, t_ns, {
        layout.FORCE.path: picked[:, ring.F_H].copy(),
        layout.ARM_QD.path: qd[:, :6].copy(),
        layout.BASE_TWIST.path: qd[:, 6:].copy(),
        layout.WHEELS.path: wheel_speeds(picked, wheels),
        layout.LIMIT_SCALE.path: picked[:, ring.LIMIT_SCALE:ring.LIMIT_SCALE + 1].copy(),
        layout.NEAREST.path: picked[:, ring.NEAREST:ring.NEAREST + 1].copy(),
    })


def loop_timing(rows: F64, period_ns: int) -> Columns:
    """The loop timing each row carries for the cycle before it (compute, slack,
    latency [us]) at that cycle's index and deadline (rows without timing skipped)."""
    had = rows[np.isfinite(rows[:, ring.PREV_COMPUTE])]
    cycle, t_ns = _index(had)
    missed = had[:, ring.PREV_MISSED].astype(np.int64)
    values = np.empty((len(had), 3))
    values[:, 0] = had[:, ring.PREV_COMPUTE] * 1e-3
    values[:, 1] = had[:, ring.PREV_SLACK] * 1e-3
    values[:, 2] = had[:, ring.PREV_LATENCY] * 1e-3
    # the previous deadline: after a late cycle the loop skips ``missed`` periods
    return Columns(cycle - 1, t_ns - period_ns * (1 + missed), {layout.LOOP_TIMING.path: values})


def plot_stride(loop_rate_hz: float, plot_rate_hz: float) -> int:
    """Cycles between two plot rows: round(loop rate / plot rate), at least 1."""
    return max(1, round(loop_rate_hz / plot_rate_hz))
