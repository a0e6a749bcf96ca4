"""Show the daemon's state: safety state, fault, IDK mode, loop timing, robot.

Exits 0 when a daemon answered, 2 with one line when none is running.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from mmctl.runtime.client import add_client_arguments, call, summary
from mmctl.runtime.liveview import misses_text


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
          f"{misses_text(loop)}")
    robot = st.get("robot")
    if robot:
        desired = robot.get("desired") or {}
        print(f"end-effector: {robot['ee_position']} m, measured "
              f"{_or_unknown(robot.get('ee_speed_m_s'))} m/s (desired "
              f"{desired.get('ee_speed_m_s')} m/s), base {_or_unknown(robot.get('base_speed_m_s'))}"
              f" m/s, f_h {robot['f_h'][:3]} N, E_K {_or_unknown(robot.get('energy_J'))} J "
              "(measured)")
    caps = st.get("caps")
    if caps:
        limit = (robot or {}).get("limit") or "none"
        near = (robot or {}).get("nearest_parts")
        if near:
            limit += f" (nearest parts: {near['pair']} {near['distance_m']} m)"
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


def _or_unknown(v: Any) -> str:
    """A measured figure, or why there is none (the newest cycles could not read a device)."""
    return "unknown" if v is None else str(v)
