#!/usr/bin/env python3
"""Instructions per control update under valgrind's callgrind: a cost figure without noise.

Wall-clock figures of the cycle (``mmctl bench idk``, ``mmctl bench loop``) move by tens
of per cent from minute to minute on a shared machine.  The number of instructions the
CPU executes for one update does not: this tool counts them with callgrind (its ``Ir``
event) for ``--n`` updates after ``--warmup`` ones and prints the count per update.

    .venv/bin/python tools/update_cost.py [--mode MODE ...] [--n 2000] [--json]

What runs: the target (``--target``; ``cycle`` = :meth:`mmctl.control.cycle.CycleChain.
cycle`, built from ``--config``, default ``config/sim.yaml``) with scripted readings: the
arm still at ``robot.q_des``, the base at the origin, and a steady 20 N push on the handle
(x of the sensor frame, on top of the handle's weight), a new sensor sample every cycle,
the robot armed (``active``): the controller runs every cycle in the given IDK mode
(``min-energy``, ``locomotion``, ``switch``, ``constrained-min-energy``; several modes
or ``all`` give one row each).  The readings are built before the measured region; in
it only the target's calls run (and their loop).  Python's garbage collector is frozen
and off in the region (the daemon keeps it out of its cycle, issue 28).

How: one ``valgrind --tool=callgrind`` process runs this file with ``--inner``: it builds
every workload and warms it up with instrumentation off (``--instr-atstart=no``: valgrind
runs the imports ~3x faster that way), then switches instrumentation on
(``callgrind_control --instr=on``) and runs each measured region inside
``sys.call_tracing``, whose C function callgrind toggles collection on
(``--toggle-collect=sys_call_tracing``) and dumps after (``--dump-after``): one dump per
mode, holding only that region's instructions.  A Python without that symbol (stripped)
collects nothing, and the tool says so.  Figures are for this machine's Python, numpy and
Pinocchio builds; compare only figures taken with the same ones.

Another callable can be measured later: add a builder to :data:`TARGETS`.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = ROOT / "config" / "sim.yaml"
MODES: tuple[str, ...] = ("min-energy", "locomotion", "switch", "constrained-min-energy")
PUSH_N = 20.0
"""[N] the steady push on the handle, along the sensor's x axis."""

#: the C function of ``sys.call_tracing`` in CPython: callgrind collects inside it only
_REGION_FN = "sys_call_tracing"


class Workload(NamedTuple):
    """A target prepared for measurement.

    make(count): the inputs of the next ``count`` updates (readings, clock), built outside
    the measured region; run(items): one update per item (the measured call);
    check(): after the run, None if the last update commanded motion without a fault,
    else what went wrong (a faulted update is cheaper and would mislead).
    """

    make: Callable[[int], list[Any]]
    run: Callable[[list[Any]], None]
    check: Callable[[], str | None]


def cycle_workload(cfg: Any, mode: str) -> Workload:
    """:meth:`CycleChain.cycle` in ``mode`` with the scripted readings of the module doc."""
    from mmctl.control.cycle import CycleChain, CycleResult, CycleState, Readings
    from mmctl.types import ArmState, Odometry, Wrench

    chain = CycleChain(cfg)
    dt = chain.dt
    q_a = np.asarray(cfg.robot.q_des, dtype=float)[:6].copy()
    q = np.concatenate((q_a, np.zeros(3)))
    r_sensor = chain.model.fk_base(q, "sensor").rotation
    raw = chain.wrench.gravity_wrench(r_sensor)
    raw[0] += PUSH_N
    force, torque = raw[:3].copy(), raw[3:].copy()
    qd_a = np.zeros(6)
    state: list[CycleState] = [CycleState(chain.controller.initial_state(mode),
                                          chain.wrench.initial_state())]
    last: list[CycleResult | None] = [None]
    clock = [100.0, 0]  # [s], sensor sample counter

    def make(count: int) -> list[tuple[Readings, float]]:
        items = []
        t, seq = float(clock[0]), int(clock[1])
        for _ in range(count):
            t += dt
            seq += 1
            items.append((Readings(ArmState(q_a, qd_a, t, 2, 1),
                                   Wrench(force, torque, t, seq),
                                   Odometry(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, t), dt, True), t))
        clock[0], clock[1] = t, seq
        return items

    def run(items: list[tuple[Readings, float]]) -> None:
        cycle = chain.cycle
        s = state[0]
        res = None
        for r, now in items:
            s, res = cycle(s, r, now)
        state[0] = s
        last[0] = res

    def check() -> str | None:
        res = last[0]
        if res is None:
            return "no update ran"
        if res.fault is not None:
            return f"the last update faulted: {res.fault.value} {res.fault_details}"
        if not np.abs(res.qd_cmd).max() > 0.0:
            return "the last update commanded no motion"
        return None

    return Workload(make, run, check)


def update_workload(cfg: Any, mode: str) -> Workload:
    """The whole pure update (:class:`mmctl.control.update.Update`: the chain plus the
    safety latch, the arm hold, the enabling switch and the button read from the arm
    sample's inputs, the base divider), armed, on the readings of :func:`cycle_workload`
    (the enabling contacts held)."""
    from mmctl.control.cycle import CycleChain
    from mmctl.control.update import (
        BeginEnable,
        Commands,
        EnableCheck,
        EnableFinish,
        Readings,
        SetMode,
        Update,
    )
    from mmctl.types import ArmState, Odometry, Wrench

    update = Update(cfg, CycleChain(cfg))
    chain = update.chain
    dt = chain.dt
    q_a = np.asarray(cfg.robot.q_des, dtype=float)[:6].copy()
    q = np.concatenate((q_a, np.zeros(3)))
    r_sensor = chain.model.fk_base(q, "sensor").rotation
    raw = chain.wrench.gravity_wrench(r_sensor)
    rest_f, rest_t = raw[:3].copy(), raw[3:].copy()
    raw[0] += PUSH_N
    force, torque = raw[:3].copy(), raw[3:].copy()
    qd_a = np.zeros(6)
    held = 0
    for i in cfg.enabling.inputs:
        held |= (0 if cfg.enabling.active_low else 1) << i
    clock = [100.0, 0, 0]  # [s], sensor sample counter, cycle index

    def readings(f: Any, tq: Any) -> Readings:
        t, seq, k = clock[0] + dt, clock[1] + 1, clock[2] + 1
        clock[0], clock[1], clock[2] = t, seq, k
        return Readings(k, t, dt, ArmState(q_a, qd_a, t, 2, 1), Wrench(f, tq, t, seq),
                        Odometry(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, t), held)

    s = update.initial_state()
    for cmd in (SetMode(mode), BeginEnable(), EnableCheck(), EnableFinish()):
        s, _, _ = update(s, readings(rest_f, rest_t), [cmd])
    if not s.safety.armed:
        raise RuntimeError(f"the update did not arm: {s.safety.as_dict()}")
    state = [s]
    last: list[Commands | None] = [None]

    def make(count: int) -> list[Readings]:
        return [readings(force, torque) for _ in range(count)]

    def run(items: list[Readings]) -> None:
        up = update
        st = state[0]
        cmds = None
        for r in items:
            st, cmds, _ = up(st, r)
        state[0] = st
        last[0] = cmds

    def check() -> str | None:
        c = last[0]
        if c is None:
            return "no update ran"
        if c.stop or c.qd_arm is None or not np.abs(c.qd_arm).max() > 0.0:
            return f"the last update commanded no motion ({state[0].safety.as_dict()})"
        return None

    return Workload(make, run, check)


#: --target: name -> builder (config, IDK mode) -> Workload
TARGETS: dict[str, Callable[[Any, str], Workload]] = {"cycle": cycle_workload,
                                                      "update": update_workload}


class Figure(NamedTuple):
    """One mode's count: instructions [Ir] of the whole region and per update."""

    mode: str
    total: int
    per_update: float


# --- inside valgrind ---------------------------------------------------------------------

def _region(run: Callable[[list[Any]], None], items: list[Any]) -> None:
    run(items)


def inner(args: argparse.Namespace) -> int:
    """Build, warm up, switch instrumentation on, run one measured region per mode."""
    from mmctl.config import load_config

    cfg = load_config(args.config)
    build = TARGETS[args.target]
    loads = []
    for mode in args.mode:
        w = build(cfg, mode)
        if args.warmup:
            w.run(w.make(args.warmup))
        loads.append((mode, w, w.make(args.n)))
    if args.instr_on:  # valgrind started with instrumentation off (faster start-up)
        r = subprocess.run(["callgrind_control", "--instr=on", str(os.getpid())],
                           capture_output=True, text=True, check=False)
        if r.returncode != 0:
            print(f"update_cost: callgrind_control failed: {r.stdout}{r.stderr}",
                  file=sys.stderr)
            return 3
    gc.collect()
    gc.freeze()
    gc.disable()
    for _, w, items in loads:
        sys.call_tracing(_region, (w.run, items))
    gc.enable()
    problems = {mode: w.check() for mode, w, _ in loads}
    print(json.dumps({"problems": {m: p for m, p in problems.items() if p is not None}}))
    return 0


# --- outside -----------------------------------------------------------------------------

def _totals(path: Path) -> int:
    """The Ir total of one callgrind dump (its ``totals:`` or ``summary:`` line)."""
    summary = None
    for line in path.read_text().splitlines():
        if line.startswith("totals:"):
            return int(line.split()[1])
        if line.startswith("summary:"):
            summary = int(line.split()[1])
    if summary is None:
        raise RuntimeError(f"{path}: no totals in the callgrind output")
    return summary


def measure(modes: Sequence[str], n: int, warmup: int = 200, target: str = "cycle",
            config: str | Path = DEFAULT_CONFIG, fast_start: bool = True,
            valgrind: str = "valgrind") -> list[Figure]:
    """Run the target under callgrind; one :class:`Figure` per mode (in order).

    Raises RuntimeError when valgrind fails, collects nothing or an update faulted."""
    with tempfile.TemporaryDirectory(prefix="update_cost-") as tmp:
        out = Path(tmp) / "callgrind.out"
        cmd = [valgrind, "--tool=callgrind", "--collect-atstart=no",
               f"--toggle-collect={_REGION_FN}", f"--dump-after={_REGION_FN}",
               f"--callgrind-out-file={out}", f"--instr-atstart={'no' if fast_start else 'yes'}",
               sys.executable, str(Path(__file__).resolve()), "--inner",
               "--target", target, "--n", str(n), "--warmup", str(warmup),
               "--config", str(config), "--mode", *modes]
        if fast_start:
            cmd.append("--instr-on")
        env = dict(os.environ, PYTHONHASHSEED="0", OPENBLAS_NUM_THREADS="1",
                   OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"valgrind exited with {proc.returncode}:\n"
                               f"{proc.stderr[-3000:]}")
        report = json.loads(proc.stdout.strip().splitlines()[-1])
        if report["problems"]:
            raise RuntimeError(f"not a moving update: {report['problems']}")
        dumps = sorted(Path(tmp).glob("callgrind.out.*"),
                       key=lambda p: int(p.name.rsplit(".", 1)[1]))
        if len(dumps) != len(modes):
            raise RuntimeError(f"{len(dumps)} callgrind dumps for {len(modes)} modes: does "
                               f"{sys.executable} have the symbol {_REGION_FN}?")
        figures = []
        for mode, dump in zip(modes, dumps):
            total = _totals(dump)
            if total <= 0:
                raise RuntimeError(f"callgrind collected nothing in {_REGION_FN} "
                                   f"(a stripped Python?)")
            figures.append(Figure(mode, total, total / n))
        return figures


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--mode", nargs="+", default=["min-energy"],
                   choices=[*MODES, "all"], help="IDK mode(s) of the controller; all: the "
                   "four (default min-energy)")
    p.add_argument("--n", type=int, default=2000, help="measured updates per mode (>= 1)")
    p.add_argument("--warmup", type=int, default=200, help="updates before the measured ones")
    p.add_argument("--target", choices=sorted(TARGETS), default="cycle",
                   help="the callable measured (cycle: CycleChain.cycle)")
    p.add_argument("--config", default=str(DEFAULT_CONFIG), help="YAML config")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--slow-start", action="store_true",
                   help="instrument from the start (if callgrind_control cannot switch it on)")
    p.add_argument("--inner", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--instr-on", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.n < 1 or args.warmup < 0:
        p.error("--n must be >= 1 and --warmup >= 0")
    if "all" in args.mode:
        args.mode = list(MODES)
    if args.inner:
        return inner(args)
    valgrind = shutil.which("valgrind")
    if valgrind is None:
        print("update_cost: valgrind not found (apt-get install valgrind)", file=sys.stderr)
        return 2
    try:
        figures = measure(args.mode, args.n, args.warmup, args.target, args.config,
                          not args.slow_start, valgrind)
    except RuntimeError as e:
        print(f"update_cost: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps({
            "target": args.target, "n": args.n, "warmup": args.warmup,
            "config": str(args.config), "python": sys.version.split()[0],
            "ir_per_update": {f.mode: round(f.per_update, 1) for f in figures},
            "ir_total": {f.mode: f.total for f in figures}}))
        return 0
    print(f"instructions per update (callgrind Ir), target {args.target}, {args.n} updates "
          f"after {args.warmup} warm-up, {Path(args.config).name}")
    print(f"{'mode':<26}{'Ir/update':>12}{'Ir total':>16}")
    for f in figures:
        print(f"{f.mode:<26}{math.floor(f.per_update + 0.5):>12,}{f.total:>16,}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
