"""`mmctl study --quick` end to end through the real control step(), and determinism."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.errors import ConfigError
from mmctl.model import RobotModel
from mmctl.sim.human import HandleObservation, HumanAction, SimulatedHuman
from mmctl.study.config import StudyConfig
from mmctl.study.report import results_csv
from mmctl.study.runner import run_execution, run_study, start_configuration, study_task
from mmctl.study.users import draw_user

USERS = 2


@pytest.fixture(scope="module")
def quick_cli(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("study")
    rc = main(["study", "--quick", "--users", str(USERS), "--seed", "7", "--jobs", "2",
               "--out", str(out)])
    assert rc == 0
    return out


def test_quick_study_writes_every_output(quick_cli: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("results.csv", "summary.json", "boxplots.png", "velocity.png", "energy.png"):
        f = quick_cli / name
        assert f.is_file() and f.stat().st_size > 0, name
    for name in ("boxplots.png", "velocity.png", "energy.png"):
        assert (quick_cli / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader((quick_cli / "results.csv").open()))
    assert len(rows) == USERS * 3
    assert [r["strategy"] for r in rows[:3]] == ["locomotion", "switch", "min-energy"]
    for r in rows:
        assert r["completed"] == "1" and r["faults"] == "0"
        assert 0.0 < float(r["E"]) < 20.0
        assert 2.0 < float(r["F_h"]) < 40.0
        assert 0.03 < float(r["v"]) < 0.5
        assert 0.0 <= float(r["x_f"]) < 1.5
        assert 3.0 < float(r["T_f"]) < 60.0
        # the human asks to switch whatever the approach (one far hole)
        assert int(r["switches"]) >= 1
    doc = json.loads((quick_cli / "summary.json").read_text())
    assert set(doc["medians"]) == {"locomotion", "switch", "min-energy"}
    for med in doc["medians"].values():
        assert set(med) == {"E", "F_h", "v", "x_f", "T_f"}
    assert set(doc["friedman"]) == {"E", "F_h", "v", "x_f", "T_f"}
    pairs = {"locomotion vs switch", "locomotion vs min-energy", "switch vs min-energy"}
    for metric in ("E", "F_h", "v", "x_f", "T_f"):
        assert set(doc["pairwise"][metric]) == pairs
        for r in doc["pairwise"][metric].values():
            assert 0.0 <= r["p"] <= r["p_corr"] <= 1.0
    assert doc["median_user"] in range(USERS)


def test_base_moves_least_with_min_energy(quick_cli: Path) -> None:
    rows = list(csv.DictReader((quick_cli / "results.csv").open()))
    by = {(int(r["user"]), r["strategy"]): r for r in rows}
    for u in range(USERS):
        assert float(by[u, "min-energy"]["E_base"]) < float(by[u, "locomotion"]["E_base"])
        assert float(by[u, "min-energy"]["E"]) < float(by[u, "locomotion"]["E"])


def test_same_seed_same_results_whatever_the_jobs(quick_cli: Path) -> None:
    study = StudyConfig.make(quick=True, users=USERS, seed=7)
    res = run_study(study, jobs=1)
    assert results_csv(res.executions) == (quick_cli / "results.csv").read_text()


def test_human_sees_no_mode_in_a_closed_loop_run() -> None:
    """Closed-loop runs under two approaches: replaying each run's observations into a
    fresh human reproduces every action exactly, so nothing but the observations
    reaches the human; the same human faces both approaches."""
    study = StudyConfig.make(quick=True, users=1, seed=3, t_max=3.0)
    logs = {}
    for strategy in ("locomotion", "min-energy"):
        log: list[tuple[HandleObservation, HumanAction]] = []
        ex, _, _ = run_execution(study, 0, strategy, observe=lambda o, a, log=log: log.append((o, a)))
        assert not ex.completed and ex.T_f == pytest.approx(3.0, abs=0.01)  # t_max reached
        logs[strategy] = log
    cfg = study.control_config("min-energy")
    task = study_task(RobotModel(cfg.robot), start_configuration(cfg), study.holes)
    for log in logs.values():
        fresh = SimulatedHuman(draw_user(3, 0), task)
        for obs, act in log:
            again = fresh.update(obs)
            np.testing.assert_array_equal(again.force, act.force)
            assert (again.switch_request, again.phase) == (act.switch_request, act.phase)
    # the approaches did differ (so the check is not vacuous)
    a, b = (np.array([o.base for o, _ in logs[s]]) for s in ("locomotion", "min-energy"))
    assert np.abs(a - b).max() > 1e-3


def test_bad_arguments() -> None:
    with pytest.raises(ConfigError, match="strategies"):
        StudyConfig(strategies=("nonsense",))
    with pytest.raises(ConfigError):
        StudyConfig(users=0)
    assert main(["study", "--jobs", "0"]) == 2
