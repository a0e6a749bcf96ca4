"""A configuration for a daemon on the simulated robot's own process, per test.

Everything the simulated robot serves sits on the test's own loopback address (fake UR
ports, socketcand), and its control socket in the test's directory, so tests running
in parallel never meet.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[1]


def _merge(into: dict[str, Any], extra: dict[str, Any]) -> None:
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(into.get(key), dict):
            _merge(into[key], value)
        else:
            into[key] = copy.deepcopy(value)


#: Overrides that put every staleness timeout, the devices' own watchdogs and the loop's
#: miss budget beyond what a loaded 2-core machine can exhaust in a test (it starves the
#: loop, the arm's process, the simulated robot's process and its socketcand traffic for
#: a while): for tests of something else, where any fault is a failure.  The faults
#: themselves are tested on a scripted clock (test_fault_matrix.py).
LOAD_PROOF: dict[str, Any] = {
    "arm": {"stale_cycles": 10_000, "watchdog_min_frequency": 1.0},
    # (can.connect_timeout: a start-up under load saw no reply to a calibration read
    # within the 0.5 s default)
    "sensor": {"wrench": {"stale_timeout": 5.0}, "can": {"connect_timeout": 10.0}},
    # (sdo_timeout: a starved simulation answers the SDOs late: seen > 0.5 s at an
    # enable, > 3 s at start-up with both cores busy: "no drive answers")
    "base": {"canopen": {"heartbeat_timeout": 5.0, "sdo_timeout": 10.0},
             "command_watchdog": 10.0},
    "loop": {"max_consecutive_misses": 5_000, "max_total_misses": 1_000_000_000},
    # (an enable that reconnects the arm starts a ur_rtde process: > 5 s when starved)
    "daemon": {"command_timeout": 30.0},
}


def sim_config(host: str, tmp: Path, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """config/sim.yaml moved to ``host``, the simulation's socket in ``tmp``, + ``extra``."""
    cfg: dict[str, Any] = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["arm"]["host"] = host
    cfg["sim"]["host"] = host
    cfg["sim"]["socket_path"] = str(tmp / "sim.sock")
    cfg["sensor"]["can"]["host"] = host
    cfg["base"]["canopen"]["host"] = host
    _merge(cfg, extra or {})
    return cfg


def write_sim_config(host: str, tmp: Path, extra: dict[str, Any] | None = None,
                     name: str = "daemon.yaml") -> Path:
    """:func:`sim_config` written to ``tmp / name``."""
    path = tmp / name
    path.write_text(yaml.safe_dump(sim_config(host, tmp, extra)))
    return path
