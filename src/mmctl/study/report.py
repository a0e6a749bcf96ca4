"""Tables and files of the study: medians next to the paper's, the significance table,
``results.csv`` and ``summary.json``."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

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
from mmctl.study.stats import ALPHA, MetricAnalysis, analyse


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


def median_table(execs: Sequence[Execution]) -> str:
    """Markdown table: per approach, the simulated median and the paper's (— where the
    paper has none: x_f after the hold)."""
    med = medians(execs)
    names = metrics_of(execs)
    head = "| approach | " + " | ".join(f"{METRIC_LABELS[m]} sim | paper" for m in names) + " |"
    sep = "|---|" + "---:|---:|" * len(names)
    lines = [head, sep]
    for s, row in med.items():
        paper = PAPER_MEDIANS.get(s, {})
        cells = [f"{_fmt(row[m])} | {_fmt(paper[m]) if m in paper else '—'}" for m in names]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
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


def significance_table(analysis: Sequence[MetricAnalysis], alpha: float = ALPHA) -> str:
    """Markdown table in the paper's Table IV format (p_corr by the normal approximation,
    as the paper), with the exact p_corr, the effect size (rank-biserial r, positive:
    the first approach higher) and the median paired difference with their bootstrap
    95 % intervals, and the paper's p_corr alongside.  A pair is "Significant" only
    after a significant Friedman test of its metric ("not tested" otherwise)."""
    lines = [
        ("| Metric | Comparison | p_corr | Significance | paper p_corr | p_corr exact "
        "| r [95 % CI] | median a − b [95 % CI] |"),
        "|---|---|---:|---|---:|---:|---|---|",
    ]
    for ma in analysis:
        for r in ma.pairwise:
            paper = PAPER_PCORR.get(ma.metric, {}).get((r.a, r.b))
            cmp_ = f"{APPROACH_NAMES.get(r.a, r.a)} vs {APPROACH_NAMES.get(r.b, r.b)}"
            if not r.gated:
                sig = f"Not tested (Friedman p = {_fmt_p(ma.friedman.pvalue)})"
            else:
                sig = "Significant" if r.significant(alpha) else "Not significant"
            pp = _fmt_p(paper) if paper is not None else "—"
            lines.append(f"| {METRIC_LABELS[ma.metric]} | {cmp_} | {_fmt_p(r.pvalue_corrected)} "
                         f"| {sig} | {pp} | {_fmt_p(r.pvalue_exact_corrected)} "
                         f"| {r.effect:+.2f} {_ci(*r.effect_ci)} "
                         f"| {_fmt(r.diff_median)} {_ci(*r.diff_ci)} |")
    return "\n".join(lines)


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


def summary(
    execs: Sequence[Execution], analysis: Sequence[MetricAnalysis], meta: dict[str, Any]
) -> dict[str, Any]:
    """The summary.json document."""
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
                    "p_corr": _num(r.pvalue_corrected), "significant": r.significant(),
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
        "paper_medians": PAPER_MEDIANS,
        "median_user": median_user(execs),
        "incomplete": [f"user {e.user} {e.strategy}" for e in execs if not e.completed],
        **meta,
    }


def write_outputs(
    out: Path, execs: Sequence[Execution], meta: dict[str, Any]
) -> tuple[list[MetricAnalysis], dict[str, Any]]:
    """Write results.csv and summary.json into ``out``; return the analysis and summary."""
    out.mkdir(parents=True, exist_ok=True)
    analysis = analyse(cast(Any, values(execs)), metrics_of(execs))
    (out / "results.csv").write_text(results_csv(execs), encoding="utf-8")
    doc = summary(execs, analysis, meta)
    (out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return analysis, doc
