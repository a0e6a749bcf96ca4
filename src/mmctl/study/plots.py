"""Figures of the study (matplotlib, Agg backend, imported on use).

* ``boxplots.png`` — the five metrics over the users, one box per approach (paper Fig. 5),
  the median a black line on every box, brackets with stars over the pairs summary.json
  calls significant;
* ``velocity.png`` — ||v(kT)|| of the median user, one panel per approach (Fig. 6);
* ``energy.png`` — E_K(kT) of the median user, base share shaded (Fig. 7).

In the switch panels, locomotion phases are shaded.  The analyses' figures:

* ``sweep.png`` — the inertia-weighting sweep's Ē–x_f curves and limit-active fractions
  (:func:`sweep_curve`, `mmctl study sweep`);
* ``sensitivity.png`` — the Morris screening's μ* ranking per conclusion
  (:func:`sensitivity_chart`, `mmctl study sensitivity`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mmctl.study.report import strategies_of, values
from mmctl.study.results import APPROACH_NAMES, METRIC_LABELS, METRICS, Execution

_COLOURS = ("tab:red", "tab:orange", "tab:green", "tab:blue", "tab:purple")


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


def _stars(p: float) -> str:
    """Significance stars of a Holm-corrected p-value: * < 0.05, ** < 0.01, *** < 0.001."""
    return "***" if p < 0.001 else "**" if p < 0.01 else "*"


def significance_marks(summary: Mapping[str, Any] | None, metric: str,
                       names: Sequence[str]) -> list[tuple[str, str, str]]:
    """The pairs of ``metric`` that ``summary`` (summary.json's document) calls
    significant (Holm-corrected, after a significant Friedman test), as (a, b, stars),
    for the approaches in ``names``; in summary.json's pair order."""
    if not summary:
        return []
    out = []
    for key, r in (summary.get("pairwise", {}).get(metric, {}) or {}).items():
        a, _, b = key.partition(" vs ")
        if a in names and b in names and r.get("significant") and r.get("p_corr") is not None:
            out.append((a, b, _stars(float(r["p_corr"]))))
    return out


def boxplots(execs: Sequence[Execution], path: Path,
             summary: Mapping[str, Any] | None = None) -> list[tuple[str, str, str, str]]:
    """Fig. 5: one panel per metric, one box per approach; the median a black line on
    every box; with ``summary`` (summary.json's document) a bracket with stars over
    every pair it calls significant.  Returns the marks drawn: (metric, a, b, stars)."""
    plt = _pyplot()
    vals = values(execs)
    names = list(vals)
    marks: list[tuple[str, str, str, str]] = []
    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.1 * len(METRICS), 4.0))
    for ax, m in zip(axes, METRICS):
        data = [vals[s][m] for s in names]
        bp = ax.boxplot(data, patch_artist=True, widths=0.6,
                        medianprops={"color": "black", "linewidth": 2.2, "zorder": 4},
                        flierprops={"markersize": 4})
        for patch, c in zip(bp["boxes"], _COLOURS):
            patch.set_facecolor(c)
            patch.set_alpha(0.45)
        ax.set_xticks(range(1, len(names) + 1))
        ax.set_xticklabels([APPROACH_NAMES.get(s, s).replace(" ", "\n") for s in names],
                           fontsize=8)
        ax.set_title(METRIC_LABELS[m])
        ax.grid(axis="y", alpha=0.3)
        pairs = significance_marks(summary, m, names)
        if pairs:
            lo = min(float(np.min(d)) for d in data)
            hi = max(float(np.max(d)) for d in data)
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
                ax.text(0.5 * (x1 + x2), y - 0.05 * step, stars, ha="center", va="bottom",
                        fontsize=9)
            marks += [(m, a, b, stars) for a, b, stars in pairs]
            ax.set_ylim(top=hi + step * (0.9 + len(pairs)))
    n_users = len(next(iter(vals.values()))["E"]) if vals else 0
    note = ("  (brackets: Wilcoxon, Holm-corrected, after a significant Friedman test; "
            "* p < 0.05, ** < 0.01, *** < 0.001)" if summary else "")
    fig.suptitle(f"Peg-in-hole study, {n_users} simulated users{note}", fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return marks


def _shade_locomotion(ax: Any, e: Execution) -> None:
    loc = e.series.locomotion.astype(bool)
    if not loc.any():
        return
    t = e.series.t
    edges = np.flatnonzero(np.diff(np.concatenate(([0], loc.astype(np.int8), [0]))))
    for a, b in zip(edges[::2], edges[1::2]):
        ax.axvspan(float(t[a]), float(t[min(b, len(t) - 1)]), color="0.85", zorder=0)


def time_series(execs: Sequence[Execution], user: int, path: Path, what: str) -> None:
    """Fig. 6 (``what="speed"``) or Fig. 7 (``what="energy"``) for ``user``."""
    plt = _pyplot()
    names = strategies_of(execs)
    rows = {e.strategy: e for e in execs if e.user == user}
    fig, axes = plt.subplots(len(names), 1, figsize=(8.0, 1.9 * len(names) + 0.6), sharex=True,
                             squeeze=False)
    ymax = max(float(np.max(getattr(rows[s].series, what), initial=0.0)) for s in names)
    for ax, s, c in zip(axes[:, 0], names, _COLOURS):
        e = rows[s]
        _shade_locomotion(ax, e)
        ax.plot(e.series.t, getattr(e.series, what), color=c, lw=0.9)
        if what == "energy":
            ax.fill_between(e.series.t, 0.0, e.series.energy_base, color=c, alpha=0.25, lw=0,
                            label="base share")
            ax.legend(loc="upper right", fontsize=7)
        ax.set_ylim(0.0, 1.05 * ymax if ymax > 0 else 1.0)
        ax.set_ylabel("‖v‖ [m/s]" if what == "speed" else "E_K [J]")
        ax.set_title(f"{APPROACH_NAMES.get(s, s)}  (T_f = {e.T_f:.1f} s)", fontsize=9)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("t [s]")
    title = "End-effector speed" if what == "speed" else "Total kinetic energy"
    fig.suptitle(f"{title}, median user #{user}")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def write_figures(execs: Sequence[Execution], user: int, out: Path,
                  summary: Mapping[str, Any] | None = None) -> list[Path]:
    """All three figures into ``out`` (the boxplots with ``summary``'s significance
    marks); returns their paths."""
    paths = [out / "boxplots.png", out / "velocity.png", out / "energy.png"]
    boxplots(execs, paths[0], summary)
    time_series(execs, user, paths[1], "speed")
    time_series(execs, user, paths[2], "energy")
    return paths


def sweep_curve(rows: Sequence[Any], path: Path, meta: Mapping[str, Any] | None = None) -> None:
    """The inertia-weighting sweep (``rows``: :class:`mmctl.study.sweep.SweepRow`): left,
    median Ē against median x_f, one curve per projector through the base scales
    (labelled), the paper's point (s = 1, dynamically consistent) starred, the coupled
    ablation as diamonds and the locomotion approach as a square; right, the median
    fraction of samples on which a limit bound the command, against the scale."""
    plt = _pyplot()
    fig, (ax, axl) = plt.subplots(1, 2, figsize=(12.0, 4.8),
                                  gridspec_kw={"width_ratios": [1.6, 1.0]})
    curves: dict[str, list[Any]] = {}
    for r in rows:
        if r.setting is not None and not r.setting.coupled:
            curves.setdefault(r.setting.projector, []).append(r)
    colours = {"dynamic": "tab:green", "euclidean": "tab:blue"}
    for proj, rs in curves.items():
        rs = sorted(rs, key=lambda r: r.setting.base_scale)
        c = colours.get(proj, "tab:gray")
        label = ("dynamically consistent  I − J_M# J" if proj == "dynamic"
                 else "ordinary  I − J# J")
        ax.plot([r.x_f for r in rs], [r.E for r in rs], "o-", color=c, ms=4, lw=1.2,
                label=f"min-energy, {label}")
        held = [r for r in rs if math.isfinite(getattr(r, "x_f_hold", math.nan))]
        if held:  # the same settings after the end-of-trial hold: how far x_f recovers
            ax.plot([r.x_f_hold for r in held], [r.E for r in held], "o--", color=c, ms=4,
                    mfc="none", lw=0.8, alpha=0.8, label=f"  the same after the hold ({proj})")
        for r in (rs[0], rs[-1]) if len(rs) > 1 else rs:  # the ends: which way s grows
            ax.annotate(f"s={r.setting.base_scale:.2g}", (r.x_f, r.E),
                        textcoords="offset points", xytext=(5, 4), fontsize=7, color=c)
        axl.plot([r.setting.base_scale for r in rs], [100 * r.limited for r in rs], "o-",
                 color=c, ms=4, lw=1.2, label=proj)
    for r in rows:
        s = r.setting
        if s is None:
            ax.plot(r.x_f, r.E, "s", color="tab:red", ms=8, label="locomotion")
            axl.axhline(100 * r.limited, color="tab:red", ls="--", lw=1, label="locomotion")
        elif s.coupled:
            c = colours.get(s.projector, "tab:gray")
            ax.plot(r.x_f, r.E, "D", color=c, mfc="none", ms=8, mew=1.5,
                    label=f"coupled M, s = 1, {s.projector}")
            axl.plot(s.base_scale, 100 * r.limited, "D", color=c, mfc="none", ms=8, mew=1.5,
                     label=f"coupled, {s.projector}")
        elif s.paper:
            ax.plot(r.x_f, r.E, "*", color="black", ms=15, zorder=5,
                    label="the paper's min-energy (s = 1, dynamic)")
        if s is not None and r.dominates:
            ax.plot(r.x_f, r.E, "o", mfc="none", mec="gold", ms=13, mew=2, zorder=6)
    ax.set_xlabel("median x_f [m]")
    ax.set_ylabel("median Ē [J]")
    ax.set_title("Ē–x_f over the base's weight s·M_b in the IDK", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    axl.set_xscale("log")
    axl.set_xlabel("base weight scale s")
    axl.set_ylabel("samples with a limit active [%] (median user)")
    axl.set_title("How often the limits bind", fontsize=10)
    axl.grid(alpha=0.3)
    axl.legend(fontsize=7, loc="best")
    if meta:
        fig.suptitle(f"Inertia-weighting sweep: {meta.get('users')} users, seed "
                     f"{meta.get('seed')}, {'quick' if meta.get('quick') else 'full'} task",
                     fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def sensitivity_chart(claims: Sequence[Mapping[str, Any]], path: Path,
                      title: str = "") -> None:
    """Morris screening: one panel per conclusion, the factors ranked by μ* (bars,
    normalised to the panel's largest; σ as a black tick), the bars coloured by the
    share of the Morris points at which the conclusion holds, and at the panel's right
    edge one square per level of the factor (low to high): filled where the conclusion
    holds at most of that level's points.

    ``claims``: one mapping per conclusion with ``claim`` (text) and ``factors`` (a list
    of mappings with ``name``, ``mu_star``, ``sigma``, ``holds`` in [0, 1] and
    optionally ``holds_by_level``: [value, held, points] per level)."""
    plt = _pyplot()
    from matplotlib import colormaps

    cmap = colormaps["RdYlGn"]
    n = len(claims)
    cols = 3 if n >= 3 else max(n, 1)
    nrows = max(1, -(-n // cols))
    k = max((len(c["factors"]) for c in claims), default=1)
    fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 0.22 * k * nrows + 1.2 * nrows + 0.8),
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
    text = ((title + "\n" if title else "") + "μ* / max μ* (bars), σ / max μ* (ticks); "
            "colour: share of points where the conclusion holds (red 0 → green 1)\n"
            "■/□ per level of the factor, low → high: holds / not at most points")
    fig.suptitle(text, fontsize=9)
    # the panels below the title's lines (tight_layout alone let them overlap)
    top = 1.0 - (0.17 * (text.count("\n") + 1) + 0.15) / fig.get_figheight()
    fig.tight_layout(rect=(0.0, 0.0, 1.0, top))
    _save(fig, path)
    plt.close(fig)
