"""Figures of the study (matplotlib, Agg backend, imported on use).

* ``boxplots.png`` — the five metrics over the users, one box per approach (paper Fig. 5),
  the median a black line on every box, each user's values joined by a thin grey line
  (paired; below :data:`PAIRED_LINES_MIN` users a dot per user instead), the paper's
  median a red diamond, brackets over the pairs summary.json calls significant (by
  ``p_holm``, :mod:`mmctl.study.report`) labelled with the direction and stars
  ("L > S ***");
* ``velocity.png`` — ||v(kT)|| of the median user, one panel per approach (Fig. 6; the
  simulated hand follows the simulated person's own plan);
* ``energy.png`` — E_K(kT) of the median user, base share shaded (Fig. 7).

In the switch panels, locomotion phases are shaded.  The analyses' figures:

* ``sweep.png`` — the inertia-weighting sweep's Ē–x_f curves and limit-active fractions
  with the paper's measured min-energy point, raw and relative to its locomotion
  (:func:`sweep_curve`, `mmctl study sweep`);
* ``sweep-gain.png`` — a sweep over the null-space gain's magnitude: Ē against x_f read
  at T_f, at fixed delays after it and at the hold's end, and x_f against the time it is
  read, with the paper's point (:func:`gain_read_curve`, `mmctl study sweep --gains`);
* ``sensitivity.png`` — the Morris screening's μ* ranking per conclusion
  (:func:`sensitivity_chart`, `mmctl study sensitivity`).

Every figure has a legend for each of its markers and shadings and a caption at its
bottom (:data:`CAPTION_GID`): what it shows, n (users, executions) and the robot's
conditions.  Each ``*_figure`` function returns the matplotlib Figure unsaved (the
tests read its legends and caption); the others save it and close it.
"""
from __future__ import annotations

import math
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mmctl.study.report import (
    P_METHODS,
    conditions_text,
    smallest_p_holm,
    strategies_of,
    values,
)
from mmctl.study.results import (
    APPROACH_NAMES,
    METRIC_LABELS,
    METRICS,
    PAPER_MEDIANS,
    X_F_DELAYS,
    Execution,
)
from mmctl.study.stats import ALPHA

_COLOURS = ("tab:red", "tab:orange", "tab:green", "tab:blue", "tab:purple")
#: The gid of every figure's caption (one of ``fig.texts``).
CAPTION_GID = "caption"
#: The caption's font size [pt].
CAPTION_SIZE = 6.5
#: The legend label of the shading in velocity.png and energy.png.
LOCOMOTION_LABEL = "switch in its locomotion sub-mode (after a button press)"
#: From this many users on, the boxplots join each user's values by a line; below it
#: they draw a dot per user (a handful of lines over a box hides the box).
PAIRED_LINES_MIN = 10
#: The gids of the boxplots' per-user lines, per-user dots and the paper's medians.
USER_LINE_GID = "user-line"
USER_DOTS_GID = "user-dots"
PAPER_MEDIAN_GID = "paper-median"
#: The legend label of the paper's medians in boxplots.png.
PAPER_MEDIAN_LABEL = "paper's median (Tables I-III)"
#: The paper's measured min-energy point (Table III): median x_f [m], median Ē [J], and
#: its locomotion's median Ē [J] (Table I), for sweep.png.
PAPER_MIN_ENERGY_XF = PAPER_MEDIANS["min-energy"]["x_f"]
PAPER_MIN_ENERGY_E = PAPER_MEDIANS["min-energy"]["E"]
PAPER_LOCOMOTION_E = PAPER_MEDIANS["locomotion"]["E"]
#: sweep.png's legend labels of the paper's measured point, raw and normalised.
PAPER_POINT_LABEL = (f"paper's measured min-energy (x_f = {PAPER_MIN_ENERGY_XF:g} m, "
                     f"Ē = {PAPER_MIN_ENERGY_E:g} J)")
PAPER_POINT_REL_LABEL = (f"paper's measured min-energy relative to its locomotion (Ē "
                         f"{PAPER_MIN_ENERGY_E:g}/{PAPER_LOCOMOTION_E:g} = "
                         f"{PAPER_MIN_ENERGY_E / PAPER_LOCOMOTION_E:.2f}× the simulation's "
                         "locomotion; right axis)")
#: sweep.png's legend label of the simulation's run of the paper's setting.
SIM_POINT_LABEL = "simulation's min-energy (s = 1, dynamic: the paper's setting)"
#: The sentence velocity.png's caption says about the hand's motion.
PLAN_NOTE = ("The simulated hand tracks its own planned motion: the trajectory it leads "
             "the robot along is the simulated person's plan (minimum-jerk reaches between "
             "the holes), not a measured human's, so the curve shows how the robot follows "
             "a planned hand, not how a person moved.")


def _pyplot() -> Any:
    from mmctl.extras import require

    require("study", "the study's figures")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> None:
    # no timestamps in the PNG metadata: same data -> same file
    fig.savefig(path, dpi=110, metadata={"Software": None})


def _close(fig: Any) -> None:
    _pyplot().close(fig)


def caption_of(fig: Any) -> str:
    """The caption :func:`_layout` wrote into ``fig`` ("" if none), unwrapped."""
    for t in fig.texts:
        if t.get_gid() == CAPTION_GID:
            return " ".join(str(t.get_text()).split())
    return ""


def _layout(fig: Any, caption: str, legend_rows: int = 0, top_in: float = 0.0) -> float:
    """Grow ``fig`` by its caption (wrapped to the figure's width, small font) and
    ``legend_rows`` rows of a figure legend above it, write the caption at the bottom,
    lay the axes out above both (``top_in`` [in] kept free at the top); returns the
    figure fraction where the legend's band starts."""
    width = max(60, int(fig.get_figwidth() * 72.0 / (0.56 * CAPTION_SIZE)))
    lines: list[str] = []
    for para in caption.split("\n"):
        lines += textwrap.wrap(para, width) or [""]
    cap_h = len(lines) * CAPTION_SIZE * 1.3 / 72.0 + 0.12  # [in]
    leg_h = 0.22 * legend_rows + (0.1 if legend_rows else 0.0)
    h = float(fig.get_figheight()) + cap_h + leg_h + top_in
    fig.set_figheight(h)
    fig.text(0.008, 0.06 / h, "\n".join(lines), ha="left", va="bottom", fontsize=CAPTION_SIZE,
             color="0.2", gid=CAPTION_GID)
    fig.tight_layout(rect=(0.0, (cap_h + leg_h) / h, 1.0, 1.0 - top_in / h))
    return cap_h / h


def _setting(doc: Mapping[str, Any] | None) -> str:
    """", seed 0, quick wall task" from a summary or meta document (what it has)."""
    if not doc:
        return ""
    out = ""
    if doc.get("seed") is not None:
        out += f", seed {doc['seed']}"
    if "quick" in doc:
        out += f", {'quick' if doc['quick'] else 'full'} {doc.get('task', 'wall')} task"
    return out


def _stars(p: float) -> str:
    """Significance stars of a Holm-corrected p-value: * < 0.05, ** < 0.01, *** < 0.001."""
    return "***" if p < 0.001 else "**" if p < 0.01 else "*"


def _p_holm(r: Mapping[str, Any]) -> float | None:
    """A pair's deciding p in summary.json (``p_holm``; ``p_corr`` in a summary written
    before ``p_holm`` existed, which decided by it)."""
    p = r.get("p_holm", r.get("p_corr"))
    return None if p is None else float(p)


def significance_marks(summary: Mapping[str, Any] | None, metric: str,
                       names: Sequence[str]) -> list[tuple[str, str, str]]:
    """The pairs of ``metric`` that ``summary`` (summary.json's document) calls
    significant (``p_holm``, after a significant Friedman test), as (a, b, stars by
    ``p_holm``), for the approaches in ``names``; in summary.json's pair order."""
    if not summary:
        return []
    out = []
    for key, r in (summary.get("pairwise", {}).get(metric, {}) or {}).items():
        a, _, b = key.partition(" vs ")
        p = _p_holm(r)
        if a in names and b in names and r.get("significant") and p is not None:
            out.append((a, b, _stars(p)))
    return out


def short_name(strategy: str) -> str:
    """The approach's initials for a bracket's label: L, S, ME, M, CME."""
    name = APPROACH_NAMES.get(strategy, strategy)
    return "".join(w[0].upper() for w in name.replace("-", " ").split())


def higher_of(summary: Mapping[str, Any] | None, metric: str, a: str, b: str) -> str | None:
    """Which of the pair ``a``, ``b`` has the higher values of ``metric`` by summary.json's
    pair record: the sign of its rank-biserial r (positive: ``a``), else of its median
    paired difference a − b; None when neither says."""
    r = ((summary or {}).get("pairwise", {}).get(metric) or {}).get(f"{a} vs {b}") or {}
    for key in ("rank_biserial", "median_difference"):
        x = r.get(key)
        if x is not None and math.isfinite(float(x)) and float(x) != 0.0:
            return a if float(x) > 0.0 else b
    return None


def mark_label(summary: Mapping[str, Any] | None, metric: str, a: str, b: str,
               stars: str) -> str:
    """A bracket's text: the higher approach first, "L > S ***" (no direction known:
    "L – S ***")."""
    hi = higher_of(summary, metric, a, b)
    if hi is None:
        return f"{short_name(a)} – {short_name(b)} {stars}"
    lo = b if hi == a else a
    return f"{short_name(hi)} > {short_name(lo)} {stars}"


def _floor_text(users: int, pairs: int, method: str) -> str:
    how = (f"exact: {pairs} × 2/2^{users}" if method == "exact"
           else f"normal approximation: {pairs} × the tail at z = "
           f"{math.sqrt(3.0 * users * (users + 1) / (2.0 * (2 * users + 1))):.2f}")
    return f"{smallest_p_holm(users, pairs, method):.3g} ({how})"


def _boxplot_caption(n_users: int, names: Sequence[str], summary: Mapping[str, Any] | None,
                     marks: Sequence[tuple[str, str, str, str]], unfinished: int = 0) -> str:
    k = len(names)
    what = (f"The paper's Fig. 5 in simulation: one panel per metric, one box per approach "
            f"over n = {n_users} users (every user did every approach: {n_users} × {k} = "
            f"{n_users * k} executions{_setting(summary)}).")
    what += (" Thin grey lines join each user's values over the approaches (the tests are "
             "paired: a line's slope is that user's difference)."
             if n_users >= PAIRED_LINES_MIN else
             f" Grey dots: one per user (below {PAIRED_LINES_MIN} users dots, not lines).")
    paper = [s for s in names if s in PAPER_MEDIANS]
    if paper:
        what += (" Red diamonds: the paper's medians (its Tables I-III, measured with 27 "
                 "people on the real robot), at "
                 + ", ".join(APPROACH_NAMES.get(s, s) for s in paper) + ".")
    abbrev = ", ".join(f"{short_name(s)} = {APPROACH_NAMES.get(s, s)}" for s in names)
    if unfinished:
        what += (f" Red crosses: the {unfinished} unfinished executions (T_f where they "
                 "ended); their users are left out of the tests.")
    if not summary:
        return what + " No significance marks: drawn without summary.json."
    tested_n = int(summary.get("tested_users", n_users))
    excluded = len(summary.get("excluded_users") or [])
    if excluded:
        what += f" The tests: n = {tested_n} users ({excluded} unfinished excluded)."
    n_users = tested_n
    fams = {m: list((summary.get("pairwise", {}).get(m) or {}).values()) for m in METRICS}
    fams = {m: rs for m, rs in fams.items() if rs}
    methods = {m: str(rs[0].get("p_holm_method", "normal")) for m, rs in fams.items()}
    floors = {m: smallest_p_holm(n_users, len(rs), methods[m]) for m, rs in fams.items()}
    one = len(set(methods.values())) == 1 and len({len(rs) for rs in fams.values()}) == 1
    how = (f"two-sided Wilcoxon signed-rank, {P_METHODS[next(iter(methods.values()))]}, "
           f"Holm-corrected over the metric's {len(next(iter(fams.values())))} pairs"
           if one and fams else "two-sided Wilcoxon signed-rank, Holm-corrected")
    if fams and all(f >= ALPHA for f in floors.values()):
        m0 = next(iter(fams))
        floor = (_floor_text(n_users, len(fams[m0]), methods[m0]) if one else
                 ", ".join(f"{METRIC_LABELS[m]} {f:.3g}" for m, f in floors.items()))
        sig = (f" No brackets can appear: with n = {n_users} users the smallest p_holm "
               f"({how}) any pair can reach is {floor}, not below {ALPHA:g}.")
    else:
        sig = (f" Brackets: the pairs with p_holm < {ALPHA:g} ({how}), tested only after "
               f"a significant Friedman test of the metric, labelled with the direction "
               f"(\"L > S\": the first approach's values are the higher, by the sign of the "
               f"pair's rank-biserial r; {abbrev}) and stars * < 0.05, ** < 0.01, "
               f"*** < 0.001; "
               + ("no pair is significant in any panel." if not marks else
                  "a panel without a bracket has no significant pair."))
    cond = conditions_text(summary.get("conditions"))
    return what + sig + (" " + cond if cond else "")


def boxplots_figure(execs: Sequence[Execution], summary: Mapping[str, Any] | None = None
                    ) -> tuple[Any, list[tuple[str, str, str, str]]]:
    """Fig. 5, unsaved: one panel per metric, one box per approach; the median a black
    line on every box; each user's values joined by a thin grey line (gid
    :data:`USER_LINE_GID`, one per user) or, below :data:`PAIRED_LINES_MIN` users, a grey
    dot per user (gid :data:`USER_DOTS_GID`, one set per approach); the paper's median a
    red diamond per approach (gid :data:`PAPER_MEDIAN_GID`); unfinished executions a red
    cross; with ``summary`` (summary.json's document) a bracket over every pair it calls
    significant, labelled with the direction and stars ("L > S ***",
    :func:`mark_label`); a legend of these marks and a caption.  Returns the figure and
    the marks drawn: (metric, a, b, stars)."""
    plt = _pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    vals = values(execs)
    names = list(vals)
    users = sorted({e.user for e in execs})
    n_users = len(users)
    lines = n_users >= PAIRED_LINES_MIN
    unfinished = [e for e in execs if not e.completed]
    marks: list[tuple[str, str, str, str]] = []
    fliers = False
    paper_drawn = False
    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.1 * len(METRICS), 4.0))
    xs = np.arange(1, len(names) + 1, dtype=float)
    for ax, m in zip(axes, METRICS):
        data = [vals[s][m] for s in names]
        bp = ax.boxplot(data, patch_artist=True, widths=0.6,
                        medianprops={"color": "black", "linewidth": 2.2, "zorder": 4},
                        flierprops={"markersize": 4})
        fliers = fliers or any(len(f.get_xdata()) for f in bp["fliers"])
        for patch, c in zip(bp["boxes"], _COLOURS):
            patch.set_facecolor(c)
            patch.set_alpha(0.45)
        per_user = np.vstack(data).T if data else np.zeros((0, 0))  # (users, approaches)
        if lines:
            for row in per_user:
                ax.plot(xs, row, color="0.45", lw=0.5, alpha=0.6, zorder=3, gid=USER_LINE_GID)
        else:
            offs = np.linspace(-0.12, 0.12, n_users) if n_users > 1 else np.zeros(1)
            for j in range(len(names)):
                ax.plot(xs[j] + offs, per_user[:, j], ls="none", marker="o", ms=3.5,
                        mfc="0.35", mec="white", mew=0.4, zorder=5, gid=USER_DOTS_GID)
        for e in unfinished:
            ax.plot(xs[names.index(e.strategy)], e.metric(m), ls="none", marker="x",
                    color="tab:red", ms=6, mew=1.4, zorder=6, gid="unfinished")
        paper_y = [PAPER_MEDIANS[s][m] if m in PAPER_MEDIANS.get(s, {}) else math.nan
                   for s in names]
        if any(math.isfinite(y) for y in paper_y):
            ax.plot(xs, paper_y, ls="none", marker="D", ms=6.5, mfc="tab:red", mec="darkred",
                    mew=0.8, zorder=7, gid=PAPER_MEDIAN_GID)
            paper_drawn = True
        ax.set_xticks(xs)
        ax.set_xticklabels([APPROACH_NAMES.get(s, s).replace(" ", "\n") + f"\n({short_name(s)})"
                            for s in names], fontsize=8)
        ax.set_title(METRIC_LABELS[m])
        ax.grid(axis="y", alpha=0.3)
        pairs = significance_marks(summary, m, names)
        if pairs:
            finite = [float(y) for y in paper_y if math.isfinite(y)]
            lo = min([float(np.min(d)) for d in data] + finite)
            hi = max([float(np.max(d)) for d in data] + finite)
            span = (hi - lo) or max(abs(hi), 1.0) * 0.1
            step = 0.13 * span
            # narrow brackets below wide ones; each on a level of its own
            drawn = sorted(pairs, key=lambda t: (abs(names.index(t[1]) - names.index(t[0])),
                                                 min(names.index(t[0]), names.index(t[1]))))
            for level, (a, b, stars) in enumerate(drawn):
                x1, x2 = names.index(a) + 1, names.index(b) + 1
                y = hi + step * (0.5 + level)
                ax.plot([x1, x1, x2, x2], [y - 0.2 * step, y, y, y - 0.2 * step],
                        color="black", lw=0.9)
                ax.text(0.5 * (x1 + x2), y - 0.05 * step, mark_label(summary, m, a, b, stars),
                        ha="center", va="bottom", fontsize=7.5, gid="bracket-label")
            marks += [(m, a, b, stars) for a, b, stars in pairs]
            ax.set_ylim(top=hi + step * (0.9 + len(pairs)))
    fig.suptitle(f"Peg-in-hole study: {n_users} simulated users × {len(names)} approaches",
                 fontsize=10)
    handles = [Line2D([], [], color="black", lw=2.2, label="median"),
               Patch(facecolor="0.8", edgecolor="black", label="box: quartiles (middle half)"),
               Line2D([], [], color="black", lw=1.0,
                      label="whiskers: furthest user within 1.5 box heights of the box")]
    if fliers:
        handles.append(Line2D([], [], ls="none", marker="o", mfc="none", mec="black", ms=4,
                              label="a user beyond the whiskers"))
    handles.append(Line2D([], [], color="0.45", lw=0.8, label="one user's values (paired)")
                   if lines else
                   Line2D([], [], ls="none", marker="o", ms=3.5, mfc="0.35", mec="white",
                          label="one user"))
    if paper_drawn:
        handles.append(Line2D([], [], ls="none", marker="D", ms=6.5, mfc="tab:red",
                              mec="darkred", label=PAPER_MEDIAN_LABEL))
    if unfinished:
        handles.append(Line2D([], [], ls="none", marker="x", color="tab:red", ms=6, mew=1.4,
                              label="unfinished (its user left out of the tests)"))
    if marks:
        handles.append(Line2D([], [], color="black", lw=0.9,
                              label=f"bracket: p_holm < {ALPHA:g}, \"L > S\": L higher "
                              "(* < 0.05, ** < 0.01, *** < 0.001)"))
    rows = 1 if len(handles) <= 5 else 2
    band = _layout(fig, _boxplot_caption(n_users, names, summary, marks, len(unfinished)),
                   legend_rows=rows)
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, band),
               ncol=-(-len(handles) // rows), fontsize=7, frameon=False)
    return fig, marks


def boxplots(execs: Sequence[Execution], path: Path,
             summary: Mapping[str, Any] | None = None) -> list[tuple[str, str, str, str]]:
    """Fig. 5 (:func:`boxplots_figure`) into ``path``.  Returns the marks drawn:
    (metric, a, b, stars)."""
    fig, marks = boxplots_figure(execs, summary)
    _save(fig, path)
    _close(fig)
    return marks


def _shade_locomotion(ax: Any, e: Execution) -> bool:
    """Shade ``e``'s locomotion phases (gid "locomotion"); whether there were any."""
    loc = e.series.locomotion.astype(bool)
    if not loc.any():
        return False
    t = e.series.t
    edges = np.flatnonzero(np.diff(np.concatenate(([0], loc.astype(np.int8), [0]))))
    for a, b in zip(edges[::2], edges[1::2]):
        ax.axvspan(float(t[a]), float(t[min(b, len(t) - 1)]), color="0.85", zorder=0,
                   gid="locomotion")
    return True


def time_series_figure(execs: Sequence[Execution], user: int, what: str,
                       summary: Mapping[str, Any] | None = None) -> Any:
    """Fig. 6 (``what="speed"``) or Fig. 7 (``what="energy"``) for ``user``, unsaved,
    with a legend below the panels (the curve; the base's share; the switch approach's
    locomotion phases, when there are any) and a caption; ``summary`` (summary.json's
    document): the setting and conditions for the caption."""
    plt = _pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    names = strategies_of(execs)
    rows = {e.strategy: e for e in execs if e.user == user}
    fig, axes = plt.subplots(len(names), 1, figsize=(8.0, 1.9 * len(names) + 0.6), sharex=True,
                             squeeze=False)
    ymax = max(float(np.max(getattr(rows[s].series, what), initial=0.0)) for s in names)
    shaded = False
    for ax, s, c in zip(axes[:, 0], names, _COLOURS):
        e = rows[s]
        shaded = _shade_locomotion(ax, e) or shaded
        ax.plot(e.series.t, getattr(e.series, what), color=c, lw=0.9)
        if what == "energy":
            ax.fill_between(e.series.t, 0.0, e.series.energy_base, color=c, alpha=0.25, lw=0)
        ax.set_ylim(0.0, 1.05 * ymax if ymax > 0 else 1.0)
        ax.set_ylabel("‖v‖ [m/s]" if what == "speed" else "E_K [J]")
        ax.set_title(f"{APPROACH_NAMES.get(s, s)}  (T_f = {e.T_f:.1f} s)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("t [s]")
    title = "End-effector speed" if what == "speed" else "Total kinetic energy"
    fig.suptitle(f"{title}, median user #{user}")
    handles: list[Any] = [Line2D([], [], color=_COLOURS[0], lw=0.9, label=(
        "end-effector speed ‖v‖" if what == "speed" else "E_K, whole body")
        + " (in each panel its approach's colour)")]
    if what == "energy":
        handles.append(Patch(facecolor=_COLOURS[0], alpha=0.25, lw=0,
                             label="the base's share of E_K (filled)"))
    if shaded:
        handles.append(Patch(facecolor="0.85", label=LOCOMOTION_LABEL))
    n_users = len({e.user for e in execs})
    peak = max(float(np.max(rows[s].series.energy, initial=0.0)) for s in names)
    shown = ("The end-effector's linear speed ‖v(kT)‖ (the paper's Fig. 6)" if what == "speed"
             else "The whole-body kinetic energy E_K(kT) = ½ q̇ᵀ M q̇ (block-diagonal M; "
             "the paper's Fig. 7), the base's share filled")
    shade = (f"grey: {LOCOMOTION_LABEL}" if shaded else
             "no locomotion phase to shade for this user" if "switch" in names else "")
    caption = (f"{shown}, of the median user #{user}, one panel per approach"
               + (f"; {shade}" if shade else "") + ". The median user is the one most often "
               f"nearest the median over the approaches and the paper's five metrics, of "
               f"n = {n_users} users × {len(names)} approaches = {n_users * len(names)} "
               f"executions{_setting(summary)}. Peak E_K of these {len(names)} executions: "
               f"{peak:.3g} J." + (" " + PLAN_NOTE if what == "speed" else ""))
    cond = conditions_text((summary or {}).get("conditions"))
    band = _layout(fig, caption + (" " + cond if cond else ""),
                   legend_rows=1 if len(handles) <= 2 else 2)
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, band), ncol=2,
               fontsize=7, frameon=False)
    return fig


def time_series(execs: Sequence[Execution], user: int, path: Path, what: str,
                summary: Mapping[str, Any] | None = None) -> None:
    """Fig. 6 or 7 (:func:`time_series_figure`) into ``path``."""
    fig = time_series_figure(execs, user, what, summary)
    _save(fig, path)
    _close(fig)


def write_figures(execs: Sequence[Execution], user: int, out: Path,
                  summary: Mapping[str, Any] | None = None) -> list[Path]:
    """All three figures into ``out`` (the boxplots with ``summary``'s significance
    marks; its setting and conditions in every caption); returns their paths."""
    paths = [out / "boxplots.png", out / "velocity.png", out / "energy.png"]
    boxplots(execs, paths[0], summary)
    time_series(execs, user, paths[1], "speed", summary)
    time_series(execs, user, paths[2], "energy", summary)
    return paths


def sweep_figure(rows: Sequence[Any], meta: Mapping[str, Any] | None = None) -> Any:
    """The inertia-weighting sweep, unsaved (``rows``: :class:`mmctl.study.sweep.SweepRow`;
    ``meta``: users, seed, quick, task, conditions for the title and caption): left,
    median Ē against median x_f, one curve per projector through the base scales
    (labelled), the simulation's min-energy at the paper's setting (s = 1, dynamically
    consistent) starred, the coupled ablation as diamonds, the locomotion approach as a
    square, a setting that dominates the simulation's min-energy ringed, and the
    paper's *measured* min-energy point (Table III: x_f = 0.08 m, Ē = 0.86 J) as a red
    diamond, raw, and hollow at its ratio to the paper's locomotion (0.86/2.52 = 0.34)
    times the simulation's locomotion Ē, read on a right axis Ē / locomotion's Ē (when
    the sweep ran locomotion); right, the median fraction of samples on which a limit
    bound the command, against the scale (the paper reports none: no paper point).

    A grid over the null-space gain's magnitude at one scale (``gain_scale``) draws its
    curves along the gain instead (``G×g`` at their ends, the gain on the right panel's
    axis); a grid over both draws one curve per projector and gain."""
    plt = _pyplot()
    fig, (ax, axl) = plt.subplots(1, 2, figsize=(12.0, 4.8),
                                  gridspec_kw={"width_ratios": [1.6, 1.0]})
    plain = [r for r in rows if r.setting is not None and not r.setting.coupled]
    gains = {_gain(r.setting) for r in plain}
    by_gain = len(gains) > 1 and len({r.setting.base_scale for r in plain}) == 1

    def along(r: Any) -> float:
        return _gain(r.setting) if by_gain else float(r.setting.base_scale)

    def end_label(r: Any) -> str:
        return f"G×{_gain(r.setting):.2g}" if by_gain else f"s={r.setting.base_scale:.2g}"

    curves: dict[tuple[str, float], list[Any]] = {}
    for r in plain:
        other = float(r.setting.base_scale) if by_gain else _gain(r.setting)
        curves.setdefault((r.setting.projector, other), []).append(r)
    colours = {"dynamic": "tab:green", "euclidean": "tab:blue"}
    per_projector = max((sum(1 for k in curves if k[0] == pr) for pr in colours), default=1)
    cycle = iter(_COLOURS * 4)
    for (proj, other), rs in curves.items():
        rs = sorted(rs, key=along)
        c = colours.get(proj, "tab:gray") if per_projector == 1 else next(cycle)
        label = ("dynamically consistent  I − J_M# J" if proj == "dynamic"
                 else "ordinary  I − J# J")
        if by_gain:
            label += f", s = {other:g}, over G's magnitude"
        elif len(gains) > 1 or other != 1.0:
            label += f", G×{other:g}"
        ax.plot([r.x_f for r in rs], [r.E for r in rs], "o-", color=c, ms=4, lw=1.2,
                label=f"min-energy, {label}")
        held = [r for r in rs if math.isfinite(getattr(r, "x_f_hold", math.nan))]
        if held:  # the same settings after the end-of-trial hold: how far x_f recovers
            ax.plot([r.x_f_hold for r in held], [r.E for r in held], "o--", color=c, ms=4,
                    mfc="none", lw=0.8, alpha=0.8, label=f"  the same after the hold ({proj})")
        for r in (rs[0], rs[-1]) if len(rs) > 1 else rs:  # the ends: which way s grows
            ax.annotate(end_label(r), (r.x_f, r.E),
                        textcoords="offset points", xytext=(5, 4), fontsize=7, color=c)
        axl.plot([along(r) for r in rs], [100 * r.limited for r in rs], "o-",
                 color=c, ms=4, lw=1.2, label=proj if per_projector == 1 else f"{proj} {other:g}")
    ringed = False
    for r in rows:
        s = r.setting
        if s is None:
            ax.plot(r.x_f, r.E, "s", color="tab:red", ms=8, label="locomotion")
            axl.axhline(100 * r.limited, color="tab:red", ls="--", lw=1, label="locomotion")
        elif s.coupled:
            c = colours.get(s.projector, "tab:gray")
            ax.plot(r.x_f, r.E, "D", color=c, mfc="none", ms=8, mew=1.5,
                    label=f"coupled M, s = 1, {s.projector}")
            axl.plot(along(r), 100 * r.limited, "D", color=c, mfc="none", ms=8, mew=1.5,
                     label=f"coupled, {s.projector}")
        elif s.paper:
            ax.plot(r.x_f, r.E, "*", color="black", ms=15, zorder=5, label=SIM_POINT_LABEL)
        if s is not None and r.dominates:
            ax.plot(r.x_f, r.E, "o", mfc="none", mec="gold", ms=13, mew=2, zorder=6,
                    label="_nolegend_" if ringed else "dominates the simulation's "
                    "min-energy (lower median Ē and x_f than s = 1)")
            ringed = True
    loco = next((r for r in rows if r.setting is None and r.E > 0), None)
    _paper_points(ax, float(loco.E) if loco is not None else math.nan)
    ax.set_xlabel("median x_f [m]")
    ax.set_ylabel("median Ē [J]")
    ax.set_title("Ē–x_f over the null-space gain's magnitude G×g" if by_gain
                 else "Ē–x_f over the base's weight s·M_b in the IDK", fontsize=10)
    ax.grid(alpha=0.3)
    axl.set_xscale("log")
    axl.set_xlabel("gain scale g on the paper's G" if by_gain else "base weight scale s")
    axl.set_ylabel("samples with a limit active [%] (median user)")
    axl.set_title("How often the limits bind", fontsize=10)
    axl.grid(alpha=0.3)
    axl.legend(fontsize=7, loc="best")
    n = _sweep_header(fig, "Inertia-weighting sweep", rows, meta)
    caption = ("Left: each point the medians over the users of one setting of the min-energy "
               "IDK, the base's inertia weighted s·M_b in its solution (Ē is measured with "
               "the true block-diagonal M throughout), with the dynamically consistent or "
               "the ordinary null-space projector; dashed, hollow: the same settings' x_f "
               "after the end-of-trial hold. Black star: the simulation's min-energy at the "
               "paper's setting (s = 1, dynamic, block-diagonal M), not the paper's "
               "result. Red diamond: the paper's measured min-energy (its Table III, 27 "
               f"people on the real robot: x_f = {PAPER_MIN_ENERGY_XF:g} m, Ē = "
               f"{PAPER_MIN_ENERGY_E:g} J); hollow red diamond: the same point relative to "
               f"the paper's locomotion (Ē {PAPER_MIN_ENERGY_E:g}/{PAPER_LOCOMOTION_E:g} = "
               f"{PAPER_MIN_ENERGY_E / PAPER_LOCOMOTION_E:.2f}×), drawn at that multiple of "
               "the simulation's locomotion Ē and read on the right axis (Ē / the "
               "simulation's locomotion Ē), which compares the energy saving rather than "
               "the robots' absolute energies. Right: the median user's share of samples on "
               f"which a limit bound the command (the paper reports none). {n}.")
    if len(gains) > 1 or gains - {1.0}:
        caption += (" The null-space gain G = g·diag(1, 1, 1, 1, 1, 1, 0, 0, 0) [1/s] (the "
                    "paper's: g = 1) in the min-energy settings; locomotion keeps the "
                    "paper's G." + (" Curves run along g at the one scale s." if by_gain
                                    else ""))
    _caption_and_legend(fig, ax, caption, meta)
    return fig


def _paper_points(ax: Any, e_loc: float) -> None:
    """The paper's measured min-energy point on the Ē–x_f axes: raw, and (``e_loc``
    finite: the simulation's locomotion Ē) at the paper's ratio to its own locomotion,
    read on a right axis in multiples of the simulation's locomotion Ē."""
    ax.plot(PAPER_MIN_ENERGY_XF, PAPER_MIN_ENERGY_E, "D", mfc="tab:red", mec="darkred",
            ms=8, zorder=7, gid="paper-point", label=PAPER_POINT_LABEL)
    if not math.isfinite(e_loc):
        return
    ratio = PAPER_MIN_ENERGY_E / PAPER_LOCOMOTION_E
    ax.plot(PAPER_MIN_ENERGY_XF, ratio * e_loc, "D", mfc="none", mec="tab:red", mew=1.6,
            ms=8, zorder=7, gid="paper-point-relative", label=PAPER_POINT_REL_LABEL)
    sec = ax.secondary_yaxis("right", functions=(lambda e: e / e_loc, lambda q: q * e_loc))
    sec.set_ylabel("median Ē / the simulation's locomotion Ē", fontsize=8)
    sec.tick_params(labelsize=7)


def _caption_and_legend(fig: Any, ax: Any, caption: str,
                        meta: Mapping[str, Any] | None) -> None:
    """A sweep figure's caption (with the study's conditions) and, above it, the left
    panel's legend in two columns under the panels (its entries would hide the curves)."""
    cond = conditions_text((meta or {}).get("conditions"))
    handles, labels = ax.get_legend_handles_labels()
    band = _layout(fig, caption + (" " + cond if cond else ""),
                   legend_rows=-(-len(handles) // 2))
    fig.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.01, band), ncol=2,
               fontsize=7, frameon=False)


def _sweep_header(fig: Any, title: str, rows: Sequence[Any],
                  meta: Mapping[str, Any] | None) -> str:
    """A sweep figure's title (users, seed, task) and its caption's count of settings,
    users and executions."""
    users = (meta or {}).get("users")
    if meta:
        fig.suptitle(f"{title}: {users} users, seed {meta.get('seed')}, "
                     f"{'quick' if meta.get('quick') else 'full'} task", fontsize=10)
    if users is None:
        return f"{len(rows)} settings; n (users) not given"
    return (f"n = {users} users: {len(rows)} settings (locomotion included) × {users} users "
            f"= {len(rows) * int(users)} executions{_setting(meta)}")


def sweep_curve(rows: Sequence[Any], path: Path, meta: Mapping[str, Any] | None = None) -> None:
    """The inertia-weighting sweep (:func:`sweep_figure`) into ``path``."""
    fig = sweep_figure(rows, meta)
    _save(fig, path)
    _close(fig)


def _gain(setting: Any) -> float:
    return float(getattr(setting, "gain_scale", 1.0))


#: The legend label of the paper's x_f in sweep-gain.png's right panel.
PAPER_XF_LABEL = f"paper's min-energy x_f = {PAPER_MIN_ENERGY_XF:g} m (read at T_f)"


def gain_read_figure(rows: Sequence[Any], meta: Mapping[str, Any] | None = None,
                     hold_time: float | None = None) -> Any:
    """A sweep over the null-space gain's magnitude, unsaved (``rows``:
    :class:`mmctl.study.sweep.SweepRow` with ``x_f_after``; ``meta`` as for
    :func:`sweep_figure`; ``hold_time`` [s]: when the hold ends after T_f, default
    the study's :data:`~mmctl.study.users.HOLD_TIME`).

    Left: median Ē against median x_f read at T_f, at each of :data:`X_F_DELAYS` after
    it and at the hold's end, one curve per read time through the gains (of the
    block-diagonal min-energy settings at one base scale and projector: the projector
    sets the line style), the gains written at the T_f curve, locomotion's point, and
    the paper's measured min-energy raw and at its ratio to its locomotion times the
    simulation's locomotion Ē (right axis: Ē / the simulation's locomotion Ē, as in
    sweep.png).  Right: median x_f against the time it is read after T_f, one line per
    setting (labelled with its Ē / locomotion's Ē), the paper's x_f as a red line."""
    from mmctl.study.users import HOLD_TIME

    plt = _pyplot()
    from matplotlib import colormaps

    hold = HOLD_TIME if hold_time is None else float(hold_time)
    fig, (ax, axr) = plt.subplots(1, 2, figsize=(12.0, 4.8),
                                  gridspec_kw={"width_ratios": [1.4, 1.0]})
    reads = ["T_f", *(f"T_f + {d:g} s" for d in X_F_DELAYS), f"hold's end (T_f + {hold:g} s)"]
    times = [0.0, *X_F_DELAYS, hold]

    def xs(r: Any) -> list[float]:
        after = list(getattr(r, "x_f_after", ()))
        after += [math.nan] * (len(X_F_DELAYS) - len(after))
        return [r.x_f, *after[: len(X_F_DELAYS)], getattr(r, "x_f_hold", math.nan)]

    loco = next((r for r in rows if r.setting is None and r.E > 0), None)
    e_loc = float(loco.E) if loco is not None else math.nan
    groups: dict[tuple[str, float], list[Any]] = {}
    for r in rows:
        if r.setting is not None and not r.setting.coupled:
            groups.setdefault((r.setting.projector, float(r.setting.base_scale)), []).append(r)
    styles = {"dynamic": "-", "euclidean": "--"}
    read_colours = [colormaps["viridis"](i / max(len(reads) - 1, 1)) for i in range(len(reads))]
    all_rs = [r for rs in groups.values() for r in rs]
    gain_cmap = colormaps["plasma"]
    g_all = sorted({_gain(r.setting) for r in all_rs}) or [1.0]
    lg = [math.log(g) for g in g_all]

    def g_colour(g: float) -> Any:
        span = (lg[-1] - lg[0]) or 1.0
        return gain_cmap(0.85 * (math.log(g) - lg[0]) / span)

    for (proj, scale), rs in groups.items():
        rs = sorted(rs, key=lambda r: _gain(r.setting))
        ls = styles.get(proj, ":")
        name = f"{proj}, s = {scale:g}"
        for i, read in enumerate(reads):
            pts = [(xs(r)[i], r.E) for r in rs]
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o", ls=ls, color=read_colours[i],
                    ms=4, lw=1.1, label=f"x_f read at {read} ({name})")
        for r in rs:  # the gains along the T_f curve
            ax.annotate(f"G×{_gain(r.setting):g}", (r.x_f, r.E), textcoords="offset points",
                        xytext=(5, 3), fontsize=7, color="0.25")
            rel = f"Ē {r.E / e_loc:.2f}× loc." if math.isfinite(e_loc) else f"Ē {r.E:.2f} J"
            axr.plot(times, xs(r), "o", ls=ls, color=g_colour(_gain(r.setting)), ms=4, lw=1.1,
                     label=f"{proj} G×{_gain(r.setting):g} ({rel})")
    if loco is not None:
        ax.plot(loco.x_f, loco.E, "s", color="tab:red", ms=8, label="locomotion (x_f at T_f)")
        axr.plot(times, xs(loco), "s", ls=":", color="tab:red", ms=5, lw=1,
                 label="locomotion (paper's G)")
    _paper_points(ax, e_loc)
    axr.axhline(PAPER_MIN_ENERGY_XF, color="tab:red", lw=1.2, gid="paper-x-f",
                label=PAPER_XF_LABEL)
    ax.set_xlabel("median x_f [m], read at the time the colour gives")
    ax.set_ylabel("median Ē [J] (over 0..T_f)")
    ax.set_title("Ē–x_f over the null-space gain G×g, x_f read at T_f and later", fontsize=10)
    ax.grid(alpha=0.3)
    axr.set_xlabel("time after T_f at which x_f is read [s] (the hold ends at "
                   f"{hold:g} s)")
    axr.set_ylabel("median x_f [m]")
    axr.set_title("x_f against the time it is read", fontsize=10)
    # room above the lines for the legend (two columns), which would hide them
    top = max((x for r in rows for x in xs(r) if math.isfinite(x)), default=PAPER_MIN_ENERGY_XF)
    axr.set_ylim(0.0, 1.45 * max(top, PAPER_MIN_ENERGY_XF))
    axr.grid(alpha=0.3)
    axr.legend(fontsize=6, loc="upper right", ncol=2)
    n = _sweep_header(fig, "Null-space gain and read time", rows, meta)
    caption = ("Left: each point the medians over the users of one min-energy setting, the "
               "arm's null-space gain G = g·diag(1, 1, 1, 1, 1, 1, 0, 0, 0) [1/s] (the "
               "paper's: g = 1; written along the T_f curve), Ē over 0..T_f as the paper "
               "defines it, x_f = ||p − p_des|| of the handle relative to the base read at "
               "T_f (the paper's definition) or later, during the end-of-trial hold in "
               "which the person keeps the peg in the last hole and the robot runs on "
               "(colour: when it is read). Red diamond: the paper's measured min-energy "
               f"(Table III: x_f = {PAPER_MIN_ENERGY_XF:g} m, Ē = {PAPER_MIN_ENERGY_E:g} J); "
               f"hollow: at the paper's ratio to its locomotion ({PAPER_MIN_ENERGY_E:g}/"
               f"{PAPER_LOCOMOTION_E:g} = {PAPER_MIN_ENERGY_E / PAPER_LOCOMOTION_E:.2f}×) "
               "times the simulation's locomotion Ē, read on the right axis. Right: the same "
               "x_f against the time it is read, one line per setting; red: the paper's "
               f"x_f. Locomotion keeps the paper's G. {n}.")
    _caption_and_legend(fig, ax, caption, meta)
    return fig


def gain_read_curve(rows: Sequence[Any], path: Path,
                    meta: Mapping[str, Any] | None = None) -> None:
    """The gain and read-time figure (:func:`gain_read_figure`) into ``path``."""
    fig = gain_read_figure(rows, meta)
    _save(fig, path)
    _close(fig)


def sensitivity_caption(doc: Mapping[str, Any]) -> str:
    """The sensitivity chart's caption from sensitivity.json's document (with the
    ``users``, ``points_n``, ``strategies``, ``r_crit`` and ``conditions`` that `mmctl
    study sensitivity` records)."""
    users, points = doc.get("users"), doc.get("points_n", len(doc.get("points", [])))
    k = len(doc.get("strategies") or ()) or 3
    claims = doc.get("claims", [])
    n = (f"n = {users} users per point: {points} Morris points × {users} users × {k} "
         f"approaches = {int(points) * int(users) * k} executions" if users and points
         else "n (users) not recorded")
    r_crit = doc.get("r_crit")
    held = (f"; a claim holds at a point where the rank-biserial r of its users' paired "
            f"differences meets r_crit = {float(r_crit):.3f}" if r_crit is not None else "")
    caption = (f"Morris screening of the paper's {len(claims)} claims, one panel each, over "
               f"{len(doc.get('factors', []))} factors ({n}{_setting(doc)}){held}. Bars: "
               "μ*, the mean |elementary effect| of the factor on the claim's median paired "
               "difference, relative to the panel's largest.")
    cond = conditions_text(doc.get("conditions"))
    return caption + (" " + cond if cond else "")


def sensitivity_figure(claims: Sequence[Mapping[str, Any]], title: str = "",
                       caption: str | None = None) -> Any:
    """Morris screening, unsaved: one panel per conclusion, the factors ranked by μ*
    (bars, normalised to the panel's largest; σ as a black tick), the bars coloured by
    the share of the Morris points at which the conclusion holds (colour bar), and at
    the panel's right edge one square per level of the factor (low to high): filled
    where the conclusion holds at most of that level's points; a legend of these marks
    and ``caption`` (:func:`sensitivity_caption`; without one, a note that n is not
    known) at the bottom.

    ``claims``: one mapping per conclusion with ``claim`` (text) and ``factors`` (a list
    of mappings with ``name``, ``mu_star``, ``sigma``, ``holds`` in [0, 1] and
    optionally ``holds_by_level``: [value, held, points] per level)."""
    plt = _pyplot()
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    cmap = colormaps["RdYlGn"]
    n = len(claims)
    cols = 3 if n >= 3 else max(n, 1)
    nrows = max(1, -(-n // cols))
    k = max((len(c["factors"]) for c in claims), default=1)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 0.22 * k * nrows + 1.2 * nrows + 0.4),
                             squeeze=False)
    for ax, c in zip(axes.ravel(), claims):
        fs = sorted(c["factors"], key=lambda f: f["mu_star"])
        top = max((f["mu_star"] for f in fs), default=0.0) or 1.0
        y = np.arange(len(fs))
        ax.barh(y, [f["mu_star"] / top for f in fs], color=[cmap(f["holds"]) for f in fs],
                edgecolor="0.3", lw=0.5)
        ax.plot([f["sigma"] / top for f in fs], y, "|", color="black", ms=8)
        for yi, f in zip(y, fs):  # where in its range: one square per level, low -> high
            lv = f.get("holds_by_level") or []
            marks = "".join("■" if n and h / n >= 0.5 else "□" for _v, h, n in lv)
            ax.text(1.0, yi, marks, transform=ax.get_yaxis_transform(), ha="right",
                    va="center", fontsize=6, color="0.2")
        ax.set_yticks(y)
        ax.set_yticklabels([f["name"] for f in fs], fontsize=7)
        # room at the right for the per-level squares
        ax.set_xlim(0.0, max(1.35, max((f["sigma"] / top for f in fs), default=0.0) * 1.1))
        ax.set_title(str(c["claim"]), fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
        ax.grid(axis="x", alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=9)
    if caption is None:
        caption = (f"Morris screening of {n} claims; n (users, executions) not given to the "
                   "chart: see sensitivity.json.")
    handles = [
        Patch(facecolor="0.75", edgecolor="0.3", lw=0.5,
              label="bar: μ* / the panel's largest μ* (colour: share of points where the "
              "claim holds, scale at right)"),
        Line2D([], [], ls="none", marker="|", color="black", ms=8,
               label="σ / the panel's largest μ* (how much the effect depends on the "
               "other factors)"),
        Line2D([], [], ls="none", marker="s", color="0.2", ms=5,
               label="right edge, one per level of the factor (low → high): the claim "
               "holds at most of its points"),
        Line2D([], [], ls="none", marker="s", mfc="none", mec="0.2", ms=5,
               label="... it does not"),
    ]
    band = _layout(fig, caption, legend_rows=2, top_in=0.15 if title else 0.0)
    fig.legend(handles=handles, loc="lower left", bbox_to_anchor=(0.01, band), ncol=2,
               fontsize=7, frameon=False)
    h = float(fig.get_figheight())
    cax = fig.add_axes((0.74, band + 0.14 / h, 0.22, 0.09 / h))
    bar = fig.colorbar(ScalarMappable(norm=Normalize(0.0, 1.0), cmap=cmap), cax=cax,
                       orientation="horizontal")
    bar.set_label("bar colour: share of the points where the claim holds", fontsize=7)
    cax.xaxis.set_label_position("top")
    bar.ax.tick_params(labelsize=6)
    return fig


def sensitivity_chart(claims: Sequence[Mapping[str, Any]], path: Path,
                      title: str = "", caption: str | None = None) -> None:
    """The Morris screening's chart (:func:`sensitivity_figure`) into ``path``."""
    fig = sensitivity_figure(claims, title, caption)
    _save(fig, path)
    _close(fig)


def write_sensitivity_figure(doc: Mapping[str, Any], path: Path) -> Path:
    """sensitivity.png from sensitivity.json's document (``doc``), its title and caption
    from what the document records; returns ``path``.  Also redraws a chart from a
    stored sensitivity.json."""
    title = (f"Morris screening: {doc.get('trajectories')} trajectories, "
             f"{doc.get('users')} users per point, seed {doc.get('seed')}")
    sensitivity_chart(doc["claims"], path, title, sensitivity_caption(doc))
    return path
