"""Shared fixtures.

``loopback_host`` hands every test its own 127.0.0.x address so servers on the fixed
UR ports (29999, 30003, 30004) of parallel tests never collide.
"""

from __future__ import annotations

import itertools
import os

import pytest

_counter = itertools.count()


def _worker_index() -> int:
    name = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    digits = "".join(ch for ch in name if ch.isdigit())
    return int(digits or 0)


@pytest.fixture
def loopback_host() -> str:
    """A loopback address unique to this test: 127.<10+worker>.<a>.<b>."""
    n = next(_counter)
    return f"127.{10 + _worker_index()}.{n // 250}.{n % 250 + 2}"
