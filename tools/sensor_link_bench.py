#!/usr/bin/env python3
"""What the loop pays for the F/T sensor: in its process, or behind the link process.

The fake CAN F/T sensor runs on a ``virtual`` channel served by the simulator's
socketcand server, in a process of its own (as ``mmctl sim`` does).  A loop at
``--rate`` Hz (absolute ``perf_counter_ns`` deadlines) then reads the sensor for
``--cycles`` cycles, two ways, against the same fake:

* ``in-process``: :class:`CanForceSensor` as the daemon holds it today: ``read()`` at
  the start of the cycle, ``--compute`` us of busy work, ``request_next()`` at its end;
* ``link-process``: :class:`SensorLinkProcess` (the same transport in a child, polled
  ``--lead`` before each deadline of the loop's grid): ``read()`` at the start of the
  cycle, the same busy work.

A ``baseline`` loop whose read() returns a constant shows what any call costs right
after the loop wakes (cold caches).  Printed per way: the loop's ``read()`` cost [us] (p50/p90/p99/max), the sample's age
when the loop got it [us], the samples that were new, and the reads that raised (a
stale or status fault).  The age runs from the request the sample answers (the
sample is at most that old): ``request_next()`` at the end of the previous cycle
in-process, the child's request (``SensorLinkProcess.timing()``) for the link process.
(The sample's own time stamp is no measure in-process: it is taken when the loop's
``read()`` decodes the reply.)  Then the link process's ``read()`` back to back (mean
of 20 000 calls, ns) and its age since the child decoded the sample.

    .venv/bin/python tools/sensor_link_bench.py [--cycles 5000] [--rate 500]
        [--compute 600] [--lead 1000] [--rt-priority 0] [--json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing as mp
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from mmctl.config import default_config
from mmctl.config.sensor import SensorConfig
from mmctl.errors import MmctlError
from mmctl.types import Wrench

CHANNEL = "bench-ft"


def serve(conn: Connection) -> None:
    """Spawned: socketcand server + fake sensor on 127.0.0.1 until the pipe says stop."""
    from mmctl.sim.fake_ft_can import FakeFtCanSensor
    from mmctl.sim.socketcand import SocketcandServer
    from mmctl.sim.wrench_source import ConstantWrench

    with SocketcandServer("127.0.0.1", port=0, channels=[CHANNEL]) as server, \
            FakeFtCanSensor(ConstantWrench((1.0, 2.0, 10.0, 0.1, 0.2, 0.3)), channel=CHANNEL):
        conn.send(server.address)
        try:
            conn.recv()
        except EOFError:
            pass


def sensor_config(address: tuple[str, int]) -> SensorConfig:
    cfg = default_config().sensor
    host, port = address
    can = dataclasses.replace(cfg.can, interface="socketcand",  # type: ignore[type-var]
                              channel=CHANNEL, host=host, port=port)
    return dataclasses.replace(cfg, transport="can", can=can)  # type: ignore[type-var]


def busy(ns: int) -> None:
    end = time.perf_counter_ns() + ns
    while time.perf_counter_ns() < end:
        pass


def run_loop(read: Callable[[], Wrench], after: Callable[[], None] | None, cycles: int,
             period_ns: int, compute_ns: int, first_deadline: int,
             asked_at: Callable[[], int] | None = None) -> dict[str, Any]:
    """The loop's read at each deadline; costs [ns] and ages [ns] of each read.  The age
    runs from the request the sample answers: ``after`` (request_next) in this loop, or
    ``asked_at()`` (the link process's record says when its child asked)."""
    cost = np.empty(cycles, dtype=np.int64)
    age = np.zeros(cycles, dtype=np.int64)
    decoded = np.zeros(cycles, dtype=np.int64)
    clock = time.perf_counter_ns
    faults: dict[str, int] = {}
    new = 0
    last_seq = -1
    asked = 0  # when ``after`` (request_next) last ran
    deadline = first_deadline
    for k in range(cycles):
        now = clock()
        if deadline > now:
            time.sleep((deadline - now) * 1e-9)
        t0 = clock()
        try:
            w = read()
        except MmctlError as exc:
            t1 = clock()
            cause = getattr(exc, "cause", None)
            name = type(exc).__name__ if cause is None else str(cause.value)
            faults[name] = faults.get(name, 0) + 1
        else:
            t1 = clock()
            # in-process the sample is stamped when read() decodes it, so its age says
            # nothing: the data is as old as the request it answers
            since = asked if asked_at is None else asked_at()
            age[k] = t1 - since if since else 0  # (no request yet: no age)
            decoded[k] = t1 - round(w.timestamp * 1e9)
            if w.sequence != last_seq:
                new += 1
                last_seq = w.sequence
        cost[k] = t1 - t0
        busy(compute_ns)
        if after is not None:
            try:
                after()
                asked = clock()
            except MmctlError as exc:
                faults[type(exc).__name__] = faults.get(type(exc).__name__, 0) + 1
        deadline += period_ns
        end = clock()
        if end > deadline:  # skip, never burst (as the loop does)
            deadline += ((end - deadline) // period_ns + 1) * period_ns
    ok = age > 0
    return {"read_us": pct(cost / 1e3), "age_us": pct(age[ok] / 1e3),
            "since_decoded_us": pct(decoded[ok] / 1e3),
            "new_samples": new, "cycles": cycles, "faults": faults}


def back_to_back(read: Callable[[], Wrench], n: int = 20_000) -> float:
    """Mean cost of ``read()`` called ``n`` times in a row [ns] (faults count too)."""
    t0 = time.perf_counter_ns()
    for _ in range(n):
        try:
            read()
        except MmctlError:
            pass
    return (time.perf_counter_ns() - t0) / n


def pct(x: np.ndarray) -> dict[str, float]:
    if len(x) == 0:
        return {}
    return {"p50": float(np.percentile(x, 50)), "p90": float(np.percentile(x, 90)),
            "p99": float(np.percentile(x, 99)), "max": float(x.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=5000)
    ap.add_argument("--rate", type=float, default=500.0, help="loop rate [Hz]")
    ap.add_argument("--compute", type=float, default=600.0,
                    help="busy work per cycle after the read [us]")
    ap.add_argument("--lead", type=float, default=1000.0,
                    help="the link process asks this long before each deadline [us]")
    ap.add_argument("--rt-priority", type=int, default=0,
                    help="SCHED_FIFO priority of this loop and of the link's child (0: none)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    from mmctl.runtime.loop import apply_realtime
    from mmctl.transports.sensor.can_ft import CanForceSensor
    from mmctl.transports.sensor.link_process import SensorLinkProcess

    period_ns = round(1e9 / args.rate)
    compute_ns = round(args.compute * 1e3)
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    fake = ctx.Process(target=serve, args=(child,), daemon=True)
    fake.start()
    child.close()
    address = parent.recv()
    cfg = sensor_config(address)
    if args.rt_priority:
        apply_realtime(args.rt_priority, ())
    results: dict[str, Any] = {}
    fixed = Wrench(np.zeros(3), np.zeros(3), 0.0, 0)
    results["baseline"] = run_loop(lambda: fixed, None, args.cycles, period_ns, compute_ns,
                                   time.perf_counter_ns() + 10 * period_ns)
    try:
        with CanForceSensor(cfg.can, stale_timeout=cfg.wrench.stale_timeout) as sensor:
            start = time.perf_counter_ns() + 100 * period_ns
            results["in-process"] = run_loop(sensor.read, sensor.request_next, args.cycles,
                                             period_ns, compute_ns, start)
        origin = time.perf_counter_ns()  # the loop's grid: origin + k period
        link = SensorLinkProcess(cfg, period=period_ns / 1e9, origin_ns=origin,
                                 lead=args.lead * 1e-6, rt_priority=args.rt_priority)
        with link:
            behind = time.perf_counter_ns() + 100 * period_ns - origin
            first = origin + (behind // period_ns + 1) * period_ns  # on the grid
            results["link-process"] = run_loop(link.read, None, args.cycles, period_ns,
                                               compute_ns, first,
                                               lambda: link.timing().requested_ns)
            results["link_read_back_to_back_ns"] = back_to_back(link.read)
    finally:
        parent.send("stop")
        fake.join(10.0)
        if fake.is_alive():
            fake.kill()
    if args.json:
        print(json.dumps(results, indent=2))
        return
    print(f"{args.cycles} cycles at {args.rate:g} Hz, {args.compute:g} us of work per cycle, "
          f"lead {args.lead:g} us; fake CAN sensor over socketcand in another process")
    print("                 loop's read() [us]                sample age at read [us]")
    print("  way            p50     p90     p99     max       p50     p90     p99     max"
          "   new   faults")
    for way in ("baseline", "in-process", "link-process"):
        r = results[way]
        c, a = r["read_us"], r["age_us"]
        print(f"  {way:<12} {c['p50']:7.1f} {c['p90']:7.1f} {c['p99']:7.1f} {c['max']:7.1f}"
              f"   {a.get('p50', 0):7.1f} {a.get('p90', 0):7.1f} {a.get('p99', 0):7.1f}"
              f" {a.get('max', 0):7.1f}  {r['new_samples']:5d}   {r['faults'] or '-'}")
    d = results["link-process"]["since_decoded_us"]
    print(f"  link-process: read() back to back {results['link_read_back_to_back_ns']:.0f} ns;"
          f" age since the child decoded the sample p50 {d.get('p50', 0):.1f},"
          f" p99 {d.get('p99', 0):.1f} us")


if __name__ == "__main__":
    main()
