"""Show the hand-guiding caps hold: hard pushes on the simulated robot's plant.

For each IDK strategy and each limits profile, the pure controller (the daemon's
``Controller.step``, admittance to limits) runs in closed loop with the simulated
robot's own plant (:class:`mmctl.sim.plant.Plant`: the fake UR's joints under speedJ,
the fake drives' wheels) for ``--seconds`` per push; the person pushes hard
(``--force`` N) along each of four horizontal directions, then lets go.  Reported per
run, from the plant's *actual* velocities (what a person would be hit with), next to
the cap: the largest whole-body kinetic energy E_K (the paper's block-diagonal M), base
linear speed and end-effector linear speed; and which limit bound the command most
often.  Exit 1 when a measured maximum exceeds its cap by more than ``--tolerance``
(the arm and the drives follow a command one cycle late)."""

from __future__ import annotations

import argparse
import collections
import json
import math
from typing import Any

import numpy as np

from mmctl.config import Config, default_config, load_config

DIRECTIONS = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))
MODES = ("min-energy", "locomotion", "manipulation")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="YAML config (default: built-in defaults)")
    p.add_argument("--force", type=float, default=80.0, metavar="N",
                   help="the push [N] (default 80: well past what the caps allow)")
    p.add_argument("--seconds", type=float, default=3.0, metavar="S",
                   help="how long each push lasts (default 3)")
    p.add_argument("--tolerance", type=float, default=0.03,
                   help="allowed relative excess of a measured maximum (default 0.03)")
    p.add_argument("--json", action="store_true", help="print the results as JSON")


def run_pushes(cfg: Config, mode: str, profile: str, force: float,
               seconds: float) -> dict[str, Any]:
    """Push along each of :data:`DIRECTIONS` for ``seconds``, then let go for a second;
    the maxima of the plant's actual E_K, base and end-effector speed, and the caps."""
    from mmctl.control.energy import kinetic_energy
    from mmctl.control.step import Controller, StepInputs
    from mmctl.sim.plant import Plant

    ctl = Controller(cfg)
    model = ctl.model
    state = ctl.set_profile(ctl.initial_state(mode), profile)
    dt = 1.0 / cfg.loop.rate_hz
    q0 = np.concatenate((np.asarray(cfg.robot.q_des, dtype=float), np.zeros(3)))
    plant = Plant(cfg, q0)
    limits = ctl.limits_reduced if profile == "reduced" else ctl.limits
    e_max = base_max = ee_max = 0.0
    bound: collections.Counter[str] = collections.Counter()
    cycles = 0
    for dx, dy in DIRECTIONS:
        f = np.array([force * dx, force * dy, 0.0, 0.0, 0.0, 0.0])
        for k in range(int((seconds + 1.0) / dt)):
            q, qd = plant.state()
            push = f if k * dt < seconds else np.zeros(6)
            state, out = ctl.step(state, StepInputs(push, q, qd, dt))
            if out.fault is not None:
                raise RuntimeError(f"{mode}/{profile}: fault {out.fault.value} at cycle {cycles}")
            bound[out.limit or "none"] += 1
            kin = model.update(q)
            e_max = max(e_max, kinetic_energy(kin.M_a, kin.M_b, qd).total)
            base_max = max(base_max, math.hypot(qd[6], qd[7]))
            v = kin.J @ qd
            ee_max = max(ee_max, float(np.linalg.norm(v[:3])))
            plant.step(out.qdot_arm, out.base_twist, dt)
            cycles += 1
    return {
        "mode": mode, "profile": profile, "force_N": force, "cycles": cycles,
        "energy_J": {"max": e_max, "cap": limits.energy},
        "base_speed_m_s": {"max": base_max, "cap": limits.v_lin},
        "ee_speed_m_s": {"max": ee_max, "cap": limits.ee_lin},
        "binding": dict(bound.most_common()),
    }


def exceeded(r: dict[str, Any], tolerance: float) -> list[str]:
    """The quantities of a :func:`run_pushes` result above their cap (+ tolerance)."""
    return [k for k in ("energy_J", "base_speed_m_s", "ee_speed_m_s")
            if r[k]["max"] > r[k]["cap"] * (1.0 + tolerance)]


def run(args: argparse.Namespace) -> int:
    from mmctl.control.step import whole_body_caps
    from mmctl.errors import MmctlError
    from mmctl.model import RobotModel

    if not (args.force > 0 and args.seconds > 0 and args.tolerance >= 0):
        raise MmctlError("--force and --seconds must be > 0, --tolerance >= 0")
    cfg = load_config(args.config) if args.config else default_config()
    caps = whole_body_caps(cfg, RobotModel(cfg.robot).arm_mass)
    results = [run_pushes(cfg, m, p, args.force, args.seconds)
               for p in ("normal", "reduced") for m in MODES]
    bad = {f"{r['mode']}/{r['profile']}": exceeded(r, args.tolerance) for r in results}
    bad = {k: v for k, v in bad.items() if v}
    if args.json:
        print(json.dumps({"body_region": cfg.limits.body_region, "caps": caps._asdict(),
                          "results": results, "exceeded": bad}, indent=2))
    else:
        print(f"caps ({cfg.limits.body_region}, ISO/TS 15066): E_K {caps.energy:.3f} J, "
              f"base {caps.base_speed:.3f} m/s, end-effector {caps.ee_speed:.3f} m/s; "
              f"pushes of {args.force:g} N for {args.seconds:g} s along +x, +y, -x, -y")
        print(f"{'mode/profile':26} {'E_K max/cap [J]':>18} {'base max/cap [m/s]':>20} "
              f"{'ee max/cap [m/s]':>18}  binding most")
        for r in results:
            def pair(key: str, r: dict[str, Any] = r) -> str:
                return f"{r[key]['max']:.3f} / {r[key]['cap']:.3f}"
            top = ", ".join(f"{k} {100 * n / r['cycles']:.0f}%"
                            for k, n in list(r["binding"].items())[:2])
            print(f"{r['mode'] + '/' + r['profile']:26} {pair('energy_J'):>18} "
                  f"{pair('base_speed_m_s'):>20} {pair('ee_speed_m_s'):>18}  {top}")
        print("every maximum within its cap" if not bad else f"EXCEEDED: {bad}")
    return 1 if bad else 0
