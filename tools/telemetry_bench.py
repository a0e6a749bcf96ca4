#!/usr/bin/env python3
"""Telemetry overhead on the control loop: the real control chain, telemetry off vs on.

Runs :class:`mmctl.runtime.core.ControlCore` (wrench processing, admittance, min-energy
IDK, limits, energy: the daemon's per-cycle math) in a real 500 Hz
:class:`~mmctl.runtime.loop.CycleLoop`, fed with synthetic device readings (a person
pushing the handle while the measured joints follow the command), in alternating
phases with telemetry off and on (the cycle's row into the sample ring, publisher
writing a real ``.rrd``).  Prints compute time / wake latency percentiles and missed
deadlines per condition.

    .venv/bin/python tools/telemetry_bench.py [--seconds 40] [--phases 4] [--json]

No device I/O: this isolates what telemetry adds to the cycle.  `mmctl bench loop
--telemetry` measures the same on the whole daemon with the simulated robot.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from mmctl.bench.telemetry_overhead import compare, format_report
from mmctl.config import default_config
from mmctl.runtime.core import ControlCore
from mmctl.runtime.loop import Tick
from mmctl.types import ArmState, Odometry, Wrench


def make_body_factory(cfg):  # type: ignore[no-untyped-def]
    """body_for(service, origin_ns) -> body(tick): one ControlCore cycle (+ telemetry hook)."""

    def body_for(service, origin_ns):  # type: ignore[no-untyped-def]
        core = ControlCore(cfg)
        hook = service.hook(core)
        q = np.concatenate((np.asarray(cfg.robot.q_des, dtype=float), np.zeros(3)))
        qd = np.zeros(9)
        dt = 1.0 / cfg.loop.rate_hz

        def body(tick: Tick) -> None:
            nonlocal q, qd
            t = (tick.deadline_ns - origin_ns) * 1e-9
            push = 25.0 * math.sin(0.4 * t) ** 2
            now = time.monotonic()
            arm = ArmState(q[:6].copy(), qd[:6].copy(), t, 2, 0)
            wrench = Wrench(np.array([0.0, push, 0.0]), np.zeros(3), now, tick.index)
            odom = Odometry(q[6], q[7], q[8], qd[6], qd[7], qd[8], now)
            r = core.step(arm, wrench, odom, dt, active=True, now=now)
            qd = r.qd_cmd.copy()
            q = q + qd * dt
            if hook is not None:
                hook(r, tick.index, t, "armed")

        return body

    return body_for


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=40.0, help="total run time [s]")
    ap.add_argument("--phases", type=int, default=4, help="alternating off/on phases")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    cfg = default_config()
    report = compare(cfg, make_body_factory(cfg), args.seconds, args.phases)
    print(json.dumps(report, indent=2) if args.json else format_report(report))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
