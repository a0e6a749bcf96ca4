"""Bring up the omnidirectional base: enable the drives, report their states, and
optionally drive a small twist for a few seconds, then stop.

  mmctl probe base                                  # the configured transport
  mmctl probe base --simulate --twist 0.1 0 0 --seconds 1 --json
  mmctl probe base --transport serial --port /dev/ttyUSB0

Per drive it reports the link state (CANopen NMT state from the heartbeat, or the
serial link), the CiA 402 state and the statusword; with --twist, the odometry before
and after and the cost of one cycle (send_twist + read_odometry) [us].

--simulate starts simulated drives inside this process (a python-can ``virtual`` bus
exists only within one process, so they cannot run elsewhere), or, with --transport
serial, a simulated bridge on a pseudo-terminal.  When nothing answers it exits with
status 2 and one line such as "no drive answers on channel 'mmctl-base' (node ids 1,
2, 3, 4)".
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from typing import Any, TextIO, cast

_STOP_WAIT = 3.0  # longest wait for the wheels to stop after the twist [s]


class _Stderr:
    """sys.stderr looked up at every write (pytest swaps it between tests)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()

    def isatty(self) -> bool:
        return sys.stderr.isatty()


def _seconds(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= 60.0:
        raise argparse.ArgumentTypeError(f"{text} s: must be > 0 and <= 60")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="F", help="YAML config file (default: built-in defaults)")
    p.add_argument("--transport", choices=("canopen", "serial"),
                   help="override base.transport")
    p.add_argument("--port", metavar="P", help="serial port (overrides base.serial.port)")
    p.add_argument("--twist", nargs=3, type=float, metavar=("VX", "VY", "WZ"),
                   help="drive this base twist [m/s, m/s, rad/s] for --seconds, then stop")
    p.add_argument("--seconds", type=_seconds, default=1.0, metavar="S",
                   help="how long to apply --twist [s] (default 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--simulate", action="store_true",
                   help="start simulated drives (CANopen, in-process) or bridge (serial, pty)")


def _odo(o: Any) -> dict[str, float]:
    return {k: round(float(getattr(o, k)), 6) for k in ("x", "y", "yaw", "vx", "vy", "wz")}


def _drives(base: Any) -> list[dict[str, Any]]:
    return [{"wheel": d.name, "address": d.address, "link": d.link, "state": d.state,
             "statusword": f"0x{d.statusword:04X}", "error_code": f"0x{d.error_code:04X}"}
            for d in base.drive_status()]


def _drive_twist(base: Any, twist: list[float], seconds: float, rate_hz: float) -> dict[str, Any]:
    """Cycle send_twist + read_odometry at ``rate_hz`` for ``seconds``, then stop and
    wait for the wheels to stop; returns cycle count and timing [us]."""
    import numpy as np

    period_ns = round(1e9 / rate_hz)
    n = max(1, round(seconds * rate_hz))
    cost = np.empty(n)
    commanded = None
    deadline = time.perf_counter_ns()
    for k in range(n):
        t0 = time.perf_counter_ns()
        commanded = base.send_twist(*twist)
        base.read_odometry()
        cost[k] = (time.perf_counter_ns() - t0) / 1e3
        deadline += period_ns
        left = deadline - time.perf_counter_ns()
        if left > 0:
            time.sleep(left / 1e9)
    end = time.monotonic() + _STOP_WAIT
    while True:
        base.stop()
        o = base.read_odometry()
        if abs(o.vx) + abs(o.vy) + abs(o.wz) < 1e-3 or time.monotonic() > end:
            break
        time.sleep(period_ns / 1e9)
    return {
        "twist": twist,
        "commanded": [round(v, 6) for v in commanded] if commanded else None,
        "seconds": seconds,
        "cycles": n,
        "cycle_us": {"mean": round(float(cost.mean()), 1),
                     "p50": round(float(np.percentile(cost, 50)), 1),
                     "p99": round(float(np.percentile(cost, 99)), 1),
                     "max": round(float(cost.max()), 1)},
    }


def run(args: argparse.Namespace) -> int:
    from mmctl.config import default_config, load_config
    from mmctl.runtime.logging import setup_logging
    from mmctl.transports.base import open_base

    setup_logging("warning", stream=cast(TextIO, _Stderr()))  # stdout carries the report only
    # canopen logs SDO aborts itself; the probe reports them as one line instead
    logging.getLogger("canopen").setLevel(logging.CRITICAL)
    cfg: Any = load_config(args.config) if args.config else default_config()
    transport = args.transport or cfg.base.transport
    port = args.port
    sim: Any = None
    if args.simulate:
        if transport == "canopen":
            # the simulated drives run in this process: on python-can's virtual bus,
            # whatever interface the configuration names for the robot
            cfg = dataclasses.replace(cfg, base=dataclasses.replace(
                cfg.base, canopen=dataclasses.replace(cfg.base.canopen, interface="virtual")))
            from mmctl.sim.fake_drives import FakeDrives

            sim = FakeDrives(cfg).start()
        else:
            from mmctl.sim.fake_serial_bridge import FakeSerialBridge

            sim = FakeSerialBridge(cfg).start()
            port = sim.port
    report: dict[str, Any] = {"transport": transport, "simulated": bool(args.simulate)}
    if transport == "canopen":
        report["channel"] = cfg.base.canopen.channel
        report["node_ids"] = list(cfg.base.canopen.node_ids)
    else:
        report["port"] = port or cfg.base.serial.port
    base = open_base(cfg, transport=transport, port=port)
    try:
        base.connect()
        report["before_enable"] = _drives(base)
        base.enable()
        report["drives"] = _drives(base)
        report["odometry_before"] = _odo(base.read_odometry())
        if args.twist:
            report["motion"] = _drive_twist(base, list(args.twist), args.seconds,
                                            cfg.loop.rate_hz)
        report["odometry_after"] = _odo(base.read_odometry())
        base.disable()
    finally:
        base.close()
        if sim is not None:
            sim.stop()
    _print(report, args.json)
    return 0


def _print(report: dict[str, Any], as_json: bool) -> None:
    if as_json:
        print(json.dumps(report, indent=2))
        return
    where = (f"channel {report['channel']!r} (node ids "
             f"{', '.join(map(str, report['node_ids']))})" if report["transport"] == "canopen"
             else f"port {report['port']}")
    print(f"base: {report['transport']} on {where}"
          + (" [simulated]" if report["simulated"] else ""))
    for d in report["drives"]:
        print(f"  {d['wheel']} ({d['address']}): link {d['link']}, {d['state']}, "
              f"statusword {d['statusword']}, error {d['error_code']}")
    for key in ("odometry_before", "odometry_after"):
        o = report[key]
        print(f"{key.replace('_', ' ')}: x={o['x']:+.4f} m y={o['y']:+.4f} m "
              f"yaw={o['yaw']:+.4f} rad")
        if key == "odometry_before" and "motion" in report:
            m = report["motion"]
            c = m["cycle_us"]
            print(f"twist {tuple(m['twist'])} for {m['seconds']} s: {m['cycles']} cycles, "
                  f"{c['mean']} us/cycle mean, p99 {c['p99']} us, max {c['max']} us")
