"""Weigh the handle: the sensor's bias, the handle's mass and centre of mass.

  mmctl calibrate tool                      run it; print the fit and a YAML snippet
  mmctl calibrate tool --poses 12 --json    more poses; everything as JSON
  mmctl calibrate tool --write robot.yaml   and put mass and centre of mass into that file

The robot must be armed and still, and nobody may touch the handle: the daemon turns
the wrist (wrists 1-3, within sensor.calibration.wrist_range of where it stands, at
most sensor.calibration.speed) through N orientations, averages the raw wrench at
each, and returns to the start pose; the base does not move.  A force on the handle
beyond the handle's own weight stops the robot and disarms it, and so does Ctrl-C
here.  The fit (linear least squares, docs/hand-guiding.md): mass, centre of mass in
the sensor frame, the sensor's bias, the residuals and the design's condition number;
a warning when the poses did not spread enough.  ``--write`` changes only
``sensor.wrench.handle_mass`` and ``handle_com`` in FILE (comments and layout kept,
the whole file checked before it is replaced); the daemon uses them once restarted
(the bias is the tare's: `mmctl tare`).  Exit status 0 with a fit that determines
every unknown, 1 without one (nothing written), 2 when it was refused or aborted.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mmctl.runtime.client import add_client_arguments, call

#: [s] between two progress requests
POLL = 0.25


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--poses", type=int, metavar="N",
                   help="orientations to weigh, 4..50 (default sensor.calibration.poses)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--write", metavar="FILE",
                   help="put handle_mass and handle_com into FILE's sensor.wrench section")
    add_client_arguments(p)


def _vec(v: list[float | None], nd: int) -> str:
    return "[" + ", ".join("nan" if x is None else f"{x:.{nd}f}" for x in v) + "]"


def snippet(fit: dict[str, Any]) -> str:
    """The YAML lines for ``sensor.wrench`` (mass [kg] and centre of mass [m], 0.1 g
    and 0.01 mm)."""
    return (f"sensor:\n  wrench:\n    handle_mass: {fit['mass_kg']:.5f}\n"
            f"    handle_com: {_vec(fit['com_m'], 5)}\n")


def report(st: dict[str, Any]) -> str:
    """The fit for a person."""
    fit, conf = st["fit"], st["configured"]
    lines = [
        (f"mass: {fit['mass_kg']:.4f} kg +- {fit['mass_std_kg'] or 0:.4f} "
         f"(configured {conf['handle_mass']:g})"),
        (f"centre of mass: {_vec(fit['com_m'], 4)} m +- {_vec(fit['com_std_m'], 4)} "
         f"(sensor frame; configured {_vec(conf['handle_com'], 4)})"),
        f"bias: force {_vec(fit['bias'][:3], 3)} N, torque {_vec(fit['bias'][3:], 4)} N m",
        (f"residual: force rms {fit['residual_force_rms_N']:.3f} N (max "
         f"{fit['residual_force_max_N']:.3f}), torque rms "
         f"{fit['residual_torque_rms_Nm']:.4f} N m (max {fit['residual_torque_max_Nm']:.4f})"),
        (f"poses: {fit['poses']} in {st['elapsed_s']:.1f} s, gravity directions spread "
         f"over {fit['spread_deg']:.0f} deg, condition {fit['condition'] or 'inf'}"),
    ]
    lines += [f"warning: {w}" for w in fit["warnings"]]
    return "\n".join(lines)


def _write(target: Path, fit: dict[str, Any]) -> None:
    from mmctl.commands.yaml_edit import set_entries, write_checked
    from mmctl.errors import MmctlError

    mass = round(fit["mass_kg"], 5)
    com = [round(x, 5) for x in fit["com_m"]]
    text = target.read_text() if target.exists() else ""
    out = set_entries(text, ("sensor", "wrench"),
                      {"handle_mass": f"{mass:.5f}", "handle_com": _vec(com, 5)},
                      "calibrated by mmctl calibrate tool")

    def check(cfg: Any) -> None:
        w = cfg.sensor.wrench
        if w.handle_mass != mass or list(w.handle_com) != com:
            raise MmctlError(f"{target}: the fit did not round-trip (a second sensor: "
                             "section?)")

    write_checked(target, out, check)


def _interrupt_on_hangup() -> Callable[[], None]:
    """SIGTERM and SIGHUP (the terminal closed) stop the calibration as Ctrl-C does;
    returns what puts the previous handlers back (a no-op off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def interrupt(_signum: int, _frame: Any) -> None:
        raise KeyboardInterrupt

    old = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}

    def restore() -> None:
        for sig, handler in old.items():
            signal.signal(sig, handler)

    return restore


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import MmctlError

    params: dict[str, Any] = {"action": "start"}
    if args.poses is not None:
        params["poses"] = args.poses
    start = call(args, "calibrate", **params)
    if not args.json:
        print(f"calibrating: {start['poses']} poses, about {start['estimated_s']:.0f} s; "
              "hands off the handle (Ctrl-C stops the robot)", file=sys.stderr)
    shown: tuple[Any, ...] = ()
    restore = _interrupt_on_hangup()
    try:
        while True:
            time.sleep(POLL)
            st = call(args, "calibrate", action="status")
            if st["phase"] in ("done", "aborted"):
                break
            now = (st["pose"], st["phase"] == "returning")
            if not args.json and now != shown:
                shown = now
                where = "back to the start" if now[1] else f"pose {st['pose']}/{st['poses']}"
                print(f"  {where}", file=sys.stderr)
    except KeyboardInterrupt:
        try:
            call(args, "calibrate", action="abort")
        finally:
            print("calibration aborted: the robot is stopped and disarmed", file=sys.stderr)
        raise
    finally:
        restore()
    if st["phase"] == "aborted":
        raise MmctlError(f"calibration aborted: {st['error']}; the robot is stopped and "
                         "disarmed (`mmctl enable`, then calibrate again)")
    fit = st["fit"]
    determined = not fit["undetermined"] and fit["mass_kg"] is not None \
        and None not in fit["com_m"]
    if args.write and not determined:
        raise MmctlError(f"nothing written to {args.write}: " + "; ".join(fit["warnings"]))
    if args.write:
        _write(Path(args.write), fit)
        st["written"] = args.write
    if args.json:
        print(json.dumps(st, indent=2, sort_keys=True))
    else:
        print(report(st))
        if determined:
            print(snippet(fit), end="")
        if args.write:
            print(f"written to {args.write}")
    return 0 if determined else 1
