"""The inertia-weighting sweep (`mmctl study sweep`; the paper's future work: "task-
dependent tuning of inertia-based weights").

The min-energy IDK solves the task with the whole-body inertia as the metric,
``qdot = J_M# v_d + P z`` with ``J_M# = M^-1 J^T (J M^-1 J^T)^-1``, ``M = blockdiag(M_a,
M_b)`` and M_b = diag(115 kg, 115 kg, I_bz).  The sweep changes, in the **weighting
only**, the base's own inertia to ``s M_b`` (``s`` = ``base_scale``; 1 = the paper;
s < 1 makes the base cheaper: it moves more, s > 1 dearer: the arm does more), and the
null-space projector ``P``:

* ``dynamic`` -- the paper's dynamically consistent ``I - J_M# J`` (the solution is
  the M-closest point to ``z`` on the task manifold);
* ``euclidean`` -- the ordinary ``I - J# J`` with the Moore-Penrose ``J#`` (what the
  locomotion approach projects with), ``qdot = J_M# v_d + (I - J# J) z``;

and, as an ablation, the coupled whole-body inertia (``robot.full_inertia``: the
arm-base coupling the paper neglects in its eq. 11) with the base's own part scaled the
same way.  The *measured* energy E_K (the metric Ē) always uses the true block-diagonal
M of the paper's eq. 10: only the controller's weighting changes.

The null-space gain's magnitude is a third dimension (issue 32): ``gain_scale`` g
multiplies the arm's entries of G (``idk.null_gain``; the paper's G = diag(1, ..., 1,
0, 0, 0) [1/s], so g = 1 is the paper) in ``z = G (q_des - q)``, in the min-energy
executions only (the locomotion reference keeps the configured G).  Every execution
also reads x_f again at fixed delays after T_f within the end-of-trial hold
(:data:`mmctl.study.results.X_F_DELAYS`, :attr:`Execution.x_f_after`), so the sweep
tells when x_f is read as well as how the solver is set.

Every setting runs the same users through the study's executions
(:func:`mmctl.study.runner.run_execution` with a :class:`Setting` as its variant) on the
study's executor, so for a given seed the numbers do not depend on ``--jobs``.  The
locomotion approach runs alongside as the reference point.  At ``base_scale`` 1 with
the dynamic projector and no coupling the solver computes exactly what the plain
min-energy strategy computes (``tests/test_study_sweep.py`` compares the executions).

Outputs: ``sweep.csv`` (one row per setting: medians over the users, x_f also after
the end-of-trial hold and at the delays, the limit-active fraction, whether it
dominates the simulation's min-energy at the paper's setting, s = 1 dynamic, g = 1:
``paper`` = 1 marks that row, a setting, not the paper's measured result),
``sweep.png`` (:func:`mmctl.study.plots.sweep_curve`) and, when the grid has more than
one gain, ``sweep-gain.png`` (:func:`mmctl.study.plots.gain_read_curve`: Ē against x_f
read at T_f, at the delays and at the hold's end, over the gains).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.config.control import IdkConfig
from mmctl.control.cycle import CycleChain
from mmctl.control.idk import min_energy, min_energy_block, null_project
from mmctl.control.limits import Limits
from mmctl.control.strategies import MinEnergy
from mmctl.errors import ConfigError
from mmctl.model.robot import Kinematics
from mmctl.sim.human import HumanParams
from mmctl.study.config import StudyConfig
from mmctl.study.executor import Executor, run_all
from mmctl.study.results import X_F_DELAYS, Execution
from mmctl.study.runner import Progress, run_execution
from mmctl.study.users import draw_user

Vec = NDArray[np.float64]

#: The null-space projectors the sweep compares (see the module docstring).
PROJECTORS: tuple[str, ...] = ("dynamic", "euclidean")

#: Default base scales: 10^(k/4), k = -4..4 (0.1 .. 10, log-spaced, 1 = the paper).
DEFAULT_SCALES: tuple[float, ...] = tuple(float(10.0 ** (k / 4.0)) for k in range(-4, 5))

#: Default null-space gain scales: the paper's G only.
DEFAULT_GAINS: tuple[float, ...] = (1.0,)

#: The configuration's own bound on each entry of ``idk.null_gain`` [1/s].
MAX_NULL_GAIN: float = float(next(f for f in fields(IdkConfig)  # type: ignore[arg-type]
                                  if f.name == "null_gain").metadata["le"])


def scaled_gain(null_gain: Sequence[float], gain_scale: float) -> tuple[float, ...]:
    """``idk.null_gain`` (9,) with its arm entries (the first six) times ``gain_scale``,
    the base's as they are; ConfigError naming ``idk.null_gain`` when an entry leaves
    the configuration's range (<= :data:`MAX_NULL_GAIN`)."""
    g = tuple(float(v) * gain_scale if i < 6 else float(v) for i, v in enumerate(null_gain))
    if max(g) > MAX_NULL_GAIN:
        raise ConfigError("idk.null_gain", [round(v, 6) for v in g],
                          f"must be <= {MAX_NULL_GAIN:g} [1/s] in every entry (the "
                          f"configuration's range); the gain scale {gain_scale:g} times the "
                          "configured G exceeds it")
    return g


@dataclass(frozen=True)
class Setting:
    """One point of the sweep, and the :class:`mmctl.study.runner.Variant` that runs it.

    base_scale: factor s > 0 on the base's own inertia M_b in the IDK's weighting
    (1 = the paper); projector: ``dynamic`` or ``euclidean`` null-space projector;
    coupled: the coupled whole-body inertia (``robot.full_inertia``) instead of the
    paper's block-diagonal M; gain_scale: factor g > 0 on the arm's entries of the
    null-space gain G (``idk.null_gain``; 1 = the paper's G).
    """

    base_scale: float = 1.0
    projector: str = "dynamic"
    coupled: bool = False
    gain_scale: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.base_scale) and self.base_scale > 0.0):
            raise ConfigError("sweep.base_scale", self.base_scale, "must be a number > 0")
        if not (math.isfinite(self.gain_scale) and self.gain_scale > 0.0):
            raise ConfigError("sweep.gain_scale", self.gain_scale, "must be a number > 0")
        if self.projector not in PROJECTORS:
            raise ConfigError("sweep.projector", self.projector,
                              f"must be one of {', '.join(PROJECTORS)}")

    @property
    def paper(self) -> bool:
        """The paper's setting of min-energy: scale 1, dynamically consistent,
        block-diagonal M, the paper's G (its simulation, not the paper's measured
        result)."""
        return (self.base_scale == 1.0 and self.projector == "dynamic" and not self.coupled
                and self.gain_scale == 1.0)

    @property
    def label(self) -> str:
        """Short text, e.g. ``s=0.32 dynamic``, ``s=1 euclidean coupled`` or ``s=1
        dynamic G×4`` (the gain only when it is not the paper's)."""
        return (f"s={self.base_scale:.3g} {self.projector}"
                + (" coupled" if self.coupled else "")
                + (f" G×{self.gain_scale:.3g}" if self.gain_scale != 1.0 else ""))

    # --- the Variant interface (mmctl.study.runner.Variant) -----------------------
    def config(self, cfg: Config) -> Config:
        """``robot.full_inertia`` on for the coupled ablation, the arm's entries of
        ``idk.null_gain`` times ``gain_scale`` (:func:`scaled_gain`); at the paper's
        setting ``cfg`` itself."""
        if self.coupled:
            cfg = replace(cfg, robot=replace(cfg.robot, full_inertia=True))  # type: ignore[type-var]
        if self.gain_scale != 1.0:
            cfg = replace(cfg, idk=replace(  # type: ignore[type-var]
                cfg.idk, null_gain=scaled_gain(cfg.idk.null_gain, self.gain_scale)))
        return cfg

    def chain(self, cfg: Config) -> CycleChain:
        """The robot's cycle chain with :class:`WeightedMinEnergy` as its min-energy
        solver (the other solvers as built)."""
        chain = CycleChain(cfg)
        ctl = chain.controller
        ctl.use_strategy("min-energy", WeightedMinEnergy(cfg, ctl.limits, self))
        return chain

    def user(self, seed: int, index: int) -> HumanParams:
        """The study's own users: the sweep changes the robot only."""
        return draw_user(seed, index)


class WeightedMinEnergy(MinEnergy):
    """:class:`~mmctl.control.strategies.MinEnergy` with the base's own inertia scaled
    by ``setting.base_scale`` in the weighting and ``setting.projector`` as the
    null-space projector.  With scale 1 and the dynamic projector it computes what
    MinEnergy computes (the same calls on the same numbers).  With
    ``idk.avoid_joint_limits`` the hand-over re-solves with the same weighting and
    projector on the free coordinates."""

    name = "min-energy"

    def __init__(self, cfg: Config, limits: Limits | None, setting: Setting) -> None:
        super().__init__(cfg, limits)
        self.scale = setting.base_scale
        self.euclidean = setting.projector == "euclidean"

    def _inertia(self, k: Kinematics) -> Vec:
        """The weighting's M (9, 9): the base's own part scaled (coupled: the arm's
        share of the base block unchanged, so M stays positive definite)."""
        if self.full and k.M_full is not None:
            M = k.M_full.copy()
            M[6, 6] += (self.scale - 1.0) * k.M_b[0]
            M[7, 7] += (self.scale - 1.0) * k.M_b[1]
            M[8, 8] += (self.scale - 1.0) * k.M_b[2]
            return M
        M = np.zeros((9, 9))
        M[:6, :6] = k.M_a
        M[6, 6], M[7, 7], M[8, 8] = k.M_b * self.scale
        return M

    def _whole(self, k: Kinematics, v_d: Vec, z: Vec) -> Vec:
        if self.full and k.M_full is not None:
            return self._weighted(k.J, self._inertia(k), v_d, z)
        m_b = k.M_b * self.scale
        if not self.euclidean:
            return min_energy_block(k.J, k.M_a, m_b, v_d, z, self.thr, self.damp).x
        x = min_energy_block(k.J, k.M_a, m_b, v_d, None, self.thr, self.damp).x
        out: Vec = x + null_project(k.J, z, self.thr, self.damp).x
        return out

    def _weighted(self, J: Vec, M: Vec, v_d: Vec, z: Vec) -> Vec:
        thr, damp = self.thr, self.damp
        if not self.euclidean:
            return min_energy(J, M, v_d, z, singular_threshold=thr, max_damping=damp)
        x = min_energy(J, M, v_d, singular_threshold=thr, max_damping=damp)
        out: Vec = x + null_project(J, z, thr, damp).x
        return out

def settings(scales: Sequence[float] = DEFAULT_SCALES, projectors: Sequence[str] = PROJECTORS,
             coupled: bool = True, gains: Sequence[float] = DEFAULT_GAINS) -> list[Setting]:
    """Every (projector, gain, scale), in that nesting, then the coupled ablation at
    scale 1 with each projector and gain (``coupled``).  With the default gains (the
    paper's G only) the grid is the (scale, projector) grid of before issue 32."""
    out = [Setting(float(s), pr, False, float(g)) for pr in projectors for g in gains
           for s in scales]
    if coupled:
        out += [Setting(1.0, pr, True, float(g)) for pr in projectors for g in gains]
    return out


class SweepRow(NamedTuple):
    """One setting's executions summarised over the users: ``approach`` is
    ``min-energy`` (with ``setting``) or ``locomotion`` (setting None); medians of the
    paper's metrics [J, N, m/s, m, s]; limited: median over users of the fraction of
    samples on which a limit bound the command; completed: executions finished within
    the time limit; dominates: median Ē and median x_f both below those of the
    simulation's min-energy at the paper's setting (s = 1, dynamic, block, G);
    x_f_hold: median x_f after the end-of-trial hold [m] (NaN: no hold); x_f_after:
    median x_f read :data:`~mmctl.study.results.X_F_DELAYS` after T_f [m], one per
    delay (NaN where an execution has none)."""

    approach: str
    setting: Setting | None
    users: int
    E: float
    F_h: float
    v: float
    x_f: float
    T_f: float
    E_base: float
    limited: float
    completed: int
    faults: int
    dominates: bool
    x_f_hold: float = math.nan
    x_f_after: tuple[float, ...] = ()


class SweepResult(NamedTuple):
    """rows: one per setting (locomotion last); executions[i]: row i's executions in
    user order; cpu_time [s] and control cycles summed over the workers."""

    rows: list[SweepRow]
    executions: list[list[Execution]]
    cpu_time: float
    cycles: int


Job = tuple[StudyConfig, int, str, Setting | None, int]


def _work(job: Job) -> tuple[int, Execution, float, int]:
    study, user, strategy, setting, index = job
    ex, cpu, cycles = run_execution(study, user, strategy, variant=setting)
    return index, ex, cpu, cycles


def _row(approach: str, setting: Setting | None, execs: Sequence[Execution]) -> SweepRow:
    def med(name: str) -> float:
        return float(np.median([getattr(e, name) for e in execs]))

    def after(i: int) -> float:
        vals = [e.x_f_after[i] if len(e.x_f_after) > i else math.nan for e in execs]
        return float(np.median(vals))

    return SweepRow(approach, setting, len(execs), med("E"), med("F_h"), med("v"), med("x_f"),
                    med("T_f"), med("E_base"), med("limited"),
                    sum(1 for e in execs if e.completed), sum(e.faults for e in execs), False,
                    med("x_f_hold"), tuple(after(i) for i in range(len(X_F_DELAYS))))


def run_sweep(study: StudyConfig, grid: Sequence[Setting], executor: Executor | None = None,
              progress: Progress | None = None, locomotion: bool = True) -> SweepResult:
    """Every setting of ``grid`` (min-energy) and, with ``locomotion``, the locomotion
    approach, for the users of ``study`` (its ``strategies`` are not used), on
    ``executor`` (default: this process)."""
    if not grid:
        raise ConfigError("sweep.settings", [], "name at least one setting")
    entries: list[tuple[str, Setting | None]] = [("min-energy", s) for s in grid]
    if locomotion:
        entries.append(("locomotion", None))
    jobs: list[Job] = [(study, u, a, s, i) for i, (a, s) in enumerate(entries)
                       for u in range(study.users)]
    def describe(r: tuple[int, Execution, float, int]) -> str:
        a, s = entries[r[0]]
        return f"user {r[1].user} {a if s is None else s.label}"

    done = run_all(_work, jobs, executor, 1, progress, describe)
    done.sort(key=lambda r: (r[0], r[1].user))
    per: list[list[Execution]] = [[] for _ in entries]
    for i, ex, _cpu, _cyc in done:
        per[i].append(ex)
    rows = [_row(a, s, per[i]) for i, (a, s) in enumerate(entries)]
    paper = next((r for r in rows if r.setting is not None and r.setting.paper), None)
    if paper is not None:
        rows = [r._replace(dominates=r.setting is not None and not r.setting.paper
                           and r.E < paper.E and r.x_f < paper.x_f) for r in rows]
    return SweepResult(rows, per, sum(r[2] for r in done), sum(r[3] for r in done))


#: sweep.csv's columns of x_f read after T_f, one per delay: ``x_f_0.5s`` ...
AFTER_COLUMNS: tuple[str, ...] = tuple(f"x_f_{d:g}s" for d in X_F_DELAYS)

#: sweep.csv columns, in order (issue 32's appended: the gain scale, x_f at the delays).
CSV_COLUMNS: tuple[str, ...] = (
    "approach", "base_scale", "projector", "coupled", "paper", "users", "E", "F_h", "v", "x_f",
    "T_f", "E_base", "limited", "completed", "faults", "dominates", "x_f_hold",
    "gain_scale", *AFTER_COLUMNS,
)


def _after(r: SweepRow, i: int) -> float:
    return r.x_f_after[i] if len(r.x_f_after) > i else math.nan


def sweep_csv(rows: Sequence[SweepRow]) -> str:
    """sweep.csv content: one row per setting (floats with 10 significant digits)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        s = r.setting
        w.writerow([r.approach, "" if s is None else format(s.base_scale, ".10g"),
                    "" if s is None else s.projector, "" if s is None else int(s.coupled),
                    int(s is not None and s.paper), r.users,
                    *(format(getattr(r, m), ".10g")
                      for m in ("E", "F_h", "v", "x_f", "T_f", "E_base", "limited")),
                    r.completed, r.faults, int(r.dominates), format(r.x_f_hold, ".10g"),
                    "" if s is None else format(s.gain_scale, ".10g"),
                    *(format(_after(r, i), ".10g") for i in range(len(X_F_DELAYS)))])
    return buf.getvalue()


def read_sweep_csv(text: str) -> list[SweepRow]:
    """sweep.csv's content back as rows (its 10 significant digits), to redraw the
    figures without running the sweep again; a file from before issue 32 (no
    ``gain_scale``, no reads after T_f) reads as the paper's G with no reads."""
    out = []
    for d in csv.DictReader(io.StringIO(text)):
        setting = None
        if d["base_scale"]:
            setting = Setting(float(d["base_scale"]), d["projector"], d["coupled"] == "1",
                              float(d.get("gain_scale") or 1.0))
        after = tuple(float(d[c]) for c in AFTER_COLUMNS if d.get(c))

        def num(m: str, d: dict[str, str] = d) -> float:
            return float(d[m])

        out.append(SweepRow(
            d["approach"], setting, int(d["users"]), num("E"), num("F_h"), num("v"),
            num("x_f"), num("T_f"), num("E_base"), num("limited"), int(d["completed"]),
            int(d["faults"]), d["dominates"] == "1", float(d.get("x_f_hold") or math.nan),
            after))
    return out


def sweep_table(rows: Sequence[SweepRow]) -> str:
    """Markdown table of the sweep: one row per setting; "min-energy (paper's setting)"
    is the simulation's run at s = 1, dynamic, block-diagonal M, the paper's G (not the
    paper's measured numbers), and "dominates" compares with that row.  G: the gain
    scale g on the paper's G; Ē / loc.: the row's median Ē over the locomotion row's
    (the paper's min-energy: 0.86 / 2.52 = 0.34); x_f then x_f read +d s after T_f
    and at the end of the hold."""
    loco = next((r.E for r in rows if r.setting is None and r.E > 0), math.nan)
    after = "".join(f" x_f +{d:g} s [m] |" for d in X_F_DELAYS)
    lines = [("| approach | s | G | projector | M | Ē [J] | Ē / loc. | x_f [m] |" + after
              + " x_f hold [m] | F̄_h [N] | T_f [s] | base share of Ē | limit active "
              "| dominates s = 1 |"),
             "|---|---:|---:|---|---|---:|---:|---:|" + "---:|" * len(X_F_DELAYS)
             + "---:|---:|---:|---:|---:|---|"]
    for r in rows:
        s = r.setting
        share = r.E_base / r.E if r.E > 0 else math.nan
        name = "min-energy (paper's setting)" if s is not None and s.paper else r.approach
        reads = "".join(f" {_after(r, i):.3f} |" for i in range(len(X_F_DELAYS)))
        lines.append(
            f"| {name} | {'' if s is None else f'{s.base_scale:.3g}'} "
            f"| {'' if s is None else f'{s.gain_scale:.3g}'} "
            f"| {'' if s is None else s.projector} "
            f"| {'' if s is None else ('coupled' if s.coupled else 'block')} "
            f"| {r.E:.3f} | {r.E / loco:.2f} | {r.x_f:.3f} |{reads} {r.x_f_hold:.3f} "
            f"| {r.F_h:.2f} | {r.T_f:.2f} | {100 * share:.0f} % "
            f"| {100 * r.limited:.1f} % | {'yes' if r.dominates else ''} |")
    return "\n".join(lines)


def write_sweep(out: Path, result: SweepResult, meta: dict[str, Any],
                figure: bool = True) -> list[Path]:
    """sweep.csv (and sweep.png) into ``out``; returns the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "sweep.csv"]
    paths[0].write_text(sweep_csv(result.rows), encoding="utf-8")
    if figure:
        from mmctl.study.plots import sweep_curve

        paths.append(out / "sweep.png")
        sweep_curve(result.rows, paths[1], meta)
        if len({r.setting.gain_scale for r in result.rows if r.setting is not None}) > 1:
            from mmctl.study.plots import gain_read_curve

            paths.append(out / "sweep-gain.png")
            gain_read_curve(result.rows, paths[-1], meta)
    return paths
