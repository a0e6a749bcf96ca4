"""The robot's model: its URDF, and the distances between its own parts.

  mmctl model urdf                         the whole robot as URDF on stdout
  mmctl model urdf --output robot.urdf     into a file
  mmctl model urdf --base planar           with odom and the base's planar joints
  mmctl model distances                    each checked pair's distance at robot.q_des
  mmctl model distances --q 0 -1.9 2.6 -1.6 -1.6 0

The URDF is written from the numbers the controller uses (`robot:` of --config): its
forward kinematics equal the model's, and its collision shapes are the ones the
self-collision check measures (docs/hand-guiding.md, "The robot's body").
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mmctl.runtime.client import load


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=("urdf", "distances"),
                   help="urdf: write the URDF; distances: the body's pairs at a pose")
    p.add_argument("--config", metavar="FILE", help="config file (default: the default one)")
    p.add_argument("--base", choices=("fixed", "planar"), default="fixed",
                   help="urdf: base_link as the root (fixed, default; odometry gives "
                   "odom -> base_link) or odom and three planar joints (planar)")
    p.add_argument("--output", "-o", metavar="FILE", help="urdf: write here instead of stdout")
    p.add_argument("--q", nargs=6, type=float, metavar="Q",
                   help="distances: the six arm joints [rad] (default: robot.q_des)")


def run(args: argparse.Namespace) -> int:
    cfg = load(args.config)
    if args.what == "urdf":
        from mmctl.model.urdf import urdf

        text = urdf(cfg, args.base)
        if args.output:
            Path(args.output).write_text(text, encoding="utf-8")
            print(f"wrote {args.output} ({len(text)} characters)", file=sys.stderr)
        else:
            sys.stdout.write(text)
        return 0
    import numpy as np

    from mmctl.model.geometry import BodyModel
    from mmctl.model.robot import RobotModel

    model = RobotModel(cfg.robot)
    body = BodyModel(cfg.robot, model.arm, model.mount)
    q = np.asarray(args.q if args.q else cfg.robot.q_des, dtype=float)
    print(f"{'pair':<24} {'distance [m]':>12}")
    for d in sorted(body.distances(q), key=lambda d: d.distance):
        print(f"{d.pair[0] + ' - ' + d.pair[1]:<24} {d.distance:12.4f}")
    return 0
