"""Bracket one task execution: `mmctl trial start`, then `mmctl trial stop`.

The daemon counts every control cycle between the two (both included) and, on stop,
computes the paper's metrics (eq. 14-16): average kinetic energy E [J], average human
force F_h [N], average end-effector speed v [m/s], final displacement
x_f = |p(T_f) - p_des| [m] and execution time T_f [s].  It logs them as one event and
writes them into the recording (entity trial/metrics); `stop` prints them.
`mmctl trial status` lists the trials of this daemon run.
"""

from __future__ import annotations

import argparse
import json

from mmctl.runtime.client import add_client_arguments, call


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("start", "stop", "status"))
    add_client_arguments(p)
    p.add_argument("--json", action="store_true", help="print the daemon's answer as JSON")


def run(args: argparse.Namespace) -> int:
    res = call(args, "trial", action=args.action)
    if args.json:
        print(json.dumps(res))
        return 0
    if args.action == "start":
        print(f"trial {res['trial']} started")
    elif args.action == "stop":
        print(_line(res))
    else:
        print(f"trial running: {'yes' if res['active'] else 'no'}")
        for t in res["trials"]:
            print(_line(t))
    return 0


def _line(t: dict) -> str:  # type: ignore[type-arg]
    return (f"trial {t['trial']}: E={t['E']:.4f} J  F_h={t['F_h']:.3f} N  v={t['v']:.4f} m/s  "
            f"x_f={t['x_f']:.4f} m  T_f={t['T_f']:.3f} s  ({t['samples']} cycles "
            f"{t['start_cycle']}-{t['stop_cycle']})")
