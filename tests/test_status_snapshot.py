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


def test_status_names_the_robots_nearest_parts_and_the_fault_names_the_pair(
        make_rig: Callable[..., Rig]) -> None:  # noqa: F811
    from test_fault_matrix import Q_SELF_COLLISION

    rig = make_rig()
    rig.arm_and_push()
    robot = rig.daemon.status()["robot"]
    assert robot["nearest_parts"]["pair"] == "deck-upper_arm"  # at q_des, 10.6 cm apart
    assert robot["nearest_parts"]["distance_m"] == pytest.approx(0.1059, abs=0.002)
    rig.arm.q = Q_SELF_COLLISION.copy()
    rig.step(1)
    st = rig.daemon.status()
    assert st["fault"] == "self_collision"
    assert st["fault_details"]["pair"] == "deck-handle" and st["fault_details"]["distance_m"] < 0
