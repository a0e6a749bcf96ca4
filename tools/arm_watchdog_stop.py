"""What the controller's RTDE watchdog does when the daemon goes quiet: figures.

    .venv/bin/python tools/arm_watchdog_stop.py [--min-frequency 10] [--speed 0.58]

The real ur_rtde client (UrRtdeArm) drives the fake UR controller (its own process)
with speedJ at ``--speed`` rad/s on the base joint for 1 s at 500 Hz, as an armed
daemon does, then sends nothing more (a daemon frozen by SIGSTOP, hung, or killed).
Printed, in controller time: the watchdog's delay from the last package to the program
stop, the time from the last package to rest, and the joint's travel meanwhile, next
to what it travels without a watchdog (the speed kept until someone intervenes).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mmctl.config import config_from_dict
from mmctl.sim.fake_ur import CommandKind, start_fake_ur
from mmctl.transports.ur_rtde_arm import UrRtdeArm


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.11")
    p.add_argument("--min-frequency", type=float, default=10.0,
                   help="arm.watchdog_min_frequency [Hz] (robot: 10)")
    p.add_argument("--speed", type=float, default=0.58, help="base joint speed [rad/s]")
    p.add_argument("--acceleration", type=float, default=4.0, help="speedJ acceleration")
    args = p.parse_args()
    with start_fake_ur(args.host) as fake:
        cfg = config_from_dict({"arm": {"host": fake.host,
                                        "watchdog_min_frequency": args.min_frequency}})
        arm = UrRtdeArm.from_config(cfg)
        arm.connect()
        qd = np.array([args.speed, 0, 0, 0, 0, 0])
        next_t = time.perf_counter()
        for _ in range(500):
            arm.read_state()
            arm.speed_j(qd, args.acceleration, 0.002)
            next_t += 0.002
            time.sleep(max(0.0, next_t - time.perf_counter()))
        # quiet from here: no package reaches the controller
        samples = []
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            s = fake.state()
            samples.append((s.controller_time, s.q[0], s.qd[0], s.runtime_state))
            if s.runtime_state != 2 and s.qd[0] == 0.0:
                break
            time.sleep(0.0005)
        last = fake.commands(CommandKind.SPEEDJ)[-1].controller_time
        stop = next(c.controller_time for c in fake.commands(CommandKind.PROGRAM)
                    if (c.text or "").startswith("stopped (rtde watchdog"))
        t = np.array([x[0] for x in samples])
        q = np.array([x[1] for x in samples])
        v = np.array([x[2] for x in samples])
        rest = t[np.argmax(v == 0.0)]
        q_last = np.interp(last, t, q) if last >= t[0] else q[0]
        travel = q[-1] - q_last
        arm.close()
    print(f"watchdog min frequency {args.min_frequency:g} Hz (timeout "
          f"{1e3 / args.min_frequency:.0f} ms), base joint at {args.speed} rad/s")
    print(f"program stopped {1e3 * (stop - last):.0f} ms after the last package")
    print(f"joint at rest   {1e3 * (rest - last):.0f} ms after the last package")
    print(f"travel after the last package {travel:.4f} rad "
          f"(without the watchdog: {args.speed:.2f} rad per second of silence)")


if __name__ == "__main__":
    main()
