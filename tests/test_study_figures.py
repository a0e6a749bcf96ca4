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
    PAPER_MEDIAN_GID,
    PAPER_MEDIAN_LABEL,
    PAPER_POINT_LABEL,
    PAPER_POINT_REL_LABEL,
    SIM_POINT_LABEL,
    USER_DOTS_GID,
    USER_LINE_GID,
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
    for label in (SIM_POINT_LABEL, "locomotion", "coupled M, s = 1, dynamic",
                  "dominates the simulation's min-energy (lower median Ē and x_f than s = 1)",
                  PAPER_POINT_LABEL, PAPER_POINT_REL_LABEL):
        assert label in labels, label
    # the simulation's point is not called the paper's
    assert SIM_POINT_LABEL.startswith("simulation's min-energy")
    assert not any(lb.startswith("the paper's min-energy") for lb in labels)
    cap = caption_of(fig)
    assert "n = 3 users: 6 settings (locomotion included) × 3 users = 18 executions" in cap
    assert "no ISO/TS 15066 caps" in cap


def _gid_lines(ax: Any, gid: str) -> list[Any]:
    return [ln for ln in ax.get_lines() if ln.get_gid() == gid]


def test_sweep_draws_the_papers_measured_point_raw_and_relative(figures: list[Any]) -> None:
    rows = _sweep_rows()  # the simulation's locomotion: Ē 2.0 J
    fig = sweep_figure(rows, {"users": 3})
    figures.append(fig)
    ax = fig.axes[0]
    (raw,) = _gid_lines(ax, "paper-point")
    assert list(raw.get_xdata()) == [0.08] and list(raw.get_ydata()) == [0.86]
    (rel,) = _gid_lines(ax, "paper-point-relative")
    # 0.86 / 2.52 of the simulation's locomotion (2.0 J), on the right axis 0.34
    assert list(rel.get_xdata()) == [0.08]
    assert abs(float(rel.get_ydata()[0]) - 2.0 * 0.86 / 2.52) < 1e-12
    assert "0.86/2.52 = 0.34×" in PAPER_POINT_REL_LABEL
    assert "Red diamond: the paper's measured min-energy" in caption_of(fig)
    assert "not the paper's result" in caption_of(fig)
    # no locomotion in the sweep: no ratio to draw it at, the raw point stays
    fig2 = sweep_figure([r for r in rows if r.setting is not None], {"users": 3})
    figures.append(fig2)
    assert _gid_lines(fig2.axes[0], "paper-point")
    assert not _gid_lines(fig2.axes[0], "paper-point-relative")
    assert PAPER_POINT_REL_LABEL not in _legend_labels(fig2)


def test_boxplots_join_each_users_values_from_ten_users(figures: list[Any],
                                                        quick_conditions: dict[str, Any]) -> None:
    ex = _execs(12)
    fig, _marks = boxplots_figure(ex, _doc(ex, quick_conditions))
    figures.append(fig)
    panels = fig.axes[:5]
    for ax in panels:
        lines = _gid_lines(ax, USER_LINE_GID)
        assert len(lines) == 12  # one per user
        assert all(len(ln.get_xdata()) == 3 for ln in lines)  # through its 3 approaches
        assert not _gid_lines(ax, USER_DOTS_GID)
    # user 0's line in the Ē panel passes through its three values
    e0 = [e.E for e in ex if e.user == 0]
    assert [float(y) for y in _gid_lines(panels[0], USER_LINE_GID)[0].get_ydata()] == e0
    assert "one user's values (paired)" in _legend_labels(fig)
    assert "Thin grey lines join each user's values" in caption_of(fig)


def test_boxplots_draw_dots_below_ten_users(figures: list[Any]) -> None:
    fig, _ = boxplots_figure(_execs(4))
    figures.append(fig)
    for ax in fig.axes[:5]:
        assert not _gid_lines(ax, USER_LINE_GID)
        dots = _gid_lines(ax, USER_DOTS_GID)
        assert len(dots) == 3 and all(len(d.get_xdata()) == 4 for d in dots)
    assert "one user" in _legend_labels(fig)
    assert "Grey dots: one per user" in caption_of(fig)


def test_boxplots_mark_the_papers_medians(figures: list[Any]) -> None:
    fig, _ = boxplots_figure(_execs(4))
    figures.append(fig)
    assert PAPER_MEDIAN_LABEL in _legend_labels(fig)
    assert PAPER_MEDIAN_LABEL.startswith("paper's median")
    for ax, m in zip(fig.axes[:5], ("E", "F_h", "v", "x_f", "T_f")):
        (d,) = _gid_lines(ax, PAPER_MEDIAN_GID)
        assert [float(y) for y in d.get_ydata()] == [
            {"locomotion": {"E": 2.52, "F_h": 15.84, "v": 0.16, "x_f": 0.09, "T_f": 31.77},
             "switch": {"E": 0.95, "F_h": 11.31, "v": 0.14, "x_f": 0.28, "T_f": 32.97},
             "min-energy": {"E": 0.86, "F_h": 12.30, "v": 0.14, "x_f": 0.08, "T_f": 28.33},
             }[s][m] for s in STRATS]


def test_brackets_say_which_approach_is_higher(figures: list[Any],
                                               quick_conditions: dict[str, Any]) -> None:
    ex = _execs(12)  # locomotion's Ē above both others' for every user
    doc = _doc(ex, quick_conditions)
    fig, _marks = boxplots_figure(ex, doc)
    figures.append(fig)
    texts = [t.get_text() for t in fig.axes[0].texts if t.get_gid() == "bracket-label"]
    assert "L > S **" in texts and "L > ME **" in texts
    # x_f grows with the approach's index: switch below min-energy
    (xf_ax,) = [ax for ax in fig.axes if ax.get_title() == "x_f [m]"]
    xf = [t.get_text() for t in xf_ax.texts if t.get_gid() == "bracket-label"]
    assert any(t.startswith("ME > S ") for t in xf) and any(t.startswith("S > L ") for t in xf)
    # the direction follows summary.json's sign: flipped there, flipped in the label
    doc["pairwise"]["E"]["locomotion vs switch"]["rank_biserial"] *= -1
    fig2, _ = boxplots_figure(ex, doc)
    figures.append(fig2)
    assert "S > L **" in [t.get_text() for t in fig2.axes[0].texts]
    assert "L > S" in caption_of(fig) and "L = Locomotion" in caption_of(fig)


def test_boxplots_flag_the_unfinished(figures: list[Any],
                                      quick_conditions: dict[str, Any]) -> None:
    ex = [e._replace(completed=False, T_f=60.0) if (e.user, e.strategy) == (2, "switch")
          else e for e in _execs(12)]
    from mmctl.study.report import tested

    meta = {"users": 12, "seed": 0, "quick": True, "task": "wall",
            "conditions": quick_conditions}
    doc = summary(ex, analyse(values(tested(ex)), ("E", "F_h", "v", "x_f", "T_f")), meta)
    fig, _ = boxplots_figure(ex, doc)
    figures.append(fig)
    assert sum(len(_gid_lines(ax, "unfinished")) for ax in fig.axes[:5]) == 5
    assert "unfinished (its user left out of the tests)" in _legend_labels(fig)
    assert "n = 11 users (1 unfinished excluded)" in caption_of(fig)


def test_the_velocity_caption_says_the_hand_follows_a_plan(figures: list[Any]) -> None:
    ex = _execs(3)
    speed = time_series_figure(ex, 0, "speed")
    energy = time_series_figure(ex, 0, "energy")
    figures += [speed, energy]
    cap = caption_of(speed)
    assert "The simulated hand tracks its own planned motion" in cap
    assert "the simulated person's plan" in cap and "not a measured human's" in cap
    assert "planned motion" not in caption_of(energy)


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
