"""Statistics of the study: Friedman test, pairwise Wilcoxon signed-rank tests and the
Holm-Bonferroni correction (the paper's Table IV).

The Wilcoxon p-values use the normal approximation without continuity correction
(``method="approx"``) by default: that is what reproduces the paper's floor
``p_corr = 1.682e-5`` for 27 users who all rank the same way
(``3 x 5.606e-6``, the two-sided normal tail at ``z = 4.541``); the exact
distribution would give ``3 x 1.49e-8``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from itertools import combinations
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

#: The paper's significance level.
ALPHA = 0.05


class TestResult(NamedTuple):
    """A test statistic and its p-value."""

    statistic: float
    pvalue: float


class PairwiseResult(NamedTuple):
    """One pairwise comparison of one metric."""

    a: str
    b: str
    statistic: float
    pvalue: float
    pvalue_corrected: float

    def significant(self, alpha: float = ALPHA) -> bool:
        """Whether the Holm-corrected p-value is below ``alpha``."""
        return self.pvalue_corrected < alpha


def holm(pvalues: ArrayLike) -> np.ndarray:
    """Holm-Bonferroni step-down adjusted p-values, in the input order.

    With the m p-values sorted ascending, p_(1) <= ... <= p_(m), the adjusted value is
    ``max_{j <= i} min(1, (m - j + 1) p_(j))``; reject H_i when it is below alpha.
    """
    p = np.asarray(pvalues, dtype=float)
    if p.ndim != 1:
        raise ValueError(f"pvalues must be 1-D, got shape {p.shape}")
    if np.any((p < 0.0) | (p > 1.0)) or not np.all(np.isfinite(p)):
        raise ValueError("pvalues must lie in [0, 1]")
    m = p.size
    order = np.argsort(p, kind="stable")
    scaled = np.minimum(1.0, (m - np.arange(m)) * p[order])
    adjusted_sorted = np.maximum.accumulate(scaled)
    out = np.empty(m)
    out[order] = adjusted_sorted
    return out


def friedman(*groups: ArrayLike) -> TestResult:
    """Friedman test over k >= 3 related samples (one array per approach, same users)."""
    from scipy import stats

    arrays = [np.asarray(g, dtype=float) for g in groups]
    if len(arrays) < 3:
        raise ValueError("the Friedman test needs at least 3 groups")
    if len({a.size for a in arrays}) != 1:
        raise ValueError("every group must have one value per user")
    if np.allclose(np.ptp(np.vstack(arrays), axis=0), 0.0):
        return TestResult(0.0, 1.0)  # every user identical across groups: no effect
    res = stats.friedmanchisquare(*arrays)
    return TestResult(float(res.statistic), float(res.pvalue))


def wilcoxon(x: ArrayLike, y: ArrayLike, method: str = "approx") -> TestResult:
    """Two-sided Wilcoxon signed-rank test of the paired samples ``x`` and ``y``.

    ``method``: ``"approx"`` (normal approximation, no continuity correction: the
    paper's convention), ``"exact"`` or ``"auto"`` (scipy's choice).  Zero
    differences are dropped (Wilcoxon's convention); all-zero differences give p = 1.
    """
    from scipy import stats

    a = np.asarray(x, dtype=float)
    b = np.asarray(y, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples differ in shape: {a.shape} vs {b.shape}")
    if np.all(a - b == 0.0):
        return TestResult(0.0, 1.0)
    res = stats.wilcoxon(a, b, zero_method="wilcox", correction=False, method=method)
    return TestResult(float(res.statistic), float(res.pvalue))


def pairwise_wilcoxon_holm(
    groups: Mapping[str, ArrayLike], method: str = "approx"
) -> list[PairwiseResult]:
    """Wilcoxon signed-rank test for every pair of groups, Holm-corrected within the family.

    Pairs are taken in the mapping's order: (g0, g1), (g0, g2), (g1, g2), ...
    """
    names = list(groups)
    pairs = list(combinations(names, 2))
    raw = [wilcoxon(groups[a], groups[b], method) for a, b in pairs]
    adjusted = holm([r.pvalue for r in raw]) if raw else np.empty(0)
    return [
        PairwiseResult(a, b, r.statistic, r.pvalue, float(pc))
        for (a, b), r, pc in zip(pairs, raw, adjusted)
    ]


class MetricAnalysis(NamedTuple):
    """Friedman test and Holm-corrected pairwise tests of one metric."""

    metric: str
    friedman: TestResult
    pairwise: list[PairwiseResult]


def analyse(
    values: Mapping[str, Mapping[str, Sequence[float]]],
    metrics: Sequence[str],
    method: str = "approx",
) -> list[MetricAnalysis]:
    """Run the paper's statistics on ``values[approach][metric]`` (one value per user).

    The Friedman test is run over all approaches given (needs >= 3); the pairwise
    family of each metric is every pair of approaches.
    """
    approaches = list(values)
    out = []
    for m in metrics:
        groups = {a: np.asarray(values[a][m], dtype=float) for a in approaches}
        fr = friedman(*groups.values()) if len(groups) >= 3 else TestResult(float("nan"), float("nan"))
        out.append(MetricAnalysis(m, fr, pairwise_wilcoxon_holm(groups, method)))
    return out
