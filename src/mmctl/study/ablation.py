"""Which of the paper's claims come from the control law, and which from modelling
choices (`mmctl study ablate`, issue 32).

Each ablation removes one modelling choice of the simulation and leaves the control
law alone; the same users run every approach again, and each claim's effect (the
matched-pairs rank-biserial r of a − b, :func:`mmctl.study.stats.rank_biserial`) is
set beside the baseline's.  A claim whose effect vanishes or turns when one choice is
removed comes from that choice, not from the control law:

* ``press_cost_0``: the mode button costs no time (the person's ``press_time`` 0 s;
  the pause drives T_f L<S, T_f S>ME and v̄ L>S, the issue's suspicion);
* ``dead_band_0``: the sensor chain's dead band 0 N / 0 N m
  (``sensor.wrench.deadband_force``/``_torque``: F̄_h ≈ B v̄ + dead band);
* ``no_decision_delay``: the switching policy acts at once (``decision_delay`` 0 s);
* ``no_slip``: the mecanum wheels do not slip (``sim.base_slip_*`` 0).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mmctl.config import Config
from mmctl.control.cycle import CycleChain
from mmctl.sim.human import HumanParams
from mmctl.study.config import StudyConfig
from mmctl.study.executor import Executor, run_all
from mmctl.study.replication import paper_claims
from mmctl.study.results import APPROACH_NAMES, METRIC_LABELS, Execution
from mmctl.study.runner import Progress, run_execution
from mmctl.study.sensitivity import override
from mmctl.study.stats import paired_differences, rank_biserial
from mmctl.study.users import draw_user


@dataclass(frozen=True)
class Ablation:
    """One modelling choice removed: configuration keys set, person fields set."""

    name: str
    what: str
    config_values: tuple[tuple[str, float], ...] = ()
    person: tuple[tuple[str, float], ...] = ()

    def config(self, cfg: Config) -> Config:
        return override(cfg, self.config_values)

    def chain(self, cfg: Config) -> CycleChain:
        return CycleChain(cfg)

    def user(self, seed: int, index: int) -> HumanParams:
        return dataclasses.replace(draw_user(seed, index), **dict(self.person))


#: The baseline and the four ablations, in the table's order.
ABLATIONS: tuple[Ablation, ...] = (
    Ablation("baseline", "the study as it is"),
    Ablation("press_cost_0", "the mode button costs no time (press_time 0 s)",
             person=(("press_time", 0.0),)),
    Ablation("dead_band_0", "no dead band in the sensor chain (0 N, 0 N m)",
             config_values=(("sensor.wrench.deadband_force", 0.0),
                            ("sensor.wrench.deadband_torque", 0.0))),
    Ablation("no_decision_delay", "the switching policy acts at once (decision_delay 0 s)",
             person=(("decision_delay", 0.0),)),
    Ablation("no_slip", "no mecanum slip (sim.base_slip_longitudinal, _lateral 0)",
             config_values=(("sim.base_slip_longitudinal", 0.0),
                            ("sim.base_slip_lateral", 0.0))),
)

Job = tuple[StudyConfig, int, str, Ablation]


def _work(job: Job) -> tuple[str, Execution, float, int]:
    study, user, strategy, ab = job
    ex, cpu, cycles = run_execution(study, user, strategy, variant=ab)
    return ab.name, ex, cpu, cycles


def run_ablations(study: StudyConfig, ablations: Sequence[Ablation] = ABLATIONS,
                  executor: Executor | None = None, jobs: int = 1,
                  progress: Progress | None = None) -> dict[str, list[Execution]]:
    """Every user with every approach under every ablation: executions by ablation."""
    work = [(study, u, s, ab) for ab in ablations for u in range(study.users)
            for s in study.strategies]
    done = run_all(_work, work, executor, jobs, progress,
                   lambda r: f"{r[0]} user {r[1].user} {r[1].strategy}")
    out: dict[str, list[Execution]] = {ab.name: [] for ab in ablations}
    for name, ex, _, _ in done:
        out[name].append(ex)
    return out


def effects(execs: Sequence[Execution]) -> dict[tuple[str, str, str], float]:
    """Each paper claim's r (a − b, users that finished every approach only)."""
    done = {e.user for e in execs} - {e.user for e in execs if not e.completed}
    by = {(e.user, e.strategy): e for e in execs if e.user in done}
    users = sorted(done)
    out = {}
    for c in paper_claims():
        a = np.array([by[(u, c.a)].metric(c.metric) for u in users])
        b = np.array([by[(u, c.b)].metric(c.metric) for u in users])
        out[(c.metric, c.a, c.b)] = (float(rank_biserial(paired_differences(a, b)))
                                     if users else math.nan)
    return out


#: |r| below this counts as "no effect" in the verdict: the paper's test of 27 users
#: becomes significant at r = 0.527 (sensitivity.R_CRIT), half of it is a small effect
SMALL = 0.25


def table(results: Mapping[str, Sequence[Execution]]) -> tuple[str, list[dict[str, Any]]]:
    """Markdown: per claim, r under the baseline and each ablation, and which choice
    the claim's effect rests on (its r falls below :data:`SMALL` or turns sign without
    it); the rows as data for JSON."""
    names = list(results)
    eff = {n: effects(results[n]) for n in names}
    head = "| claim | " + " | ".join(names) + " | rests on |"
    lines = [head, "|---|" + "---:|" * len(names) + "---|"]
    rows = []
    for c in paper_claims():
        key = (c.metric, c.a, c.b)
        base = eff["baseline"][key] if "baseline" in eff else math.nan
        rests = []
        if c.differ and math.isfinite(base) and c.direction * base >= SMALL:
            for n in names:
                r = eff[n][key]
                if n != "baseline" and math.isfinite(r) and c.direction * r < SMALL:
                    rests.append(n)
        label = METRIC_LABELS.get(c.metric, c.metric)
        na, nb = APPROACH_NAMES.get(c.a, c.a), APPROACH_NAMES.get(c.b, c.b)
        sym = "≈" if not c.differ else (">" if c.direction > 0 else "<")
        cells = " | ".join("—" if not math.isfinite(eff[n][key]) else f"{eff[n][key]:+.2f}"
                           for n in names)
        verdict = (", ".join(rests) if rests else
                   ("—" if not c.differ else
                    "the control law (no ablation removes it)" if c.direction * base >= SMALL
                    else "not reproduced at baseline"))
        lines.append(f"| {label}: {na} {sym} {nb} | {cells} | {verdict} |")
        rows.append({"claim": c.text(), "r": {n: eff[n][key] for n in names},
                     "rests_on": rests})
    return "\n".join(lines), rows
