"""The study's planning statistics (issue 32): Holm undone, TOST, the sample size
against textbook values and Monte Carlo, the table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from mmctl.study import power as pw
from mmctl.study.results import PAPER_PCORR
from mmctl.study.stats import holm


def test_undo_holm_inverts_holm_where_no_running_maximum_raised_a_value() -> None:
    raw = {("a", "b"): 0.001, ("a", "c"): 0.02, ("b", "c"): 0.3}
    adjusted = dict(zip(raw, holm(list(raw.values())), strict=True))
    back = pw.undo_holm(adjusted)
    for pair, p in raw.items():
        assert back[pair] == pytest.approx(p, rel=1e-12)


def test_the_paper_floor_is_flagged_and_means_z_of_4_54() -> None:
    effects = {(e.metric, e.a, e.b): e for e in pw.paper_effects()}
    floor = effects[("E", "locomotion", "switch")]
    assert floor.floor and floor.z == pytest.approx(4.541, abs=0.01)
    # the largest p of a family is its raw p: E switch vs min-energy, p_corr 0.337
    e = effects[("E", "switch", "min-energy")]
    assert not e.floor and e.p_raw == pytest.approx(0.337)
    assert e.r == pytest.approx(stats.norm.isf(0.337 / 2) / math.sqrt(27))
    assert len(effects) == sum(len(f) for f in PAPER_PCORR.values()) == 15


def test_rank_biserial_of_z_matches_the_statistic_of_untied_ranks() -> None:
    """n = 10 untied differences, 8 positive: r_rb from the ranks equals the one from
    the normal approximation's z."""
    from mmctl.study.stats import rank_biserial

    d = np.array([1, 2, 3, 4, 5, 6, 7, 8, -9, -10], dtype=float) * 0.1
    t_plus = sum(range(1, 9))
    n = 10
    z = (t_plus - n * (n + 1) / 4) / math.sqrt(n * (n + 1) * (2 * n + 1) / 24)
    assert pw.rank_biserial_of_z(z, n) == pytest.approx(float(rank_biserial(d)), abs=1e-12)


@pytest.mark.parametrize(("d_z", "n"), [(0.5, 34), (0.8, 15), (0.3, 90)])
def test_paired_t_sample_size_matches_gpower(d_z: float, n: int) -> None:
    """G*Power 3 (matched pairs, two-tailed, alpha 0.05, power 0.8): d_z 0.5 -> 34,
    0.8 -> 15, 0.3 -> 90."""
    assert pw.n_paired_t(d_z, 0.8, 0.05) == n


def test_the_power_formula_agrees_with_a_monte_carlo_of_the_t_test() -> None:
    rng = np.random.default_rng(1)
    n, d_z, reps = 20, 0.6, 4000
    x = rng.normal(d_z, 1.0, size=(reps, n))
    p = stats.ttest_1samp(x, 0.0, axis=1).pvalue
    assert float(np.mean(p < 0.05)) == pytest.approx(pw.power_paired_t(d_z, n, 0.05), abs=0.025)


def test_the_wilcoxon_size_with_holm_reaches_80_percent_in_the_projects_pipeline() -> None:
    """The planned n for d_z = 0.8, Holm over three pairs, run through the project's own
    Friedman + Wilcoxon + Holm: power about 0.8 (>= 0.72 with 400 runs' noise)."""
    n = pw.n_wilcoxon(0.8)
    assert n == math.ceil(pw.n_paired_t(0.8, 0.8, 0.05 / 3) / (3 / math.pi))
    power = pw.monte_carlo_power(0.8, 1.0, n, reps=400, seed=3)
    assert power >= 0.72, (n, power)
    assert pw.monte_carlo_power(0.8, 1.0, max(3, n // 3), reps=200, seed=4) < power


def test_tost_finds_equivalence_inside_the_margin_and_not_at_it() -> None:
    rng = np.random.default_rng(2)
    inside = rng.normal(0.0, 0.2, 40)
    assert pw.tost_wilcoxon(inside, 0.5)[2] < 0.05
    at_margin = rng.normal(0.5, 0.2, 40)
    assert pw.tost_wilcoxon(at_margin, 0.5)[2] > 0.05
    with pytest.raises(ValueError, match="margin"):
        pw.tost_wilcoxon(inside, 0.0)


def test_tost_holds_its_level_at_the_margin() -> None:
    """A true median on the margin: equivalence claimed in at most ~alpha of samples."""
    rng = np.random.default_rng(5)
    reps = 600
    hits = sum(pw.tost_wilcoxon(rng.normal(0.3, 1.0, 30), 0.3)[2] < 0.05 for _ in range(reps))
    assert hits / reps <= 0.05 + 0.025, hits / reps


def test_the_size_table_covers_every_claim_and_uses_the_simulation() -> None:
    rng = np.random.default_rng(0)
    sim = {a: {m: rng.normal(1.0, 0.1, 27) + (0.5 if a == "locomotion" else 0.0)
               for m in ("E", "F_h", "v", "x_f", "T_f")}
           for a in ("locomotion", "switch", "min-energy")}
    rows = pw.size_table(sim)
    assert len(rows) == 15
    by = {(r.metric, r.a, r.b): r for r in rows}
    e = by[("E", "locomotion", "switch")]
    assert e.paper_claim == "a > b" and e.n_paper is not None and e.n_paper <= 27
    assert e.sim_mean_diff == pytest.approx(float(np.mean(sim["locomotion"]["E"]
                                                          - sim["switch"]["E"])))
    assert by[("E", "switch", "min-energy")].paper_claim == "≈"
    assert set(pw.MARGINS) == {"E", "F_h", "v", "x_f", "T_f"}


def test_the_exact_signed_rank_p_equals_scipys_without_ties() -> None:
    from mmctl.study.stats import signed_rank_exact

    rng = np.random.default_rng(7)
    for n in (5, 9, 16):
        d = rng.normal(0.3, 1.0, n)
        want = stats.wilcoxon(d, method="exact").pvalue
        assert signed_rank_exact(d, np.zeros(n)) == pytest.approx(want, rel=1e-9)


def test_the_exact_signed_rank_p_with_ties_and_zeros_equals_all_sign_patterns() -> None:
    """T_f quantised to 2 ms ties; the permutation distribution of the mid-ranks,
    enumerated by brute force over all 2^n sign patterns, is the reference."""
    from itertools import product

    from mmctl.study.stats import signed_rank_exact

    d = np.array([0.002, 0.002, -0.004, 0.006, 0.0, 0.006, 0.008, -0.002, 0.010, 0.004])
    nz = d[d != 0.0]
    ranks = stats.rankdata(np.abs(nz))
    t = ranks[nz > 0].sum()
    mid = ranks.sum() / 2
    hits = sum(abs(sum(r for r, s in zip(ranks, signs, strict=True) if s) - mid)
               >= abs(t - mid) - 1e-9 for signs in product((0, 1), repeat=nz.size))
    assert signed_rank_exact(d, np.zeros_like(d)) == pytest.approx(hits / 2 ** nz.size)
    assert signed_rank_exact(np.ones(4), np.ones(4)) == 1.0


def test_no_bootstrap_interval_below_ten_users() -> None:
    from mmctl.study.stats import MIN_BOOTSTRAP_N, median_ci, pairwise_wilcoxon_holm

    small = pairwise_wilcoxon_holm({"a": [3.0, 4.0, 5.0], "b": [1.0, 1.5, 2.0]})[0]
    assert math.isnan(small.effect_ci[0]) and math.isnan(small.diff_ci[1])
    assert small.effect == 1.0 and small.diff_median == 2.5
    assert math.isnan(median_ci([1.0, 2.0, 3.0])[1]) and median_ci([1.0, 2.0, 3.0])[0] == 2.0
    n = MIN_BOOTSTRAP_N
    big = pairwise_wilcoxon_holm({"a": np.arange(n) + 1.0, "b": np.zeros(n)})[0]
    assert all(math.isfinite(x) for x in (*big.effect_ci, *big.diff_ci))


def test_differences_equal_up_to_float_noise_are_ties() -> None:
    """T_f is a multiple of the 2 ms period: a - b of such values must tie exactly."""
    from mmctl.study.stats import paired_differences, signed_rank_exact, wilcoxon

    a = np.array([29.034, 30.1, 28.002, 31.5]) + np.array([0.0, 1e-14, -2e-14, 0.0])
    b = np.array([28.9, 29.966, 27.868, 31.366])
    d = paired_differences(a, b)
    assert np.unique(d).size == 1  # all 0.134
    # all four positive and tied: the same p as four equal differences
    assert wilcoxon(a, b).pvalue == wilcoxon(np.full(4, 0.134), np.zeros(4)).pvalue
    assert signed_rank_exact(a, b) == pytest.approx(2 / 16)


def test_mmctl_study_power_reads_a_results_csv_and_writes_its_tables(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import csv
    import json

    from mmctl.cli import main
    from mmctl.study.results import CSV_COLUMNS

    rng = np.random.default_rng(4)
    path = tmp_path / "results.csv"
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for u in range(12):
            for s, shift in (("locomotion", 1.0), ("switch", 0.0), ("min-energy", 0.02)):
                vals = {c: "0" for c in CSV_COLUMNS}
                vals.update(user=str(u), strategy=s, completed="1", stopped="")
                for m in ("E", "F_h", "v", "x_f", "T_f"):
                    vals[m] = repr(10.0 + shift + rng.normal(0.0, 0.01))
                w.writerow([vals[c] for c in CSV_COLUMNS])
    out = tmp_path / "p"
    assert main(["study", "power", "--results", str(path), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "## Participants for 80% power" in text and "beside the simulation (12 users)" in text
    doc = json.loads((out / "power.json").read_text())
    assert len(doc["sizes"]) == len(doc["claims"]) == 15
    e = next(c for c in doc["claims"] if (c["metric"], c["a"], c["b"])
             == ("E", "locomotion", "switch"))
    assert e["sim_r_rb"] == 1.0 and e["sim_diff"] == pytest.approx(1.0, abs=0.05)
    # a claim of no difference gets its TOST p; switch vs min-energy differ by 0.02 < 0.1
    s = next(c for c in doc["claims"] if (c["metric"], c["a"], c["b"])
             == ("E", "switch", "min-energy"))
    assert s["tost_p"] < 0.05
    assert main(["study", "power", "--results", str(tmp_path / "none.csv")]) == 2
