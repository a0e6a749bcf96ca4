"""Run a fake UR10e controller (RTDE 30004, dashboard 29999, script 30003) in the foreground.

The real ur_rtde client (``mmctl probe arm``, the daemon) can then connect to it:

    mmctl fake-ur --host 127.0.0.5 &
    mmctl probe arm --host 127.0.0.5 --jog-joint 0 --speed 0.1 --seconds 1

Joints follow speedJ with its acceleration limit; Ctrl-C stops it.
"""

from __future__ import annotations

import argparse

from mmctl.config.robot import DEFAULT_Q_DES


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default="127.0.0.2",
                   help="loopback address to serve on (default 127.0.0.2)")
    p.add_argument("--q-init", type=float, nargs=6, metavar="RAD", default=list(DEFAULT_Q_DES),
                   help="initial joint positions [rad] (default: robot.q_des)")


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import TransportError
    from mmctl.runtime.logging import setup_logging
    from mmctl.sim.fake_ur import server

    setup_logging("info")

    if not args.host.startswith("127."):
        raise TransportError(f"--host {args.host}: the fake serves on loopback only (127.x.y.z)")
    print(f"fake UR controller on {args.host}: dashboard {server.DASHBOARD_PORT}, "
          f"script {server.SCRIPT_PORT}, RTDE {server.RTDE_PORT} (Ctrl-C to stop)", flush=True)
    try:
        signum = server.run(args.host, args.q_init, stop_signals=True)
    except OSError as exc:
        raise TransportError(f"cannot serve on {args.host}: {exc.strerror or exc}") from None
    return 0 if signum is None else 128 + signum  # as a shell reports a signal's end
