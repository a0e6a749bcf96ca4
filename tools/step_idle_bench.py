#!/usr/bin/env python3
"""The control step's cost after the thread was idle: back to back vs sleep between.

The daemon's cycle runs once per 2 ms and sleeps in between.  On some machines (small
VMs in particular) a thread that just slept runs the same Python code several times
slower (cold caches, idle CPU states).  This measures :meth:`ControlCore.step` (the
whole control chain, no device I/O) with a person pushing the handle, first back to
back, then with ``--sleep`` seconds of ``time.sleep`` between steps, and prints both.

    .venv/bin/python tools/step_idle_bench.py [--cycles 5000] [--sleep 0.0015] [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from mmctl.config import default_config
from mmctl.runtime.core import ControlCore
from mmctl.types import ArmState, Odometry, Wrench


def measure(cycles: int, sleep_s: float) -> np.ndarray:
    """Per-step times [us] of ``cycles`` steps (the first 500 dropped as warm-up)."""
    cfg = default_config()
    core = ControlCore(cfg)
    dt = 1.0 / cfg.loop.rate_hz
    q = np.concatenate((np.asarray(cfg.robot.q_des, dtype=float), np.zeros(3)))
    qd = np.zeros(9)
    out = np.empty(cycles)
    for k in range(cycles):
        t, now = k * dt, time.monotonic()
        arm = ArmState(q[:6].copy(), qd[:6].copy(), t, 2, 0)
        wrench = Wrench(np.array([0.0, 25.0 * math.sin(0.4 * t) ** 2, 0.0]), np.zeros(3),
                        now, k)
        odom = Odometry(q[6], q[7], q[8], qd[6], qd[7], qd[8], now)
        t0 = time.perf_counter_ns()
        r = core.step(arm, wrench, odom, dt, active=True, now=now)
        out[k] = (time.perf_counter_ns() - t0) / 1e3
        qd = r.qd_cmd.copy()
        q = q + qd * dt
        if sleep_s > 0:
            time.sleep(sleep_s)
    return out[500:]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5000, help="steps per condition")
    ap.add_argument("--sleep", type=float, default=0.0015, help="idle time between steps [s]")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    res = {}
    for name, s in (("back_to_back", 0.0), (f"sleep_{args.sleep:g}s", args.sleep)):
        a = measure(args.cycles, s)
        res[name] = {"p50_us": round(float(np.percentile(a, 50)), 1),
                     "p99_us": round(float(np.percentile(a, 99)), 1)}
    if args.json:
        print(json.dumps(res))
        return
    for name, r in res.items():
        print(f"step() {name:>16}: p50 {r['p50_us']:7.1f} us   p99 {r['p99_us']:7.1f} us")


if __name__ == "__main__":
    main()
