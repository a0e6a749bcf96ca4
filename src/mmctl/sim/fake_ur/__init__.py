"""A fake UR10e controller: RTDE (30004), dashboard (29999) and script (30003) servers
that the real ur_rtde client talks to, with the arm joints as a simulated plant.

:class:`FakeURController` (imported lazily so the fake's own process starts without
numpy) runs it in a separate process; :mod:`mmctl.sim.fake_ur.server` is that process.
"""

from __future__ import annotations

from typing import Any

from mmctl.sim.fake_ur.log import CommandKind, FakeCommand

__all__ = ["CommandKind", "FakeCommand", "FakeURController", "start_fake_ur"]


def __getattr__(name: str) -> Any:
    if name in ("FakeURController", "start_fake_ur"):
        from mmctl.sim.fake_ur import controller

        return getattr(controller, name)
    raise AttributeError(name)
