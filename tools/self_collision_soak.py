#!/usr/bin/env python3
"""Random pushes toward the robot's own body: the smallest distance ever seen, and the
self-collision check's cost.

The controller (``config/sim.yaml`` or ``--config``) drives the simulated robot's own
plant (:class:`mmctl.sim.plant.Plant`, as ``tests/test_self_collision.py``); a person
pushes the handle ``--pushes`` times with 30-80 N in a random direction (pointing down
half the time or more, where the deck is) for ``--seconds``, then lets go for 0.3 s;
each push starts where the last left the robot, in a mode drawn from min-energy,
manipulation, locomotion and switch.  Every 5th cycle the robot's parts are measured
independently of the controller (``BodyModel.closest``).

Printed: the smallest distance seen [m] with its pair and push, how many pushes the
check braked, faults (any is a failure: exit 1), and the cost of the check inside the
controller's step: ``brake`` per cycle (p50/p99 [us], its share of the step) and one
measure (every pair's distance, the watched pairs' gradients) and its look-ahead.

    .venv/bin/python tools/self_collision_soak.py [--pushes 200] [--seconds 1.5]
        [--seed 29] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
MODES = ("min-energy", "manipulation", "locomotion", "switch")


def soak(cfg: Any, pushes: int, seconds: float, seed: int) -> dict[str, Any]:
    import mmctl.control.body as body_module
    from mmctl.control.step import Controller, StepInputs
    from mmctl.model.geometry import BodyModel
    from mmctl.model.planar import world_to_base
    from mmctl.sim.plant import Plant

    ctl = Controller(cfg)
    assert ctl.body is not None, "safety.collision_check is off in this config"
    body = BodyModel(cfg.robot, ctl.model.arm, ctl.model.mount)
    dt = 1.0 / cfg.loop.rate_hz
    rng = np.random.default_rng(seed)
    brake_ns: list[int] = []
    near_ns: list[int] = []
    step_ns: list[int] = []
    clock = time.perf_counter_ns
    brake, near = body_module.BodyCheck.brake, body_module.BodyCheck._measure
    ahead_ns: list[int] = []
    look = body_module.BodyCheck._look_ahead

    def timed_look(self: Any, *a: Any) -> Any:
        t0 = clock()
        out = look(self, *a)
        ahead_ns.append(clock() - t0)
        return out


    def timed_brake(self: Any, *a: Any) -> Any:
        t0 = clock()
        out = brake(self, *a)
        brake_ns.append(clock() - t0)
        return out

    def timed_near(self: Any, *a: Any) -> Any:
        t0 = clock()
        out = near(self, *a)
        near_ns.append(clock() - t0)
        return out

    body_module.BodyCheck.brake = timed_brake  # type: ignore[method-assign]
    body_module.BodyCheck._measure = timed_near  # type: ignore[method-assign]
    body_module.BodyCheck._look_ahead = timed_look  # type: ignore[method-assign]
    try:
        plant = Plant(cfg, np.concatenate((ctl.q_des[:6], np.zeros(3))))
        lowest = (np.inf, ("", ""), -1)
        braked = faults = 0
        for i in range(pushes):
            mode = MODES[int(rng.integers(len(MODES)))]
            direction = rng.normal(size=3)
            if rng.random() < 0.5:
                direction[2] = -abs(direction[2])
            force = rng.uniform(30.0, 80.0) * direction / np.linalg.norm(direction)
            state = ctl.initial_state(mode)
            hit = False
            for k in range(int((seconds + 0.3) / dt)):
                q, qd = plant.state()
                push = force if k * dt < seconds else np.zeros(3)
                f_h = np.concatenate((world_to_base(push, float(q[8])), np.zeros(3)))
                t0 = clock()
                state, out = ctl.step(state, StepInputs(f_h, q, qd, dt))
                step_ns.append(clock() - t0)
                if out.fault is not None:
                    faults += 1
                    print(f"push {i}: fault {out.fault.value} {out.body}", file=sys.stderr)
                    break
                hit = hit or out.limit == "self_collision"
                if k % 5 == 0:
                    d = body.closest(q[:6])
                    if d.distance < lowest[0]:
                        lowest = (d.distance, d.pair, i)
                plant.step(out.qdot_arm, out.base_twist, dt)
            braked += hit
            if (i + 1) % 20 == 0:
                print(f"\rself-collision soak: {i + 1}/{pushes} pushes", end="",
                      file=sys.stderr, flush=True)
        print(file=sys.stderr)
    finally:
        body_module.BodyCheck.brake = brake  # type: ignore[method-assign]
        body_module.BodyCheck._measure = near  # type: ignore[method-assign]
        body_module.BodyCheck._look_ahead = look  # type: ignore[method-assign]

    def pct(xs: list[int], p: float) -> float:
        return round(float(np.percentile(xs, p)) / 1e3, 1) if xs else float("nan")

    return {
        "pushes": pushes, "seconds": seconds, "seed": seed,
        "margin_m": cfg.safety.collision_margin,
        "smallest_m": round(float(lowest[0]), 5), "smallest_pair": "-".join(lowest[1]),
        "smallest_push": lowest[2], "braked_pushes": braked, "faults": faults,
        "cycles": len(step_ns),
        "step_us": {"p50": pct(step_ns, 50), "p99": pct(step_ns, 99)},
        "brake_us": {"p50": pct(brake_ns, 50), "p99": pct(brake_ns, 99)},
        "measure_us": {"p50": pct(near_ns, 50), "p99": pct(near_ns, 99),
                       "per_cycle": round(len(near_ns) / max(len(brake_ns), 1), 3)},
        "look_ahead_us": {"p50": pct(ahead_ns, 50), "p99": pct(ahead_ns, 99)},
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "config" / "sim.yaml"))
    p.add_argument("--pushes", type=int, default=200)
    p.add_argument("--seconds", type=float, default=1.5)
    p.add_argument("--seed", type=int, default=29)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    sys.path.insert(0, str(ROOT / "src"))
    from mmctl.config import load_config

    r = soak(load_config(args.config), args.pushes, args.seconds, args.seed)
    if args.json:
        print(json.dumps(r))
    else:
        print(f"{r['pushes']} pushes of 30-80 N, {r['cycles']} cycles: smallest distance "
              f"{r['smallest_m']:.4f} m ({r['smallest_pair']}, push {r['smallest_push']}) "
              f"against the margin {r['margin_m']} m; braked in {r['braked_pushes']} pushes; "
              f"faults {r['faults']}")
        print(f"cost in the controller's step: brake p50/p99 {r['brake_us']['p50']}/"
              f"{r['brake_us']['p99']} us (step {r['step_us']['p50']}/{r['step_us']['p99']} us); "
              f"a measure {r['measure_us']['p50']}/{r['measure_us']['p99']} us (and its "
              f"look-ahead {r['look_ahead_us']['p50']}/{r['look_ahead_us']['p99']} us) in "
              f"{r['measure_us']['per_cycle']:.0%} of the cycles")
    return 1 if r["faults"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
