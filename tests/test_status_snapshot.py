"""The control socket's ``status`` is a snapshot (issue 17): one build serves every
client asking within its age, and a change of state, fault or mode shows at once."""

from __future__ import annotations

from collections.abc import Callable

import pytest

import mmctl.runtime.daemon as daemon_module
from test_fault_matrix import Rig, make_rig, model  # noqa: F401 -- fixtures


def test_status_is_a_snapshot_renewed_on_a_change(make_rig: Callable[..., Rig],  # noqa: F811
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(daemon_module, "STATUS_MAX_AGE", 1e9)  # age out of the picture
    rig = make_rig()
    rig.step(3)
    first = rig.daemon.handle({"cmd": "status"}, None)
    rig.step(5)
    assert rig.daemon.handle({"cmd": "status"}, None) is first  # one build for all
    assert first["cycles"] == 3 and first["state"] == "disarmed"
    rig.enable()
    armed = rig.daemon.handle({"cmd": "status"}, None)
    assert armed is not first and armed["state"] == "armed"
    rig.daemon.call("mode", mode="switch")
    assert rig.daemon.handle({"cmd": "status"}, None)["mode"] == "switch"
    monkeypatch.setattr(daemon_module, "STATUS_MAX_AGE", -1.0)  # always too old
    rig.step(2)
    fresh = rig.daemon.handle({"cmd": "status"}, None)
    assert fresh["cycles"] == rig.daemon.cycles
