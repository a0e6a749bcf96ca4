"""Values the study passes around: one execution's metrics and time series, and the
paper's reference numbers."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

#: The five metrics, in the paper's column order.
METRICS: tuple[str, ...] = ("E", "F_h", "v", "x_f", "T_f")
#: Beyond the paper's: x_f after the end-of-trial hold (issue 19).
EXTRA_METRICS: tuple[str, ...] = ("x_f_hold",)
#: What the tables, results.csv and summary.json report: the paper's five, then ours.
REPORT_METRICS: tuple[str, ...] = (*METRICS, *EXTRA_METRICS)
#: Column headers as the paper prints them.
METRIC_LABELS: dict[str, str] = {
    "E": "Ē [J]", "F_h": "F̄_h [N]", "v": "v̄ [m/s]", "x_f": "x_f [m]", "T_f": "T_f [s]",
    "x_f_hold": "x_f hold [m]",
}
#: How each approach is named in the paper's tables.
APPROACH_NAMES: dict[str, str] = {
    "locomotion": "Locomotion",
    "switch": "Switch",
    "min-energy": "Minimum Energy",
    "manipulation": "Manipulation",
    "constrained-min-energy": "Constrained Min. Energy",
}
#: [s] after T_f, within the end-of-trial hold, at which x_f is read again
#: (:attr:`Execution.x_f_after`; issue 32: when does the paper's x_f = 0.08 m hold?).
X_F_DELAYS: tuple[float, ...] = (0.5, 1.0, 2.0)

#: The paper's approaches, in its order.
PAPER_APPROACHES: tuple[str, ...] = ("locomotion", "switch", "min-energy")

#: The paper's medians (Tables I-III; SPEC §4).
PAPER_MEDIANS: dict[str, dict[str, float]] = {
    "locomotion": {"E": 2.52, "F_h": 15.84, "v": 0.16, "x_f": 0.09, "T_f": 31.77},
    "switch": {"E": 0.95, "F_h": 11.31, "v": 0.14, "x_f": 0.28, "T_f": 32.97},
    "min-energy": {"E": 0.86, "F_h": 12.30, "v": 0.14, "x_f": 0.08, "T_f": 28.33},
}

#: The paper's Holm-corrected p-values (Table IV), keyed by metric then (a, b).
PAPER_PCORR: dict[str, dict[tuple[str, str], float]] = {
    "E": {("locomotion", "switch"): 1.682e-5, ("locomotion", "min-energy"): 1.682e-5,
          ("switch", "min-energy"): 0.337},
    "F_h": {("locomotion", "switch"): 9.410e-4, ("locomotion", "min-energy"): 0.0153,
            ("switch", "min-energy"): 0.0609},
    "v": {("locomotion", "switch"): 0.0172, ("locomotion", "min-energy"): 0.0977,
          ("switch", "min-energy"): 0.0977},
    "x_f": {("locomotion", "switch"): 1.682e-5, ("locomotion", "min-energy"): 0.414,
            ("switch", "min-energy"): 1.682e-5},
    "T_f": {("locomotion", "switch"): 0.0285, ("locomotion", "min-energy"): 0.0285,
            ("switch", "min-energy"): 4.412e-4},
}


class Series(NamedTuple):
    """Decimated time series of one execution (float32 to keep them small).

    t [s]; speed: end-effector linear speed ||v|| [m/s]; energy: E_K [J] from the
    actual velocities; energy_base: the base's share [J]; force: ||f_h|| [N];
    deviation: ||p - p_des|| of the handle relative to the base [m] (x_f at T_f);
    locomotion: 1 where the switch strategy was in locomotion, else 0.
    """

    t: NDArray[np.float32]
    speed: NDArray[np.float32]
    energy: NDArray[np.float32]
    energy_base: NDArray[np.float32]
    force: NDArray[np.float32]
    deviation: NDArray[np.float32]
    locomotion: NDArray[np.int8]


class Execution(NamedTuple):
    """One user with one approach.

    E [J], F_h [N], v [m/s], x_f [m], T_f [s]: the paper's metrics, every one from what
    the robot measures (one velocity source, as a real study's log: the arm's joints
    and the base's wheel odometry; E and v both from those velocities), F_h as the
    paper defines it, ||f_h|| of the wrench after the sensor chain (bias, handle
    weight, filter, the 2 N dead band: what the controller is pushed with);
    F_applied [N]: the mean force the person's hand applied, before the sensor chain;
    E_base [J]: mean kinetic energy of the base alone; F_max [N]: peak ||f_h||;
    wall_clearance [m]: the smallest distance of the base's deck (its footprint) to
    the task's surface plane (the wall's face as the handle meets it), from the base's
    true pose; E_base_near [J]: the base's mean kinetic energy while its deck was within
    :data:`NEAR_WALL` of that plane (NaN: never); switches: presses
    of the handle's mode button (only the switch condition has one: 0 otherwise);
    completed: the user finished
    the last insertion before the time limit (otherwise T_f is the limit); x_f_hold
    [m]: x_f at the end of the end-of-trial hold (the peg kept in the last hole
    ``hold_time`` after T_f; = x_f when unfinished); faults:
    cycles on which the controller reported a fault; stopped: the fault the safety
    state machine latched and stopped the robot for (nobody re-enables in a study:
    the execution then ends unfinished), "" when none; limited: fraction of the samples
    k = 1..N on which a limit bound the controller's command (``StepOutputs.limit``
    not empty: any of :data:`mmctl.control.limits.LIMIT_NAMES`; the sweep reports it);
    x_f_after [m]: x_f read :data:`X_F_DELAYS` after T_f, one per delay (the cycle
    ``round(delay / dt)`` after T_f's, the hold's last if the hold is shorter; = x_f
    when unfinished; empty: an execution made before issue 32).
    """

    user: int
    strategy: str
    E: float
    F_h: float
    v: float
    x_f: float
    T_f: float
    E_base: float
    F_max: float
    switches: int
    completed: bool
    faults: int
    series: Series
    limited: float = 0.0
    x_f_hold: float = math.nan
    stopped: str = ""
    F_applied: float = math.nan
    wall_clearance: float = math.nan
    E_base_near: float = math.nan
    x_f_after: tuple[float, ...] = ()

    def metric(self, name: str) -> float:
        """One of :data:`METRICS` by name."""
        return float(getattr(self, name))


#: [m] "near the wall" for :attr:`Execution.E_base_near`
NEAR_WALL = 0.5

#: results.csv columns, in order.
CSV_COLUMNS: tuple[str, ...] = (
    "user", "strategy", *REPORT_METRICS, "E_base", "F_max", "switches", "completed",
    "faults", "stopped", "limited", "F_applied", "wall_clearance", "E_base_near",
)


def csv_row(e: Execution) -> list[str]:
    """The execution as results.csv fields (floats with 10 significant digits)."""
    fl = [format(e.metric(m), ".10g") for m in (*REPORT_METRICS, "E_base", "F_max")]
    more = [format(e.metric(m), ".10g")
            for m in ("limited", "F_applied", "wall_clearance", "E_base_near")]
    return [str(e.user), e.strategy, *fl, str(e.switches), str(int(e.completed)), str(e.faults),
            e.stopped, *more]
