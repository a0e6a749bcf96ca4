#!/usr/bin/env python3
"""What the loop pays for the base: the CANopen master in its process, or behind the
link process.

The fake CiA 402 drives run on a ``virtual`` channel served by the simulator's
socketcand server, in a process of their own (as ``mmctl sim`` does).  A loop at
``--rate`` Hz (absolute ``perf_counter_ns`` deadlines) then drives the base for
``--cycles`` cycles, two ways, against the same fake:

* ``in-process``: :class:`CanopenBase` as the daemon holds it with ``base.process``
  off: ``read_odometry()`` at the start of the cycle, ``--compute`` us of busy work,
  ``send_twist()`` (four RPDOs + SYNC through the socketcand client) at its end;
* ``link-process``: :class:`BaseLinkProcess` (``base.process``): the same calls, which
  copy the newest record and leave the twist in the command mailbox (eventfd wake-up).

Each cycle's twist differs (``vx`` steps through 40 values), so the drive's own log of
the targets it received (:meth:`FakeDrives.command_log`, CLOCK_MONOTONIC, one clock for
every process) says when each command reached it.  Printed per way [us]:
``read_odometry()`` and ``send_twist()`` cost (p50/p90/p99/max), and the command
latency: from the start of ``send_twist()`` to the front-left drive receiving that
target (commands superseded before the child sent them are counted as ``dropped``).

    .venv/bin/python tools/base_link_bench.py [--cycles 5000] [--rate 500]
        [--compute 600] [--rt-priority 0] [--json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from mmctl.config import Config, config_from_dict
from mmctl.errors import MmctlError
from mmctl.transports.base import Base

CHANNEL = "bench-base"
STEPS = 40  # distinct twists, cycled: a frame is matched to its command by its value


def config(address: tuple[str, int] | None = None) -> Config:
    host, port = address or ("127.0.0.1", 29536)
    # a loaded machine's stall is not a dead master: the figures, not the watchdogs
    return config_from_dict({"base": {"canopen": {
        "interface": "socketcand", "host": host, "port": port, "channel": CHANNEL,
        "heartbeat_timeout": 1.0, "sdo_timeout": 2.0}, "command_watchdog": 2.0}})


def serve(conn: Connection) -> None:
    """Spawned: socketcand server + fake drives on 127.0.0.1; ("log",) answers the
    front-left drive's target log; ("stop",) or a closed pipe ends it."""
    from mmctl.sim.fake_drives import FakeDrives
    from mmctl.sim.socketcand import SocketcandServer

    with SocketcandServer("127.0.0.1", port=0, channels=[CHANNEL]) as server:
        cfg = config(server.address)
        with FakeDrives(cfg) as fakes:
            conn.send(server.address)
            while True:
                try:
                    msg = conn.recv()
                except EOFError:
                    return
                if msg[0] != "log":
                    return
                conn.send(fakes.command_log(cfg.base.canopen.node_ids[0]))


def pct(x: np.ndarray) -> dict[str, float]:
    if x.size == 0:
        return {}
    p50, p90, p99 = np.percentile(x, [50, 90, 99])
    return {"p50": round(float(p50), 1), "p90": round(float(p90), 1),
            "p99": round(float(p99), 1), "max": round(float(x.max()), 1)}


def busy(ns: int) -> None:
    end = time.perf_counter_ns() + ns
    while time.perf_counter_ns() < end:
        pass


def run_loop(base: Base, cfg: Config, cycles: int, period_ns: int,
             compute_ns: int) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """The loop: read at each deadline, work, send.  Returns (figures, the send start
    times [ns], the front-left target in counts/s each send asked for)."""
    from mmctl.transports.base.kinematics import WheelCommand

    wheel = WheelCommand(cfg.base.mecanum, cfg.limits.wheel_velocity)
    per_rad = cfg.base.canopen.counts_per_rev / (2 * np.pi)
    vx = [0.05 + 0.01 * i for i in range(STEPS)]
    expect = [round(float(wheel(v, 0.0, 0.0)[0][0]) * per_rad) for v in vx]
    read_cost = np.empty(cycles, dtype=np.int64)
    send_cost = np.empty(cycles, dtype=np.int64)
    sent_at = np.empty(cycles, dtype=np.int64)
    wanted = np.empty(cycles, dtype=np.int64)
    clock = time.perf_counter_ns
    faults: dict[str, int] = {}
    deadline = clock() + period_ns
    for k in range(cycles):
        now = clock()
        if deadline > now:
            time.sleep((deadline - now) * 1e-9)
        t0 = clock()
        try:
            base.read_odometry()
        except MmctlError as exc:
            cause = getattr(exc, "cause", None)
            name = type(exc).__name__ if cause is None else str(cause.value)
            faults[name] = faults.get(name, 0) + 1
        t1 = clock()
        busy(compute_ns)
        t2 = clock()
        try:
            base.send_twist(vx[k % STEPS], 0.0, 0.0)
        except MmctlError as exc:
            faults[type(exc).__name__] = faults.get(type(exc).__name__, 0) + 1
        t3 = clock()
        read_cost[k], send_cost[k] = t1 - t0, t3 - t2
        sent_at[k], wanted[k] = t2, expect[k % STEPS]
        deadline += period_ns
        end = clock()
        if end > deadline:  # skip, never burst (as the loop does)
            deadline += ((end - deadline) // period_ns + 1) * period_ns
    figures = {"read_odometry_us": pct(read_cost / 1e3), "send_twist_us": pct(send_cost / 1e3),
               "cycles": cycles, "faults": faults}
    return figures, sent_at, wanted


def latencies(log: list[tuple[float, int]], sent_at: np.ndarray, wanted: np.ndarray,
              period_ns: int) -> tuple[np.ndarray, int]:
    """For each command, the first target the drive received with its value after it
    was sent, within STEPS / 2 periods (after that the value comes round again): the
    delays [ns], and how many commands never arrived (superseded)."""
    t = np.array([round(s * 1e9) for s, _ in log], dtype=np.int64)
    v = np.array([c for _, c in log], dtype=np.int64)
    out = []
    dropped = 0
    window = STEPS // 2 * period_ns
    for at, want in zip(sent_at, wanted):
        i = int(np.searchsorted(t, at))
        hit = np.nonzero(v[i:i + 4 * STEPS] == want)[0]
        if hit.size and t[i + hit[0]] - at < window:
            out.append(t[i + hit[0]] - at)
        else:  # superseded before the child sent it, or refused (a fault)
            dropped += 1
    return np.array(out, dtype=np.int64), dropped


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=5000)
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--compute", type=float, default=600.0, help="busy work per cycle [us]")
    ap.add_argument("--rt-priority", type=int, default=0,
                    help="SCHED_FIFO of the loop and the link's child (0: normal)")
    ap.add_argument("--batch-delay", type=float, default=None,
                    help="the link process's batch_delay [us] (default: its own)")
    ap.add_argument("--only", choices=("in-process", "link-process"), default=None)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    from mmctl.runtime.loop import apply_realtime
    from mmctl.transports.base.canopen_base import CanopenBase
    from mmctl.transports.base.link_process import BaseLinkProcess

    ctx = mp.get_context("spawn")
    conn, child = ctx.Pipe()
    proc = ctx.Process(target=serve, args=(child,), daemon=True)
    proc.start()
    child.close()
    address = conn.recv()
    cfg = config(address)
    period_ns = round(1e9 / args.rate)
    compute_ns = round(args.compute * 1e3)
    apply_realtime(args.rt_priority, ())
    poll = {} if args.batch_delay is None else {"batch_delay": args.batch_delay * 1e-6}
    ways: dict[str, Callable[[], Base]] = {
        "in-process": lambda: CanopenBase(cfg.base, cfg.limits),
        "link-process": lambda: BaseLinkProcess(cfg, period=period_ns * 1e-9, **poll,
                                                rt_priority=args.rt_priority),
    }
    if args.only:
        ways = {args.only: ways[args.only]}
    results: dict[str, Any] = {}
    try:
        for name, build in ways.items():
            base = build()
            with base:
                base.enable()
                figures, sent_at, wanted = run_loop(base, cfg, args.cycles, period_ns,
                                                    compute_ns)
                base.stop()
                base.disable()
            conn.send(("log",))
            delay, dropped = latencies(conn.recv(), sent_at, wanted, period_ns)
            figures["command_latency_us"] = pct(delay / 1e3)
            figures["dropped"] = dropped
            results[name] = figures
    finally:
        conn.send(("stop",))
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
    if args.json:
        print(json.dumps(results, indent=2))
        return
    print(f"{args.cycles} cycles at {args.rate:g} Hz, {args.compute:g} us of work per "
          "cycle; all in us")
    print(f"{'way':<14}{'call':<20}{'p50':>9}{'p90':>9}{'p99':>9}{'max':>10}")
    for name, r in results.items():
        for key in ("read_odometry_us", "send_twist_us", "command_latency_us"):
            p = r[key]
            if p:
                print(f"{name:<14}{key[:-3]:<20}{p['p50']:>9.1f}{p['p90']:>9.1f}"
                      f"{p['p99']:>9.1f}{p['max']:>10.1f}")
        print(f"{name:<14}dropped {r['dropped']}, faults {r['faults']}")


if __name__ == "__main__":
    main()
