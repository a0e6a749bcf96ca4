"""The paper's claims, and their tally over replicated populations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mmctl.study.replication import holds, paper_claims, tally, tally_table
from mmctl.study.stats import analyse


def test_the_claims_are_the_papers_table() -> None:
    claims = {(c.metric, c.a, c.b): c for c in paper_claims()}
    assert len(claims) == 15
    e = claims[("E", "locomotion", "min-energy")]
    assert e.differ and e.direction == 1  # 2.52 J vs 0.86 J, p_corr 1.682e-5
    assert e.text() == "Ē [J]: Locomotion > Minimum Energy"
    same = claims[("E", "switch", "min-energy")]
    assert not same.differ and same.direction == 0  # p_corr 0.337
    x = claims[("x_f", "switch", "min-energy")]
    assert x.differ and x.direction == 1  # 0.28 m vs 0.08 m


def _analysis(shift: float, seed: int) -> list:  # type: ignore[type-arg]
    """E: locomotion higher than the two others by ``shift``, 27 users."""
    rng = np.random.default_rng(seed)
    base = rng.normal(1.0, 0.2, 27)
    values = {"locomotion": {"E": base + shift + rng.normal(0, 0.05, 27)},
              "switch": {"E": base + rng.normal(0, 0.05, 27)},
              "min-energy": {"E": base + rng.normal(0, 0.05, 27)}}
    return analyse(values, ["E"])


def test_a_claim_holds_where_the_population_agrees_with_the_paper() -> None:
    claims = {(c.metric, c.a, c.b): c for c in paper_claims()}
    agree, reverse, none = _analysis(1.0, 0), _analysis(-1.0, 0), _analysis(0.0, 0)
    loco_me = claims[("E", "locomotion", "min-energy")]
    assert holds(loco_me, agree) is True
    assert holds(loco_me, reverse) is False  # significant, the other way
    assert holds(loco_me, none) is False  # no difference found
    sw_me = claims[("E", "switch", "min-energy")]
    assert holds(sw_me, agree) is True  # neither differs: as the paper
    assert holds(claims[("x_f", "switch", "min-energy")], agree) is None  # no x_f here
    rows = tally({0: agree, 1: reverse, 2: agree})
    row = next(r for r in rows if r["claim"] == loco_me.text())
    assert row["holds"] == [0, 2] and row["fails"] == [1]
    table = tally_table(rows, 3)
    assert f"| {loco_me.text()} | 1.682e-05 | 2/3 | 1 |" in table


@pytest.mark.timeout(900)
def test_seeds_replicate_the_study_and_tally_the_claims(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from mmctl.cli import main

    rc = main(["study", "--quick", "--users", "3", "--seeds", "2", "--seed", "4",
               "--jobs", "1", "--no-figures", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads((tmp_path / "replication.json").read_text())
    assert doc["seeds"] == [4, 5] and len(doc["claims"]) == 15
    for row in doc["claims"]:
        assert sorted(row["holds"] + row["fails"]) == [4, 5]
    for seed in (4, 5):
        assert (tmp_path / f"seed-{seed}" / "results.csv").is_file()
    out = capsys.readouterr().out
    assert "| paper's claim | paper p_corr | holds in | fails for seeds |" in out


def test_the_tally_decides_each_seed_by_the_users_its_tests_ran_on() -> None:
    """A seed whose unfinished executions leave 12 users tested decides by the exact p
    (up to 20 users), one with 21 by the normal approximation: the same pair of
    samples (exact p_holm 0.048, normal 0.056) holds in the first and fails in the
    second, whatever the study's own user count."""
    rng = np.random.default_rng(4)
    n = 12
    base = rng.normal(1.0, 0.2, n)
    noise = [rng.normal(0.0, 0.05, n) for _ in range(3)]
    values = {"locomotion": {"E": base + 0.052 + noise[0]}, "switch": {"E": base + noise[1]},
              "min-energy": {"E": base + noise[2]}}
    a = analyse(values, ["E"])
    pair = next(r for r in a[0].pairwise if {r.a, r.b} == {"locomotion", "min-energy"})
    assert pair.pvalue_exact_corrected < 0.05 <= pair.pvalue_corrected
    claim = next(c for c in paper_claims() if (c.metric, c.a, c.b) == (
        "E", "locomotion", "min-energy"))

    def row(users: object) -> dict:  # type: ignore[type-arg]
        return next(r for r in tally({0: a, 1: a}, users=users)  # type: ignore[arg-type]
                    if r["claim"] == claim.text())

    per_seed = row({0: 12, 1: 21})
    assert per_seed["holds"] == [0] and per_seed["fails"] == [1]
    assert row(12)["holds"] == [0, 1]
    assert row(27)["fails"] == [0, 1]
