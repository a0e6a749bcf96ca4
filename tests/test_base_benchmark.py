"""Cost of one base cycle (send_twist + read_odometry) per transport [us].

A benchmark that prints figures (``pytest -s tests/test_base_benchmark.py``); it
asserts only that the cycles ran.  The CANopen figure includes the python-can virtual
bus (a deep copy of every frame) and the simulated drives' thread competing for the
GIL in the same process; the serial figure is given both with the simulated bridge in
this process and in a separate process (closer to real hardware).
"""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from mmctl.config import Config, config_from_dict
from mmctl.sim.fake_drives import FakeDrives
from mmctl.sim.fake_serial_bridge import FakeSerialBridge
from mmctl.transports.base import Base, open_base

N = 1000
PERIOD_NS = 2_000_000


def _measure(base: Base, label: str) -> None:
    send = np.empty(N)
    read = np.empty(N)
    nxt = time.perf_counter_ns()
    for k in range(N):
        t0 = time.perf_counter_ns()
        base.send_twist(0.2, 0.1, 0.2)
        t1 = time.perf_counter_ns()
        base.read_odometry()
        t2 = time.perf_counter_ns()
        send[k], read[k] = (t1 - t0) / 1e3, (t2 - t1) / 1e3
        nxt += PERIOD_NS
        left = nxt - time.perf_counter_ns()
        if left > 0:
            time.sleep(left / 1e9)
    total = send + read
    print(f"\n{label}: {N} cycles at 500 Hz, us per cycle: mean {total.mean():.0f}, "
          f"median {np.median(total):.0f}, p99 {np.percentile(total, 99):.0f} "
          f"(send_twist median {np.median(send):.0f}, read_odometry median "
          f"{np.median(read):.0f})")
    assert np.isfinite(total).all() and base.read_odometry().timestamp > 0.0


def _cfg() -> Config:
    return config_from_dict({"base": {
        "canopen": {"interface": "virtual", "channel": f"bench-{uuid.uuid4().hex[:10]}",
                    "heartbeat_timeout": 5.0,
                    "sdo_timeout": 5.0},
        "serial": {"link_timeout": 5.0, "timeout": 1.0}}})


def test_canopen_cycle_cost() -> None:
    cfg = _cfg()
    with FakeDrives(cfg), open_base(cfg, transport="canopen") as base:
        base.enable()
        _measure(base, "canopen (virtual bus, drives in-process)")


def test_serial_cycle_cost_bridge_in_process() -> None:
    cfg = _cfg()
    with FakeSerialBridge(cfg) as bridge, open_base(cfg, transport="serial",
                                                   port=bridge.port) as base:
        base.enable()
        _measure(base, "serial (pty, bridge in-process)")


_BRIDGE = """
import sys
from mmctl.config import default_config
from mmctl.sim.fake_serial_bridge import FakeSerialBridge
with FakeSerialBridge(default_config()) as b:
    print("PORT", b.port, flush=True)
    sys.stdin.read()
"""


@contextmanager
def _bridge_process() -> Iterator[str]:
    proc = subprocess.Popen([sys.executable, "-c", _BRIDGE], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        line = ""
        while not line.startswith("PORT "):  # the bridge also logs to stdout
            line = proc.stdout.readline()
            assert line, "the bridge process ended before naming its port"
        yield line.split()[1]
    finally:
        assert proc.stdin is not None
        proc.stdin.close()
        proc.wait(timeout=10)


def test_serial_cycle_cost_bridge_in_another_process() -> None:
    cfg = _cfg()
    with _bridge_process() as port, open_base(cfg, transport="serial", port=port) as base:
        base.enable()
        _measure(base, "serial (pty, bridge in a separate process)")
