"""Read the force/torque sensor and print the wrench it measures.

Connects with the real transport (``--transport can``: ATI Net F/T CAN layout over
python-can; ``rdt``: ATI RDT over UDP), reads ``--samples`` fresh samples paced at
``--rate`` (the control loop's 500 Hz by default; 0 = back to back) and prints the mean
and last force [N] and torque [N m] in the sensor frame, the lost / out-of-order
counters and the time one ``read()`` takes.  Nothing is tared or filtered.

``--simulate`` starts the simulated sensor in this process first and probes it through
the same client code: on CAN the fake answers on the ``virtual`` channel (a python-can
``virtual`` bus exists only inside one process, so this is the only way to demo the CAN
probe without hardware); on RDT it serves on 127.0.0.1 at an ephemeral port.  The
simulated sensor measures a constant wrench (2, -1, 10 N; 0.1, -0.05, 0.02 N m).

With ``--json`` one JSON object is printed::

    {"transport": "can", "link": "virtual:mmctl-sensor@0x20", "simulated": false,
     "samples": 100, "reads": 100, "lost": 0, "out_of_order": 0, "status": 0,
     "force": {"mean": [fx, fy, fz], "last": [fx, fy, fz]},      # [N]
     "torque": {"mean": [tx, ty, tz], "last": [tx, ty, tz]},     # [N m]
     "read_us": {"mean": ..., "p99": ..., "max": ...}, "rate_hz": 500.0}

When nothing answers (or the sensor reports a fault) one line names the link and the
cause, and the exit status is 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from typing import Any, TextIO, cast

SIMULATED_WRENCH = (2.0, -1.0, 10.0, 0.1, -0.05, 0.02)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--transport", choices=("can", "rdt"), help="default: sensor.transport")
    p.add_argument("--config", metavar="F", help="YAML config (default: built-in defaults)")
    can = p.add_argument_group("CAN")
    can.add_argument("--interface", help="python-can interface (default: sensor.can.interface)")
    can.add_argument("--channel", help="python-can channel (default: sensor.can.channel)")
    can.add_argument("--base-id", type=lambda s: int(s, 0), metavar="N",
                     help="CAN base id, e.g. 0x20 (default: sensor.can.base_id)")
    rdt = p.add_argument_group("RDT")
    rdt.add_argument("--host", help="sensor address (default: sensor.rdt.host)")
    rdt.add_argument("--port", type=int, help="UDP port (default: sensor.rdt.port)")
    p.add_argument("--samples", type=int, default=100, metavar="N", help="fresh samples (100)")
    p.add_argument("--rate", type=float, default=500.0, metavar="HZ",
                   help="read rate [Hz] (500; 0 = back to back)")
    p.add_argument("--stale-timeout", type=float, metavar="S",
                   help="stale-sample fault after S seconds (default: sensor.wrench.stale_timeout)")
    p.add_argument("--simulate", action="store_true",
                   help="start the simulated sensor in this process and probe it")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _sensor_config(args: argparse.Namespace) -> Any:
    from mmctl.config import default_config, load_config

    cfg: Any = (load_config(args.config) if args.config else default_config()).sensor
    # --simulate runs the fake in this process: on python-can's virtual bus unless an
    # interface is named (then refused: a fake cannot serve a real bus)
    interface = args.interface or ("virtual" if args.simulate else None)
    can_over = {k: v for k, v in (("interface", interface), ("channel", args.channel),
                                  ("base_id", args.base_id)) if v is not None}
    rdt_over = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
    wrench = cfg.wrench
    if args.stale_timeout is not None:
        wrench = dataclasses.replace(wrench, stale_timeout=args.stale_timeout)
    return dataclasses.replace(
        cfg, transport=args.transport or cfg.transport, wrench=wrench,
        can=dataclasses.replace(cfg.can, **can_over), rdt=dataclasses.replace(cfg.rdt, **rdt_over),
    )


def _start_fake(cfg: Any) -> tuple[Any, Any]:
    """Start the simulated sensor for ``cfg``; returns (fake, cfg pointing at it)."""
    from mmctl.errors import ConfigError
    from mmctl.sim.wrench_source import ConstantWrench

    source = ConstantWrench(SIMULATED_WRENCH)
    if cfg.transport == "can":
        from mmctl.sim.fake_ft_can import FakeFtCanSensor

        if cfg.can.interface != "virtual":
            raise ConfigError("--interface", cfg.can.interface,
                              "--simulate runs the fake on python-can's 'virtual' interface only")
        can_fake = FakeFtCanSensor(source, channel=cfg.can.channel, base_id=cfg.can.base_id)
        return can_fake.start(), cfg
    from mmctl.sim.fake_rdt import FakeRdtServer

    fake = FakeRdtServer(source, host="127.0.0.1", port=0,
                         counts_per_force=cfg.rdt.counts_per_force,
                         counts_per_torque=cfg.rdt.counts_per_torque).start()
    host, port = fake.address
    return fake, dataclasses.replace(cfg, rdt=dataclasses.replace(cfg.rdt, host=host, port=port))


def _collect(sensor: Any, samples: int, rate: float) -> dict[str, Any]:
    import numpy as np

    from mmctl.errors import TransportError

    period = 1.0 / rate if rate > 0 else 0.0
    wrenches: list[Any] = []
    read_ns: list[int] = []
    seq = None
    reads = 0
    deadline = time.monotonic() + 5.0 + 3.0 * samples * max(period, 0.002)
    next_t = time.monotonic()
    while len(wrenches) < samples:
        if period:
            next_t += period
            pause = next_t - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        t0 = time.perf_counter_ns()
        w = sensor.read()
        read_ns.append(time.perf_counter_ns() - t0)
        reads += 1
        if w.sequence != seq:
            seq = w.sequence
            wrenches.append(w)
        if time.monotonic() > deadline:
            raise TransportError(f"only {len(wrenches)}/{samples} fresh samples in {reads} reads")
    arr = np.array([w.as_array() for w in wrenches])
    us = np.array(read_ns) / 1e3
    mean = arr.mean(axis=0)
    last = arr[-1]
    stats = sensor.stats()
    return {
        "samples": len(wrenches), "reads": reads, "lost": stats.lost,
        "out_of_order": stats.out_of_order, "status": wrenches[-1].status,
        "force": {"mean": mean[:3].tolist(), "last": last[:3].tolist()},
        "torque": {"mean": mean[3:].tolist(), "last": last[3:].tolist()},
        "read_us": {"mean": float(us.mean()), "p99": float(np.percentile(us, 99)),
                    "max": float(us.max())},
        "rate_hz": rate,
    }


class _Stderr:
    """sys.stderr looked up at every write (pytest swaps it between tests)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()

    def isatty(self) -> bool:
        return sys.stderr.isatty()


def _vec(v: list[float]) -> str:
    return " ".join(f"{x:+10.4f}" for x in v)


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import ConfigError
    from mmctl.runtime.logging import setup_logging
    from mmctl.transports.sensor import open_sensor

    setup_logging("warning", stream=cast(TextIO, _Stderr()))  # stdout: the result only
    if args.samples <= 0:
        raise ConfigError("--samples", args.samples, "must be > 0")
    if args.rate < 0:
        raise ConfigError("--rate", args.rate, "must be >= 0 [Hz]")
    cfg = _sensor_config(args)
    fake = None
    try:
        if args.simulate:
            fake, cfg = _start_fake(cfg)
        sensor = open_sensor(cfg)
        with sensor:
            report = _collect(sensor, args.samples, args.rate)
            link = sensor.link
    finally:
        if fake is not None:
            fake.stop()
    report = {"transport": cfg.transport, "link": link, "simulated": bool(args.simulate), **report}
    if args.json:
        print(json.dumps(report))
        return 0
    rate = f"{args.rate:g} Hz" if args.rate else "back to back"
    print(f"sensor {cfg.transport} {link}{' (simulated)' if args.simulate else ''}: "
          f"{report['samples']} samples in {report['reads']} reads, lost {report['lost']}, "
          f"out of order {report['out_of_order']}, status 0x{report['status']:X}")
    print(f"force  [N]    mean {_vec(report['force']['mean'])}   last {_vec(report['force']['last'])}")
    print(f"torque [N m]  mean {_vec(report['torque']['mean'])}   last {_vec(report['torque']['last'])}")
    r = report["read_us"]
    print(f"read() {r['mean']:.1f} us mean, {r['p99']:.1f} us p99, {r['max']:.1f} us max ({rate})")
    return 0
