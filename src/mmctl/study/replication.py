"""The study replicated over several simulated populations (`mmctl study --seeds N`):
in how many of them each of the paper's claims holds.

A *claim* is one cell of the paper's Table IV read with its medians (Table III): for a
metric and a pair of approaches (a, b), either "a and b differ, a's median is higher"
(or lower), when the paper's p_corr < 0.05, or "a and b do not differ" otherwise.  In
one replication the claim holds when the pair is significant there (after a
significant Friedman test, :mod:`mmctl.study.stats`) with the paper's direction (the
sign of the median paired difference), or is not significant for a claim of no
difference.  The claims come from the paper's numbers only (``PAPER_PCORR``,
``PAPER_MEDIANS``): nothing here is tuned to the simulation.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

from mmctl.study.results import APPROACH_NAMES, METRIC_LABELS, PAPER_MEDIANS, PAPER_PCORR
from mmctl.study.stats import ALPHA, MetricAnalysis


class Claim(NamedTuple):
    """metric, the pair (a, b), whether the paper finds a difference, and its direction
    (+1: a's median higher, -1: lower, 0: no difference claimed)."""

    metric: str
    a: str
    b: str
    differ: bool
    direction: int

    def text(self) -> str:
        na, nb = APPROACH_NAMES.get(self.a, self.a), APPROACH_NAMES.get(self.b, self.b)
        label = METRIC_LABELS.get(self.metric, self.metric)
        if not self.differ:
            return f"{label}: {na} ≈ {nb}"
        return f"{label}: {na} {'>' if self.direction > 0 else '<'} {nb}"


def paper_claims(alpha: float = ALPHA) -> list[Claim]:
    """Every cell of the paper's Table IV as a claim (metric order, then pair order)."""
    out = []
    for metric, pairs in PAPER_PCORR.items():
        for (a, b), p in pairs.items():
            differ = p < alpha
            diff = PAPER_MEDIANS[a][metric] - PAPER_MEDIANS[b][metric]
            direction = (1 if diff > 0 else -1 if diff < 0 else 0) if differ else 0
            out.append(Claim(metric, a, b, differ, direction))
    return out


def holds(claim: Claim, analysis: Sequence[MetricAnalysis], alpha: float = ALPHA,
          users: int | None = None) -> bool | None:
    """Whether ``claim`` holds in one study's ``analysis`` (None: the study lacks the
    metric or the pair).  ``users``: the study's users, to decide with the tables' own
    p_holm (:func:`mmctl.study.report.decides`: exact up to 20 users); None: the normal
    approximation's Holm p."""
    from mmctl.study.report import decides, p_method

    for ma in analysis:
        if ma.metric != claim.metric:
            continue
        for r in ma.pairwise:
            if {r.a, r.b} != {claim.a, claim.b}:
                continue
            sign = 1 if (r.a, r.b) == (claim.a, claim.b) else -1
            d = sign * r.diff_median
            direction = 1 if d > 0 else -1 if d < 0 else 0
            sig = (r.significant(alpha) if users is None
                   else decides(r, p_method(ma, users), alpha))
            if not claim.differ:
                return not sig
            return sig and direction == claim.direction
    return None


def tally(analyses: Mapping[int, Sequence[MetricAnalysis]],
          alpha: float = ALPHA, users: int | Mapping[int, int] | None = None
          ) -> list[dict[str, Any]]:
    """Per claim: the seeds where it holds and where it does not.  ``users``: the users
    each seed's tests ran on (a mapping seed -> users tested, i.e. without the users an
    unfinished execution excluded, :func:`mmctl.study.report.tested`; or one count for
    every seed), to decide with that seed's tables' own p_holm (see :func:`holds`)."""
    rows = []
    per_seed = users if isinstance(users, Mapping) else {s: users for s in analyses}
    for c in paper_claims(alpha):
        verdicts = {seed: holds(c, a, alpha, per_seed[seed]) for seed, a in analyses.items()}
        rows.append({
            "claim": c.text(), "metric": c.metric, "a": c.a, "b": c.b,
            "paper_p_corr": PAPER_PCORR[c.metric][(c.a, c.b)],
            "holds": sorted(s for s, v in verdicts.items() if v),
            "fails": sorted(s for s, v in verdicts.items() if v is False),
        })
    return rows


def tally_table(rows: Sequence[dict[str, Any]], n: int) -> str:
    """Markdown: each claim, the paper's p_corr, in how many of the ``n`` populations
    it holds, and the seeds where it fails."""
    lines = ["| paper's claim | paper p_corr | holds in | fails for seeds |",
             "|---|---:|---:|---|"]
    for r in rows:
        p = r["paper_p_corr"]
        ptxt = f"{p:.3g}" if p >= 0.01 or math.isnan(p) else f"{p:.3e}"
        fails = ", ".join(str(s) for s in r["fails"][:12]) + (" ..." if len(r["fails"]) > 12
                                                             else "")
        lines.append(f"| {r['claim']} | {ptxt} | {len(r['holds'])}/{n} | {fails or '—'} |")
    return "\n".join(lines)
