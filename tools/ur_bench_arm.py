"""Per-call cost of UrRtdeArm.read_state and speed_j against the fake UR controller.

    .venv/bin/python tools/ur_bench_arm.py [--host 127.0.0.9] [--cycles 2000] [--process]

--process measures the daemon's arm, ur_rtde in a child process (UrRtdeProcessArm:
a read takes the child's answer to the previous cycle's request; speed_j is a message).

Runs a 500 Hz loop (read_state then speed_j each period, as the daemon does) and
prints the median, 90th and 99th percentile of each call in microseconds, then the
same calls back to back (warm caches, no sleeping).  The figures include whatever the
machine's load adds: run it on an idle machine for the numbers that matter.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from mmctl.config import config_from_dict
from mmctl.sim.fake_ur import start_fake_ur
from mmctl.transports.ur_rtde_arm import UrRtdeArm
from mmctl.transports.ur_rtde_process import UrRtdeProcessArm


def _stats(name: str, ns: list[int]) -> str:
    us = np.array(ns) / 1e3
    return (f"{name:<12} p50 {np.percentile(us, 50):6.1f}  p90 {np.percentile(us, 90):6.1f}  "
            f"p99 {np.percentile(us, 99):6.1f} us  (n={len(us)})")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.9")
    p.add_argument("--cycles", type=int, default=2000)
    p.add_argument("--process", action="store_true", help="the daemon's process arm")
    args = p.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    with start_fake_ur(args.host) as fake:
        cfg = config_from_dict({"arm": {"host": fake.host, "stale_cycles": 1000}})
        arm_type = UrRtdeProcessArm(cfg.arm, cfg.limits) if args.process \
            else UrRtdeArm.from_config(cfg)
        print("UrRtdeProcessArm (ur_rtde in a child)" if args.process
              else "UrRtdeArm (ur_rtde in this process)")
        with arm_type as arm:
            qd = np.array([0.05, -0.05, 0.05, 0.0, 0.05, -0.05])
            for paced in (True, False):
                reads: list[int] = []
                sends: list[int] = []
                deadline = time.perf_counter()
                arm.read_state()
                time.sleep(0.01)
                for i in range(args.cycles):
                    t0 = time.perf_counter_ns()
                    arm.read_state()
                    t1 = time.perf_counter_ns()
                    arm.speed_j(qd if i % 2 else -qd)
                    t2 = time.perf_counter_ns()
                    reads.append(t1 - t0)
                    sends.append(t2 - t1)
                    if paced:
                        deadline += 0.002
                        pause = deadline - time.perf_counter()
                        if pause > 0:
                            time.sleep(pause)
                print("500 Hz loop:" if paced else "back to back:")
                print("  " + _stats("read_state", reads))
                print("  " + _stats("speed_j", sends))
            arm.stop()


if __name__ == "__main__":
    main()
