"""The sweep's null-space gain dimension and x_f read after T_f (issue 32, point 5): the
gain scale reaches the controller and nothing else, g = 1 is the plain study exactly,
x_f at the delays is the deviation at the right cycle, the CSV, table, figure and the
command's option."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.control.cycle import CycleChain
from mmctl.errors import ConfigError
from mmctl.model import RobotModel
from mmctl.sim.human import HandleObservation, HumanAction, Phase
from mmctl.study.config import StudyConfig
from mmctl.study.plots import (
    PAPER_POINT_LABEL,
    PAPER_POINT_REL_LABEL,
    PAPER_XF_LABEL,
    caption_of,
    gain_read_figure,
    sweep_figure,
)
from mmctl.study.results import X_F_DELAYS, csv_row
from mmctl.study.runner import run_execution
from mmctl.study.sweep import (
    AFTER_COLUMNS,
    CSV_COLUMNS,
    Setting,
    SweepRow,
    read_sweep_csv,
    run_sweep,
    scaled_gain,
    settings,
    sweep_csv,
    sweep_table,
)

PNG = b"\x89PNG\r\n\x1a\n"


def test_the_gain_scale_reaches_the_controllers_g_and_only_the_arms_entries() -> None:
    cfg = StudyConfig.make(quick=True).control_config("min-energy")
    assert Setting(1.0).config(cfg) is cfg  # the paper's setting: the configuration itself
    assert Setting(1.0, gain_scale=1.0).paper
    for g in (0.5, 4.0, 100.0):
        s = Setting(1.0, gain_scale=g)
        assert not s.paper and s.label == f"s=1 dynamic G×{g:.3g}"
        c = s.config(cfg)
        assert c.idk.null_gain == (g,) * 6 + (0.0,) * 3
        assert c.robot == cfg.robot and c.limits == cfg.limits  # nothing else changes
        chain = s.chain(c)
        # the cycle's z = G (q_des - q) uses the scaled G
        assert np.array_equal(chain.controller.gain, np.array((g,) * 6 + (0.0,) * 3))
    # the coupled ablation and the gain together
    c = Setting(1.0, "euclidean", True, 2.0).config(cfg)
    assert c.robot.full_inertia and c.idk.null_gain[:6] == (2.0,) * 6
    # base entries are kept, not scaled
    assert scaled_gain((1.0,) * 6 + (0.5, 0.5, 0.0), 3.0) == (3.0,) * 6 + (0.5, 0.5, 0.0)
    with pytest.raises(ConfigError, match=r"idk.null_gain.*<= 100"):
        Setting(1.0, gain_scale=101.0).config(cfg)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ConfigError, match="sweep.gain_scale"):
            Setting(1.0, gain_scale=bad)


def test_the_null_space_term_scales_with_the_gain() -> None:
    """One control cycle away from q_des with the hand off: the whole command is the
    null-space term P G (q_des - q), so it scales with g (up to the limits, which the
    small offset keeps off)."""
    study = StudyConfig.make(quick=True)
    cfg0 = study.control_config("min-energy")
    outs = {}
    for g in (1.0, 2.0):
        cfg = Setting(1.0, gain_scale=g).config(cfg0)
        chain = CycleChain(cfg)
        ctl = chain.controller
        q = np.concatenate((np.asarray(cfg.robot.q_des), np.zeros(3)))
        q[:6] += np.array([0.02, -0.015, 0.01, 0.02, -0.01, 0.015])
        outs[g] = ctl.gain * (ctl.q_des - q)
        kin = ctl.model.update(q)
        from mmctl.control.strategies import Problem

        solver = ctl.strategies["min-energy"]
        outs[("x", g)] = solver.solve(Problem(kin, np.zeros(6), q, np.zeros(9), chain.dt,
                                              outs[g]))
    assert np.allclose(outs[2.0], 2.0 * outs[1.0], atol=0.0)
    x1, x2 = outs[("x", 1.0)], outs[("x", 2.0)]
    assert np.linalg.norm(x1) > 1e-4
    assert np.allclose(x2, 2.0 * x1, rtol=1e-9, atol=1e-12)


def test_the_gains_grid_keeps_the_old_grid_by_default() -> None:
    old = settings((0.5, 1.0), ("dynamic", "euclidean"), coupled=True)
    assert old == settings((0.5, 1.0), ("dynamic", "euclidean"), True, (1.0,))
    grid = settings((1.0,), ("dynamic",), coupled=False, gains=(0.5, 1.0, 2.0))
    assert [g.label for g in grid] == ["s=1 dynamic G×0.5", "s=1 dynamic", "s=1 dynamic G×2"]
    assert [g.paper for g in grid] == [False, True, False]
    both = settings((1.0,), ("dynamic", "euclidean"), coupled=True, gains=(1.0, 2.0))
    assert [g.label for g in both][-4:] == ["s=1 dynamic coupled", "s=1 dynamic coupled G×2",
                                            "s=1 euclidean coupled",
                                            "s=1 euclidean coupled G×2"]


def _deviations(study: StudyConfig, strategy: str, variant: Any = None
                ) -> tuple[Any, list[float], int, int]:
    """One execution and ||p_base - p_des|| every cycle, rebuilt from what the person
    observed (the handle in the world, the base's pose), the T_f cycle and the last."""
    cfg = study.control_config(strategy)
    if variant is not None:
        cfg = variant.config(cfg)
    model = RobotModel(cfg.robot)
    p_des = model.update(np.concatenate((np.asarray(cfg.robot.q_des), np.zeros(3))),
                         inertia=False).p_base
    dev: list[float] = []
    k_done: list[int] = []
    k_end: list[int] = []

    def observe(obs: HandleObservation, act: HumanAction) -> None:
        x, y, yaw = (float(v) for v in obs.base)
        c, s = math.cos(yaw), math.sin(yaw)
        d = np.asarray(obs.position, dtype=float) - np.array([x, y, 0.0])
        p_base = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]])
        if act.done and not k_done:
            k_done.append(len(dev))
        if act.phase is Phase.DONE:
            k_end.append(len(dev))
        dev.append(float(np.linalg.norm(p_base - p_des)))

    ex, _cpu, _cycles = run_execution(study, 0, strategy, observe=observe, variant=variant)
    return ex, dev, k_done[0], k_end[0]


@pytest.mark.parametrize("strategy", ["min-energy", "locomotion"])
def test_x_f_after_is_the_deviation_at_its_cycle(strategy: str) -> None:
    study = StudyConfig.make(quick=True, users=1, seed=2)
    ex, dev, k_done, k_end = _deviations(study, strategy)
    assert ex.completed and len(ex.x_f_after) == len(X_F_DELAYS)
    assert k_end == len(dev) - 1  # the hold's end is the last cycle
    assert dev[k_done] == pytest.approx(ex.x_f, abs=1e-12)  # delay 0: x_f itself
    assert dev[k_end] == pytest.approx(ex.x_f_hold, abs=1e-12)  # the end: x_f_hold
    for d, x in zip(X_F_DELAYS, ex.x_f_after):
        k = k_done + round(d / study.dt)
        assert k < k_end
        assert x == pytest.approx(dev[k], abs=1e-12), d
    # the hold's end is ~3 s after T_f
    assert (k_end - k_done) * study.dt == pytest.approx(3.0, abs=3 * study.dt)


def test_an_unfinished_execution_reads_x_f_at_t_f() -> None:
    from dataclasses import replace

    study = replace(StudyConfig.make(quick=True, users=1, seed=2), t_max=2.0)
    ex, _cpu, _cycles = run_execution(study, 0, "min-energy")
    assert not ex.completed
    assert ex.x_f_after == (ex.x_f,) * len(X_F_DELAYS)


def test_gain_one_is_the_plain_study_and_another_gain_is_not() -> None:
    study = StudyConfig.make(quick=True, users=1, seed=4, strategies=("min-energy",))
    plain, _cpu, _cycles = run_execution(study, 0, "min-energy")
    res = run_sweep(study, [Setting(1.0), Setting(1.0, gain_scale=4.0)], locomotion=False)
    same, other = res.executions[0][0], res.executions[1][0]
    assert csv_row(same) == csv_row(plain) and same.x_f_after == plain.x_f_after
    for a, b in zip(same.series, plain.series):
        assert np.array_equal(a, b)
    assert csv_row(other) != csv_row(plain)
    # a stronger pull toward q_des: x_f smaller at T_f, and after it
    assert other.x_f < same.x_f and other.x_f_hold < same.x_f_hold
    assert res.rows[1].x_f_after == other.x_f_after  # one user: the median is the value


def _rows() -> list[SweepRow]:
    base = SweepRow("min-energy", Setting(1.0), 3, 0.5, 12.0, 0.14, 0.5, 29.0, 0.3, 0.05, 3, 0,
                    False, 0.3, (0.45, 0.4, 0.35))
    return [base._replace(setting=Setting(1.0, gain_scale=0.5), E=0.45, x_f=0.6,
                          x_f_after=(0.58, 0.55, 0.5), x_f_hold=0.45),
            base,
            base._replace(setting=Setting(1.0, gain_scale=4.0), E=0.7, x_f=0.3,
                          x_f_after=(0.2, 0.15, 0.1), x_f_hold=0.08),
            base._replace(approach="locomotion", setting=None, E=2.0, x_f=0.04,
                          x_f_after=(0.04, 0.04, 0.04), x_f_hold=0.04)]


def test_csv_and_table_carry_the_gain_and_the_delays() -> None:
    assert CSV_COLUMNS[:17][-1] == "x_f_hold"  # the columns of before keep their places
    assert AFTER_COLUMNS == tuple(f"x_f_{d:g}s" for d in X_F_DELAYS)
    assert AFTER_COLUMNS == ("x_f_0.5s", "x_f_1s", "x_f_2s")
    rows = list(csv.DictReader(sweep_csv(_rows()).splitlines()))
    assert [r["gain_scale"] for r in rows] == ["0.5", "1", "4", ""]
    assert [r["paper"] for r in rows] == ["0", "1", "0", "0"]
    assert [r["x_f_1s"] for r in rows] == ["0.55", "0.4", "0.15", "0.04"]
    # a row without reads (made before issue 32): NaN
    old = _rows()[1]._replace(x_f_after=())
    assert next(csv.DictReader(sweep_csv([old]).splitlines()))["x_f_2s"] == "nan"
    table = sweep_table(_rows())
    head = table.splitlines()[0]
    assert "| G |" in head and "Ē / loc." in head and "x_f +0.5 s [m]" in head
    line = table.splitlines()[4]  # G x 4
    assert "| 4 |" in line and "| 0.35 |" in line and "| 0.200 | 0.150 | 0.100 | 0.080 |" in line


def test_sweep_csv_reads_back() -> None:
    rows = _rows()
    back = read_sweep_csv(sweep_csv(rows))
    assert back == rows  # every field (these numbers have fewer than 10 digits)
    assert back[2].setting == Setting(1.0, "dynamic", False, 4.0) and back[3].setting is None
    # a file from before issue 32: the paper's G, no reads after T_f
    old_cols = CSV_COLUMNS[:17]
    text = "\n".join(",".join(r.split(",")[:17]) for r in sweep_csv(rows).splitlines())
    assert text.splitlines()[0].split(",") == list(old_cols)
    old = read_sweep_csv(text)
    assert [r.setting for r in old] == [Setting(1.0), Setting(1.0), Setting(1.0), None]
    assert all(r.x_f_after == () for r in old) and old[2].x_f_hold == 0.08


def test_the_gain_figure_draws_every_read_and_the_papers_point() -> None:
    fig = gain_read_figure(_rows(), {"users": 3, "seed": 0, "quick": True, "task": "wall"})
    try:
        ax, axr = fig.axes[0], fig.axes[1]
        labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
        for read in ("T_f", "T_f + 0.5 s", "T_f + 1 s", "T_f + 2 s", "hold's end (T_f + 3 s)"):
            assert f"x_f read at {read} (dynamic, s = 1)" in labels, read
        assert PAPER_POINT_LABEL in labels and PAPER_POINT_REL_LABEL in labels
        (raw,) = [ln for ln in ax.get_lines() if ln.get_gid() == "paper-point"]
        assert list(raw.get_xdata()) == [0.08] and list(raw.get_ydata()) == [0.86]
        (rel,) = [ln for ln in ax.get_lines() if ln.get_gid() == "paper-point-relative"]
        assert list(rel.get_ydata()) == [pytest.approx(0.86 / 2.52 * 2.0)]
        right = [t.get_text() for t in axr.get_legend().get_texts()]
        assert PAPER_XF_LABEL in right and "dynamic G×4 (Ē 0.35× loc.)" in right
        g4 = next(ln for ln in axr.get_lines() if ln.get_label().startswith("dynamic G×4"))
        assert list(g4.get_ydata()) == [0.3, 0.2, 0.15, 0.1, 0.08]
        assert list(g4.get_xdata()) == [0.0, *X_F_DELAYS, 3.0]
        assert "n = 3 users: 4 settings (locomotion included) × 3 users = 12 executions" in (
            caption_of(fig))
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)
    fig = sweep_figure(_rows(), {"users": 3})  # a gain-only grid: its curve runs along g
    try:
        assert "null-space gain" in fig.axes[0].get_title()
        assert fig.axes[1].get_xlabel() == "gain scale g on the paper's G"
        assert "Curves run along g" in caption_of(fig)
    finally:
        import matplotlib.pyplot as plt

        plt.close(fig)


def test_gains_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["study", "sweep", "--help"])
    assert "--gains G [G ...]" in capsys.readouterr().out
    for bad, msg in (("0", "--gains = 0.0: each gain scale must be a number > 0"),
                     ("nan", "--gains = nan: each gain scale must be a number > 0"),
                     ("150", "--gains = 150.0: makes idk.null_gain")):
        assert main(["study", "sweep", "--quick", "--users", "1", "--gains", bad,
                     "--out", str(tmp_path)]) == 2
        assert msg in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["study", "sweep", "--gains", "two"])
    assert "invalid float value: 'two'" in capsys.readouterr().err
    assert not (tmp_path / "sweep.csv").exists()


def test_sweep_command_with_gains_writes_its_files(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["study", "sweep", "--quick", "--users", "1", "--scales", "1", "--projectors",
               "dynamic", "--no-coupled", "--gains", "1", "3", "--jobs", "1", "--out",
               str(tmp_path)])
    assert rc == 0
    rows = list(csv.DictReader((tmp_path / "sweep.csv").open()))
    assert [(r["approach"], r["gain_scale"], r["paper"]) for r in rows] == [
        ("min-energy", "1", "1"), ("min-energy", "3", "0"), ("locomotion", "", "0")]
    for r in rows:
        reads = [float(r[c]) for c in ("x_f", *AFTER_COLUMNS, "x_f_hold")]
        assert all(0.0 <= x < 1.5 for x in reads)
    for name in ("sweep.png", "sweep-gain.png"):
        png = (tmp_path / name).read_bytes()
        assert png[:8] == PNG and len(png) > 10_000, name
    out = capsys.readouterr().out
    assert "| G |" in out and "| min-energy | 1 | 3 | dynamic | block |" in out
