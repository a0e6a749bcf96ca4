"""The simulated robot: run it (`mmctl sim`), or talk to a running one.

`mmctl sim` runs the whole simulated robot in this process (and the fake UR
controller's): fake UR10e controller (RTDE, dashboard, script ports on arm.host), fake
ATI sensor and four CiA 402 drives on virtual CAN channels served by socketcand on
sim.host:sim.can_port, the plant and a simulated person.  `mmctl run` on the same
configuration attaches to it (or, when none answers, starts its own).

  mmctl sim status              the person, the push, the faults, the true joints
  mmctl sim push 20 0 0         push the handle with 20 N along world x (until ended)
  mmctl sim push 20 0 0 --seconds 2
  mmctl sim person on|off       the simulated person takes over / lets go (ends a push)
  mmctl sim press               press the handle button (switch mode)
  mmctl sim enabling hold|release   the person holds / releases the enabling switch
  mmctl sim slider 0.5          the pendant's speed slider: the UR runs speedJ at 50 %
  mmctl sim fault NAME [--off]  inject a fault into the fakes (--list: the names)
  mmctl sim stop                end the simulation
"""

from __future__ import annotations

import argparse
import json
from typing import Any

ACTIONS = ("status", "push", "person", "press", "enabling", "slider", "fault", "stop")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", nargs="?", choices=ACTIONS, metavar="ACTION",
                   help=f"one of {', '.join(ACTIONS)}; none: run the simulated robot")
    p.add_argument("values", nargs="*", metavar="ARG",
                   help="push: FX FY FZ [N]; person: on|off; enabling: hold|release; "
                   "slider: FRACTION; fault: NAME")
    p.add_argument("--config", metavar="FILE", help="YAML config (default: config/sim.yaml)")
    p.add_argument("--seconds", type=float, metavar="S", help="push: end it after S seconds")
    p.add_argument("--off", action="store_true", help="fault: switch it off again")
    p.add_argument("--list", action="store_true", help="fault: list the fault names")
    p.add_argument("--json", action="store_true", help="status: the full status as JSON")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="how long to wait for the simulation's answer [s] (default 10)")
    g = p.add_argument_group("running the simulation")
    g.add_argument("--log", metavar="DIR", help="write the fakes' command logs to DIR at the end")
    g.add_argument("--log-level", choices=("debug", "info", "warning", "error"),
                   help="override daemon.log_level")
    g.add_argument("--log-json", action="store_true", help="JSON log lines even on a TTY")
    g.add_argument("--cpus", metavar="LIST",
                   help="run the simulation (and the fake UR's process) on these CPUs only, "
                   "e.g. 0 or 0,2: keep it off the control loop's CPUs, as hardware would be")
    g.add_argument("--log-console", action="store_true", help=argparse.SUPPRESS)
    g.add_argument("--exit-with-parent", action="store_true", help=argparse.SUPPRESS)
    g.add_argument("--delete-config", action="store_true", help=argparse.SUPPRESS)


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import MmctlError

    if args.action is None:
        if args.values:
            raise MmctlError(f"unexpected arguments {args.values}; actions: {', '.join(ACTIONS)}")
        return _serve(args)
    if args.action == "fault" and args.list:
        from mmctl.sim.world import FAULTS

        for name, what in FAULTS.items():
            print(f"{name:22} {what}")
        return 0
    req = _request(args)
    result = _call(args, *req)
    _print(args, result)
    return 0


def _serve(args: argparse.Namespace) -> int:
    import faulthandler
    import os
    from pathlib import Path

    from mmctl.runtime.client import load
    from mmctl.runtime.logging import setup_logging
    from mmctl.sim.service import SimService

    faulthandler.enable()
    if args.cpus:
        try:
            os.sched_setaffinity(0, {int(c) for c in args.cpus.split(",") if c.strip()})
        except (ValueError, OSError) as exc:
            from mmctl.errors import MmctlError

            raise MmctlError(f"--cpus {args.cpus!r}: {exc}") from None
    cfg = load(args.config)
    if args.delete_config and args.config:  # a temporary file written by `mmctl run`
        Path(args.config).unlink(missing_ok=True)
    json_logs = True if args.log_json else (False if args.log_console else None)
    setup_logging(args.log_level or cfg.daemon.log_level, json=json_logs)
    service = SimService(cfg, log_dir=Path(args.log) if args.log else None,
                         exit_with_parent=args.exit_with_parent)
    try:
        return service.run()
    except KeyboardInterrupt:
        return 130


def _request(args: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    from mmctl.errors import MmctlError

    a, v = args.action, args.values
    if a == "push":
        if len(v) != 3:
            raise MmctlError("push needs three numbers FX FY FZ [N] (world frame)")
        try:
            force = [float(x) for x in v]
        except ValueError:
            raise MmctlError(f"push needs three numbers FX FY FZ [N], got {v}") from None
        return "push", {"force": force, "seconds": args.seconds}
    if a == "person":
        if v not in (["on"], ["off"]):
            raise MmctlError("person needs on or off")
        return "person", {"on": v[0] == "on"}
    if a == "enabling":
        if v not in (["hold"], ["release"]):
            raise MmctlError("enabling needs hold or release")
        return "enabling", {"held": v[0] == "hold"}
    if a == "slider":
        try:
            (fraction,) = [float(x) for x in v]
        except ValueError:
            raise MmctlError("slider needs one fraction 0..1 (the pendant's speed slider)") \
                from None
        return "slider", {"fraction": fraction}
    if a == "fault":
        if len(v) != 1:
            raise MmctlError("fault needs one NAME (mmctl sim fault --list)")
        return "fault", {"name": v[0], "on": not args.off}
    if v:
        raise MmctlError(f"{a} takes no arguments, got {v}")
    return a, {}


def _call(args: argparse.Namespace, cmd: str, params: dict[str, Any]) -> Any:
    from mmctl.runtime.client import load
    from mmctl.runtime.ipc import request
    from mmctl.runtime.sim_link import absent_message, sim_socket_path

    path = sim_socket_path(load(args.config))
    return request(path, cmd, timeout=args.timeout, absent=absent_message(path), **params)


def _print(args: argparse.Namespace, st: Any) -> None:
    if args.json or not isinstance(st, dict) or "person" not in st:
        print(json.dumps(st, indent=2, sort_keys=True))
        return
    push = st.get("push")
    enabling = st.get("enabling")
    print(f"person: {st['person']}" + (f" (push {push} N)" if push else "")
          + f"  button: {'pressed' if st.get('button') else 'released'}"
          + (f"  enabling switch: {enabling}" if enabling else ""))
    print(f"faults: {', '.join(st.get('faults') or []) or '-'}")
    if st.get("handle_world"):
        print(f"handle: {st['handle_world']} m (world), hand force {st.get('hand_force')} N")
    if st.get("arm_q"):
        print(f"arm q: {st['arm_q']} rad")
    can = st.get("socketcand")
    if can:
        print(f"socketcand: {can['address']} ({can['clients']} client(s))")
    if st.get("error"):
        print(f"error: {st['error']}")
