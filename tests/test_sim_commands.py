"""The simulation's control-socket commands are validated like the configuration: an
unknown field, a wrong type or a value out of range is one error naming the command, the
field, the value and what is allowed, and nothing is applied.

Through :meth:`SimService.handle` on a service that never started (no fakes, no
socket): a bad request must fail before it touches the world.  The real `mmctl sim`
socket answers the same (tests/test_sim_process.py)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest

from mmctl.config import config_from_dict
from mmctl.errors import MmctlError
from mmctl.sim.service import FIELDS, BadRequest, SimService
from mmctl.sim.world import FAULTS
from simconfig import sim_config


@pytest.fixture
def service(tmp_path: Path) -> Iterator[SimService]:
    cfg = config_from_dict(sim_config("127.0.0.2", tmp_path, {"sim": {"human": True}}))
    svc = SimService(cfg)  # not run: no fake is started, no socket opened
    svc.world.human_on = True
    yield svc


def _world_state(svc: SimService) -> tuple[Any, ...]:
    w = svc.world
    return (w.push, w.human_on, w._push_until, w._hold_until, w._press_until,
            sorted(w._faults), w._step, svc._stop.is_set())


def _bad(svc: SimService, req: dict[str, Any]) -> BadRequest:
    before = _world_state(svc)
    with pytest.raises(BadRequest) as info:
        svc.handle(req, cast(Any, None))
    assert _world_state(svc) == before, "a rejected request changed the world"
    assert str(info.value).count("\n") == 0
    return info.value


def test_every_command_has_its_fields_listed(service: SimService) -> None:
    assert set(FIELDS) == set(service._handlers)


@pytest.mark.parametrize(("req", "field", "fragment"), [
    # push: the force
    ({"cmd": "push"}, "force", "is required"),
    ({"cmd": "push", "force": "30"}, "force", "must be a list of 3 numbers [N] or null"),
    ({"cmd": "push", "force": [1, 2]}, "force", "must be a list of 3 numbers"),
    ({"cmd": "push", "force": {"x": 1}}, "force", "must be a list of 3 numbers"),
    ({"cmd": "push", "force": [1, "2", 3]}, "force[1]", "must be a number [N]"),
    ({"cmd": "push", "force": [1, True, 3]}, "force[1]", "must be a number [N]"),
    ({"cmd": "push", "force": [1, 2, None]}, "force[2]", "must be a number [N]"),
    ({"cmd": "push", "force": [1e309, 0, 0]}, "force[0]", "finite"),
    ({"cmd": "push", "force": [0, -5000, 0]}, "force[1]", "must be >= -1000 and <= 1000 [N]"),
    # push: how long
    ({"cmd": "push", "force": [0, 30, 0], "seconds": "x"}, "seconds", "must be a number [s]"),
    ({"cmd": "push", "force": [0, 30, 0], "seconds": True}, "seconds", "must be a number [s]"),
    ({"cmd": "push", "force": [0, 30, 0], "seconds": 0}, "seconds", "must be > 0 and <= 3600"),
    ({"cmd": "push", "force": [0, 30, 0], "seconds": -1}, "seconds", "must be > 0"),
    ({"cmd": "push", "force": [0, 30, 0], "seconds": 1e6}, "seconds", "<= 3600 [s]"),
    ({"cmd": "push", "force": None, "seconds": 5}, "seconds", "must be null when force is null"),
    # a field the command does not take (the "duration": "x" left a push on)
    ({"cmd": "push", "force": [0, 30, 0], "duration": "x"}, "duration",
     "unknown field; push takes: force, seconds"),
    # person
    ({"cmd": "person", "on": "false"}, "on", "must be true or false (a JSON boolean)"),
    ({"cmd": "person", "on": 0}, "on", "must be true or false"),
    ({"cmd": "person", "on": None}, "on", "must be true or false"),
    ({"cmd": "person", "hold": "long"}, "hold", "must be a number [s]"),
    ({"cmd": "person", "hold": -1}, "hold", "must be >= 0 and <= 60 [s]"),
    ({"cmd": "person", "hold": 61}, "hold", "<= 60"),
    ({"cmd": "person", "on": False, "hold": "x"}, "hold", "must be a number"),  # nothing of it
    ({"cmd": "person", "off": True}, "off", "unknown field; person takes: on, hold"),
    # fault
    ({"cmd": "fault"}, "name", "must be one of: sensor_silent"),
    ({"cmd": "fault", "name": 3}, "name", "must be one of"),
    ({"cmd": "fault", "name": "gremlins"}, "name", "must be one of"),
    ({"cmd": "fault", "name": "sensor_silent", "on": "false"}, "on", "a JSON boolean"),
    ({"cmd": "fault", "name": "sensor_silent", "on": 1}, "on", "a JSON boolean"),
    ({"cmd": "fault", "name": "sensor_silent", "state": "on"}, "state",
     "unknown field; fault takes: name, on"),
    # log
    ({"cmd": "log", "since": "0"}, "since", "must be a number [s]"),
    ({"cmd": "log", "since": float("nan")}, "since", "finite"),
    ({"cmd": "log", "since": -1}, "since", "must be >= 0 [s]"),
    ({"cmd": "log", "until": 5}, "until", "unknown field; log takes: since"),
    # the commands without fields
    ({"cmd": "status", "verbose": True}, "verbose", "unknown field; status takes: (none)"),
    ({"cmd": "press", "seconds": 1}, "seconds", "unknown field; press takes: (none)"),
    ({"cmd": "stop", "now": True}, "now", "unknown field; stop takes: (none)"),
])
def test_a_bad_request_is_one_error_naming_the_field_and_applies_nothing(
        service: SimService, req: dict[str, Any], field: str, fragment: str) -> None:
    err = _bad(service, req)
    assert err.cmd == req["cmd"] and err.field == field
    assert str(err).startswith(f"{req['cmd']}: {field} = "), str(err)
    assert fragment in str(err), str(err)


def test_the_protocol_s_own_fields_are_not_unknown(service: SimService) -> None:
    """``timeout_s`` (every ControlClient request) passes; only the fields are checked."""
    err = _bad(service, {"cmd": "fault", "name": "nope", "timeout_s": 10.0})
    assert err.field == "name"


def test_valid_values_pass_the_checks() -> None:
    from mmctl.sim.service import json_bool, json_number, push_force

    assert push_force({"force": [0, 30.5, -1000]}) == [0.0, 30.5, -1000.0]
    assert push_force({"force": None}) is None
    assert json_bool("person", {"on": False}, "on", True) is False
    assert json_bool("fault", {}, "on", True) is True
    assert json_number("push", "seconds", 3600, 0.0, 3600.0, "s", lo_open=True) == 3600.0


def test_unknown_commands_are_named(service: SimService) -> None:
    with pytest.raises(MmctlError, match="unknown command 'explode'; known: status, push"):
        service.handle({"cmd": "explode"}, cast(Any, None))


def test_the_known_faults_are_listed_in_the_error(service: SimService) -> None:
    err = _bad(service, {"cmd": "fault", "name": "gremlins"})
    assert all(name in str(err) for name in FAULTS)
