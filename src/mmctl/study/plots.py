"""Figures of the study (matplotlib, Agg backend, imported on use).

* ``boxplots.png`` — the five metrics over the users, one box per approach (paper Fig. 5);
* ``velocity.png`` — ||v(kT)|| of the median user, one panel per approach (Fig. 6);
* ``energy.png`` — E_K(kT) of the median user, base share shaded (Fig. 7).

In the switch panels, locomotion phases are shaded.
"""

from __future__ import annotations

from collections.abc import Sequence
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


def boxplots(execs: Sequence[Execution], path: Path) -> None:
    """Fig. 5: one panel per metric, one box per approach."""
    plt = _pyplot()
    vals = values(execs)
    names = list(vals)
    fig, axes = plt.subplots(1, len(METRICS), figsize=(3.0 * len(METRICS), 3.6))
    for ax, m in zip(axes, METRICS):
        data = [vals[s][m] for s in names]
        bp = ax.boxplot(data, patch_artist=True, widths=0.6)
        for patch, c in zip(bp["boxes"], _COLOURS):
            patch.set_facecolor(c)
            patch.set_alpha(0.45)
        ax.set_xticks(range(1, len(names) + 1))
        ax.set_xticklabels([APPROACH_NAMES.get(s, s).replace(" ", "\n") for s in names],
                           fontsize=8)
        ax.set_title(METRIC_LABELS[m])
        ax.grid(axis="y", alpha=0.3)
    n_users = len(next(iter(vals.values()))["E"]) if vals else 0
    fig.suptitle(f"Peg-in-hole study, {n_users} simulated users")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


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


def write_figures(execs: Sequence[Execution], user: int, out: Path) -> list[Path]:
    """All three figures into ``out``; returns their paths."""
    paths = [out / "boxplots.png", out / "velocity.png", out / "energy.png"]
    boxplots(execs, paths[0])
    time_series(execs, user, paths[1], "speed")
    time_series(execs, user, paths[2], "energy")
    return paths
