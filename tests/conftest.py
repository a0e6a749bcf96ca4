"""Shared fixtures and test-wide settings.

``loopback_host`` hands every test its own 127.x.y.z address so servers on the fixed
UR ports (29999, 30003, 30004) of parallel tests never collide; an address whose
ports are already taken (another test run on the same machine) is skipped.

Hypothesis runs without deadlines or the too-slow health check: CI machines have two
shared cores, and speed is measured by benchmarks, never asserted in tests.
"""

from __future__ import annotations

import faulthandler
import itertools
import os
from collections.abc import Iterator

import pytest
import structlog
from hypothesis import HealthCheck, settings

from mmctl.sim.fake_ur.server import ports_free

settings.register_profile(
    "mmctl",
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
settings.load_profile("mmctl")

_UR_PORTS = (29999, 30003, 30004)
_counter = itertools.count()


def _worker_index() -> int:
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    digits = "".join(ch for ch in name if ch.isdigit())
    return int(digits or 0)




@pytest.fixture
def loopback_host() -> str:
    """A loopback address unique to this test whose UR ports are free.

    127.<10 + xdist worker>.<pid-derived>.<counter>: distinct per worker and per test
    process, so concurrent pytest runs on one machine do not collide either.
    """
    block = os.getpid() % 200
    for _ in range(1000):
        n = next(_counter)
        host = f"127.{10 + _worker_index()}.{(block + n // 250) % 250}.{n % 250 + 2}"
        if ports_free(host, _UR_PORTS):
            return host
    raise RuntimeError("no loopback address with free UR ports")


#: Last resort against a test that hangs inside C++ code holding the GIL (ur_rtde's
#: blocking calls do), where pytest-timeout's SIGALRM handler can never run: a C
#: watchdog thread dumps every thread's stack and ends the worker process, so xdist
#: reports the test as crashed and the run goes on instead of hanging CI.  It fires this
#: long after the test's own pytest-timeout (its mark, else the ini's), never before it:
#: a fixed 420 s once ended a worker inside a study test (pytest-timeout 600 s) that was slow,
#: not hung, on a busy machine (CI, both cores busy).
HARD_TIMEOUT_GRACE_S = 120.0


def hard_timeout(item: pytest.Item) -> float:
    """The hard timeout of ``item`` [s]: its pytest-timeout plus the grace."""
    mark = item.get_closest_marker("timeout")
    if mark is not None and mark.args:
        limit = float(mark.args[0])
    else:
        limit = float(item.config.getini("timeout") or 0.0)
    return max(limit, 300.0) + HARD_TIMEOUT_GRACE_S


@pytest.fixture(autouse=True)
def _hard_timeout(request: pytest.FixtureRequest) -> Iterator[None]:
    faulthandler.dump_traceback_later(hard_timeout(request.node), exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.fixture(autouse=True)
def _reset_structlog() -> Iterator[None]:
    """Undo any structlog configuration a test (e.g. the daemon's set-up) made."""
    yield
    structlog.reset_defaults()
