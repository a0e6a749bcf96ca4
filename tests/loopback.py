"""A loopback address of its own for each simulated robot of a module-scoped fixture.

The fake UR's ports are fixed (29999, 30003, 30004; the simulated robot's socketcand
server: 29536), so every fake needs an address no other test uses at the same time:
xdist workers of this run, and other test runs on the same machine (the conftest's
``loopback_host`` fixture does the same for function-scoped tests).
"""

from __future__ import annotations

import itertools
import os

from mmctl.sim.fake_ur.server import ports_free

PORTS = (29999, 30003, 30004, 29536)
_counter = itertools.count()


def free_loopback_host(block: int) -> str:
    """127.<10 + xdist worker>.<block>.<n>, n derived from this process's id, the first
    whose ports are free (``block``: the test module's own third byte)."""
    digits = "".join(ch for ch in os.environ.get("PYTEST_XDIST_WORKER", "gw0") if ch.isdigit())
    worker = 10 + int(digits or 0)
    for _ in range(250):
        host = f"127.{worker}.{block}.{(os.getpid() + next(_counter)) % 250 + 2}"
        if ports_free(host, PORTS):
            return host
    raise RuntimeError(f"no loopback address 127.{worker}.{block}.* with free ports")


