"""CPU cost of the simulated base's wheel plant: how long (process CPU time) one second of
a moving base takes to integrate, advanced in 2-ms calls as the fake drives' SYNCs do and
in one lazy call as a status request after a quiet second does (config/sim.yaml's
sim.base_* dynamics, every wheel turning, a new target each call).

    .venv/bin/python tools/wheel_plant_bench.py [--seconds 5]

The simulation runs this plant in real time: a cost near 1 s per second means the
simulation needs a whole core whenever the base moves (what a busy machine could not
give it; see docs/sim.md)."""

from __future__ import annotations

import argparse
import time

from mmctl.config import load_config
from mmctl.sim.wheels import BaseDynamics, WheelPlant


def _plant() -> WheelPlant:
    cfg = load_config("config/sim.yaml")
    p = WheelPlant(cfg.base.mecanum, 2.0, 0.5, t0=0.0,
                   dynamics=BaseDynamics.from_config(cfg.sim))
    for w in range(4):
        p.track(w, 0.0)
    return p


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="simulated seconds (5)")
    n = max(1, round(ap.parse_args().seconds / 0.002))
    p = _plant()
    c0 = time.process_time()
    for k in range(1, n + 1):
        t = k * 0.002
        for w in range(4):
            p.command(w, 3.0 if w % 2 else -3.0, t)
        p.advance(t)
    synced = (time.process_time() - c0) / (n * 0.002)
    p = _plant()
    for w in range(4):
        p.command(w, 3.0 if w % 2 else -3.0, 0.0)
    c0 = time.process_time()
    p.advance(n * 0.002)
    lazy = (time.process_time() - c0) / (n * 0.002)
    print(f"wheel plant, {n * 0.002:g} s of a moving base: {synced * 1e3:.1f} ms CPU per "
          f"second in 2-ms calls, {lazy * 1e3:.1f} ms CPU per second in one call")


if __name__ == "__main__":
    main()
