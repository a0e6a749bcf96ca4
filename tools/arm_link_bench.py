"""What the daemon's arm (UrRtdeProcessArm) costs the loop, against the fake UR controller.

    .venv/bin/python tools/arm_link_bench.py [--host 127.0.0.29] [--cycles 5000]
        [--busy 600] [--before OTHER_TREE/src]

Runs a 500 Hz loop of read_state(), ``--busy`` us of work, speed_j() (as the daemon's
cycle does) with the real ur_rtde client in the arm's child process, the fake
controller (:mod:`mmctl.sim.fake_ur`) in another process on its own loopback address,
and prints in microseconds:

* read_state and speed_j: what each call costs the loop (p50, p90, p99, max);
* new: the reads that brought a sample with a new controller time;
* speedJ latency: from the loop's speed_j call to the fake controller's reception of
  that speedJ (both CLOCK_MONOTONIC; each command carries a marker in qd[5]), and how
  many of the loop's speedJs reached the controller (the rest were superseded by a
  newer one before the child took them).

``--before DIR`` first runs the same measurement with the package in ``DIR`` (e.g. a
``git worktree`` of an older commit: ``git worktree add --detach /tmp/arm-before
<commit>``) in a subprocess, for a before/after in one run.  The figures include the
machine's load: it is printed first.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from mmctl.config import config_from_dict
from mmctl.errors import SafetyFault
from mmctl.sim.fake_ur import CommandKind, start_fake_ur
from mmctl.transports import ur_rtde_process
from mmctl.transports.ur_rtde_process import UrRtdeProcessArm

PERIOD = 0.002
MARK = 1e-6
"""[rad/s] qd[5] of the loop's i-th speed_j is (i + 1) * MARK: which one arrived."""


def _row(name: str, us: list[float] | np.ndarray) -> str:
    a = np.asarray(us, dtype=float)
    if not a.size:
        return f"  {name:<16} (none)"
    p50, p90, p99 = np.percentile(a, [50, 90, 99])
    return (f"  {name:<16} p50 {p50:7.1f}  p90 {p90:7.1f}  p99 {p99:7.1f}  "
            f"max {a.max():8.1f} us  (n={a.size})")


def _busy(us: float) -> None:
    end = time.perf_counter_ns() + int(us * 1e3)
    while time.perf_counter_ns() < end:
        pass


def measure(host: str, cycles: int, busy: float, label: str) -> None:
    print(f"{label}: {ur_rtde_process.__file__}")
    print(f"  load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    with start_fake_ur(host) as fake:
        cfg = config_from_dict({"arm": {"host": fake.host, "stale_cycles": 1000}})
        with UrRtdeProcessArm(cfg.arm, cfg.limits) as arm:
            for _ in range(500):  # the watchdog set, caches warm
                try:
                    arm.read_state()
                except SafetyFault:
                    pass
                arm.kick_watchdog()
                time.sleep(PERIOD)
            reads, sends, sent_at = [], [], []
            new, last_t = 0, None
            deadline = time.perf_counter()
            for i in range(cycles):
                deadline += PERIOD
                t0 = time.perf_counter_ns()
                state = arm.read_state()
                t1 = time.perf_counter_ns()
                _busy(busy)
                sign = 1.0 if (i // 250) % 2 else -1.0
                qd = [0.02 * sign, -0.02 * sign, 0.02 * sign, 0.0, 0.0, (i + 1) * MARK]
                t2 = time.perf_counter_ns()
                arm.speed_j(qd, 4.0, PERIOD)
                t3 = time.perf_counter_ns()
                reads.append((t1 - t0) / 1e3)
                sends.append((t3 - t2) / 1e3)
                sent_at.append(t2 * 1e-9)  # perf_counter and monotonic: one clock on Linux
                if state.controller_time != last_t:
                    new, last_t = new + 1, state.controller_time
                pause = deadline - time.perf_counter()
                if pause > 0:
                    time.sleep(pause)
                else:
                    deadline = time.perf_counter()
            arm.stop()
            time.sleep(0.2)
        received = {}
        for c in fake.commands(CommandKind.SPEEDJ):
            if c.qd is not None and c.qd[5] > 0 and c.received is not None:
                received[round(c.qd[5] / MARK) - 1] = c.received
    latency = [(received[i] - sent_at[i]) * 1e6 for i in sorted(received) if i < cycles]
    print(f"  {cycles} cycles at 500 Hz, {busy:g} us of work between read and speed_j")
    print(_row("read_state", reads))
    print(_row("speed_j", sends))
    print(f"  {'new samples':<16} {new} of {cycles} reads")
    print(_row("speedJ latency", latency))
    print(f"  {'speedJs arrived':<16} {len(latency)} of {cycles}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.29", help="the fake controller's address")
    p.add_argument("--cycles", type=int, default=5000)
    p.add_argument("--busy", type=float, default=600.0,
                   help="[us] of work per cycle between read_state and speed_j")
    p.add_argument("--before", type=Path, default=None,
                   help="a tree's src/ to measure first, in a subprocess (the old code)")
    p.add_argument("--label", default="this tree", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.before is not None:
        host = args.host.rsplit(".", 1)
        other = f"{host[0]}.{(int(host[1]) % 250) + 1}"
        env = {**os.environ, "PYTHONPATH": str(args.before.resolve())}
        subprocess.run([sys.executable, __file__, "--host", other, "--cycles",
                        str(args.cycles), "--busy", str(args.busy), "--label", "before"],
                       env=env, check=True)
    measure(args.host, args.cycles, args.busy, args.label)


if __name__ == "__main__":
    main()
