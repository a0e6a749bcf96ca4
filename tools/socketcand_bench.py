#!/usr/bin/env python3
"""Round-trip latency through the simulator's socketcand server.

A responder on the virtual side (like a drive answering an SDO) echoes every request
frame on the answer id; a python-can socketcand client (``tcp_tune=True``, as the daemon
opens it) sends a request, waits for the answer and times the round trip with
``perf_counter_ns``.  By default the server and responder run in a child process, like
the simulator and the daemon; ``--same-process`` puts all in one.  Prints p50/p90/p99/max
of the round trip in microseconds.

    .venv/bin/python tools/socketcand_bench.py [--count 5000] [--same-process] [--json]

One request is outstanding at a time (request/answer, as an SDO or a sync-driven PDO
exchange), so each figure is client send -> TCP -> server -> virtual bus -> responder ->
virtual bus -> server -> TCP -> client recv.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import threading
import time
from multiprocessing.connection import Connection

import can
import numpy as np

from mmctl.sim.socketcand import SocketcandServer

CHANNEL = "bench"
REQUEST_ID = 0x601
ANSWER_ID = 0x581


def respond(bus: can.BusABC, stop: threading.Event) -> None:
    """Answer every REQUEST_ID frame with ANSWER_ID and the same data until ``stop``."""
    while not stop.is_set():
        msg = bus.recv(timeout=0.1)
        if msg is not None and msg.arbitration_id == REQUEST_ID:
            bus.send(can.Message(arbitration_id=ANSWER_ID, data=msg.data,
                                 is_extended_id=False))


def serve(conn: Connection) -> None:
    """Child process: server + responder; sends the address, runs until told to stop."""
    stop = threading.Event()
    with SocketcandServer(port=0, channels=[CHANNEL]) as server:
        bus = can.Bus(interface="virtual", channel=CHANNEL)
        t = threading.Thread(target=respond, args=(bus, stop), name="bench-responder",
                             daemon=True)
        t.start()
        conn.send(server.address)
        conn.recv()  # parent says stop
        stop.set()
        t.join()
        bus.shutdown()
        conn.send(dict(server.stats))


def measure(host: str, port: int, count: int, warmup: int) -> np.ndarray:
    """Round-trip times [us] of ``count`` request/answer exchanges after ``warmup``."""
    bus = can.Bus(interface="socketcand", host=host, port=port, channel=CHANNEL,
                  tcp_tune=True)
    rtt = np.empty(count)
    try:
        for i in range(-warmup, count):
            data = (i & 0xFFFFFFFF).to_bytes(4, "little") + b"\x40\x00\x10\x00"
            t0 = time.perf_counter_ns()
            bus.send(can.Message(arbitration_id=REQUEST_ID, data=data, is_extended_id=False))
            while True:
                msg = bus.recv(timeout=5.0)
                if msg is None:
                    raise RuntimeError(f"no answer to request {i} within 5 s")
                if msg.arbitration_id == ANSWER_ID and bytes(msg.data) == data:
                    break
            if i >= 0:
                rtt[i] = (time.perf_counter_ns() - t0) / 1e3
    finally:
        bus.shutdown()
    return rtt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=5000, help="timed round trips")
    ap.add_argument("--warmup", type=int, default=200, help="untimed round trips first")
    ap.add_argument("--same-process", action="store_true",
                    help="server, responder and client in one process")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args()

    if args.same_process:
        stop = threading.Event()
        with SocketcandServer(port=0, channels=[CHANNEL]) as server:
            bus = can.Bus(interface="virtual", channel=CHANNEL)
            t = threading.Thread(target=respond, args=(bus, stop), daemon=True)
            t.start()
            try:
                rtt = measure(*server.address, args.count, args.warmup)
            finally:
                stop.set()
                t.join()
                bus.shutdown()
            stats = dict(server.stats)
    else:
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        proc = ctx.Process(target=serve, args=(child,), name="socketcand-bench-server")
        proc.start()
        try:
            host, port = parent.recv()
            rtt = measure(host, port, args.count, args.warmup)
        finally:
            parent.send("stop")
            stats = parent.recv()
            proc.join(10)

    p50, p90, p99 = np.percentile(rtt, [50, 90, 99])
    figures = {
        "count": args.count,
        "processes": 1 if args.same_process else 2,
        "rtt_us_p50": round(float(p50), 1),
        "rtt_us_p90": round(float(p90), 1),
        "rtt_us_p99": round(float(p99), 1),
        "rtt_us_max": round(float(rtt.max()), 1),
        "server_stats": stats,
    }
    if args.json:
        print(json.dumps(figures))
        return
    where = "one process" if args.same_process else "server in a child process"
    print(f"socketcand round trip, {args.count} request/answer exchanges ({where}):")
    print(f"  p50 {p50:7.1f} us   p90 {p90:7.1f} us   p99 {p99:7.1f} us   "
          f"max {rtt.max():7.1f} us")
    print(f"  server stats: {stats}")


if __name__ == "__main__":
    main()
