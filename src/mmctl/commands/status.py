"""Show the daemon's state: safety state, fault, IDK mode, loop timing, robot.

Exits 0 when a daemon answered, 2 with one line when none is running.
"""

from __future__ import annotations

import argparse
import json

from mmctl.runtime.client import add_client_arguments, call, summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_client_arguments(p)
    p.add_argument("--json", action="store_true", help="print the full status as JSON")


def run(args: argparse.Namespace) -> int:
    st = call(args, "status")
    if args.json:
        print(json.dumps(st, indent=2, sort_keys=True))
        return 0
    print(summary(st))
    loop = st.get("loop", {})
    print(f"loop: {loop.get('rate_hz')} Hz, {st.get('cycles')} cycles, "
          f"compute p99 {loop.get('compute_p99_us')} us, "
          f"wake latency p99 {loop.get('latency_p99_us')} us, "
          f"misses {loop.get('total_misses')} (rate {loop.get('miss_rate')})")
    robot = st.get("robot")
    if robot:
        print(f"end-effector: {robot['ee_position']} m, v_d {robot['v_d'][:3]} m/s, "
              f"f_h {robot['f_h'][:3]} N, E_K {robot['energy_J']} J")
    caps = st.get("caps")
    if caps:
        limit = (robot or {}).get("limit") or "none"
        print(f"limits: profile {st.get('profile')}, E_K <= {caps['energy_J']} J, base <= "
              f"{caps['base_speed_m_s']} m/s, end-effector <= {caps['ee_speed_m_s']} m/s; "
              f"binding now: {limit}")
    calib = st.get("calibration")
    if calib:
        error = f": {calib['error']}" if calib.get("error") else ""
        print(f"tool calibration: {calib['phase']} at pose {calib['pose']}/{calib['poses']}, "
              f"{calib['weighed']} weighed, {calib['elapsed_s']} s{error}")
    if st.get("fault_details"):
        print(f"fault details: {st['fault_details']}")
    return 0
