"""Statistics of the study: Friedman test, pairwise Wilcoxon signed-rank tests and the
Holm-Bonferroni correction (the paper's Table IV), and what the paper does not report:
exact p-values, effect sizes and bootstrap confidence intervals.

Pairwise tests are *gated* by the Friedman test: a pair counts as significant only when
the Friedman test of its metric is (the usual closed-testing order; the paper reports
pairs regardless).  Effect size: the matched-pairs rank-biserial correlation (Kerby
2014), ``r = (R+ - R-) / (R+ + R-)`` with R+/R- the rank sums of the positive and
negative differences (zeros dropped): +1 when every user has a > b, -1 when every one
has a < b.  Confidence intervals: 95 % percentile bootstrap over users (pairs resampled
together), :data:`BOOTSTRAP` resamples from a fixed seed, so a table is reproducible;
none below :data:`MIN_BOOTSTRAP_N` users.  Exact p-values count the signed-rank
statistic's permutation distribution with ties and zeros (:func:`signed_rank_exact`).

The Wilcoxon p-values use the normal approximation without continuity correction
(``method="approx"``) by default: that is what reproduces the paper's floor
``p_corr = 1.682e-5`` for 27 users who all rank the same way
(``3 x 5.606e-6``, the two-sided normal tail at ``z = 4.541``); the exact
distribution would give ``3 x 1.49e-8``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from itertools import combinations
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

#: The paper's significance level.
ALPHA = 0.05
#: bootstrap resamples (percentile intervals; the seed is fixed: tables reproduce)
BOOTSTRAP = 4000
#: the fewest users a bootstrap interval is given for: below, a percentile bootstrap
#: of a median has a handful of distinct values and its "interval" collapses toward a
#: point (3 users: at most 10 distinct resampled medians); NaN then, and the tables
#: say so
MIN_BOOTSTRAP_N = 10
_NAN2 = (math.nan, math.nan)


class TestResult(NamedTuple):
    """A test statistic and its p-value."""

    statistic: float
    pvalue: float


class PairwiseResult(NamedTuple):
    """One pairwise comparison of one metric: the Wilcoxon statistic, its p-value by
    ``method`` and Holm-corrected, the exact p-value (Holm-corrected too), the effect
    size (rank-biserial r, a > b positive) and the median of the paired differences
    a - b, each with its bootstrap 95 % interval; gated: the metric's Friedman test is
    significant (or there are only two groups)."""

    a: str
    b: str
    statistic: float
    pvalue: float
    pvalue_corrected: float
    pvalue_exact: float = math.nan
    pvalue_exact_corrected: float = math.nan
    effect: float = math.nan
    effect_ci: tuple[float, float] = _NAN2
    diff_median: float = math.nan
    diff_ci: tuple[float, float] = _NAN2
    gated: bool = True

    def significant(self, alpha: float = ALPHA) -> bool:
        """Whether the Friedman test allows the pair and its Holm-corrected p-value is
        below ``alpha``."""
        return self.gated and self.pvalue_corrected < alpha


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


#: [metric unit] the resolution paired differences are compared at: two differences
#: equal up to floating-point noise (T_f is a multiple of the 2 ms period; a - b of
#: such values differs in its last bits) are a tie, and a difference below it is zero.
#: Every metric is in SI units whose meaningful resolution is far coarser.
DIFF_RESOLUTION = 1e-9


def paired_differences(x: ArrayLike, y: ArrayLike) -> np.ndarray:
    """x - y, rounded to :data:`DIFF_RESOLUTION` (ties stay ties; see there)."""
    a = np.asarray(x, dtype=float)
    b = np.asarray(y, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples differ in shape: {a.shape} vs {b.shape}")
    return np.asarray(np.round((a - b) / DIFF_RESOLUTION) * DIFF_RESOLUTION)


def wilcoxon(x: ArrayLike, y: ArrayLike, method: str = "approx") -> TestResult:
    """Two-sided Wilcoxon signed-rank test of the paired samples ``x`` and ``y``.

    ``method``: ``"approx"`` (normal approximation, no continuity correction: the
    paper's convention), ``"exact"`` or ``"auto"`` (scipy's choice).  Zero
    differences are dropped (Wilcoxon's convention); all-zero differences give p = 1.
    """
    from scipy import stats

    d = paired_differences(x, y)
    if np.all(d == 0.0):
        return TestResult(0.0, 1.0)
    res = stats.wilcoxon(d, zero_method="wilcox", correction=False, method=method)
    return TestResult(float(res.statistic), float(res.pvalue))


def rank_biserial(d: ArrayLike) -> np.ndarray:
    """Matched-pairs rank-biserial correlation of the differences ``d`` (..., n), along
    the last axis (zeros dropped; all zero: 0)."""
    from scipy import stats

    x = np.asarray(d, dtype=float)
    a = np.where(x == 0.0, np.nan, np.abs(x))
    ranks = stats.rankdata(a, axis=-1, nan_policy="omit")
    plus = np.nansum(np.where(x > 0.0, ranks, 0.0), axis=-1)
    minus = np.nansum(np.where(x < 0.0, ranks, 0.0), axis=-1)
    total = plus + minus
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(total > 0.0, (plus - minus) / np.where(total > 0.0, total, 1.0), 0.0)
    return np.asarray(r)


def _resamples(n: int, seed: int = 0) -> np.ndarray:
    """(BOOTSTRAP, n) indices of users drawn with replacement."""
    return np.random.default_rng(seed).integers(0, n, size=(BOOTSTRAP, n))


def _interval(samples: np.ndarray) -> tuple[float, float]:
    lo, hi = np.percentile(samples, [2.5, 97.5])
    return float(lo), float(hi)


def median_ci(x: ArrayLike, seed: int = 0) -> tuple[float, float, float]:
    """(median, low, high): the median of ``x`` and its bootstrap 95 % interval."""
    v = np.asarray(x, dtype=float)
    if v.size == 0:
        return (math.nan, *_NAN2)
    if v.size < MIN_BOOTSTRAP_N:
        return float(np.median(v)), *_NAN2
    lo, hi = _interval(np.median(v[_resamples(v.size, seed)], axis=1))
    return float(np.median(v)), lo, hi


def _paired(a: np.ndarray, b: np.ndarray, seed: int) -> tuple[float, tuple[float, float],
                                                               float, tuple[float, float]]:
    """Effect size and median difference of the pairs (a, b), with their intervals."""
    d = paired_differences(a, b)
    if d.size == 0:
        return math.nan, _NAN2, math.nan, _NAN2
    if d.size < MIN_BOOTSTRAP_N:
        return float(rank_biserial(d)), _NAN2, float(np.median(d)), _NAN2
    boot = d[_resamples(d.size, seed)]
    return (float(rank_biserial(d)), _interval(rank_biserial(boot)),
            float(np.median(d)), _interval(np.median(boot, axis=1)))


def signed_rank_exact(x: ArrayLike, y: ArrayLike) -> float:
    """The exact two-sided p of the Wilcoxon signed-rank test of the pairs (x, y),
    ties and zeros included: zero differences dropped (Wilcoxon's convention, as
    :func:`wilcoxon`), tied |differences| given their mid-ranks, and the statistic's
    null distribution counted over all 2^n sign patterns of *those* ranks (the
    permutation distribution; scipy's "exact" assumes ranks 1..n, no ties, which the
    study's 2 ms-quantised T_f breaks).  All differences zero: p = 1.

    p = P(|T+ - E T+| >= |t+ - E T+|) under the null, T+ the sum of the positive
    differences' ranks; mid-ranks are multiples of 1/2, so the distribution is counted
    exactly on twice the ranks (integers)."""
    from scipy import stats

    d = paired_differences(x, y)
    d = d[d != 0.0]
    n = d.size
    if n == 0:
        return 1.0
    ranks2 = np.rint(2.0 * stats.rankdata(np.abs(d))).astype(np.int64)
    total = int(ranks2.sum())
    counts = np.zeros(total + 1)
    counts[0] = 1.0
    for r in ranks2:  # each rank in T+ or not: the distribution of 2 T+
        counts[r:] = counts[r:] + counts[: total + 1 - r].copy()
    counts /= counts.sum()
    t2 = int(ranks2[d > 0.0].sum())
    mid = total / 2.0
    values = np.arange(total + 1)
    extreme = np.abs(values - mid) >= abs(t2 - mid) - 1e-9
    return float(min(1.0, counts[extreme].sum()))


def _exact(a: np.ndarray, b: np.ndarray) -> float:
    """The exact p-value, ties and zeros included (:func:`signed_rank_exact`)."""
    return signed_rank_exact(a, b)


def pairwise_wilcoxon_holm(
    groups: Mapping[str, ArrayLike], method: str = "approx", gated: bool = True,
    seed: int = 0,
) -> list[PairwiseResult]:
    """Wilcoxon signed-rank test for every pair of groups, Holm-corrected within the family
    (by ``method`` and, alongside, exact), with effect sizes and bootstrap intervals.

    Pairs are taken in the mapping's order: (g0, g1), (g0, g2), (g1, g2), ...  gated:
    whether the omnibus test allows pairwise conclusions (:meth:`PairwiseResult.significant`).
    """
    names = list(groups)
    pairs = list(combinations(names, 2))
    arrays = {n: np.asarray(groups[n], dtype=float) for n in names}
    raw = [wilcoxon(arrays[a], arrays[b], method) for a, b in pairs]
    adjusted = holm([r.pvalue for r in raw]) if raw else np.empty(0)
    exact = [_exact(arrays[a], arrays[b]) for a, b in pairs]
    known = [i for i, p in enumerate(exact) if math.isfinite(p)]
    exact_adj = [math.nan] * len(exact)
    for i, pc in zip(known, holm([exact[i] for i in known]) if known else []):
        exact_adj[i] = float(pc)
    out = []
    for k, ((a, b), r, pc) in enumerate(zip(pairs, raw, adjusted)):
        eff, eff_ci, dmed, dci = _paired(arrays[a], arrays[b], seed + k)
        out.append(PairwiseResult(a, b, r.statistic, r.pvalue, float(pc), exact[k],
                                  exact_adj[k], eff, eff_ci, dmed, dci, gated))
    return out


class MetricAnalysis(NamedTuple):
    """Friedman test and Holm-corrected pairwise tests of one metric, and each group's
    median with its bootstrap 95 % interval (median, low, high)."""

    metric: str
    friedman: TestResult
    pairwise: list[PairwiseResult]
    medians: Mapping[str, tuple[float, float, float]] | None = None

    def gated(self, alpha: float = ALPHA) -> bool:
        """Whether pairwise conclusions are allowed: the Friedman test is significant
        (or there are only two groups and no omnibus test)."""
        p = self.friedman.pvalue
        return (not math.isfinite(p)) or p < alpha


def analyse(
    values: Mapping[str, Mapping[str, Sequence[float]]],
    metrics: Sequence[str],
    method: str = "approx",
) -> list[MetricAnalysis]:
    """Run the paper's statistics on ``values[approach][metric]`` (one value per user).

    The Friedman test is run over all approaches given (needs >= 3); the pairwise
    family of each metric is every pair of approaches, gated by the Friedman test at
    :data:`ALPHA`.  The bootstrap seeds depend on the metric's and the pair's position
    only: the same values give the same intervals.
    """
    approaches = list(values)
    out = []
    for i, m in enumerate(metrics):
        groups = {a: np.asarray(values[a][m], dtype=float) for a in approaches}
        fr = friedman(*groups.values()) if len(groups) >= 3 else TestResult(float("nan"), float("nan"))
        gate = (not math.isfinite(fr.pvalue)) or fr.pvalue < ALPHA
        seed = 1000 * i
        out.append(MetricAnalysis(
            m, fr, pairwise_wilcoxon_holm(groups, method, gate, seed),
            {a: median_ci(g, seed + 100 + j) for j, (a, g) in enumerate(groups.items())}))
    return out
