"""The inertia-weighting sweep (`mmctl study sweep`) and the study's figures: the
weighted solver, the sweep's identity with the plain study at the paper's setting, the
command end to end, and the boxplots' significance marks against summary.json."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.config import default_config
from mmctl.control.idk import null_project
from mmctl.control.limits import Limits
from mmctl.control.strategies import MinEnergy, Problem
from mmctl.errors import ConfigError
from mmctl.model import RobotModel
from mmctl.study.config import StudyConfig
from mmctl.study.executor import LocalProcesses
from mmctl.study.plots import boxplots, sensitivity_chart, significance_marks
from mmctl.study.report import write_outputs
from mmctl.study.results import Execution, Series, csv_row
from mmctl.study.runner import run_study
from mmctl.study.sweep import (
    DEFAULT_SCALES,
    Setting,
    WeightedMinEnergy,
    run_sweep,
    settings,
    sweep_csv,
)

PNG = b"\x89PNG\r\n\x1a\n"


def _problems(n: int = 5, full: bool = False) -> list[tuple[object, Problem]]:
    cfg = default_config()
    if full:
        from dataclasses import replace

        cfg = replace(cfg, robot=replace(cfg.robot, full_inertia=True))
    model = RobotModel(cfg.robot)
    rng = np.random.default_rng(3)
    q_des = np.concatenate((np.asarray(cfg.robot.q_des), np.zeros(3)))
    out = []
    for _ in range(n):
        q = q_des + np.concatenate((rng.uniform(-0.3, 0.3, 6), rng.uniform(-1, 1, 3)))
        kin = model.update(q)
        v_d = rng.uniform(-0.2, 0.2, 6)
        z = np.concatenate((rng.uniform(-0.3, 0.3, 6), np.zeros(3)))
        out.append((cfg, Problem(kin, v_d, q, np.zeros(9), 0.002, z)))
    return out


def _limits(cfg: object) -> Limits:
    from mmctl.control.step import Controller

    return Controller(cfg).limits  # type: ignore[arg-type]


def test_scale_one_dynamic_is_the_papers_solver_bit_for_bit() -> None:
    for cfg, p in _problems():
        lim = _limits(cfg)
        a = MinEnergy(cfg, lim).solve(p)  # type: ignore[arg-type]
        b = WeightedMinEnergy(cfg, lim, Setting(1.0, "dynamic")).solve(p)  # type: ignore[arg-type]
        assert np.array_equal(a, b)


def test_the_base_weight_moves_motion_between_arm_and_base() -> None:
    for cfg, p in _problems():
        lim = _limits(cfg)
        p0 = p._replace(z=np.zeros(9))
        base = {s: np.linalg.norm(WeightedMinEnergy(cfg, lim, Setting(s)).solve(p0)[6:8])  # type: ignore[arg-type]
                for s in (0.1, 1.0, 10.0)}
        assert base[0.1] > base[1.0] > base[10.0]
        for s in (0.1, 10.0):  # the task is still met exactly
            x = WeightedMinEnergy(cfg, lim, Setting(s)).solve(p0)  # type: ignore[arg-type]
            assert np.allclose(p.kin.J @ x, p.v_d, atol=1e-9)


def test_the_euclidean_projector_is_the_ordinary_null_space_term() -> None:
    for cfg, p in _problems():
        lim = _limits(cfg)
        dyn = WeightedMinEnergy(cfg, lim, Setting(1.0, "dynamic"))  # type: ignore[arg-type]
        euc = WeightedMinEnergy(cfg, lim, Setting(1.0, "euclidean"))  # type: ignore[arg-type]
        task = dyn.solve(p._replace(z=np.zeros(9)))
        x = euc.solve(p)
        assert np.allclose(x - task, null_project(p.kin.J, p.z).x, atol=1e-10)
        assert np.allclose(p.kin.J @ x, p.v_d, atol=1e-9)
        assert not np.allclose(x, dyn.solve(p), atol=1e-6)  # a different null-space term


def test_coupled_scaling_keeps_the_task_and_stays_definite() -> None:
    for cfg, p in _problems(3, full=True):
        lim = _limits(cfg)
        for s in (0.1, 1.0, 10.0):
            w = WeightedMinEnergy(cfg, lim, Setting(s, "dynamic", True))  # type: ignore[arg-type]
            assert np.all(np.linalg.eigvalsh(w._inertia(p.kin)) > 0.0)
            assert np.allclose(p.kin.J @ w.solve(p), p.v_d, atol=1e-9)
        a = MinEnergy(cfg, lim).solve(p)  # type: ignore[arg-type]
        b = WeightedMinEnergy(cfg, lim, Setting(1.0, "dynamic", True)).solve(p)  # type: ignore[arg-type]
        assert np.allclose(a, b, atol=1e-12)


def test_settings_grid_and_bad_settings() -> None:
    assert len(DEFAULT_SCALES) == 9 and DEFAULT_SCALES[4] == 1.0
    assert DEFAULT_SCALES[0] == pytest.approx(0.1) and DEFAULT_SCALES[-1] == pytest.approx(10.0)
    grid = settings((0.5, 1.0), ("dynamic", "euclidean"), coupled=True)
    assert [g.label for g in grid] == ["s=0.5 dynamic", "s=1 dynamic", "s=0.5 euclidean",
                                       "s=1 euclidean", "s=1 dynamic coupled",
                                       "s=1 euclidean coupled"]
    assert [g.paper for g in grid] == [False, True, False, False, False, False]
    with pytest.raises(ConfigError, match="sweep.projector"):
        Setting(1.0, "oblique")
    with pytest.raises(ConfigError, match="sweep.base_scale"):
        Setting(0.0)


def test_the_papers_setting_reproduces_the_plain_study() -> None:
    """Same users: the sweep's min-energy at s = 1 (dynamic, block M) and its locomotion,
    run in two worker processes, give the plain study's executions (run here) exactly;
    another setting does not."""
    study = StudyConfig.make(quick=True, users=2, seed=4, strategies=("locomotion", "min-energy"))
    plain = run_study(study).executions
    res = run_sweep(study, [Setting(1.0, "dynamic"), Setting(10.0, "euclidean")],
                    LocalProcesses(2))
    assert [r.approach for r in res.rows] == ["min-energy", "min-energy", "locomotion"]
    for k, strategy in ((0, "min-energy"), (2, "locomotion")):
        mine = [e for e in plain if e.strategy == strategy]
        theirs = res.executions[k]
        assert [csv_row(e) for e in theirs] == [csv_row(e) for e in mine]
        for a, b in zip(theirs, mine):
            assert a.limited == b.limited
            for x, y in zip(a.series, b.series):
                assert np.array_equal(x, y)
    other = res.executions[1]
    assert [e.E for e in other] != [e.E for e in res.executions[0]]
    assert res.rows[0].E == pytest.approx(float(np.median([e.E for e in plain
                                                           if e.strategy == "min-energy"])))
    assert all(0.0 <= r.limited <= 1.0 for r in res.rows)
    assert res.rows[0].x_f_hold == pytest.approx(
        float(np.median([e.x_f_hold for e in res.executions[0]])))


def test_sweep_command_writes_its_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["study", "sweep", "--quick", "--users", "1", "--scales", "0.3", "1",
               "--projectors", "dynamic", "--jobs", "1", "--out", str(tmp_path)])
    assert rc == 0
    rows = list(csv.DictReader((tmp_path / "sweep.csv").open()))
    assert [(r["approach"], r["base_scale"], r["projector"], r["coupled"], r["paper"])
            for r in rows] == [("min-energy", "0.3", "dynamic", "0", "0"),
                               ("min-energy", "1", "dynamic", "0", "1"),
                               ("min-energy", "1", "dynamic", "1", "0"),
                               ("locomotion", "", "", "", "0")]
    for r in rows:
        assert float(r["E"]) > 0.0 and float(r["x_f"]) > 0.0 and r["completed"] == "1"
        assert float(r["x_f_hold"]) > 0.0  # after the end-of-trial hold, for every setting
        assert 0.0 <= float(r["limited"]) <= 1.0
    png = (tmp_path / "sweep.png").read_bytes()
    assert png[:8] == PNG and len(png) > 10_000
    out = capsys.readouterr().out
    assert "Inertia-weighting sweep" in out and "min-energy (paper's setting)" in out


def test_sweep_csv_marks_domination() -> None:
    from mmctl.study.sweep import SweepRow

    paper = SweepRow("min-energy", Setting(1.0), 3, 1.0, 10, 0.1, 0.2, 30, 0.5, 0.1, 3, 0, False)
    better = paper._replace(setting=Setting(2.0), E=0.9, x_f=0.1, dominates=True)
    text = sweep_csv([paper, better])
    rows = list(csv.DictReader(text.splitlines()))
    assert [r["dominates"] for r in rows] == ["0", "1"]
    assert [r["paper"] for r in rows] == ["1", "0"]


# --- figures -------------------------------------------------------------------------

STRATS = ("locomotion", "switch", "min-energy")


def _series(n: int = 40) -> Series:
    t = np.arange(n, dtype=np.float32) * 0.01
    z = np.zeros(n, dtype=np.float32)
    return Series(t, z + 0.1, z + 1.0, z + 0.5, z + 10.0, z + 0.05, np.zeros(n, dtype=np.int8))


def _execs(n_users: int = 12) -> list[Execution]:
    """Locomotion's E clearly above the others for every user; F_h all alike (noise)."""
    rng = np.random.default_rng(11)
    out = []
    for u in range(n_users):
        for k, s in enumerate(STRATS):
            e = rng.uniform(0.4, 0.6) + (2.0 if s == "locomotion" else 0.3 * k)
            out.append(Execution(user=u, strategy=s, E=e, F_h=rng.uniform(10, 14), v=0.14,
                                 x_f=0.1 * (k + 1) + rng.uniform(0, 0.01), T_f=30.0 + u,
                                 E_base=e / 2, F_max=20.0, switches=1, completed=True,
                                 faults=0, series=_series()))
    return out


def test_boxplot_marks_follow_summary_json(tmp_path: Path) -> None:
    ex = _execs()
    write_outputs(tmp_path, ex, {"seed": 0})
    doc = json.loads((tmp_path / "summary.json").read_text())
    marks = boxplots(ex, tmp_path / "boxplots.png", doc)
    expected = [(m, *key.split(" vs "), r["significant"]) for m, pairs in doc["pairwise"].items()
                for key, r in pairs.items()]
    assert [(m, a, b) for m, a, b, _s in marks] == [(m, a, b) for m, a, b, sig in expected
                                                     if sig]
    assert ("E", "locomotion", "min-energy") in [(m, a, b) for m, a, b, _ in marks]
    for m, a, b, stars in marks:
        p = doc["pairwise"][m][f"{a} vs {b}"]["p_holm"]  # the deciding p, as the table's
        assert stars == ("***" if p < 0.001 else "**" if p < 0.01 else "*")
    png = (tmp_path / "boxplots.png").read_bytes()
    assert png[:8] == PNG and len(png) > 10_000
    # without a summary: no marks; a pair summary.json does not call significant: none
    assert boxplots(ex, tmp_path / "plain.png") == []
    doc["pairwise"]["E"]["locomotion vs min-energy"]["significant"] = False
    assert ("locomotion", "min-energy") not in [(a, b) for a, b, _ in
                                                significance_marks(doc, "E", list(STRATS))]


def test_sensitivity_chart_is_written(tmp_path: Path) -> None:
    claims = [{"claim": f"claim {i}", "factors": [
        {"name": f"f{j}", "mu_star": float(j + i), "sigma": 0.5 * j, "holds": j / 3}
        for j in range(4)]} for i in range(4)]
    sensitivity_chart(claims, tmp_path / "s.png", "test")
    png = (tmp_path / "s.png").read_bytes()
    assert png[:8] == PNG and len(png) > 10_000
