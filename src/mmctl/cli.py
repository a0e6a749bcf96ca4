"""The `mmctl` command line.

Each command lives in its own module under :mod:`mmctl.commands` with two functions,
``add_arguments(parser)`` and ``run(args) -> int``; heavy imports happen inside
``run`` so that ``mmctl --help`` and the control commands stay fast.  Register a new
command by adding one line to :data:`COMMANDS` (or to a group in :data:`GROUPS`).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from mmctl import __version__
from mmctl.errors import MmctlError

#: (command, module, one-line help)
COMMANDS: list[tuple[str, str, str]] = [
    ("check-config", "mmctl.commands.check_config", "validate a YAML config file"),
    ("config", "mmctl.commands.config", "every config key with default and range; check a file"),
    ("trial", "mmctl.commands.trial", "bracket a task execution: trial start|stop|status"),
    ("metrics", "mmctl.commands.metrics", "recompute trial metrics from a .rrd recording"),
    ("study", "mmctl.commands.study", "reproduce the paper's 27-user study in simulation"),
    ("fake-ur", "mmctl.commands.fake_ur", "run a fake UR10e controller on a loopback address"),
    ("run", "mmctl.commands.run", "run the control daemon (default: the simulated robot)"),
    ("sim", "mmctl.commands.sim", "run the simulated robot, or push/fault/status a running one"),
    ("status", "mmctl.commands.status", "show the daemon's state, mode, fault and loop timing"),
    ("enable", "mmctl.commands.enable", "arm the robot (refused while a fault is present)"),
    ("disable", "mmctl.commands.disable", "disarm: stop the arm and the base"),
    ("mode", "mmctl.commands.mode", "change the IDK strategy at run time"),
    ("switch", "mmctl.commands.switch", "switch mode: toggle manipulation / locomotion"),
    ("profile", "mmctl.commands.profile", "limits profile: normal, or reduced (0.25 m/s)"),
    ("set", "mmctl.commands.param:set",
     "change a control parameter at run time (admittance, caps, IDK gains)"),
    ("get", "mmctl.commands.param:get", "read a key of the running configuration"),
    ("tare", "mmctl.commands.tare", "re-zero the force/torque sensor"),
    ("model", "mmctl.commands.model", "the robot's URDF, and the distances between its parts"),
    ("pose", "mmctl.commands.pose", "record the arm's pose as the preferred one (robot.q_des)"),
    ("stop", "mmctl.commands.stop", "shut the daemon down"),
    ("replay", "mmctl.commands.replay",
     "run a recorded inputs log through the update again; the first differing cycle"),
]

#: group -> (help, [(sub-command, module, one-line help)])
GROUPS: dict[str, tuple[str, list[tuple[str, str, str]]]] = {
    "bench": ("benchmarks that print figures", [
        ("idk", "mmctl.bench.idk", "time the IDK strategies vs the paper's explicit inverse"),
        ("loop", "mmctl.bench.loop", "500 Hz loop timing vs a time.sleep loop"),
        ("soak", "mmctl.bench.soak", "soak the daemon: pushes, floods, faults; growth and verdict"),
        ("startup", "mmctl.bench.startup",
         "misses in short bins after start-up, enable and a fault's re-enable"),
        ("caps", "mmctl.bench.caps", "hard pushes on the simulated plant: E_K and speeds vs caps"),
    ]),
    "probe": ("bring-up probes for one device", [
        ("sensor", "mmctl.commands.probe_sensor", "read the force/torque sensor, print the wrench"),
        ("base", "mmctl.commands.probe_base", "enable the base drives, report states, drive a twist"),
        ("arm", "mmctl.commands.probe_arm", "connect to the UR10e, print its state, jog a joint"),
    ]),
    "calibrate": ("calibrations that move the robot", [
        ("tool", "mmctl.commands.calibrate_tool",
         "weigh the handle: sensor bias, mass and centre of mass by least squares"),
    ]),
}


def _add(sub: argparse._SubParsersAction[argparse.ArgumentParser], name: str, module: str, help_: str) -> None:
    """One command: ``module`` has ``add_arguments`` and ``run``; ``module:which`` has
    ``add_which_arguments`` and ``run_which`` (two commands in one module)."""
    module, _, which = module.partition(":")
    mod = importlib.import_module(module)
    p = sub.add_parser(name, help=help_, description=mod.__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    if which:
        getattr(mod, f"add_{which}_arguments")(p)
        p.set_defaults(_run=getattr(mod, f"run_{which}"))
        return
    mod.add_arguments(p)
    p.set_defaults(_run=mod.run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mmctl",
        description="Control daemon of a UR10e + RB-KAIROS+ mobile manipulator for physical "
        "human-robot interaction (minimum-energy whole-body admittance control).",
    )
    parser.add_argument("--version", action="version", version=f"mmctl {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, module, help_ in COMMANDS:
        _add(sub, name, module, help_)
    for group, (help_, members) in GROUPS.items():
        if not members:
            continue
        gp = sub.add_parser(group, help=help_, description=help_)
        gsub = gp.add_subparsers(dest="subcommand", metavar="WHAT")
        gsub.required = True
        for name, module, mhelp in members:
            _add(gsub, name, module, mhelp)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "_run"):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except MmctlError as exc:
        print(f"mmctl {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # `mmctl config reference | head`: the reader left, no traceback
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
