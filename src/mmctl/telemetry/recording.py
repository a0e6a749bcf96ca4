"""Read an mmctl ``.rrd`` recording back with rerun's own API, recompute trial metrics.

``rerun.chunk.RrdReader(path).stream().collect()`` loads the file into a
``ChunkStore``; its ``reader(index=...)`` is rerun's dataframe API (a DataFusion
DataFrame with one row per index value and one column per entity component).  The
full-rate series (E_K, ‖f_h‖, speeds, p, p_des) are read on the ``cycle`` timeline and
sliced by each trial's bracket; the metrics use the same function as the daemon
(:func:`mmctl.telemetry.trial.compute`).  rerun is imported only when reading.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.errors import MmctlError
from mmctl.telemetry import layout
from mmctl.telemetry.trial import BRACKET, TrialResult, compute

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class RecordingError(MmctlError):
    """The file is not a readable mmctl recording."""


class RecordedTrial(NamedTuple):
    """A trial bracket found in a recording; ``logged`` holds the daemon's metrics row
    (``E``, ``F_h``, ... as logged) or None when the trial was never stopped."""

    trial: int
    start_cycle: int
    stop_cycle: int | None
    logged: dict[str, float] | None


class Recording(NamedTuple):
    """The full-rate part of a recording.

    cycle: (n,) cycle indices; time_ns: (n,) [ns]; series: full-rate path -> (n, k);
    trials: brackets in start order; info: the static ``telemetry/info`` values
    (``period_s``, ``loop_rate_hz``, ...); dropped: samples the ring dropped (the last
    ``plots/telemetry/dropped`` value).
    """

    path: str
    cycle: I64
    time_ns: I64
    series: dict[str, F64]
    trials: list[RecordedTrial]
    info: dict[str, Any]
    dropped: int = 0

    @property
    def period(self) -> float:
        """The control period T [s] (from ``telemetry/info``, else the cycle spacing)."""
        if "period_s" in self.info:
            return float(self.info["period_s"])
        if len(self.cycle) >= 2:
            dc = np.diff(self.cycle)
            dt = np.diff(self.time_ns)
            ok = dc > 0
            if ok.any():
                return float(np.median(dt[ok] / dc[ok]) * 1e-9)
        raise RecordingError(f"{self.path}: cannot tell the control period (no telemetry/info)")


def _store(path: str | Path) -> Any:
    from mmctl.extras import require

    require("telemetry", "reading a recording")
    from rerun.chunk import RrdReader

    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such file")
    try:
        return RrdReader(p).stream().collect()
    except (ValueError, OSError, RuntimeError) as exc:
        raise RecordingError(f"{p}: not a readable rerun recording ({exc})") from None


def _table(store: Any, index: str | None, contents: list[str]) -> Any:
    try:
        return store.reader(index=index, contents=contents).to_arrow_table()
    except ValueError as exc:  # e.g. the index does not exist: not an mmctl recording
        raise RecordingError(f"no mmctl telemetry in this recording ({exc})") from None


def _matrix(table: Any, column: str, width: int) -> F64:
    """A list<double> column -> (n, width) float64 (rows with no value -> NaN)."""
    n = table.num_rows
    out = np.full((n, width), np.nan)
    if column not in table.column_names or n == 0:
        return out
    arr = table.column(column).combine_chunks()
    valid = arr.is_valid().to_numpy(zero_copy_only=False)
    lengths = arr.value_lengths().fill_null(0).to_numpy(zero_copy_only=False)
    values = arr.flatten().to_numpy(zero_copy_only=False)
    if np.all(lengths[valid] == width):
        out[valid] = values.reshape(-1, width)
    else:  # ragged rows (not written by mmctl): slow path
        for i, v in enumerate(arr.to_pylist()):
            if v:
                out[i, : min(len(v), width)] = v[:width]
    return out


def _first(v: Any) -> Any:
    return v[0] if isinstance(v, list) and v else v


def column_name(path: str, component: str = "Scalars:scalars") -> str:
    """The dataframe column of an entity component, e.g. ``/plots/energy:Scalars:scalars``."""
    return f"/{path}:{component}"


def entity_rows(path: str | Path, entity: str, index: str = layout.TIMELINE_CYCLE,
                store: Any = None) -> int:
    """Number of rows ``entity`` holds on ``index`` in the recording at ``path``."""
    store = store if store is not None else _store(path)
    table = _table(store, index, [f"/{entity}"])
    cols = [c for c in table.column_names if c.startswith(f"/{entity}:")]
    if not cols:
        return 0
    return int(sum(table.num_rows - table.column(c).null_count for c in cols[:1]))


def load_recording(path: str | Path) -> Recording:
    """Read the full-rate series, the trial brackets and ``telemetry/info``."""
    store = _store(path)
    paths = [s.path for s in layout.FULL_RATE]
    table = _table(store, layout.TIMELINE_CYCLE, [f"/{p}" for p in paths])
    if table.num_rows == 0 or column_name(layout.ENERGY.path) not in table.column_names:
        raise RecordingError(f"{path}: no mmctl telemetry in this recording "
                             f"(no {layout.ENERGY.path} series)")
    series = {s.path: _matrix(table, column_name(s.path), len(s.names)) for s in layout.FULL_RATE}
    present = ~np.isnan(series[layout.ENERGY.path][:, 0])
    cycle = np.asarray(table.column(layout.TIMELINE_CYCLE).to_numpy(), dtype=np.int64)[present]
    t_ns = table.column(layout.TIMELINE_TIME).cast("int64").to_numpy(zero_copy_only=False)
    series = {k: v[present] for k, v in series.items()}
    return Recording(str(path), cycle, np.asarray(t_ns, np.int64)[present], series,
                     _trials(store), _info(store), _dropped(store))


def _dropped(store: Any) -> int:
    table = _table(store, layout.TIMELINE_CYCLE, [f"/{layout.DROPPED.path}"])
    col = _matrix(table, column_name(layout.DROPPED.path), 1)[:, 0]
    col = col[~np.isnan(col)]
    return int(col.max()) if len(col) else 0


def _info(store: Any) -> dict[str, Any]:
    table = _table(store, None, ["/telemetry/info"])
    prefix = "/telemetry/info:"
    return {c[len(prefix):]: _first(table.column(c).to_pylist()[0])
            for c in table.column_names if c.startswith(prefix) and table.num_rows}


def _rows(store: Any, entity: str) -> list[dict[str, Any]]:
    table = _table(store, layout.TIMELINE_CYCLE, [f"/{entity}"])
    prefix = f"/{entity}:"
    cols = {c[len(prefix):]: table.column(c).to_pylist()
            for c in table.column_names if c.startswith(prefix)}
    rows = []
    for i in range(table.num_rows):
        row = {k: _first(v[i]) for k, v in cols.items() if v[i] is not None}
        if "trial" in row:
            rows.append(row)
    return rows


def _trials(store: Any) -> list[RecordedTrial]:
    starts = {int(r["trial"]): int(r["start_cycle"]) for r in _rows(store, BRACKET)}
    done = {int(r["trial"]): r for r in _rows(store, layout.TRIAL_METRICS)}
    out = []
    for n in sorted(set(starts) | set(done)):
        row = done.get(n)
        start = int(row["start_cycle"]) if row is not None else starts[n]
        stop = int(row["stop_cycle"]) if row is not None else None
        logged = ({k: float(row[k]) for k in (*layout.METRIC_KEYS, "samples") if k in row}
                  if row is not None else None)
        out.append(RecordedTrial(n, start, stop, logged))
    return out


def recording_metrics(rec: Recording) -> list[TrialResult]:
    """Metrics per bracketed trial, or one result for the whole recording (trial 0)
    when no trial was bracketed.  An unstopped trial runs to the end (finished=False)."""
    brackets = rec.trials or [RecordedTrial(0, int(rec.cycle[0]), int(rec.cycle[-1]), None)]
    out = []
    for b in brackets:
        stop = b.stop_cycle if b.stop_cycle is not None else int(rec.cycle[-1])
        sel = (rec.cycle >= b.start_cycle) & (rec.cycle <= stop)
        n = int(sel.sum())
        if n == 0:
            continue
        e = rec.series[layout.ENERGY.path][sel, 0]
        f = rec.series[layout.FORCE_NORM.path][sel, 0]
        v = rec.series[layout.SPEED.path][sel, 1]
        p = rec.series[layout.EE_POSITION.path][sel][-1]
        p_des = rec.series[layout.EE_POSITION_DES.path][sel][-1]
        m = compute(rec.period, e, f, v, p, p_des)
        out.append(TrialResult(b.trial, b.start_cycle, int(rec.cycle[sel][-1]), n, m,
                               finished=b.stop_cycle is not None or b.trial == 0))
    return out
