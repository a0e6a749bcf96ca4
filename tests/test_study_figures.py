"""The study's figures explain themselves: a legend entry for every shading and marker,
a caption naming n and the robot's conditions; and `mmctl study --help` shows the
analyses as optional."""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.study.config import StudyConfig
from mmctl.study.plots import (
    CAPTION_GID,
    LOCOMOTION_LABEL,
    boxplots_figure,
    caption_of,
    sensitivity_caption,
    sensitivity_figure,
    sweep_figure,
    time_series_figure,
)
from mmctl.study.report import conditions, summary, users_of, values
from mmctl.study.results import Execution, Series
from mmctl.study.stats import analyse
from mmctl.study.sweep import Setting, SweepRow

STRATS = ("locomotion", "switch", "min-energy")


def _series(n: int = 60, locomotion: bool = True) -> Series:
    t = np.arange(n, dtype=np.float32) * 0.01
    z = np.zeros(n, dtype=np.float32)
    loc = ((np.arange(n) % 20 < 10) & locomotion).astype(np.int8)
    return Series(t, z + 0.1, z + 1.0 + t, z + 0.5, z + 10.0, z + 0.05, loc)


def _execs(n_users: int, agree: bool = True) -> list[Execution]:
    """Locomotion's Ē above the others' for every user (``agree``), noise elsewhere."""
    rng = np.random.default_rng(3)
    out = []
    for u in range(n_users):
        for k, s in enumerate(STRATS):
            e = rng.uniform(0.4, 0.6) + (2.0 if s == "locomotion" and agree else 0.3 * k)
            out.append(Execution(u, s, e, rng.uniform(10, 14), 0.14, 0.1 * (k + 1)
                                 + rng.uniform(0, 0.01), 30.0 + u, e / 2, 20.0, 1, True, 0,
                                 _series(locomotion=s == "switch")))
    return out


@pytest.fixture(scope="module")
def quick_conditions() -> dict[str, Any]:
    return conditions(StudyConfig.make(quick=True))


def _doc(ex: list[Execution], cond: dict[str, Any]) -> dict[str, Any]:
    meta = {"users": users_of(ex), "seed": 0, "quick": True, "task": "wall",
            "conditions": cond}
    return summary(ex, analyse(values(ex), ("E", "F_h", "v", "x_f", "T_f")), meta)


@pytest.fixture
def figures() -> Iterator[list[Any]]:
    """Figures a test made, closed after it."""
    made: list[Any] = []
    yield made
    import matplotlib.pyplot as plt

    for fig in made:
        plt.close(fig)


def _legend_labels(fig: Any) -> list[str]:
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    legends += list(fig.legends)
    return [t.get_text() for lg in legends for t in lg.get_texts()]


def test_the_time_series_legend_names_the_shading(figures: list[Any],
                                                  quick_conditions: dict[str, Any]) -> None:
    ex = _execs(3)
    doc = _doc(ex, quick_conditions)
    for what in ("speed", "energy"):
        fig = time_series_figure(ex, 0, what, doc)
        figures.append(fig)
        labels = _legend_labels(fig)
        assert LOCOMOTION_LABEL in labels, what
        # the shading is the switch panel's only (its locomotion phases: 3 of them)
        assert [sum(a.get_gid() == "locomotion" for a in ax.patches) for ax in fig.axes] \
            == [0, 3, 0]
        assert ("the base's share of E_K (filled)" in labels) == (what == "energy")
        assert any(s.startswith("end-effector speed" if what == "speed" else "E_K, whole")
                   for s in labels)
        cap = caption_of(fig)
        assert "n = 3 users × 3 approaches = 9 executions" in cap
        assert "seed 0, quick wall task" in cap
        assert "no ISO/TS 15066 caps" in cap and "1.568 J" in cap
        assert "safety.brake_condition 1" in cap
        assert "Peak E_K of these 3 executions: 1.59 J" in cap  # 1 + t, t up to 0.59 s


def test_no_shading_no_entry_and_the_caption_says_so(figures: list[Any]) -> None:
    ex = [e._replace(series=_series(locomotion=False)) for e in _execs(3)]
    fig = time_series_figure(ex, 0, "speed")
    figures.append(fig)
    assert LOCOMOTION_LABEL not in _legend_labels(fig)
    assert "no locomotion phase to shade" in caption_of(fig)


def test_boxplots_with_three_users_say_why_no_bracket(figures: list[Any],
                                                      quick_conditions: dict[str, Any]) -> None:
    ex = _execs(3)
    doc = _doc(ex, quick_conditions)
    fig, marks = boxplots_figure(ex, doc)
    figures.append(fig)
    assert marks == []
    title = fig.get_suptitle()
    assert "3 simulated users" in title and "bracket" not in title
    cap = caption_of(fig)
    assert "n = 3 users" in cap and "3 × 3 = 9 executions" in cap
    assert "No brackets can appear" in cap and "is 0.75 (exact: 3 × 2/2^3)" in cap
    assert "no ISO/TS 15066 caps" in cap
    labels = _legend_labels(fig)
    assert labels[:3] == ["median", "box: quartiles (middle half)",
                          "whiskers: furthest user within 1.5 box heights of the box"]
    assert not any("bracket" in s for s in labels)


def test_boxplots_with_brackets_explain_them(figures: list[Any],
                                             quick_conditions: dict[str, Any]) -> None:
    ex = _execs(12)
    doc = _doc(ex, quick_conditions)
    fig, marks = boxplots_figure(ex, doc)
    figures.append(fig)
    assert ("E", "locomotion", "switch", "**") in marks  # exact: 3 x 2/2^12 = 1.5e-3
    assert any(s.startswith("bracket: p_holm < 0.05") for s in _legend_labels(fig))
    cap = caption_of(fig)
    assert "Brackets: the pairs with p_holm < 0.05" in cap and "exact distribution" in cap
    assert "n = 12 users" in cap and "No brackets can appear" not in cap


def test_boxplots_without_a_summary_say_so(figures: list[Any]) -> None:
    fig, marks = boxplots_figure(_execs(4))
    figures.append(fig)
    assert marks == []
    assert "n = 4 users" in caption_of(fig) and "drawn without summary.json" in caption_of(fig)


def _sweep_rows() -> list[SweepRow]:
    paper = SweepRow("min-energy", Setting(1.0), 3, 1.0, 10, 0.1, 0.3, 30, 0.5, 0.1, 3, 0,
                     False, 0.2)
    return [paper._replace(setting=Setting(0.3), E=1.5, x_f=0.1, x_f_hold=0.08),
            paper,
            paper._replace(setting=Setting(3.0), E=0.8, x_f=0.2, dominates=True),
            paper._replace(setting=Setting(1.0, "euclidean"), E=1.4, x_f=0.05),
            paper._replace(setting=Setting(1.0, coupled=True), E=0.9, x_f=0.25),
            paper._replace(approach="locomotion", setting=None, E=2.0, x_f=0.04,
                           x_f_hold=math.nan)]


def test_sweep_legend_and_caption(figures: list[Any], quick_conditions: dict[str, Any]) -> None:
    fig = sweep_figure(_sweep_rows(), {"users": 3, "seed": 0, "quick": True, "task": "wall",
                                       "conditions": quick_conditions})
    figures.append(fig)
    labels = _legend_labels(fig)
    for label in ("the paper's min-energy (s = 1, dynamic)", "locomotion",
                  "coupled M, s = 1, dynamic",
                  "dominates the paper's point (lower median Ē and x_f)"):
        assert label in labels, label
    cap = caption_of(fig)
    assert "n = 3 users: 6 settings (locomotion included) × 3 users = 18 executions" in cap
    assert "no ISO/TS 15066 caps" in cap


def _sensitivity_doc(cond: dict[str, Any]) -> dict[str, Any]:
    claims = [{"claim": f"claim {i}", "factors": [
        {"name": f"f{j}", "mu_star": float(j + i), "sigma": 0.5 * j, "holds": j / 3,
         "holds_by_level": [[0.0, 1, 2], [1.0, 0, 2]]} for j in range(4)]} for i in range(4)]
    return {"claims": claims, "factors": [{"name": f"f{j}"} for j in range(4)],
            "users": 2, "points_n": 10, "strategies": list(STRATS), "seed": 0,
            "quick": True, "task": "wall", "r_crit": 0.527, "conditions": cond}


def test_sensitivity_legend_colour_bar_and_caption(figures: list[Any],
                                                   quick_conditions: dict[str, Any]) -> None:
    doc = _sensitivity_doc(quick_conditions)
    fig = sensitivity_figure(doc["claims"], "title", sensitivity_caption(doc))
    figures.append(fig)
    labels = _legend_labels(fig)
    assert any(s.startswith("σ / the panel's largest μ*") for s in labels)
    assert any(s.startswith("right edge, one per level of the factor") for s in labels)
    assert "... it does not" in labels  # the hollow square
    assert any(s.startswith("bar: μ*") for s in labels)
    assert any(ax.get_xlabel() == "bar colour: share of the points where the claim holds"
               for ax in fig.axes)  # the colour bar
    cap = caption_of(fig)
    assert "n = 2 users per point: 10 Morris points × 2 users × 3 approaches = 60 executions" \
        in cap
    assert "r_crit = 0.527" in cap and "no ISO/TS 15066 caps" in cap


def test_every_caption_is_one_text_at_the_bottom(figures: list[Any]) -> None:
    fig, _ = boxplots_figure(_execs(3))
    figures.append(fig)
    caps = [t for t in fig.texts if t.get_gid() == CAPTION_GID]
    assert len(caps) == 1
    _x, y = caps[0].get_position()
    assert y < 0.05 and caps[0].get_fontsize() < 8
    # the panels sit above the caption and the legend
    assert min(ax.get_position().y0 for ax in fig.axes) > y


def _help(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 0
    return capsys.readouterr().out


def test_study_help_shows_the_analysis_as_optional(capsys: pytest.CaptureFixture[str]) -> None:
    text = _help(["study", "--help"], capsys)
    usage = text.split("\n\n")[0]
    assert usage.startswith("usage: mmctl study [-h]")
    assert "[ANALYSIS" in usage
    # every ANALYSIS of the usage inside brackets: none stands alone as required
    assert not re.search(r"(?<!\[)ANALYSIS \.\.\.", usage)
    assert usage.count("ANALYSIS") == usage.count("[ANALYSIS")
    assert "Without ANALYSIS, runs the paper's experiment" in text
    assert "analyses (optional):" in text
    for line in ("mmctl study sweep --quick --users 3 --jobs 1",
                 "mmctl study sensitivity --trajectories 2"):
        assert line in text
    for name in ("sweep", "sensitivity", "power"):  # one line each in the analyses' group
        assert re.search(rf"^ {{4}}{name} +\S", text, re.MULTILINE), name
    # the analyses' own usage is theirs, not the parent's
    assert _help(["study", "sweep", "--help"], capsys).startswith("usage: mmctl study sweep [-h]")
