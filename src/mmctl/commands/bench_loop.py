"""Time the control loop on the simulated robot, next to a plain time.sleep loop.

The daemon runs in this process on the simulated robot (fake UR controller, CAN
sensor, CANopen drives, a simulated person pushing), armed, for --seconds with its
real loop thread (absolute deadlines, sleep then spin).  Then the same daemon cycle —
the same work: read devices, control step, send commands — runs for --seconds more
in a plain loop that only calls ``time.sleep`` until each absolute deadline.  Both
report compute time (cycle body) p50/p99/max, wake latency (start minus deadline)
p50/p99/p99.9 and the deadline-miss rate; "step" is the pure control chain's share
of the compute time.  Overruns do not fault here (the budget is lifted) so both loops
do the same work for the whole run.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time
from collections.abc import Iterator
from typing import Any

TARGETS = {"compute_p99_us": 300.0, "latency_p99_us": 100.0, "miss_rate": 0.005}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=10.0, help="duration of each loop [s]")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    p.add_argument("--config", metavar="FILE", help="base config (default: config/sim.yaml)")
    p.add_argument("--host", default="127.0.0.3",
                   help="loopback address of the bench's fake UR (default 127.0.0.3)")
    p.add_argument("--rt-priority", type=int, metavar="N",
                   help="SCHED_FIFO priority of both loops (default: loop.rt_priority)")
    p.add_argument("--telemetry", action="store_true",
                   help="also time the daemon's loop with telemetry off vs on (a publisher "
                        "recording to a temporary .rrd) in alternating windows of the same "
                        "run, --seconds in all; JSON key 'telemetry'")


def _figures(snap: Any, step_us: Any) -> dict[str, float | int]:
    import numpy as np

    from mmctl.runtime.timing import summarize

    st = summarize(snap)
    out: dict[str, float | int] = {k: (round(v, 2) if isinstance(v, float) else v)
                                   for k, v in st._asdict().items()}
    out["miss_rate"] = round(st.miss_rate, 6)
    if len(step_us):
        out["step_p50_us"] = round(float(np.percentile(step_us, 50)), 2)
        out["step_p99_us"] = round(float(np.percentile(step_us, 99)), 2)
    return out


def run(args: argparse.Namespace) -> int:
    import dataclasses

    from mmctl.errors import MmctlError
    from mmctl.runtime.client import load
    from mmctl.runtime.logging import setup_logging

    if args.seconds <= 0:
        raise MmctlError(f"--seconds {args.seconds:g}: must be > 0")
    cfg: Any = load(args.config)
    n = int(args.seconds * cfg.loop.rate_hz) + 2000
    cfg = dataclasses.replace(
        cfg,
        arm=dataclasses.replace(cfg.arm, host=args.host),
        loop=dataclasses.replace(cfg.loop, timing_samples=n, max_consecutive_misses=10**9,
                                 max_total_misses=10**9,
                                 rt_priority=(cfg.loop.rt_priority if args.rt_priority is None
                                              else args.rt_priority)),
        sim=dataclasses.replace(cfg.sim, enabled=True, human=True, auto_enable=False),
    )
    with _stdout_to_stderr():  # logs (ours and the fake UR process's) stay off stdout
        setup_logging("warning", stream=sys.stderr)
        result = _measure(cfg, args, n)
    result["targets"] = TARGETS
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        _print_table(result)
    return 0


@contextlib.contextmanager
def _stdout_to_stderr() -> Iterator[None]:
    """Point file descriptor 1 at stderr for the duration (child processes too)."""
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _measure(cfg: Any, args: argparse.Namespace, n: int) -> dict[str, Any]:
    """Run the daemon's loop, then the sleep loop; their figures."""
    from mmctl.errors import MmctlError
    from mmctl.runtime.factory import create_daemon
    from mmctl.runtime.loop import Tick
    from mmctl.runtime.timing import TimingRing
    from mmctl.telemetry.service import TelemetryService

    daemon = create_daemon(cfg, socket_path=None, telemetry=TelemetryService(cfg))
    result: dict[str, Any] = {"seconds": args.seconds, "rate_hz": cfg.loop.rate_hz,
                              "rt_priority": cfg.loop.rt_priority,
                              "spin_margin_us": cfg.loop.spin_margin * 1e6,
                              "cpus": os.cpu_count(), "loadavg_1min": os.getloadavg()[0]}
    try:
        daemon.open()
        daemon.start()
        daemon.call("tare")
        while daemon.core.taring:
            time.sleep(0.01)
        deadline = time.monotonic() + 30.0
        while True:
            try:
                daemon.call("enable")
                break
            except MmctlError:  # a condition flickering at start-up: retry
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        daemon.sim.start_human()
        time.sleep(1.0)  # warm-up
        c0 = daemon.ring.count
        time.sleep(args.seconds)
        count = daemon.ring.count - c0
        snap = daemon.ring.snapshot(count)
        steps = _step_window(daemon.step_ns, snap.first_index, len(snap))
        result["loop"] = _figures(snap, steps)
        result["loop"]["armed_at_end"] = daemon.safety.armed
        if args.telemetry:
            from mmctl.telemetry.overhead import windows_on_daemon

            result["telemetry"] = windows_on_daemon(daemon, args.seconds, phases=10)
            result["telemetry"]["armed_at_end"] = daemon.safety.armed
        daemon.loop.stop()
        daemon.loop.wait(10.0)
        result["sleep_baseline"] = _in_thread(
            lambda: _sleep_loop(daemon, args.seconds, n, Tick, TimingRing), cfg.loop)
        result["sleep_baseline"]["armed_at_end"] = daemon.safety.armed
    finally:
        daemon.shutdown()
    return result


def _step_window(step_ns: Any, first_cycle: int, count: int) -> Any:
    import numpy as np

    idx = np.arange(first_cycle, first_cycle + count) % step_ns.shape[0]
    vals = step_ns[idx] / 1e3
    return vals[vals > 0]


def _in_thread(fn: Any, loop_cfg: Any) -> Any:
    """Run ``fn`` on a thread with the loop's scheduling (priority, affinity) so that
    only the waiting strategy differs; return its result or re-raise its exception."""
    import threading

    from mmctl.runtime.loop import apply_realtime

    box: dict[str, Any] = {}

    def body() -> None:
        try:
            apply_realtime(loop_cfg.rt_priority, loop_cfg.cpu_affinity, timer_slack=False)
            box["result"] = fn()
        except BaseException as exc:  # noqa: BLE001 -- re-raised in the caller below
            box["error"] = exc

    th = threading.Thread(target=body, name="mmctl-sleep-baseline")
    th.start()
    th.join()
    if "error" in box:
        raise box["error"]
    return box["result"]


def _sleep_loop(daemon: Any, seconds: float, size: int, tick_cls: Any,
                ring_cls: Any) -> dict[str, float | int]:
    """The same cycle in a plain loop: ``time.sleep`` to each absolute deadline."""
    ring = ring_cls(size)
    period = daemon.loop.period_ns
    clock = time.perf_counter_ns
    first = daemon.cycles
    deadline = clock() + period
    end = deadline + int(seconds * 1e9)
    k = 0
    while deadline < end:
        delay = deadline - clock()
        if delay > 0:
            time.sleep(delay * 1e-9)
        wake = clock()
        daemon.cycle(tick_cls(daemon.cycles, deadline, wake, period, 0, 0, False))
        done = clock()
        this = deadline
        deadline += period
        missed = 0
        if done > deadline:
            missed = (done - deadline) // period + 1
            deadline += missed * period
        ring.record(this, wake - this, done - wake, deadline - missed * period - done, missed)
        k += 1
    snap = ring.snapshot(k)
    steps = _step_window(daemon.step_ns, first, k)
    return _figures(snap, steps)


def _print_table(r: dict[str, Any]) -> None:
    print(f"mmctl bench loop: {r['seconds']:g} s per loop at {r['rate_hz']:g} Hz on the "
          f"simulated robot ({r['cpus']} CPUs, load {r['loadavg_1min']:.2f}, SCHED_FIFO "
          f"{r['rt_priority'] or 'off'}, spin {r['spin_margin_us']:g} us)")
    print(f"{'':22}{'compute p50/p99/max [us]':>28}{'step p50/p99':>16}"
          f"{'latency p50/p99/p99.9 [us]':>30}{'miss rate':>11}")
    for key, label in (("loop", "loop (sleep + spin)"), ("sleep_baseline", "time.sleep loop")):
        f = r[key]
        comp = f"{f['compute_p50_us']:.0f}/{f['compute_p99_us']:.0f}/{f['compute_max_us']:.0f}"
        step = f"{f.get('step_p50_us', 0):.0f}/{f.get('step_p99_us', 0):.0f}"
        lat = f"{f['latency_p50_us']:.0f}/{f['latency_p99_us']:.0f}/{f['latency_p999_us']:.0f}"
        print(f"{label:22}{comp:>28}{step:>16}{lat:>30}{100 * f['miss_rate']:>10.2f}%")
    if "telemetry" in r:
        from mmctl.telemetry.overhead import format_report

        print(f"\ntelemetry off vs on (daemon loop, alternating {r['seconds'] / 10:g} s windows):")
        print(format_report(r["telemetry"]))
    t = r["targets"]
    print(f"targets: compute p99 < {t['compute_p99_us']:g} us, wake latency p99 < "
          f"{t['latency_p99_us']:g} us, miss rate < {100 * t['miss_rate']:g} %")
