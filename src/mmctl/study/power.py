"""How strong each of the paper's claims is, and how many people a real study needs.

Three things a lab planning a replication asks, computed from the paper's own numbers
and from a simulated study's per-user values:

* **The effect the paper's p_corr implies.**  Holm's correction is undone within each
  metric's family of three pairs (the i-th smallest adjusted p-value was the raw one
  times ``m - i + 1``); the raw two-sided p of the Wilcoxon test's normal approximation
  gives ``z``, and with it ``r = z / sqrt(n)`` (the usual effect size of a Wilcoxon
  test) and the matched-pairs rank-biserial correlation that ``z`` means without ties
  (``r_rb = 4 z sigma_T / (n (n + 1))``, ``sigma_T`` the statistic's SD), which is the
  simulation's effect size (:mod:`mmctl.study.stats`).  A p_corr at the paper's floor
  (1.682e-5: all 27 users one way) is only a bound: ``z >= 4.54``.
* **Equivalence** for the "≈" claims: two one-sided Wilcoxon signed-rank tests
  (TOST) of the paired differences against ``±margin`` (:data:`MARGINS`, physical
  units, each with its reason); equivalence when the larger of the two p-values is
  below alpha.  "No significant difference" is not evidence of no difference.
* **Sample size** for 80 % power at alpha = 0.05 with Holm over the three pairs of a
  metric: planned at Holm's strictest step (alpha / 3, Bonferroni), for a paired
  t-test of standardised effect ``d_z`` (the noncentral t, exact), then divided by the
  Wilcoxon test's asymptotic relative efficiency 3/pi (normal data) and rounded up.
  ``d_z`` comes from the paper's implied ``z`` (``d_z = z / sqrt(n)``), or from the
  simulation's mean paired difference over an SD that is *stated*: the paper gives no
  interquartile ranges in numbers (only its boxplots), so the SD of a pair's
  differences is the one the paper's own test implies, ``|paper median difference| *
  sqrt(27) / z`` (an assumption: the difference of the medians standing in for the
  mean difference).  :func:`monte_carlo_power` checks a size with the project's own
  pipeline (Friedman gate, Wilcoxon, Holm).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from mmctl.study.results import PAPER_MEDIANS, PAPER_PCORR
from mmctl.study.stats import ALPHA, friedman, holm, wilcoxon

#: the paper's participants
PAPER_N = 27
#: the paper's smallest p_corr: all 27 users ranked one way (3 x the normal tail at
#: z = 4.541), a floor, not a value
PAPER_FLOOR = 1.682e-5
#: Wilcoxon signed-rank vs paired t: asymptotic relative efficiency for normal data
ARE_WILCOXON = 3.0 / math.pi


class Margin(NamedTuple):
    """An equivalence margin in the metric's own unit, and why that size."""

    value: float
    unit: str
    why: str


#: Equivalence margins per metric: the largest difference that would not matter.
MARGINS: dict[str, Margin] = {
    "E": Margin(0.1, "J", "a tenth of a joule: 4 % of the paper's locomotion median "
                "(2.52 J), below the 0.09 J between its switch and min-energy medians"),
    "F_h": Margin(1.0, "N", "1 N: half the sensor chain's 2 N dead band; 6 % of the "
                  "paper's 15.84 N locomotion median"),
    "v": Margin(0.013, "m/s", "the speed 1 N buys through the paper's 75 N s/m "
                "damping: a difference the person cannot feel as force"),
    "x_f": Margin(0.05, "m", "5 cm: a quarter of the 0.19-0.20 m between the paper's "
                  "switch median and the other two"),
    "T_f": Margin(2.0, "s", "2 s: 6 % of a 30 s task, below the 4.6 s between the "
                  "paper's min-energy and switch medians"),
}


def undo_holm(p_corr: Mapping[tuple[str, str], float]) -> dict[tuple[str, str], float]:
    """The raw p-values behind one family's Holm-adjusted ones: the i-th smallest
    (1-based, ties in the given order) divided by ``m - i + 1``, at most 1.  Where
    the step-down's running maximum had raised a value, this overstates the raw p
    (a conservative effect)."""
    items = sorted(p_corr.items(), key=lambda kv: kv[1])
    m = len(items)
    return {pair: min(1.0, p / (m - i)) for i, (pair, p) in enumerate(items)}


def z_of(p_two_sided: float) -> float:
    """The |z| whose two-sided normal tail is ``p``."""
    from scipy import stats

    return float(stats.norm.isf(p_two_sided / 2.0))


def rank_biserial_of_z(z: float, n: int) -> float:
    """The matched-pairs rank-biserial correlation a Wilcoxon z means for n pairs with
    no ties or zeros: ``4 z sigma_T / (n (n + 1))``, at most 1."""
    sigma = math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
    return min(1.0, 4.0 * z * sigma / (n * (n + 1)))


class PaperEffect(NamedTuple):
    """The effect one of the paper's cells implies (see the module doc)."""

    metric: str
    a: str
    b: str
    p_corr: float
    p_raw: float
    z: float
    r: float  # z / sqrt(n)
    r_rb: float  # rank-biserial, signed with the paper's medians (a > b positive)
    floor: bool  # p_corr at the paper's floor: z, r are lower bounds


def paper_effects(n: int = PAPER_N) -> list[PaperEffect]:
    """Every cell of the paper's Table IV with the effect its p_corr implies."""
    out = []
    for metric, family in PAPER_PCORR.items():
        raw = undo_holm(family)
        for (a, b), p in family.items():
            z = z_of(raw[(a, b)])
            diff = PAPER_MEDIANS[a][metric] - PAPER_MEDIANS[b][metric]
            sign = 1.0 if diff > 0 else -1.0 if diff < 0 else 0.0
            out.append(PaperEffect(metric, a, b, p, raw[(a, b)], z, z / math.sqrt(n),
                                   sign * rank_biserial_of_z(z, n),
                                   math.isclose(p, PAPER_FLOOR, rel_tol=1e-3)))
    return out


def tost_wilcoxon(d: ArrayLike, margin: float) -> tuple[float, float, float]:
    """Two one-sided Wilcoxon signed-rank tests of the paired differences ``d`` against
    ``±margin``: (p of "median <= -margin" rejected, p of "median >= +margin"
    rejected, p_TOST = the larger).  Equivalence at alpha when p_TOST < alpha."""
    from scipy import stats

    from mmctl.study.stats import paired_differences

    x = np.asarray(d, dtype=float)
    zero = np.zeros_like(x)
    if margin <= 0.0 or not math.isfinite(margin):
        raise ValueError(f"margin must be > 0, got {margin}")
    if x.size == 0:
        return math.nan, math.nan, math.nan

    def one(v: np.ndarray, alternative: str) -> float:
        if np.all(v == 0.0):
            return 1.0
        return float(stats.wilcoxon(v, zero_method="wilcox", correction=False,
                                    alternative=alternative, method="approx").pvalue)

    # (rounded: a difference equal to the margin up to float noise is zero)
    p_lo = one(paired_differences(x + margin, zero), "greater")  # H0: median <= -margin
    p_hi = one(paired_differences(x - margin, zero), "less")  # H0: median >= +margin
    return p_lo, p_hi, max(p_lo, p_hi)


def power_paired_t(d_z: float, n: int, alpha: float) -> float:
    """Power of a two-sided paired t-test at ``alpha`` for standardised effect ``d_z``
    (mean difference / SD of the differences) with n pairs: the noncentral t."""
    from scipy import stats

    if n < 2:
        return 0.0
    df = n - 1
    t_crit = float(stats.t.isf(alpha / 2.0, df))
    nc = abs(d_z) * math.sqrt(n)
    return float(stats.nct.sf(t_crit, df, nc) + stats.nct.cdf(-t_crit, df, nc))


def n_paired_t(d_z: float, power: float = 0.8, alpha: float = ALPHA,
               n_max: int = 100_000) -> int:
    """The fewest pairs for ``power`` with a paired t-test (:func:`power_paired_t`);
    n_max + 1 when even n_max is not enough (an effect of ~0)."""
    if not abs(d_z) > 0.0:
        return n_max + 1
    # start at the normal approximation, then walk the exact power
    from scipy import stats

    za, zb = float(stats.norm.isf(alpha / 2.0)), float(stats.norm.isf(1.0 - power))
    n = max(2, math.floor(((za + zb) / abs(d_z)) ** 2))
    while n > 2 and power_paired_t(d_z, n - 1, alpha) >= power:
        n -= 1
    while power_paired_t(d_z, n, alpha) < power:
        n += 1
        if n > n_max:
            return n_max + 1
    return n


def n_wilcoxon(d_z: float, power: float = 0.8, alpha: float = ALPHA, pairs: int = 3
               ) -> int:
    """Participants for a Wilcoxon signed-rank claim at ``alpha`` with Holm over
    ``pairs`` (planned at alpha / pairs), via the paired t and the ARE 3/pi."""
    return math.ceil(n_paired_t(d_z, power, alpha / pairs) / ARE_WILCOXON)


def sd_implied(metric: str, a: str, b: str, z: float, n: int = PAPER_N) -> float:
    """The SD of the paired differences the paper's test implies: ``|paper median
    difference| sqrt(n) / z`` (NaN for a zero difference)."""
    diff = abs(PAPER_MEDIANS[a][metric] - PAPER_MEDIANS[b][metric])
    return diff * math.sqrt(n) / z if diff > 0.0 and z > 0.0 else math.nan


def monte_carlo_power(mean_diff: float, sd: float, n: int, pair: int = 0, reps: int = 400,
                      alpha: float = ALPHA, seed: int = 0) -> float:
    """The share of ``reps`` simulated studies of ``n`` users in which the project's
    pipeline (Friedman over three approaches, then Wilcoxon with Holm over the three
    pairs, gated by the Friedman test) finds pair ``pair`` significant: approach 0 is
    ``mean_diff`` above the other two, per-user differences normal with SD ``sd``
    (pair 0 = (0, 1); the third approach equal to the second)."""
    rng = np.random.default_rng(seed)
    hits = 0
    for _ in range(reps):
        base = rng.normal(0.0, 1.0, n)
        g0 = base + mean_diff + rng.normal(0.0, sd / math.sqrt(2.0), n)
        g1 = base + rng.normal(0.0, sd / math.sqrt(2.0), n)
        g2 = base + rng.normal(0.0, sd / math.sqrt(2.0), n)
        groups = (g0, g1, g2)
        if friedman(*groups).pvalue >= alpha:
            continue
        pairs = [(0, 1), (0, 2), (1, 2)]
        p = holm([wilcoxon(groups[i], groups[j]).pvalue for i, j in pairs])
        hits += int(p[pair] < alpha)
    return hits / reps


class SizeRow(NamedTuple):
    """One claim's sample size (see the module doc); NaN/None where not defined."""

    metric: str
    a: str
    b: str
    paper_claim: str  # "a > b", "a < b", "≈"
    d_z_paper: float
    n_paper: int | None
    sim_mean_diff: float
    sd: float
    d_z_sim: float
    n_sim: int | None


N_CAP = 10_000  # beyond this a claim is "not detectable" in a table


def size_table(sim: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
               power: float = 0.8, alpha: float = ALPHA) -> list[SizeRow]:
    """Per claim: the participants a real study needs, from the paper's implied effect
    and (``sim``: values[approach][metric], one per user) from the simulation's mean
    paired difference over the paper-implied SD."""
    rows = []
    for e in paper_effects():
        differ = e.p_corr < alpha
        diff = PAPER_MEDIANS[e.a][e.metric] - PAPER_MEDIANS[e.b][e.metric]
        claim = ("≈" if not differ else "a > b" if diff > 0 else "a < b")
        d_paper = e.z / math.sqrt(PAPER_N)
        n_paper = n_wilcoxon(d_paper, power, alpha)
        sd = sd_implied(e.metric, e.a, e.b, e.z)
        mean_d = d_sim = math.nan
        n_sim: int | None = None
        if sim is not None:
            da = np.asarray(sim[e.a][e.metric], dtype=float)
            db = np.asarray(sim[e.b][e.metric], dtype=float)
            mean_d = float(np.mean(da - db))
            if math.isfinite(sd) and sd > 0.0:
                d_sim = mean_d / sd
                n = n_wilcoxon(d_sim, power, alpha)
                n_sim = n if n <= N_CAP else None
        rows.append(SizeRow(e.metric, e.a, e.b, claim, d_paper,
                            n_paper if n_paper <= N_CAP else None, mean_d, sd, d_sim, n_sim))
    return rows


def read_values(path: str, completed_only: bool = True
                ) -> dict[str, dict[str, list[float]]]:
    """values[approach][metric] (one per user, in user order) from a study's
    results.csv; ``completed_only``: users with an unfinished execution in any approach
    are left out of every approach (the tests are paired)."""
    import csv

    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    unfinished = {r["user"] for r in rows if completed_only and r.get("completed") == "0"}
    out: dict[str, dict[str, list[float]]] = {}
    for r in sorted(rows, key=lambda r: int(r["user"])):
        if r["user"] in unfinished:
            continue
        per = out.setdefault(r["strategy"], {})
        for m in PAPER_MEDIANS["locomotion"]:
            per.setdefault(m, []).append(float(r[m]))
    return out


class ClaimRow(NamedTuple):
    """One of the paper's cells: the simulation's effect beside the paper's."""

    metric: str
    a: str
    b: str
    paper_claim: str
    paper_r_rb: float
    paper_floor: bool
    sim_r_rb: float
    sim_r_ci: tuple[float, float]
    sim_diff: float
    sim_diff_ci: tuple[float, float]
    sim_p_holm: float
    tost_p: float  # NaN for a claim of a difference
    margin: float


def claims_table(values: Mapping[str, Mapping[str, Sequence[float]]],
                 alpha: float = ALPHA) -> list[ClaimRow]:
    """Each of the paper's 15 cells: the simulation's matched-pairs effect (rank-biserial
    r) and median paired difference with their bootstrap intervals and Holm p, the
    effect the paper's p_corr implies, and for a "≈" claim the TOST p at its margin."""
    from mmctl.study.stats import pairwise_wilcoxon_holm

    effects = {(e.metric, e.a, e.b): e for e in paper_effects()}
    rows = []
    for i, metric in enumerate(PAPER_PCORR):
        groups = {a: np.asarray(values[a][metric], dtype=float) for a in
                  ("locomotion", "switch", "min-energy")}
        pairs = {(r.a, r.b): r for r in pairwise_wilcoxon_holm(groups, seed=1000 * i)}
        for (a, b), p_corr in PAPER_PCORR[metric].items():
            e = effects[(metric, a, b)]
            r = pairs[(a, b)]
            differ = p_corr < alpha
            diff = PAPER_MEDIANS[a][metric] - PAPER_MEDIANS[b][metric]
            claim = "≈" if not differ else ">" if diff > 0 else "<"
            margin = MARGINS[metric].value
            tost = (math.nan if differ else
                    tost_wilcoxon(groups[a] - groups[b], margin)[2])
            rows.append(ClaimRow(metric, a, b, claim, e.r_rb, e.floor, r.effect, r.effect_ci,
                                 r.diff_median, r.diff_ci, r.pvalue_corrected, tost, margin))
    return rows


def _fmt(x: float, nd: int = 2) -> str:
    return "—" if not math.isfinite(x) else f"{x:+.{nd}f}"


def claims_markdown(rows: Sequence[ClaimRow], alpha: float = ALPHA) -> str:
    """The claims table as markdown (docs/study.md, `mmctl study power --results`)."""
    from mmctl.study.results import APPROACH_NAMES, METRIC_LABELS

    lines = [("| claim | paper r_rb (from p_corr) | sim r_rb [95 % CI] | sim median a−b "
             "[95 % CI] | sim p (Holm) | TOST p (margin) | verdict |"),
             "|---|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        na, nb = APPROACH_NAMES.get(r.a, r.a), APPROACH_NAMES.get(r.b, r.b)
        label = METRIC_LABELS.get(r.metric, r.metric)
        paper = ("≥ " if r.paper_floor else "") + _fmt(r.paper_r_rb)
        sim_r = f"{_fmt(r.sim_r_rb)} [{_fmt(r.sim_r_ci[0])}, {_fmt(r.sim_r_ci[1])}]"
        nd = 3 if r.metric in ("E", "v", "x_f") else 2
        d = (f"{_fmt(r.sim_diff, nd)} [{_fmt(r.sim_diff_ci[0], nd)}, "
             f"{_fmt(r.sim_diff_ci[1], nd)}]")
        if r.paper_claim == "≈":
            tost = f"{r.tost_p:.3g} (±{r.margin:g})"
            verdict = ("equivalent" if r.tost_p < alpha else
                       "differs" if r.sim_p_holm < alpha else "inconclusive")
            if verdict == "equivalent" and r.sim_p_holm < alpha:
                verdict = "equivalent (differs, by less than the margin)"
        else:
            tost = "—"
            sign = 1 if r.paper_claim == ">" else -1
            same = r.sim_diff * sign > 0
            verdict = ("reproduced" if r.sim_p_holm < alpha and same else
                       "reversed" if r.sim_p_holm < alpha else "not significant")
        lines.append(f"| {label}: {na} {r.paper_claim} {nb} | {paper} | {sim_r} | {d} | "
                     f"{r.sim_p_holm:.3g} | {tost} | {verdict} |")
    return "\n".join(lines)


def size_markdown(rows: Sequence[SizeRow]) -> str:
    """The sample-size table as markdown."""
    from mmctl.study.results import APPROACH_NAMES, METRIC_LABELS

    lines = [("| claim | d_z (paper) | n (paper effect) | SD of a−b (implied) | sim mean a−b | "
             "d_z (sim) | n (sim effect) |"), "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        na, nb = APPROACH_NAMES.get(r.a, r.a), APPROACH_NAMES.get(r.b, r.b)
        label = METRIC_LABELS.get(r.metric, r.metric)
        claim = r.paper_claim.replace("a ", "").replace(" b", "")

        def n_txt(n: int | None, d: float) -> str:
            if not math.isfinite(d):
                return "—"
            return str(n) if n is not None else f"> {N_CAP}"

        lines.append(
            f"| {label}: {na} {claim} {nb} | {r.d_z_paper:.2f} | {n_txt(r.n_paper, r.d_z_paper)} | "
            f"{'—' if not math.isfinite(r.sd) else f'{r.sd:.3g}'} | "
            f"{'—' if not math.isfinite(r.sim_mean_diff) else f'{r.sim_mean_diff:+.3g}'} | "
            f"{'—' if not math.isfinite(r.d_z_sim) else f'{r.d_z_sim:+.2f}'} | "
            f"{n_txt(r.n_sim, r.d_z_sim)} |")
    return "\n".join(lines)
