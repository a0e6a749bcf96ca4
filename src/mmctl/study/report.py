"""Tables and files of the study: medians next to the paper's, the significance table,
``results.csv`` and ``summary.json``; the conditions the study's robot runs with.

**The deciding p** (``p_holm``; the table's one p column, summary.json's ``significant``
and the boxplots' brackets): each pair's two-sided Wilcoxon signed-rank p,
Holm-Bonferroni corrected over its metric's pairs, from the **exact** distribution for
at most :data:`EXACT_MAX_USERS` users (when every pair of the family has one), else from
the **normal approximation** without continuity correction (the paper's, for its 27
users).  A pair is significant when the metric's Friedman test is and ``p_holm`` <
alpha.  :mod:`mmctl.study.stats` computes both values; this module only chooses.

**Unfinished executions** (``completed`` False: the time limit or a latched fault ended
them; their T_f is the limit, their other metrics cover part of the task) are counted
per approach in the median table and summary.json (``unfinished``) and kept in the
medians, but a user with one is left out of **every** test (:func:`tested`): the
Friedman test pairs each user's values over all approaches, and its Wilcoxon pairs
stay on the users of the Friedman test that gates them, so one n holds for a metric's
whole family; the significance table's note says "n = K users (U unfinished
excluded)".
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from mmctl.study.results import (
    APPROACH_NAMES,
    CSV_COLUMNS,
    EXTRA_METRICS,
    METRIC_LABELS,
    METRICS,
    PAPER_MEDIANS,
    PAPER_PCORR,
    Execution,
    csv_row,
)
from mmctl.study.stats import ALPHA, MetricAnalysis, PairwiseResult, analyse

if TYPE_CHECKING:
    from mmctl.study.config import StudyConfig

#: Up to this many users the deciding p (``p_holm``) comes from the exact distribution
#: of the Wilcoxon statistic; above it from the normal approximation.  scipy's
#: documentation of ``wilcoxon`` (0.7-1.2) gave the rule for the approximation: "A
#: typical rule is to require that n > 20"; the paper's 27 users are above it, so its
#: table is computed as the paper computed it.
EXACT_MAX_USERS = 20
#: How ``p_holm`` was computed, as the table's note and summary.json name it.
P_METHODS: dict[str, str] = {
    "exact": "exact distribution",
    "normal": "normal approximation without continuity correction",
}


def strategies_of(execs: Sequence[Execution]) -> list[str]:
    """Strategies in first-seen order."""
    return list(dict.fromkeys(e.strategy for e in execs))


def metrics_of(execs: Sequence[Execution]) -> tuple[str, ...]:
    """The metrics to report: the paper's five, then those of :data:`EXTRA_METRICS`
    that every execution has (x_f_hold: executions made before the hold have none)."""
    extra = tuple(m for m in EXTRA_METRICS
                  if execs and all(math.isfinite(e.metric(m)) for e in execs))
    return (*METRICS, *extra)


def values(execs: Sequence[Execution]) -> dict[str, dict[str, np.ndarray]]:
    """``values[strategy][metric]``: one value per user, in user order, for every
    metric of :func:`metrics_of`."""
    out: dict[str, dict[str, np.ndarray]] = {}
    names = metrics_of(execs)
    for s in strategies_of(execs):
        rows = sorted((e for e in execs if e.strategy == s), key=lambda e: e.user)
        out[s] = {m: np.array([e.metric(m) for e in rows]) for m in names}
    return out


def unfinished(execs: Sequence[Execution]) -> dict[str, int]:
    """Per strategy, the number of its executions not finished (``completed`` False)."""
    return {s: sum(1 for e in execs if e.strategy == s and not e.completed)
            for s in strategies_of(execs)}


def excluded_users(execs: Sequence[Execution]) -> list[int]:
    """The users with an unfinished execution in any approach, ascending."""
    return sorted({e.user for e in execs if not e.completed})


def tested(execs: Sequence[Execution]) -> list[Execution]:
    """The executions the statistical tests use: every user with an unfinished
    execution is dropped from all approaches (the tests are paired)."""
    out = set(excluded_users(execs))
    return [e for e in execs if e.user not in out]


def limited_medians(execs: Sequence[Execution]) -> dict[str, float]:
    """Per strategy, the median over its executions of the share of samples on which a
    limit bound the command [%] (:attr:`Execution.limited` x 100)."""
    return {s: 100.0 * float(np.median([e.limited for e in execs if e.strategy == s]))
            for s in strategies_of(execs)}


def medians(execs: Sequence[Execution]) -> dict[str, dict[str, float]]:
    """Median of every reported metric per strategy."""
    return {s: {m: float(np.median(x)) for m, x in v.items()} for s, v in values(execs).items()}


def median_user(execs: Sequence[Execution]) -> int:
    """The user most often closest to the median (over every strategy and metric), as
    the paper picks the user of its Figs. 6-7; ties go to the smaller summed distance
    in interquartile ranges, then the lower index."""
    vals = values(execs)
    users = sorted({e.user for e in execs})
    hits = np.zeros(len(users))
    dist = np.zeros(len(users))
    for per in vals.values():
        for m in METRICS:  # the paper's metrics: the median user of its Figs. 6-7
            x = per[m]
            med = np.median(x)
            iqr = float(np.subtract(*np.percentile(x, [75, 25]))) or 1.0
            d = np.abs(x - med) / iqr
            hits[int(np.argmin(d))] += 1
            dist += d
    best = min(range(len(users)), key=lambda i: (-hits[i], dist[i], users[i]))
    return users[best]


def _fmt(x: float) -> str:
    if not math.isfinite(x):
        return "n/a"
    return f"{x:.2f}" if abs(x) >= 0.01 or x == 0.0 else f"{x:.3f}"


#: The median table's column of the limit share and of the unfinished count.
LIMITED_LABEL = "limit binds [%]"
UNFINISHED_LABEL = "unfinished"


def median_table(execs: Sequence[Execution]) -> str:
    """Markdown table: per approach, the simulated median and the paper's (— where the
    paper has none: x_f after the hold), over every execution; then the median share of
    samples on which a limit bound the command [%] and the number of unfinished
    executions (the paper reports neither); a line under it names the unfinished."""
    med = medians(execs)
    lim = limited_medians(execs)
    bad = unfinished(execs)
    names = metrics_of(execs)
    head = ("| approach | " + " | ".join(f"{METRIC_LABELS[m]} sim | paper" for m in names)
            + f" | {LIMITED_LABEL} | {UNFINISHED_LABEL} |")
    sep = "|---|" + "---:|---:|" * len(names) + "---:|---:|"
    lines = [head, sep]
    for s, row in med.items():
        paper = PAPER_MEDIANS.get(s, {})
        cells = [f"{_fmt(row[m])} | {_fmt(paper[m]) if m in paper else '—'}" for m in names]
        n_s = sum(1 for e in execs if e.strategy == s)
        lines.append(f"| {s} | " + " | ".join(cells) + f" | {lim[s]:.1f} | {bad[s]} of {n_s} |")
    out = set(excluded_users(execs))
    if out:
        which = ", ".join(f"user {e.user} {e.strategy}" for e in execs if not e.completed)
        lines += ["", (f"Unfinished (T_f: where the execution ended, the time limit or a "
                       f"stop; kept in these medians, excluded from the tests with all "
                       f"their user's approaches): {which}.")]
    return "\n".join(lines)


def _fmt_p(p: float) -> str:
    if not math.isfinite(p):
        return "n/a"
    if p >= 0.01:
        return f"{p:.3g}"
    mant, exp = f"{p:.3e}".split("e")
    return f"{mant}e{int(exp)}"


def _ci(lo: float, hi: float) -> str:
    return f"[{_fmt(lo)}, {_fmt(hi)}]"


def p_method(ma: MetricAnalysis, users: int) -> str:
    """How ``ma``'s deciding p is computed: "exact" for at most :data:`EXACT_MAX_USERS`
    ``users`` when every pair of the family has its exact p, else "normal"."""
    if users <= EXACT_MAX_USERS and ma.pairwise and all(
            math.isfinite(r.pvalue_exact_corrected) for r in ma.pairwise):
        return "exact"
    return "normal"


def p_holm(r: PairwiseResult, method: str) -> float:
    """The deciding Holm-corrected p of the pair ``r`` by ``method`` (:func:`p_method`)."""
    return r.pvalue_exact_corrected if method == "exact" else r.pvalue_corrected


def decides(r: PairwiseResult, method: str, alpha: float = ALPHA) -> bool:
    """Whether the pair is significant: its Friedman test allows it and its ``p_holm``
    by ``method`` is below ``alpha``."""
    return r.gated and p_holm(r, method) < alpha


def smallest_p_holm(users: int, pairs: int, method: str) -> float:
    """The smallest ``p_holm`` any pair of a family of ``pairs`` can reach with ``users``
    users (all ranking the pair the same way; no zero differences): Holm's first step,
    ``pairs`` x the smallest two-sided p, ``2 / 2^n`` exactly, or the normal tail at
    ``z = sqrt(3 n (n + 1) / (2 (2 n + 1)))`` (n = 27: 3 x 5.606e-6 = 1.682e-5)."""
    n = max(users, 1)
    if method == "exact":
        p = 2.0 ** (1 - n)
    else:
        p = math.erfc(math.sqrt(3.0 * n * (n + 1) / (2.0 * (2 * n + 1))) / math.sqrt(2.0))
    return min(1.0, pairs * p)


def n_note(users: int, excluded: int) -> str:
    """"n = K users (U unfinished excluded)" (without the parenthesis when U = 0)."""
    return f"n = {users} users" + (f" ({excluded} unfinished excluded)" if excluded else "")


def p_note(analysis: Sequence[MetricAnalysis], users: int, alpha: float = ALPHA,
           excluded: int = 0) -> str:
    """The line under the significance table: the users tested (``users``; ``excluded``
    left out for an unfinished execution), how ``p_holm`` was computed, what it decides
    and the smallest value ``users`` users allow."""
    by: dict[str, list[str]] = {}
    for ma in analysis:
        by.setdefault(p_method(ma, users), []).append(METRIC_LABELS.get(ma.metric, ma.metric))
    pairs = max((len(ma.pairwise) for ma in analysis), default=0)
    rule = f"exact up to {EXACT_MAX_USERS} users, above that the paper's normal approximation"
    if len(by) == 1 and "exact" in by:
        how = f"computed from the {P_METHODS['exact']} ({users} users; {rule})"
    elif len(by) == 1:
        how = f"computed from the {P_METHODS['normal']} ({users} users; {rule})"
    else:  # few users, but some metric without an exact p
        how = "computed " + "; ".join(f"from the {P_METHODS[m]} for {', '.join(ms)}"
                                      for m, ms in by.items()) + f" (no exact p there; {rule})"
    floors = " or ".join(f"{_fmt_p(smallest_p_holm(users, pairs, m))} ({m})" for m in by)
    return (f"{n_note(users, excluded)}. "
            f"p_holm: two-sided Wilcoxon signed-rank p, Holm-Bonferroni corrected over the "
            f"metric's {pairs} pairs, {how}. It alone decides: Significant = p_holm < "
            f"{alpha:g} after a significant Friedman test. With {users} users no p_holm can "
            f"be below {floors}. summary.json keeps both corrected values besides p_holm "
            "(p_corr: normal approximation, p_exact_corr: exact).")


def significance_table(analysis: Sequence[MetricAnalysis], users: int,
                       alpha: float = ALPHA, excluded: int = 0) -> str:
    """Markdown table in the paper's Table IV format with one p column, ``p_holm``, the
    one that decides (:func:`p_method`), the effect size (rank-biserial r, positive: the
    first approach higher) and the median paired difference with their bootstrap 95 %
    intervals, and the paper's p_corr alongside; then the note saying how ``p_holm``
    was computed (:func:`p_note`).  ``users``: the number of users tested (pairs per
    test); ``excluded``: the users left out for an unfinished execution (:func:`tested`).
    A pair is "Significant" only after a significant Friedman test of its metric ("Not
    tested" otherwise)."""
    lines = [
        ("| Metric | Comparison | p_holm | Significance | paper p_corr | r [95 % CI] "
         "| median a − b [95 % CI] |"),
        "|---|---|---:|---|---:|---|---|",
    ]
    for ma in analysis:
        method = p_method(ma, users)
        for r in ma.pairwise:
            paper = PAPER_PCORR.get(ma.metric, {}).get((r.a, r.b))
            cmp_ = f"{APPROACH_NAMES.get(r.a, r.a)} vs {APPROACH_NAMES.get(r.b, r.b)}"
            if not r.gated:
                sig = f"Not tested (Friedman p = {_fmt_p(ma.friedman.pvalue)})"
            else:
                sig = "Significant" if decides(r, method, alpha) else "Not significant"
            pp = _fmt_p(paper) if paper is not None else "—"
            lines.append(f"| {METRIC_LABELS[ma.metric]} | {cmp_} | {_fmt_p(p_holm(r, method))} "
                         f"| {sig} | {pp} | {r.effect:+.2f} {_ci(*r.effect_ci)} "
                         f"| {_fmt(r.diff_median)} {_ci(*r.diff_ci)} |")
    return "\n".join(lines) + "\n\n" + p_note(analysis, users, alpha, excluded)


def median_ci_table(analysis: Sequence[MetricAnalysis]) -> str:
    """Markdown table: every approach's median of every metric with its bootstrap 95 %
    interval over the users."""
    approaches = list((analysis[0].medians or {}) if analysis else {})
    lines = ["| approach | " + " | ".join(METRIC_LABELS[ma.metric] for ma in analysis) + " |",
             "|---|" + "---|" * len(analysis)]
    for a in approaches:
        cells = []
        for ma in analysis:
            med, lo, hi = (ma.medians or {})[a]
            cells.append(f"{_fmt(med)} {_ci(lo, hi)}")
        lines.append(f"| {a} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def friedman_table(analysis: Sequence[MetricAnalysis]) -> str:
    """Markdown table of the Friedman tests."""
    lines = ["| Metric | χ² | p |", "|---|---:|---:|"]
    for ma in analysis:
        lines.append(f"| {METRIC_LABELS[ma.metric]} | {ma.friedman.statistic:.2f} "
                     f"| {_fmt_p(ma.friedman.pvalue)} |")
    return "\n".join(lines)


def results_csv(execs: Sequence[Execution]) -> str:
    """results.csv content, rows sorted by user then strategy order of ``execs``."""
    order = {s: i for i, s in enumerate(strategies_of(execs))}
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for e in sorted(execs, key=lambda e: (e.user, order[e.strategy])):
        w.writerow(csv_row(e))
    return buf.getvalue()


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def users_of(execs: Sequence[Execution]) -> int:
    """The number of users in ``execs``."""
    return len({e.user for e in execs})


def summary(
    execs: Sequence[Execution], analysis: Sequence[MetricAnalysis], meta: dict[str, Any]
) -> dict[str, Any]:
    """The summary.json document; per pair ``p_holm`` (the deciding p), its
    ``p_holm_method`` and ``significant`` by it, besides both corrected values;
    ``analysis`` made from :func:`tested` (``tested_users``, ``excluded_users``), the
    medians from every execution, ``unfinished`` counted per approach and listed in
    ``incomplete``."""
    users = users_of(tested(execs))
    methods = {ma.metric: p_method(ma, users) for ma in analysis}
    return {
        "medians": medians(execs),
        "medians_ci95": {
            ma.metric: {a: list(v) for a, v in (ma.medians or {}).items()} for ma in analysis
        },
        "friedman": {
            ma.metric: {"statistic": _num(ma.friedman.statistic), "p": _num(ma.friedman.pvalue)}
            for ma in analysis
        },
        "pairwise": {
            ma.metric: {
                f"{r.a} vs {r.b}": {
                    "statistic": _num(r.statistic), "p": _num(r.pvalue),
                    "p_corr": _num(r.pvalue_corrected),
                    "p_holm": _num(p_holm(r, methods[ma.metric])),
                    "p_holm_method": methods[ma.metric],
                    "significant": decides(r, methods[ma.metric]),
                    "tested": r.gated, "p_exact": _num(r.pvalue_exact),
                    "p_exact_corr": _num(r.pvalue_exact_corrected),
                    "rank_biserial": _num(r.effect),
                    "rank_biserial_ci95": [_num(x) for x in r.effect_ci],
                    "median_difference": _num(r.diff_median),
                    "median_difference_ci95": [_num(x) for x in r.diff_ci],
                }
                for r in ma.pairwise
            }
            for ma in analysis
        },
        "limited_median_percent": limited_medians(execs),
        "unfinished": unfinished(execs),
        "tested_users": users,
        "excluded_users": excluded_users(execs),
        "paper_medians": PAPER_MEDIANS,
        "median_user": median_user(execs),
        "incomplete": [f"user {e.user} {e.strategy}" for e in execs if not e.completed],
        **meta,
    }


def write_outputs(
    out: Path, execs: Sequence[Execution], meta: dict[str, Any]
) -> tuple[list[MetricAnalysis], dict[str, Any]]:
    """Write results.csv and summary.json into ``out``; return the analysis (of the
    users who finished every approach, :func:`tested`) and summary."""
    out.mkdir(parents=True, exist_ok=True)
    kept = tested(execs)
    # fewer than 2 users left: nothing to test (every table then says so by being empty)
    analysis = (analyse(cast(Any, values(kept)), metrics_of(execs))
                if users_of(kept) >= 2 else [])
    (out / "results.csv").write_text(results_csv(execs), encoding="utf-8")
    doc = summary(execs, analysis, meta)
    (out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return analysis, doc


def conditions(study: StudyConfig) -> dict[str, Any]:
    """What the study's robot runs with (summary.json's ``conditions``, the figures'
    captions): the whole-body caps (ISO/TS 15066) and the braking and checks of the
    control configuration of its first approach, beside the daemon's defaults."""
    from mmctl.config import default_config
    from mmctl.control.step import whole_body_caps
    from mmctl.model.robot import RobotModel

    cfg = study.control_config(study.strategies[0])
    base = default_config()
    caps = whole_body_caps(cfg, RobotModel(cfg.robot).arm_mass)
    daemon = whole_body_caps(base, RobotModel(base.robot).arm_mass)
    return {
        "config": study.config_path,
        "limits.body_region": cfg.limits.body_region,
        "caps": {"energy_J": _num(caps.energy), "base_speed_m_s": _num(caps.base_speed),
                 "ee_speed_m_s": _num(caps.ee_speed)},
        "safety.brake_condition": cfg.safety.brake_condition,
        "safety.collision_check": cfg.safety.collision_check,
        "idk.avoid_joint_limits": cfg.idk.avoid_joint_limits,
        "daemon_default": {
            "limits.body_region": base.limits.body_region,
            "energy_J": _num(daemon.energy),
            "safety.brake_condition": base.safety.brake_condition,
        },
    }


def conditions_text(cond: Mapping[str, Any] | None) -> str:
    """One sentence from :func:`conditions` for a caption ("" when ``cond`` is None)."""
    if not cond:
        return ""
    caps = cond.get("caps") or {}
    dflt = cond.get("daemon_default") or {}
    src = (f"control configuration {cond['config']}" if cond.get("config")
           else "the study's built-in settings, the paper's robot")
    if caps.get("energy_J") is None and caps.get("base_speed_m_s") is None \
            and caps.get("ee_speed_m_s") is None:
        cap = (f"no ISO/TS 15066 caps (limits.body_region {cond.get('limits.body_region')}; "
               f"the daemon's default, {dflt.get('limits.body_region')}, caps E_K at "
               f"{dflt.get('energy_J'):.4g} J)")
    else:
        parts = [f"{name} ≤ {caps[key]:.4g} {unit}" for key, name, unit in (
            ("energy_J", "E_K", "J"), ("base_speed_m_s", "base speed", "m/s"),
            ("ee_speed_m_s", "end-effector speed", "m/s")) if caps.get(key) is not None]
        cap = (f"ISO/TS 15066 caps on (limits.body_region {cond.get('limits.body_region')}): "
               + ", ".join(parts))
    brake = cond.get("safety.brake_condition")
    brake_txt = ("singularity braking only at the fault's own level (safety.brake_condition 1"
                 if brake == 1.0 else f"singularity braking from safety.brake_condition {brake:g}")
    brake_txt += f"; the daemon's {dflt.get('safety.brake_condition'):g})" \
        if dflt.get("safety.brake_condition") is not None else ")"
    checks = (f"self-collision braking {'on' if cond.get('safety.collision_check') else 'off'}, "
              f"joint-limit hand-over {'on' if cond.get('idk.avoid_joint_limits') else 'off'}")
    return f"Robot ({src}): {cap}; {brake_txt}; {checks}."
