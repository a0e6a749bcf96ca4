"""Recompute the paper's trial metrics (eq. 14-16) from a recording.

Reads FILE.rrd (written by `mmctl run --record FILE.rrd`) with rerun's dataframe API
and prints, per trial bracketed with `mmctl trial start|stop` (or for the whole
recording when none was), the average energy E [J], average human force F_h [N],
average end-effector speed v [m/s], final displacement x_f [m] and execution time
T_f [s].  With --json: one JSON object per line with keys E, F_h, v, x_f, T_f (SI),
trial, start_cycle, stop_cycle, samples, finished.
"""

from __future__ import annotations

import argparse
import json


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", metavar="FILE.rrd", help="a recording made with --record")
    p.add_argument("--json", action="store_true", help="one JSON object per trial")
    p.add_argument("--compare", action="store_true",
                   help="also print the metrics the daemon logged and the largest difference")


def run(args: argparse.Namespace) -> int:
    from mmctl.telemetry.recording import load_recording, recording_metrics

    rec = load_recording(args.file)
    results = recording_metrics(rec)
    logged = {t.trial: t.logged for t in rec.trials if t.logged is not None}
    if args.json:
        for r in results:
            d = r.as_dict()
            if args.compare:
                d["logged"] = logged.get(r.trial)
            print(json.dumps(d))
        return 0
    gaps = _gaps(rec.cycle)
    print(f"{args.file}: {len(rec.cycle)} cycles at T = {rec.period * 1e3:g} ms"
          + (f", {gaps} cycles without a sample" if gaps else "")
          + (f" ({rec.dropped} dropped by the telemetry queue)" if rec.dropped else ""))
    print(f"{'trial':>5} {'cycles':>15} {'N':>7} {'E [J]':>9} {'F_h [N]':>9} {'v [m/s]':>9} "
          f"{'x_f [m]':>9} {'T_f [s]':>9}")
    for r in results:
        m = r.metrics
        name = str(r.trial) if r.trial else "all"
        span = f"{r.start_cycle}-{r.stop_cycle}" + ("" if r.finished else "+")
        print(f"{name:>5} {span:>15} {r.samples:>7} {m.E_mean:>9.4f} {m.F_mean:>9.3f} "
              f"{m.v_mean:>9.4f} {m.x_f:>9.4f} {m.T_f:>9.3f}")
        if args.compare and r.trial in logged:
            lg = logged[r.trial]
            diff = max(abs(lg[k] - v) for k, v in zip(("E", "F_h", "v", "x_f", "T_f"), m))
            print(f"{'':>5} {'daemon logged':>15} {int(lg.get('samples', 0)):>7} {lg['E']:>9.4f} "
                  f"{lg['F_h']:>9.3f} {lg['v']:>9.4f} {lg['x_f']:>9.4f} {lg['T_f']:>9.3f}"
                  f"   max |diff| {diff:.3g}")
    if any(not r.finished for r in results):
        print("+ trial not stopped before the recording ended: metrics up to its last cycle")
    return 0


def _gaps(cycle) -> int:  # type: ignore[no-untyped-def]
    """Cycles missing between the first and last recorded one."""
    if len(cycle) < 2:
        return 0
    return int(cycle[-1] - cycle[0] + 1 - len(cycle))
