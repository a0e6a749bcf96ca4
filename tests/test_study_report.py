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

    tab = significance_table(analyse(values(ex), ("E", "x_f")))
    lines = tab.splitlines()
    assert lines[0].startswith("| Metric | Comparison | p_corr | Significance | paper p_corr "
                               "| p_corr exact | r [95 % CI] |")
    assert len(lines) == 2 + 6
    assert "Locomotion vs Minimum Energy" in lines[3] and "1.682e-5" in lines[3]
    # x_f is constant per approach with a monotone shift: every user agrees
    assert all("| Significant |" in ln for ln in lines[5:])


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
                                    "switches,completed,faults,stopped")
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
