"""Statistics of the study against hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mmctl.study.stats import analyse, friedman, holm, pairwise_wilcoxon_holm, wilcoxon


def test_holm_by_hand() -> None:
    # sorted: 0.005*4 = 0.02, 0.01*3 = 0.03, 0.03*2 = 0.06, 0.04*1 = 0.04 -> max(0.06, 0.04)
    adj = holm([0.01, 0.04, 0.03, 0.005])
    np.testing.assert_allclose(adj, [0.03, 0.06, 0.06, 0.02])


def test_holm_caps_at_one_and_keeps_order() -> None:
    np.testing.assert_allclose(holm([0.5, 0.6]), [1.0, 1.0])
    np.testing.assert_allclose(holm([0.2]), [0.2])
    np.testing.assert_allclose(holm([0.001, 0.001, 0.001]), [0.003, 0.003, 0.003])


def test_holm_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        holm([0.1, 1.5])
    with pytest.raises(ValueError):
        holm([[0.1]])


def test_wilcoxon_exact_by_hand() -> None:
    # d = x - y = 1, -2, 3, 4, 5: W- = 2; rank sums <= 2: {}, {1}, {2} -> p = 2 * 3 / 32
    x = np.array([2.0, 1.0, 6.0, 8.0, 10.0])
    y = np.array([1.0, 3.0, 3.0, 4.0, 5.0])
    r = wilcoxon(x, y, method="exact")
    assert r.statistic == 2.0
    assert r.pvalue == pytest.approx(6.0 / 32.0)


def test_wilcoxon_normal_approximation_by_hand() -> None:
    x = np.array([2.0, 1.0, 6.0, 8.0, 10.0])
    y = np.array([1.0, 3.0, 3.0, 4.0, 5.0])
    n = 5
    mean, var = n * (n + 1) / 4, n * (n + 1) * (2 * n + 1) / 24
    z = (2.0 - mean) / math.sqrt(var)
    assert wilcoxon(x, y).pvalue == pytest.approx(math.erfc(abs(z) / math.sqrt(2.0)))


def test_identical_samples_give_p_one() -> None:
    a = np.arange(5.0)
    assert wilcoxon(a, a).pvalue == 1.0
    assert friedman(a, a, a).pvalue == 1.0


def test_friedman_by_hand() -> None:
    # ranks per user: (1,2,3), (1,2,3), (1,3,2): R = 3, 7, 8
    a, b, c = [1.0, 10.0, 0.1], [2.0, 20.0, 0.3], [3.0, 30.0, 0.2]
    chi2 = 12.0 / (3 * 3 * 4) * (3**2 + 7**2 + 8**2) - 3 * 3 * 4
    r = friedman(a, b, c)
    assert r.statistic == pytest.approx(chi2)
    assert r.pvalue == pytest.approx(math.exp(-chi2 / 2.0))  # chi-square, 2 dof


def test_paper_floor_for_unanimous_27_users() -> None:
    """27 users all ranking the same way: the paper's p_corr = 1.682e-5."""
    rng = np.random.default_rng(0)
    base = rng.uniform(1.0, 2.0, 27)
    step = np.linspace(0.1, 2.7, 27)  # distinct differences: no ties in |d|
    groups = {"locomotion": base + 3.0 * step, "switch": base + step, "min-energy": base}
    res = pairwise_wilcoxon_holm(groups)
    assert [(r.a, r.b) for r in res] == [
        ("locomotion", "switch"), ("locomotion", "min-energy"), ("switch", "min-energy")
    ]
    for r in res:
        assert f"{r.pvalue_corrected:.3e}" == "1.682e-05"
        assert r.significant()


def test_analyse_shapes() -> None:
    rng = np.random.default_rng(1)
    vals = {a: {"E": rng.normal(size=9), "T_f": rng.normal(size=9)} for a in ("x", "y", "z")}
    out = analyse(vals, ["E", "T_f"])
    assert [m.metric for m in out] == ["E", "T_f"]
    assert all(len(m.pairwise) == 3 for m in out)
    assert all(0.0 <= p.pvalue <= p.pvalue_corrected <= 1.0 for m in out for p in m.pairwise)


def test_rank_biserial_by_hand() -> None:
    from mmctl.study.stats import rank_biserial

    # d = 1, -2, 3, 4, 5: R+ = 1 + 3 + 4 + 5 = 13, R- = 2 -> (13 - 2) / 15
    assert float(rank_biserial([1.0, -2.0, 3.0, 4.0, 5.0])) == pytest.approx(11.0 / 15.0)
    assert float(rank_biserial([0.0, 1.0, 2.0])) == 1.0  # the zero is dropped
    assert float(rank_biserial([-1.0, -3.0])) == -1.0
    assert float(rank_biserial([0.0, 0.0])) == 0.0
    rows = rank_biserial(np.array([[1.0, -2.0, 3.0, 4.0, 5.0], [-1.0, -1.0, -1.0, 2.0, 0.0]]))
    # second row: |d| ranks of 1, 1, 1, 2 (zero dropped) = 2, 2, 2, 4: (4 - 6) / 10
    np.testing.assert_allclose(rows, [11.0 / 15.0, -0.2])


def test_pairs_carry_exact_p_effect_and_intervals() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(10.0, 1.0, 27)
    b = a - rng.normal(0.8, 1.0, 27)  # a > b for most users
    (r,) = pairwise_wilcoxon_holm({"a": a, "b": b})
    from scipy import stats

    assert r.pvalue_exact == pytest.approx(stats.wilcoxon(a, b, method="exact").pvalue)
    assert r.pvalue_exact_corrected == r.pvalue_exact  # a family of one
    assert 0.3 < r.effect <= 1.0 and r.effect_ci[0] < r.effect < r.effect_ci[1]
    assert r.diff_ci[0] < r.diff_median < r.diff_ci[1] and r.diff_ci[0] > 0.0
    again = pairwise_wilcoxon_holm({"a": a, "b": b})[0]
    assert again == r  # the bootstrap's seed is fixed: the same table every time
    # all 4 users a > b (a tie and a zero difference among them): 2 / 2^4 exactly,
    # where the normal approximation says 0.059
    tied = pairwise_wilcoxon_holm({"a": [1.0, 2.0, 3.0, 4.0, 5.0],
                                   "b": [1.0, 1.0, 2.0, 2.0, 2.0]})[0]
    assert tied.pvalue_exact == pytest.approx(0.125) and tied.pvalue < 0.07


def test_pairs_are_significant_only_after_a_significant_friedman_test() -> None:
    """Seed 1's F_h: the pairwise p_corr was 'Significant' while the Friedman test was
    not; gated, no pair is."""
    (r,) = pairwise_wilcoxon_holm({"a": np.arange(27.0), "b": np.arange(27.0) - 1.0},
                                  gated=False)
    assert r.pvalue_corrected < 0.05 and not r.significant()
    rng = np.random.default_rng(0)
    values = {s: {"x": rng.normal(0.0, 1.0, 27)} for s in ("p", "q", "r")}
    values["r"]["x"] = values["p"]["x"] + 0.35 + rng.normal(0.0, 0.3, 27)
    (ma,) = analyse(values, ["x"])
    assert ma.gated() == (ma.friedman.pvalue < 0.05)
    assert all(p.gated == ma.gated() for p in ma.pairwise)
    assert all(p.significant() == (ma.gated() and p.pvalue_corrected < 0.05)
               for p in ma.pairwise)
    assert ma.medians is not None
    for name, (med, lo, hi) in ma.medians.items():
        assert lo <= med <= hi and med == pytest.approx(float(np.median(values[name]["x"])))
