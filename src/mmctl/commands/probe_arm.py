"""Bring-up probe of the UR10e link: connect through ur_rtde, print the arm state and
optionally jog one joint with speedJ, then stop.

    mmctl probe arm --host 192.168.1.10
    mmctl probe arm --host 127.0.0.5 --jog-joint 5 --speed 0.1 --seconds 1 --json

Fails with one line and exit status 2 when nothing answers, remote control is off or
the arm is in a protective or emergency stop.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mmctl.transports.ur_rtde_arm import UrRtdeArm
    from mmctl.types import ArmState

CAUSE_TEXT = {
    "arm_protective_stop": "the arm is in protective stop (clear it on the teach pendant)",
    "arm_emergency_stop": "the arm is in emergency stop (release the e-stop, then restart)",
    "arm_not_playing": "the control script is not running on the controller",
    "arm_disconnected": "the controller closed the connection",
    "arm_timestamp_stale": "the controller stopped streaming RTDE data",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", help="controller address (default: arm.host of the config)")
    p.add_argument("--config", help="YAML config file (default: built-in defaults)")
    p.add_argument("--jog-joint", type=int, choices=range(6), metavar="J",
                   help="joint to jog, 0 (base) .. 5 (wrist 3)")
    p.add_argument("--speed", type=float, default=0.1,
                   help="jog speed [rad/s] (clamped to the joint's limit; default 0.1)")
    p.add_argument("--seconds", type=float, default=1.0, help="jog duration [s] (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def run(args: argparse.Namespace) -> int:
    import sys

    import numpy as np

    from mmctl.config import config_from_dict, default_config, load_config, to_dict
    from mmctl.errors import MmctlError, SafetyFault
    from mmctl.runtime.logging import setup_logging
    from mmctl.transports.ur_rtde_arm import UrRtdeArm

    setup_logging("warning", stream=sys.stderr)  # stdout carries the report only

    if not (math.isfinite(args.speed) and math.isfinite(args.seconds)) or not 0 < args.seconds <= 60:
        raise MmctlError("--seconds must be in (0, 60] and --speed finite")
    cfg = load_config(args.config) if args.config else default_config()
    if args.host:  # through the validating loader, like any other config value
        raw = to_dict(cfg)
        raw["arm"]["host"] = args.host
        cfg = config_from_dict(raw, "--host")
    arm_cfg = cfg.arm
    arm = UrRtdeArm(arm_cfg, cfg.limits)
    try:
        arm.connect()
        start = _fresh_state(arm)
        end, cycles = start, 0
        if args.jog_joint is not None:
            cycles = _jog(arm, args.jog_joint, args.speed, args.seconds)
            end = _settle(arm)
    except SafetyFault as fault:
        raise MmctlError(f"{arm_cfg.host}: {CAUSE_TEXT.get(fault.cause.value, fault)} "
                         f"[{fault}]") from None
    finally:
        arm.close()
    report = {
        "host": arm_cfg.host,
        "controller_version": arm.controller_version,
        "q_start": [round(float(x), 6) for x in start.q],
        "q_end": [round(float(x), 6) for x in end.q],
        "qd": [round(float(x), 6) for x in end.qd],
        "runtime_state": int(end.runtime_state),
        "safety_status_bits": int(end.safety_bits),
        "controller_time": end.controller_time,
        "cycles_sent": cycles,
    }
    if args.json:
        print(json.dumps(report))
        return 0
    print(f"UR controller {arm_cfg.host}  PolyScope {arm.controller_version}")
    print(f"  q      [rad]   {np.array2string(start.q, precision=4)}")
    print(f"  qd     [rad/s] {np.array2string(start.qd, precision=4)}")
    print(f"  runtime state {end.runtime_state} (2 = PLAYING), "
          f"safety status bits 0x{end.safety_bits:x}")
    if args.jog_joint is not None:
        moved = float(end.q[args.jog_joint] - start.q[args.jog_joint])
        print(f"  jogged joint {args.jog_joint}: {cycles} speedJ cycles, moved {moved:+.4f} rad")
        print(f"  q end  [rad]   {np.array2string(end.q, precision=4)}")
    return 0


def _fresh_state(arm: UrRtdeArm, timeout: float = 2.0) -> ArmState:
    """read_state until a fresh sample arrives (the first reads may repeat the same
    one).  Samples streamed while the control script was still starting say so
    (``arm_not_playing``): they are waited out for ``timeout`` [s], then that fault
    stands."""
    deadline = time.monotonic() + timeout
    state = _playing(arm, deadline)
    while time.monotonic() < deadline:
        time.sleep(0.002)
        nxt = arm.read_state()
        if nxt.controller_time != state.controller_time:
            return nxt
    return state


def _playing(arm: UrRtdeArm, deadline: float) -> ArmState:
    from mmctl.errors import FaultCause, SafetyFault

    while True:
        try:
            return arm.read_state()
        except SafetyFault as fault:
            if fault.cause is not FaultCause.ARM_NOT_PLAYING or time.monotonic() > deadline:
                raise
        time.sleep(0.01)


def _jog(arm: UrRtdeArm, joint: int, speed: float, seconds: float) -> int:
    """speedJ on one joint at the arm's period for ``seconds``; returns cycles sent."""
    import numpy as np

    period = 1.0 / arm.config.frequency
    qd = np.zeros(6)
    qd[joint] = speed
    cycles = round(seconds / period)
    deadline = time.perf_counter()
    for _ in range(cycles):
        arm.read_state()
        arm.speed_j(qd, None, period)
        deadline += period
        pause = deadline - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
    _fresh_state(arm)  # stop() uses speedStop after a fresh sample
    arm.stop()
    return cycles


def _settle(arm: UrRtdeArm, timeout: float = 5.0) -> ArmState:
    """read_state until every joint is at rest (|qd| < 1e-4 rad/s) or the timeout."""
    deadline = time.monotonic() + timeout
    state = arm.read_state()
    while time.monotonic() < deadline and float(abs(state.qd).max()) >= 1e-4:
        time.sleep(0.01)
        state = arm.read_state()
    return state
