"""Record the arm's current pose as the preferred configuration ``robot.q_des``.

  mmctl pose record                      print the pose as a YAML snippet
  mmctl pose record --write robot.yaml   and put it into that config file

The pose is the daemon's newest arm sample (`mmctl status`).  It must lie inside every
joint's limits by ``limits.position_margin`` (the limits of the file written, else of
``--config``), and away from a singular configuration (``safety.max_condition``), or
nothing is written.  ``--write`` changes only the ``q_des`` entry of the ``robot:``
section (adding it when missing; the file's comments and layout stay), and checks the
whole file loads afterwards before it replaces it.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from mmctl.commands.yaml_edit import set_entries, write_checked
from mmctl.runtime.client import add_client_arguments, call, load


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("record",), help="record: the current arm pose")
    p.add_argument("--write", metavar="FILE",
                   help="put the pose into FILE's robot.q_des (the file is checked first)")
    add_client_arguments(p)


def check_pose(q: list[float], cfg: Any) -> None:
    """MmctlError naming the joint when ``q`` (6,) is not a usable preferred pose for
    ``cfg``: inside every joint's limits by the margin, not singular."""
    import numpy as np

    from mmctl.errors import MmctlError
    from mmctl.model import RobotModel

    lim = cfg.limits
    m = lim.position_margin
    for i, (x, lo, hi) in enumerate(zip(q, lim.joint_position_min, lim.joint_position_max)):
        if not lo + m <= x <= hi - m:
            raise MmctlError(f"joint {i} is at {x:.4f} rad: a preferred pose must be within "
                             f"[{lo + m:.4f}, {hi - m:.4f}] rad (limits.joint_position_min/max "
                             f"{lo:.4f}/{hi:.4f} and limits.position_margin {m:g}); move the "
                             "arm and record again")
    cond = RobotModel(cfg.robot).condition(np.concatenate((np.asarray(q, dtype=float),
                                                           np.zeros(3))))
    if cond > cfg.safety.max_condition / 10:
        raise MmctlError(f"the pose is close to a singular configuration (condition "
                         f"{cond:.3g}, the fault is at safety.max_condition = "
                         f"{cfg.safety.max_condition:g}): move the arm away and record again")


def _flow(q: list[float]) -> str:
    return "[" + ", ".join(f"{x:.5f}" for x in q) + "]"


def with_q_des(text: str, q: list[float]) -> str:
    """``text`` (a YAML config) with ``robot.q_des`` set to ``q``: the entry replaced in
    place (a flow list on one line or a block list), added under ``robot:``, or a
    ``robot:`` section appended; everything else unchanged."""
    return set_entries(text, ("robot",), {"q_des": _flow(q)}, "recorded by mmctl pose record")


def run(args: argparse.Namespace) -> int:
    from mmctl.config import load_config
    from mmctl.errors import MmctlError

    st = call(args, "status")
    robot = st.get("robot")
    if not robot or not robot.get("q"):
        raise MmctlError("the daemon has no arm sample yet: nothing to record")
    q = [float(x) for x in robot["q"][:6]]
    target = Path(args.write) if args.write else None
    cfg = load_config(target) if target is not None and target.exists() else load(args.config)
    check_pose(q, cfg)
    print(f"robot:\n  q_des: {_flow(q)}")
    if target is None:
        return 0
    text = target.read_text() if target.exists() else ""

    def check(written: Any) -> None:
        if list(written.robot.q_des) != [round(x, 5) for x in q]:
            raise MmctlError(f"{target}: q_des did not round-trip (a second robot: section?)")

    write_checked(target, with_q_des(text, q), check)
    print(f"written to {target}")
    return 0
