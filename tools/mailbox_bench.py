#!/usr/bin/env python3
"""The mailbox's costs, and how fast a command wakes the device's process.

1. In one process: ``publish()`` and ``read_into()`` (new record / nothing new), in ns
   per call (the mean of batches of 1 000 calls, p50 and p99 over the batches).
2. Across processes (the command direction): this process publishes a command at
   ``--rate`` Hz (absolute deadlines), stamped with ``now_ns()`` just before; a
   ``spawn`` child waits for it and, on seeing it, records ``now_ns() - t_ns``.  The
   child waits by

   * ``eventfd``: ``Wake(EVENTFD).wait()`` (select on an eventfd), then reads;
   * ``pipe``: the same with a pipe;
   * ``spin``: ``read_into`` in a tight loop (a core at 100 %);
   * ``sleep``: ``read_into``, then ``time.sleep(--sleep-poll)`` when nothing is new.

   For each: p50/p90/p99/max of the latency [us], the child's CPU use [% of a core] and
   how many commands it never saw (overwritten by the next one before it looked).

    .venv/bin/python tools/mailbox_bench.py [--count 2500] [--rate 500] [--json]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from mmctl.runtime.mailbox import Mailbox, MailboxLayout, Sample, Wake, WakeKind, now_ns

COMMAND = MailboxLayout("bench_command", (("qd", 6), ("acceleration", 1), ("dt", 1)))
MECHANISMS = ("eventfd", "pipe", "spin", "sleep")


def local_costs(batches: int = 300, batch: int = 1000) -> dict[str, dict[str, float]]:
    """ns per call of publish, read_into (new record) and read_into (nothing new)."""
    box = Mailbox.create(COMMAND)
    reader = Mailbox.attach(box.name, COMMAND)
    s = Sample(COMMAND)
    clock = time.perf_counter_ns
    out: dict[str, list[float]] = {"publish": [], "read_new": [], "read_nothing_new": [],
                                   "publish_and_read": []}
    try:
        for _ in range(batches):
            t0 = clock()
            for _ in range(batch):
                box.publish(1)
            t1 = clock()
            for _ in range(batch):
                reader.read_into(s)
            t2 = clock()
            for _ in range(batch):
                box.publish(1)
                reader.read_into(s)
            t3 = clock()
            out["publish"].append((t1 - t0) / batch)
            out["read_nothing_new"].append((t2 - t1) / batch)
            out["publish_and_read"].append((t3 - t2) / batch)
            out["read_new"].append((t3 - t2) / batch - (t1 - t0) / batch)
    finally:
        reader.close()
        box.close()
    return {k: {"p50": float(np.percentile(v, 50)), "p99": float(np.percentile(v, 99))}
            for k, v in out.items()}


def waiter(conn: Connection, name: str, how: str, wake: Wake | None, count: int,
           sleep_poll: float) -> None:
    """Spawned device side: wait for each command, record its latency [ns]."""
    box = Mailbox.attach(name, COMMAND)
    s = Sample(COMMAND)
    lat = np.empty(count, dtype=np.int64)
    conn.send("ready")
    cpu0, wall0 = time.process_time(), time.perf_counter()
    n = first = 0
    while n < count:
        if how in ("eventfd", "pipe"):
            assert wake is not None
            wake.wait(None)
            got = box.read_into(s)
        elif how == "spin":
            got = box.read_into(s)
        else:
            got = box.read_into(s)
            if not got:
                time.sleep(sleep_poll)
        if got:
            lat[n] = now_ns() - s.t_ns
            if n == 0:
                first = s.seq
            n += 1
    cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    missed = (s.seq - first) // 2 + 1 - count  # seq: +2 per command
    conn.send((lat, cpu / wall, missed))
    box.close()


def cross_process(how: str, count: int, rate: float, sleep_poll: float) -> dict[str, float]:
    ctx = mp.get_context("spawn")
    box = Mailbox.create(COMMAND)
    wake = Wake(WakeKind(how)) if how in ("eventfd", "pipe") else None
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=waiter, args=(child, box.name, how, wake, count, sleep_poll),
                       daemon=True)
    proc.start()
    child.close()
    try:
        parent.recv()  # ready
        period = round(1e9 / rate)
        deadline = time.perf_counter_ns() + 50 * period
        k = 0
        while not parent.poll(0):  # until the waiter saw ``count`` (it may miss some)
            if k > 20 * count:
                raise RuntimeError(f"{how}: the waiter saw fewer than {count} of {k} commands")
            time.sleep(max(0, deadline - time.perf_counter_ns()) * 1e-9)
            box.staging[:] = k
            box.publish(now_ns())
            if wake is not None:
                wake.notify()
            deadline += period
            k += 1
        lat, cpu, missed = parent.recv()
    finally:
        proc.join(10.0)
        if proc.is_alive():
            proc.kill()
            proc.join()
        box.close()
        if wake is not None:
            wake.close()
    us = lat / 1e3
    return {"p50": float(np.percentile(us, 50)), "p90": float(np.percentile(us, 90)),
            "p99": float(np.percentile(us, 99)), "max": float(us.max()),
            "cpu_percent": 100.0 * cpu, "count": len(us), "missed": missed}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=2500, help="commands per mechanism")
    ap.add_argument("--rate", type=float, default=500.0, help="commands per second [Hz]")
    ap.add_argument("--sleep-poll", type=float, default=100e-6,
                    help="the sleep mechanism's poll interval [s]")
    ap.add_argument("--only", choices=MECHANISMS, action="append",
                    help="measure only these mechanisms (repeatable)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    results: dict[str, Any] = {"local_ns": local_costs()}
    for how in args.only or MECHANISMS:
        results[how] = cross_process(how, args.count, args.rate, args.sleep_poll)
    if args.json:
        print(json.dumps(results, indent=2))
        return
    print("in one process [ns per call]:      p50     p99")
    for k, v in results["local_ns"].items():
        print(f"  {k:<28} {v['p50']:7.0f} {v['p99']:7.0f}")
    print(f"command latency across processes [us] ({args.count} at {args.rate:g} Hz):")
    print("  mechanism      p50     p90     p99     max   waiter CPU   unseen")
    for how in args.only or MECHANISMS:
        r = results[how]
        print(f"  {how:<9} {r['p50']:8.1f} {r['p90']:7.1f} {r['p99']:7.1f} {r['max']:7.1f}"
              f"   {r['cpu_percent']:5.1f} %   {r['missed']:5d}")


if __name__ == "__main__":
    main()
