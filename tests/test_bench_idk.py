"""`mmctl bench idk`: runs, prints figures, JSON has the documented shape (no timing asserts)."""

from __future__ import annotations

import json

import pytest

from mmctl.cli import main


def test_bench_idk_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "idk", "--json", "--cycles", "30"]) == 0
    out, err = capsys.readouterr()
    data = json.loads(out)
    strategies = data["strategies"]
    for name in ("min-energy", "locomotion", "manipulation", "constrained-min-energy",
                 "constrained-from-rest", "min-energy-full-inertia", "min-energy-no-avoidance"):
        assert strategies[name]["p50_us"] > 0.0
        assert strategies[name]["p99_us"] >= strategies[name]["p50_us"]
    assert data["paper_inv"]["p99_us"] >= data["paper_inv"]["p50_us"] > 0.0
    assert data["ratio_p50"] == pytest.approx(
        data["paper_inv"]["p50_us"] / strategies["min-energy"]["p50_us"], rel=0.02)
    assert data["step"]["p50_us"] > 0.0
    assert data["cycles"] == 30
    assert data["median_abs_diff_vs_paper"] < 1e-6  # same answer as the paper's formula
    assert 0.0 <= data["hand_over_share"] <= 1.0
    assert "bench idk: 30/30" in err  # progress goes to stderr


def test_bench_idk_table_and_bad_cycles(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "idk", "--cycles", "20", "--no-osqp"]) == 0
    out = capsys.readouterr().out
    assert "min-energy" in out and "paper_inv" in out and "step (whole cycle)" in out
    assert "min-energy-no-avoidance" in out and "hands a joint over in" in out
    assert main(["bench", "idk", "--cycles", "0"]) == 2
    assert "--cycles = 0: must be >= 1" in capsys.readouterr().err
