"""How soon the loop settles: misses in short bins after start-up, after the first enable
and after a fault's re-enable, against the steady rate of the same run.

The daemon runs in this process on its own simulated robot (`mmctl sim` on ``--host``),
as in `mmctl bench loop`.  The run: start, wait; tare and enable (the simulated person
then starts), wait; inject ``--fault`` into the simulation, wait for the daemon's FAULT,
remove it, enable again, wait.  Every cycle's deadline and its misses come from the
loop's own timing ring; they are binned (``--bin``) from each event on.  Misses have
the status's definition: deadlines missed / (cycles run + deadlines missed).

"Settled" is the first bin from which every later bin up to the next event stays within
``max(2 x steady, steady + 0.5 %)``, where steady is the rate over the last
``--steady`` seconds before the fault.  The issue's target is "within 2 s" of start-up
and of a re-enable.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np

from mmctl.errors import MmctlError

#: the events a run times, in order
EVENTS = ("start", "enable", "re-enable")


def add_arguments(p: argparse.ArgumentParser) -> None:
    from mmctl.bench.loop import _cpus

    p.add_argument("--after", type=float, default=8.0, metavar="S",
                   help="time measured after each event [s] (default 8)")
    p.add_argument("--bin", type=float, default=0.5, metavar="S",
                   help="width of a miss-rate bin [s] (default 0.5)")
    p.add_argument("--steady", type=float, default=4.0, metavar="S",
                   help="the steady rate: the last S seconds before the fault (default 4)")
    p.add_argument("--fault", default="drive_fault",
                   help="the simulation's fault to inject and remove (default drive_fault)")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.add_argument("--config", metavar="FILE", help="base config (default: config/sim.yaml)")
    p.add_argument("--host", default="127.0.0.5",
                   help="loopback address of the bench's own simulated robot")
    p.add_argument("--rt-priority", type=int, metavar="N", help="loop.rt_priority")
    p.add_argument("--cpu-affinity", type=_cpus, metavar="CPUS", help="loop.cpu_affinity")
    p.add_argument("--cpu-dma-latency", type=int, metavar="US", help="loop.cpu_dma_latency")


def run(args: argparse.Namespace) -> int:
    from mmctl.bench.loop import bench_config, stdout_to_stderr
    from mmctl.runtime.client import load
    from mmctl.runtime.logging import setup_logging

    if not (args.after > 0 and 0 < args.bin <= args.after and 0 < args.steady <= args.after):
        raise MmctlError(f"--after {args.after:g}, --bin {args.bin:g}, --steady "
                         f"{args.steady:g}: need 0 < bin <= after and 0 < steady <= after")
    cfg: Any = load(args.config)
    n = int((3 * args.after + 120) * cfg.loop.rate_hz)  # every cycle of the run
    cfg = bench_config(cfg, args, n)
    with stdout_to_stderr():
        setup_logging("warning", stream=sys.stderr)
        result = _measure(cfg, args)
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        _print(result)
    return 0


def _measure(cfg: Any, args: argparse.Namespace) -> dict[str, Any]:
    from mmctl.runtime.factory import create_daemon, open_sim
    from mmctl.telemetry.service import TelemetryService

    sim = open_sim(cfg)
    if sim is None:
        raise MmctlError("bench startup needs the simulated robot's own process")
    daemon = create_daemon(cfg, socket_path=None, telemetry=TelemetryService(cfg), sim=sim)
    at: dict[str, int] = {}
    try:
        daemon.open()
        daemon.start()
        at["start"] = daemon.runtime.t0_ns
        time.sleep(args.after)
        daemon.tare_and_enable(30.0)
        at["enable"] = time.perf_counter_ns()
        sim.start_human()
        time.sleep(args.after)
        at["fault"] = time.perf_counter_ns()
        sim.call("fault", name=args.fault, on=True)
        deadline = time.monotonic() + 10.0
        while daemon.safety.armed and time.monotonic() < deadline:
            time.sleep(0.01)
        if daemon.safety.armed:
            raise MmctlError(f"the daemon did not fault on {args.fault!r} within 10 s")
        sim.call("fault", name=args.fault, on=False)
        daemon.tare_and_enable(30.0)
        at["re-enable"] = time.perf_counter_ns()
        time.sleep(args.after)
        at["end"] = time.perf_counter_ns()
        snap = daemon.ring.snapshot()
        faults = daemon.safety.faults
    finally:
        try:
            daemon.shutdown()
        finally:
            sim.close()
    return _figures(snap.deadline_ns, snap.missed, at, args, faults)


def _figures(deadline_ns: np.ndarray, missed: np.ndarray, at: dict[str, int],
             args: argparse.Namespace, faults: int) -> dict[str, Any]:
    """Bin the run's cycles from each event on (see the module docstring)."""
    def rate(lo: int, hi: int) -> tuple[float, int, int]:
        sel = (deadline_ns >= lo) & (deadline_ns < hi)
        cycles, miss = int(sel.sum()), int(missed[sel].sum())
        return (100.0 * miss / max(cycles + miss, 1), cycles, miss)

    steady_pct, steady_cycles, _ = rate(at["fault"] - int(args.steady * 1e9), at["fault"])
    bound = max(2.0 * steady_pct, steady_pct + 0.5)
    ends = {"start": at["enable"], "enable": at["fault"], "re-enable": at["end"]}
    out: dict[str, Any] = {"bin_s": args.bin, "after_s": args.after, "fault": args.fault,
                           "steady_pct": round(steady_pct, 3), "steady_cycles": steady_cycles,
                           "settled_bound_pct": round(bound, 3), "faults": faults,
                           "events": {}}
    step = int(args.bin * 1e9)
    for name in EVENTS:
        t0, end = at[name], ends[name]
        bins = []
        for lo in range(t0, end - step + 1, step):
            pct, cycles, miss = rate(lo, lo + step)
            bins.append({"t_s": round((lo - t0) / 1e9, 3), "miss_pct": round(pct, 2),
                         "cycles": cycles, "missed": miss})
        settled = None
        for i in range(len(bins)):
            if all(b["miss_pct"] <= bound for b in bins[i:]):
                settled = bins[i]["t_s"]
                break
        first2 = rate(t0, t0 + int(2e9))
        out["events"][name] = {"settled_after_s": settled,
                               "first_2s_pct": round(first2[0], 3),
                               "bins": bins}
    return out


def _print(r: dict[str, Any]) -> None:
    print(f"mmctl bench startup: misses in {r['bin_s']:g} s bins after each event; steady "
          f"{r['steady_pct']:.3f} % (the {r['steady_cycles']} cycles before the fault); "
          f"settled: every later bin <= {r['settled_bound_pct']:.2f} %")
    for name, ev in r["events"].items():
        settled = ev["settled_after_s"]
        bins = " ".join(f"{b['miss_pct']:.1f}" for b in ev["bins"])
        print(f"  {name:<10} settled after {'-' if settled is None else f'{settled:g} s':>6}"
              f"   first 2 s {ev['first_2s_pct']:6.2f} %   bins [%]: {bins}")
    print(f"  faults during the run: {r['faults']} (the injected {r['fault']} is one)")
