"""Tables, files and figures of the study from synthetic executions (no simulation)."""

from __future__ import annotations

import json

import numpy as np

from mmctl.study.plots import write_figures
from mmctl.study.report import (
    median_table,
    median_user,
    medians,
    results_csv,
    significance_table,
    write_outputs,
)
from mmctl.study.results import Execution, Series

STRATS = ("locomotion", "switch", "min-energy")


def _series(n: int = 50) -> Series:
    t = np.arange(n, dtype=np.float32) * 0.01
    z = np.zeros(n, dtype=np.float32)
    loc = (np.arange(n) % 20 < 10).astype(np.int8)
    return Series(t, z + 0.1, z + 1.0, z + 0.5, z + 10.0, z + 0.05, loc)


def _execs(n_users: int = 7) -> list[Execution]:
    rng = np.random.default_rng(5)
    out = []
    for u in range(n_users):
        for k, s in enumerate(STRATS):
            e, f, v, x, t = rng.uniform(0.5, 3.0), rng.uniform(8, 16), 0.15, 0.1 * (k + 1), 30.0 + u
            out.append(Execution(u, s, e + (2.0 if s == "locomotion" else 0.0), f, v, x, t,
                                 e / 2, 2 * f, 2, True, 0, _series()))
    return out


def test_median_table_sits_next_to_the_paper() -> None:
    ex = _execs()
    tab = median_table(ex)
    lines = tab.splitlines()
    assert lines[0].startswith("| approach | Ē [J] sim | paper |")
    assert lines[2].startswith("| locomotion |") and "| 2.52 |" in lines[2]
    assert "| 0.28 |" in lines[3] and "| 28.33 |" in lines[4]
    med = medians(ex)
    assert med["switch"]["x_f"] == 0.2
    assert abs(med["min-energy"]["x_f"] - 0.3) < 1e-12
    assert med["locomotion"]["T_f"] == 33.0  # users 0..6 -> 30..36


def test_significance_table_format() -> None:
    ex = _execs()
    from mmctl.study.report import values
    from mmctl.study.stats import analyse

    tab = significance_table(analyse(values(ex), ("E", "x_f")), 7)
    table, note = tab.split("\n\n")
    lines = table.splitlines()
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    assert head == ["Metric", "Comparison", "p_holm", "Significance", "paper p_corr",
                    "r [95 % CI]", "median a − b [95 % CI]"]
    # one p column of ours, the deciding one; the other is the paper's, named so
    assert [c for c in head if c.startswith("p")] == ["p_holm", "paper p_corr"]
    assert len(lines) == 2 + 6
    assert "Locomotion vs Minimum Energy" in lines[3] and "| 1.682e-5 |" in lines[3]
    # x_f: every user agrees; 7 users decide by the exact p, 3 x 2/2^7 = 0.0469 < 0.05
    for ln in lines[5:]:
        assert "| 0.0469 | Significant |" in ln
    assert note.startswith("n = 7 users. p_holm: two-sided Wilcoxon signed-rank p, "
                           "Holm-Bonferroni corrected over the metric's 3 pairs, computed from the exact "
                           "distribution (7 users; exact up to 20 users")
    assert "It alone decides" in note and "With 7 users no p_holm can be below 0.0469 (exact)" \
        in note


def test_the_deciding_p_is_exact_for_few_users_normal_for_many() -> None:
    from mmctl.study.report import (
        EXACT_MAX_USERS,
        decides,
        p_holm,
        p_method,
        smallest_p_holm,
        summary,
        values,
    )
    from mmctl.study.stats import analyse

    assert smallest_p_holm(3, 3, "exact") == 0.75
    assert f"{smallest_p_holm(3, 3, 'normal'):.3f}" == "0.326"
    assert f"{smallest_p_holm(27, 3, 'normal'):.3e}" == "1.682e-05"  # the paper's floor
    for n, method in ((7, "exact"), (EXACT_MAX_USERS, "exact"), (27, "normal")):
        ex = _execs(n)
        (ma,) = analyse(values(ex), ("x_f",))
        assert p_method(ma, n) == method
        doc = summary(ex, [ma], {})
        for r in ma.pairwise:
            pair = doc["pairwise"]["x_f"][f"{r.a} vs {r.b}"]
            want = r.pvalue_exact_corrected if method == "exact" else r.pvalue_corrected
            assert pair["p_holm"] == want == p_holm(r, method)
            assert pair["p_holm_method"] == method
            assert pair["significant"] == decides(r, method) == (want < 0.05)
            assert pair["p_corr"] == r.pvalue_corrected  # both kept in summary.json
            assert pair["p_exact_corr"] == r.pvalue_exact_corrected
    # 7 users who all rank the approaches alike, no ties: the exact p (3 x 2/2^7 = 0.047)
    # is significant, the normal approximation's (3 x 0.018 = 0.054) would not be
    u = np.arange(7.0)
    x = {"locomotion": {"x_f": 0.01 * u}, "switch": {"x_f": 0.01 * u + 0.1 + 0.001 * u},
         "min-energy": {"x_f": 0.01 * u + 0.2 + 0.003 * u}}
    (ma,) = analyse(x, ("x_f",))
    assert p_method(ma, 7) == "exact"
    assert all(decides(r, "exact") and not r.significant() for r in ma.pairwise)
    assert [f"{r.pvalue_corrected:.3f}" for r in ma.pairwise] == ["0.054"] * 3
    tab = significance_table([ma], 27)
    assert "from the normal approximation without continuity correction" in tab


def test_median_user_is_the_one_most_often_at_the_median() -> None:
    ex = _execs()
    # make user 4 the median of everything
    ex = [e._replace(E=1.0, F_h=1.0, v=1.0, x_f=1.0, T_f=1.0) if e.user != 4 else e for e in ex]
    ex = [e._replace(E=3.0, F_h=3.0, v=3.0, x_f=3.0, T_f=3.0) if e.user in (0, 1, 2) else e
          for e in ex]
    ex = [e._replace(E=2.0, F_h=2.0, v=2.0, x_f=2.0, T_f=2.0) if e.user == 4 else e for e in ex]
    assert median_user(ex) == 4


def test_csv_is_sorted_and_stable() -> None:
    ex = _execs(3)
    shuffled = [ex[i] for i in (4, 0, 8, 2, 7, 1, 3, 6, 5)]
    text = results_csv(ex)
    assert text.splitlines()[0] == ("user,strategy,E,F_h,v,x_f,T_f,x_f_hold,E_base,F_max,"
                                    "switches,completed,faults,stopped,limited,F_applied,"
                                    "wall_clearance,E_base_near")
    rows = [ln.split(",")[:2] for ln in text.splitlines()[1:]]
    assert rows[:3] == [["0", "locomotion"], ["0", "switch"], ["0", "min-energy"]]
    assert results_csv(sorted(shuffled, key=lambda e: (e.user, STRATS.index(e.strategy)))) == text


def test_write_outputs_and_figures(tmp_path) -> None:  # type: ignore[no-untyped-def]
    ex = _execs()
    _, doc = write_outputs(tmp_path, ex, {"seed": 1})
    back = json.loads((tmp_path / "summary.json").read_text())
    assert back["seed"] == 1 and back["medians"] == doc["medians"]
    assert back["pairwise"]["E"]["locomotion vs switch"]["p_corr"] >= back["pairwise"]["E"][
        "locomotion vs switch"]["p"]
    paths = write_figures(ex, doc["median_user"], tmp_path)
    for p in paths:
        assert p.read_bytes()[:4] == b"\x89PNG"


def test_unfinished_executions_are_counted_and_left_out_of_the_tests(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from mmctl.study.report import excluded_users, tested, unfinished

    ex = _execs(12)
    ex = [e._replace(limited=0.01 * (e.user + 1)) for e in ex]
    # user 3 ran out of time with switch: T_f is the limit, far above everyone else
    ex = [e._replace(completed=False, T_f=600.0) if (e.user, e.strategy) == (3, "switch")
          else e for e in ex]
    assert unfinished(ex) == {"locomotion": 0, "switch": 1, "min-energy": 0}
    assert excluded_users(ex) == [3]
    assert {e.user for e in tested(ex)} == set(range(12)) - {3}
    assert len(tested(ex)) == 33  # the user leaves every approach, not only switch
    analysis, doc = write_outputs(tmp_path, ex, {})
    assert doc["tested_users"] == 11 and doc["excluded_users"] == [3]
    assert doc["unfinished"] == {"locomotion": 0, "switch": 1, "min-energy": 0}
    assert doc["incomplete"] == ["user 3 switch"]
    # the limit share's median [%]: users 0..11 -> 1..12 %, median 6.5 %
    assert all(abs(v - 6.5) < 1e-9 for v in doc["limited_median_percent"].values())
    # the tests ran on 11 users: the Wilcoxon statistic of a pair where every user
    # ranks alike is the rank sum 11 * 12 / 2 = 66 (with 12 users it would be 78)
    (xf,) = [ma for ma in analysis if ma.metric == "x_f"]
    assert {max(r.statistic, 66 - r.statistic) for r in xf.pairwise} == {66.0}
    # bootstrap medians over the tested users: the unfinished T_f is not among them
    assert all(hi < 600.0 for _m, _lo, hi in (xf.medians or {}).values())
    tab = significance_table(analysis, doc["tested_users"], excluded=len(doc["excluded_users"]))
    assert "n = 11 users (1 unfinished excluded)." in tab.split("\n\n")[1]
    med = median_table(ex)
    head = [c.strip() for c in med.splitlines()[0].strip("|").split("|")]
    assert head[-2:] == ["limit binds [%]", "unfinished"]
    rows = {ln.split("|")[1].strip(): ln for ln in med.splitlines()[2:5]}
    assert rows["switch"].rstrip().endswith("| 6.5 | 1 of 12 |")
    assert rows["locomotion"].rstrip().endswith("| 6.5 | 0 of 12 |")
    assert "user 3 switch" in med.splitlines()[-1]
    # without unfinished executions the note says n alone
    clean = significance_table(analyse_all(_execs(12)), 12)
    assert "n = 12 users." in clean and "excluded" not in clean


def analyse_all(ex: list[Execution]) -> list:  # type: ignore[type-arg]
    from mmctl.study.report import metrics_of, values
    from mmctl.study.stats import analyse

    return analyse(values(ex), metrics_of(ex))
