"""Sensitivity of the study's conclusions (`mmctl study sensitivity`): Morris screening
(elementary effects; SALib's sampler and analysis) over the simulated people's
population, the plant and the task layout.

**Factors** (:data:`FACTORS`, one :class:`Factor` per row; add a row to screen another
parameter): the name says what it moves --

* ``human.<key>`` -- the *median* (centre) of the population's distribution ``<key>``
  (:data:`mmctl.study.users.POPULATION`), every user drawn around it with the same
  spread and clipped to the same range; the range screened is that clipping range (the
  values we hold plausible for any one person, docs/study.md): one row per population
  entry, made from POPULATION itself;
* ``layout.<name>`` -- a change of the task (:data:`LAYOUTS`);
* anything else -- a key of the control/plant configuration (``arm.speedj_acceleration``,
  the base plant's ``sim.base_latency``, ``sim.base_velocity_tau``, ``sim.base_slip_*``),
  set through the configuration's own validation.

**Conclusions**: the paper's 15 claims (:func:`mmctl.study.replication.paper_claims`:
every cell of its Table IV, "a > b" where its p_corr < 0.05, "a ≈ b" otherwise).  A
Morris point is a small study (``--users``, default 6, on the quick task); 6 users
cannot reach the paper's significance (the smallest Holm-corrected p of 6 users is
3 × 1/32), so a claim is judged by its **effect size**: the matched-pairs
rank-biserial r of a − b over the users (:func:`mmctl.study.stats.rank_biserial`).
It holds when a study of the paper's size (27 users) with that effect would decide as
the paper did: a difference when ``direction · r ≥ R_CRIT``, none when ``|r| < R_CRIT``,
with ``R_CRIT`` the r at which the paper's test (Wilcoxon, normal approximation, Holm
over 3 pairs, first step: two-sided p < 0.05 / 3) becomes significant for 27 users
(:func:`r_crit`: 0.527).  The Morris output of a claim is the median paired difference
a − b in the metric's units, times the claim's direction (positive = the paper's way;
for a claim of no difference, a − b as is).  μ* (mean |Δy| / Δ with Δ a fraction of
the factor's range: the metric's units per the factor's whole range) ranks the factors
by how much they move it; the share of points where the claim holds at each level of a
factor says in which part of its range the conclusion holds.

Every execution runs through the study's executor (:func:`mmctl.study.runner.
run_execution` with a :class:`Point` as its variant); SALib's sampler and its bootstrap
are seeded with the study's seed, so the outputs depend on the seed only.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from mmctl.config import Config, config_from_dict, to_dict
from mmctl.control.cycle import CycleChain
from mmctl.errors import ConfigError, MmctlError
from mmctl.sim.human import HumanParams
from mmctl.study.config import StudyConfig
from mmctl.study.executor import Executor, run_all
from mmctl.study.replication import Claim, paper_claims
from mmctl.study.results import METRIC_LABELS, Execution
from mmctl.study.runner import Progress, run_execution
from mmctl.study.stats import ALPHA, rank_biserial
from mmctl.study.users import POPULATION, Draw, draw_user

#: Morris grid levels (SALib's ``num_levels``): 4, the usual choice (Saltelli et al.,
#: *Global Sensitivity Analysis: The Primer*, 2008, ch. 3: p = 4 with Δ = p / (2 (p - 1)))
LEVELS = 4
#: Morris trajectories by default (r = 4..10 is usual for screening, the Primer ch. 3;
#: the lower end: every point is a whole small study)
TRAJECTORIES = 4
#: users per Morris point by default
USERS = 6
#: the paper's study size: what the effect-size criterion is calibrated to
PAPER_USERS = 27


@dataclass(frozen=True)
class Factor:
    """One screened parameter: ``name`` (see the module docstring for what the prefix
    means), its range [``low``, ``high``] in ``unit``, and ``source``: where the range
    comes from."""

    name: str
    low: float
    high: float
    unit: str
    source: str

    @property
    def group(self) -> str:
        """``human``, ``layout`` or ``plant`` (a configuration key)."""
        head = self.name.split(".", 1)[0]
        return head if head in ("human", "layout") else "plant"

    @property
    def key(self) -> str:
        """The population entry, layout name or configuration key."""
        return self.name.split(".", 1)[1] if self.group != "plant" else self.name


_HUMAN_UNITS = {"stiffness": "N/m", "damping": "N s/m", "speed": "m/s", "reaction_time": "s",
                "dwell_time": "s", "f_comfort": "N", "comfort_reach": "m",
                "near_distance": "m", "decision_delay": "s", "force_cv": "",
                "press_time": "s"}


def _human_factors() -> list[Factor]:
    """One factor per population entry: its median over its clipping range."""
    return [Factor(f"human.{k}", d.lo, d.hi, _HUMAN_UNITS.get(k, ""),
                   f"the population's clipping range for {k} (users.py POPULATION; median "
                   f"{d.centre:g})") for k, d in POPULATION.items()]


def _spread(study: StudyConfig, value: float) -> StudyConfig:
    """The layout's lateral extent times ``value``: the wall task's near and far edges
    (both ends of their uniform draws, :class:`~mmctl.sim.human.WallFamily`), the board
    task's hole offsets from the start handle position."""
    w = study.wall
    wall = replace(w, near_edge=(value * w.near_edge[0], value * w.near_edge[1]),
                   far_edge=(value * w.far_edge[0], value * w.far_edge[1]))
    holes = tuple((value * u, value * v) for u, v in study.holes)
    return replace(study, holes=holes, wall=wall)


#: layout name -> how it changes the study
LAYOUTS: dict[str, Callable[[StudyConfig, float], StudyConfig]] = {
    "spread": _spread,
}

#: The factors screened by default (add rows here; a ``plant`` row whose configuration
#: key does not exist is refused by :func:`check_factors`).
FACTORS: tuple[Factor, ...] = (
    *_human_factors(),
    Factor("arm.speedj_acceleration", 2.0, 8.0, "rad/s^2",
           "the plant's joint acceleration = what speedJ is sent: half to twice the "
           "daemon's 4 rad/s^2 (the controller's own limits.joint_acceleration, 4, binds "
           "above it); within ur_rtde's 40 rad/s^2"),
    Factor("sim.base_latency", 0.0, 0.01, "s",
           "the base's command dead time: from none to 5 x the plant's 2 ms (a drive "
           "that acts on the 2nd-5th SYNC, or a loaded bus)"),
    Factor("sim.base_velocity_tau", 0.0, 0.04, "s",
           "the drives' velocity-loop time constant: from ideal to 4 x the plant's 10 ms "
           "(a loop tuned 4 x softer, 4 Hz)"),
    Factor("sim.base_slip_longitudinal", 0.0, 0.05, "",
           "slip along x: from none to 5 x the plant's 1 % (a softer floor)"),
    Factor("sim.base_slip_lateral", 0.0, 0.15, "",
           "slip sideways: from none to 5 x the plant's 3 % (mecanum bases strafe far "
           "shorter on carpet)"),
    Factor("layout.spread", 0.6, 1.4, "x",
           "the layout's lateral extent scaled: 0.6 brings the quick wall task's far hole "
           "(1.1-1.3 m along the wall) to 0.66-0.78 m, within every user's comfortable "
           "reach (0.8-1.0 m); 1.4 takes it to 1.54-1.82 m, past the UR10e's 1.3 m reach"),
)


def factor_by_name(name: str) -> Factor:
    """One of :data:`FACTORS`; ConfigError naming the allowed ones otherwise."""
    for f in FACTORS:
        if f.name == name:
            return f
    raise ConfigError("--factors", name, "must be one of " + ", ".join(f.name for f in FACTORS))


def _set_key(data: dict[str, Any], key: str, value: float) -> None:
    node = data
    parts = key.split(".")
    for p in parts[:-1]:
        if not isinstance(node.get(p), dict):
            raise ConfigError(key, value, "is not a configuration key")
        node = node[p]
    if parts[-1] not in node:
        raise ConfigError(key, value, "is not a configuration key")
    node[parts[-1]] = value


def override(cfg: Config, values: Sequence[tuple[str, float]]) -> Config:
    """``cfg`` with the configuration keys set, validated as a configuration file is."""
    if not values:
        return cfg
    data = to_dict(cfg)
    for key, v in values:
        _set_key(data, key, v)
    return config_from_dict(data, "sensitivity")


def population(medians: Sequence[tuple[str, float]]) -> dict[str, Draw]:
    """:data:`POPULATION` with the named entries' centres (medians) moved (kept within
    their clipping range), in POPULATION's order."""
    pop = dict(POPULATION)
    for k, v in medians:
        if k not in pop:
            raise ConfigError(f"human.{k}", v, "must name an entry of users.POPULATION: "
                              + ", ".join(POPULATION))
        d = pop[k]
        pop[k] = replace(d, centre=min(max(float(v), d.lo), d.hi))
    return pop


@dataclass(frozen=True)
class Point:
    """One Morris point as a :class:`mmctl.study.runner.Variant`: configuration keys
    and population medians to set (the layout is in the point's StudyConfig)."""

    config_values: tuple[tuple[str, float], ...] = ()
    medians: tuple[tuple[str, float], ...] = ()

    def config(self, cfg: Config) -> Config:
        return override(cfg, self.config_values)

    def chain(self, cfg: Config) -> CycleChain:
        return CycleChain(cfg)

    def user(self, seed: int, index: int) -> HumanParams:
        if not self.medians:
            return draw_user(seed, index)
        return draw_user(seed, index, population(self.medians))


def point_setting(study: StudyConfig, factors: Sequence[Factor],
                  x: Sequence[float]) -> tuple[StudyConfig, Point]:
    """The study and the variant of the Morris point ``x`` (one value per factor)."""
    cfg_vals, meds = [], []
    for f, v in zip(factors, x):
        if f.group == "human":
            meds.append((f.key, float(v)))
        elif f.group == "layout":
            study = LAYOUTS[f.key](study, float(v))
        else:
            cfg_vals.append((f.key, float(v)))
    return study, Point(tuple(cfg_vals), tuple(meds))


def check_factors(study: StudyConfig, factors: Sequence[Factor]) -> None:
    """Every factor's range is valid at both ends (a configuration key that does not
    exist or a value the configuration refuses: ConfigError now, not in a worker)."""
    if not factors:
        raise ConfigError("--factors", [], "name at least one factor")
    if len({f.name for f in factors}) != len(factors):
        raise ConfigError("--factors", [f.name for f in factors], "must not repeat a factor")
    for f in factors:
        if not f.low < f.high:
            raise ConfigError(f.name, (f.low, f.high), "the range must have low < high")
        if f.group == "layout" and f.key not in LAYOUTS:
            raise ConfigError(f.name, f.key, "must be one of layout." + ", layout.".join(LAYOUTS))
        if f.group == "human" and f.key not in POPULATION:
            raise ConfigError(f.name, f.key, "must name an entry of users.POPULATION")
        if f.group == "plant":
            cfg = study.control_config(study.strategies[0])
            for v in (f.low, f.high):
                override(cfg, [(f.key, v)])


def r_crit(n: int = PAPER_USERS, alpha: float = ALPHA, pairs: int = 3) -> float:
    """The rank-biserial r at which the paper's test of ``n`` users becomes significant:
    Wilcoxon signed-rank, normal approximation without continuity correction, Holm's
    first step over ``pairs`` pairs (two-sided p < alpha / pairs).  With ``T+`` the
    positive rank sum, ``r = (2 T+ - S) / S`` and ``z = (T+ - S/2) / sd`` (``S = n(n+1)/2``,
    ``sd = sqrt(n(n+1)(2n+1)/24)``), so ``r = 2 z sd / S``.  27 users: 0.527."""
    from scipy.stats import norm

    z = float(norm.ppf(1.0 - alpha / (2.0 * pairs)))
    s = n * (n + 1) / 2.0
    sd = math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
    return 2.0 * z * sd / s


R_CRIT = r_crit()


def judge(claim: Claim, a: np.ndarray, b: np.ndarray, crit: float = R_CRIT
          ) -> tuple[float, float, bool]:
    """(y, r, holds) of ``claim`` for one small study's paired values ``a``, ``b`` (per
    user): y the median of a − b times the claim's direction (as is for a claim of no
    difference), r the rank-biserial effect size of a − b, holds per the module's rule."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    r = float(rank_biserial(d))
    med = float(np.median(d))
    if claim.differ:
        return claim.direction * med, r, claim.direction * r >= crit
    return med, r, abs(r) < crit


Job = tuple[StudyConfig, int, str, Point, int]


def _work(job: Job) -> tuple[int, Execution, float, int]:
    study, user, strategy, point, index = job
    ex, cpu, cycles = run_execution(study, user, strategy, variant=point)
    return index, ex, cpu, cycles


def _require_salib() -> Any:
    try:
        from SALib.analyze import morris as analyze_morris
        from SALib.sample import morris as sample_morris
    except ImportError:
        raise MmctlError("the sensitivity analysis needs SALib: pip install 'mmctl[study]'"
                         ) from None
    return sample_morris, analyze_morris


def problem(factors: Sequence[Factor]) -> dict[str, Any]:
    """SALib's problem definition of ``factors``."""
    return {"num_vars": len(factors), "names": [f.name for f in factors],
            "bounds": [[f.low, f.high] for f in factors]}


def sample(factors: Sequence[Factor], trajectories: int, seed: int) -> np.ndarray:
    """SALib's Morris sample: (trajectories * (k + 1), k) points on the :data:`LEVELS`
    grid, seeded."""
    if trajectories < 2:
        raise ConfigError("--trajectories", trajectories, "must be >= 2 (Morris needs two "
                          "elementary effects per factor for sigma)")
    sample_morris, _ = _require_salib()
    x: np.ndarray = sample_morris.sample(problem(factors), trajectories, num_levels=LEVELS,
                                         seed=seed)
    return x


def run_points(study: StudyConfig, factors: Sequence[Factor], x: np.ndarray,
               executor: Executor | None = None, progress: Progress | None = None
               ) -> tuple[list[list[Execution]], float]:
    """The small study of every Morris point; per point its executions (user, then
    strategy order) and the workers' summed CPU time [s]."""
    jobs: list[Job] = []
    for i, row in enumerate(x):
        st, pt = point_setting(study, factors, [float(v) for v in row])
        jobs += [(st, u, s, pt, i) for u in range(st.users) for s in st.strategies]
    done = run_all(_work, jobs, executor, 1, progress,
                   lambda r: f"point {r[0]} user {r[1].user} {r[1].strategy}")
    order = {s: j for j, s in enumerate(study.strategies)}
    done.sort(key=lambda r: (r[0], r[1].user, order[r[1].strategy]))
    per: list[list[Execution]] = [[] for _ in range(len(x))]
    for i, ex, _cpu, _cyc in done:
        per[i].append(ex)
    return per, sum(r[2] for r in done)


def _paired(execs: Sequence[Execution], strategy: str, metric: str) -> np.ndarray:
    rows = sorted((e for e in execs if e.strategy == strategy), key=lambda e: e.user)
    return np.array([e.metric(metric) for e in rows])


def _levels(values: np.ndarray) -> list[float]:
    return sorted({round(float(v), 12) for v in values})


def analyse(factors: Sequence[Factor], x: np.ndarray, points: Sequence[Sequence[Execution]],
            seed: int, claims: Sequence[Claim] | None = None) -> dict[str, Any]:
    """Judge every claim at every point and screen the factors (SALib's Morris
    analysis, bootstrap seeded): the sensitivity.json document (without the run's
    metadata)."""
    _, analyze_morris = _require_salib()
    claims = list(claims) if claims is not None else paper_claims()
    prob = problem(factors)
    strategies = list(dict.fromkeys(e.strategy for e in points[0])) if points else []
    claims = [c for c in claims if c.a in strategies and c.b in strategies]
    pts: list[dict[str, Any]] = []
    ys = np.zeros((len(claims), len(points)))
    hold = np.zeros((len(claims), len(points)), dtype=bool)
    for j, execs in enumerate(points):
        doc: dict[str, Any] = {"x": {f.name: float(v) for f, v in zip(factors, x[j])},
                               "claims": {}}
        for i, c in enumerate(claims):
            y, r, h = judge(c, _paired(execs, c.a, c.metric), _paired(execs, c.b, c.metric))
            ys[i, j], hold[i, j] = y, h
            doc["claims"][c.text()] = {"y": y, "r": r, "holds": h}
        doc["medians"] = {s: {m: float(np.median(_paired(execs, s, m)))
                              for m in METRIC_LABELS} for s in strategies}
        # completion per execution: an unfinished one enters with T_f = t_max and its
        # x_f where it stopped, which can drive a point's outputs alone
        doc["executions"] = [{"user": e.user, "strategy": e.strategy,
                              "completed": bool(e.completed), "stopped": e.stopped,
                              "T_f": float(e.T_f)}
                             for e in sorted(execs, key=lambda e: (e.user, e.strategy))]
        doc["unfinished"] = sum(1 for e in execs if not e.completed)
        pts.append(doc)
    out_claims = []
    for i, c in enumerate(claims):
        res = analyze_morris.analyze(prob, x, ys[i], num_levels=LEVELS, seed=seed,
                                     print_to_console=False)
        mu_star = np.nan_to_num(np.asarray(res["mu_star"], dtype=float))
        order = np.argsort(-mu_star, kind="stable")
        rank = np.empty(len(factors), dtype=int)
        rank[order] = np.arange(1, len(factors) + 1)
        fs: list[dict[str, Any]] = []
        for k, f in enumerate(factors):
            by_level = []
            for lv in _levels(x[:, k]):
                sel = np.isclose(x[:, k], lv)
                by_level.append([lv, int(hold[i, sel].sum()), int(sel.sum())])
            fs.append({"name": f.name, "rank": int(rank[k]), "mu_star": float(mu_star[k]),
                       "mu_star_conf": float(np.nan_to_num(res["mu_star_conf"][k])),
                       "mu": float(np.nan_to_num(res["mu"][k])),
                       "sigma": float(np.nan_to_num(res["sigma"][k])),
                       "holds_by_level": by_level, "holds": float(hold[i].mean()),
                       "holds_where": holds_where(by_level, f)})
        fs.sort(key=lambda f: f["rank"])
        out_claims.append({"claim": c.text(), "metric": c.metric, "a": c.a, "b": c.b,
                           "differ": c.differ, "direction": c.direction,
                           "holds_share": float(hold[i].mean()), "factors": fs})
    return {"factors": [{"name": f.name, "group": f.group, "low": f.low, "high": f.high,
                         "unit": f.unit, "source": f.source} for f in factors],
            "levels": LEVELS, "r_crit": R_CRIT, "strategies": strategies,
            "claims": out_claims, "points": pts,
            "executions": sum(len(p) for p in points),
            "unfinished": sum(p["unfinished"] for p in pts)}


def holds_where(by_level: Sequence[Sequence[float]], f: Factor) -> str:
    """Where in ``f``'s range the claim holds at most of the points: ``everywhere``,
    ``nowhere`` or the levels, e.g. ``2, 4 of 2..8 rad/s^2``."""
    ok = [lv for lv, h, n in by_level if n and h / n >= 0.5]
    if len(ok) == len(by_level):
        return "everywhere"
    if not ok:
        return "nowhere"
    return ", ".join(f"{v:.3g}" for v in ok) + f" of {f.low:g}..{f.high:g} {f.unit}".rstrip()


def sensitivity_csv(doc: Mapping[str, Any]) -> str:
    """sensitivity.csv: one row per (claim, factor), factors by rank."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["claim", "holds_share", "factor", "rank", "mu_star", "mu_star_conf", "mu",
                "sigma", "holds_where", "holds_by_level"])
    for c in doc["claims"]:
        for f in c["factors"]:
            lv = " ".join(f"{v:.4g}:{h}/{n}" for v, h, n in f["holds_by_level"])
            w.writerow([c["claim"], format(c["holds_share"], ".4g"), f["name"], f["rank"],
                        format(f["mu_star"], ".6g"), format(f["mu_star_conf"], ".6g"),
                        format(f["mu"], ".6g"), format(f["sigma"], ".6g"), f["holds_where"], lv])
    return buf.getvalue()


def sensitivity_table(doc: Mapping[str, Any], top: int = 3) -> str:
    """Markdown: per claim, the share of points where it holds and the ``top`` factors
    by μ* with where in their range it holds."""
    lines = ["| paper's claim | holds at | top factors by μ* (where it holds) |", "|---|---:|---|"]
    for c in doc["claims"]:
        fs = "; ".join(f"{f['name']} {f['mu_star']:.3g} ({f['holds_where']})"
                       for f in c["factors"][:top])
        lines.append(f"| {c['claim']} | {100 * c['holds_share']:.0f} % | {fs} |")
    return "\n".join(lines)


def write_sensitivity(out: Path, doc: dict[str, Any], figure: bool = True) -> list[Path]:
    """sensitivity.csv, sensitivity.json (and sensitivity.png) into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "sensitivity.csv", out / "sensitivity.json"]
    paths[0].write_text(sensitivity_csv(doc), encoding="utf-8")
    paths[1].write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    if figure:  # (its title and caption, n included, from the document)
        from mmctl.study.plots import write_sensitivity_figure

        paths.append(write_sensitivity_figure(doc, out / "sensitivity.png"))
    return paths
