"""The safety state machine: start disarmed, latch faults, refuse re-arm while a cause persists."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from structlog.testing import capture_logs

from mmctl.errors import FaultCause
from mmctl.runtime.safety import EnableRefused, SafetyMonitor, SafetyState

OK: dict = {}


def test_starts_disarmed_and_enables_when_healthy() -> None:
    s = SafetyMonitor()
    assert s.state is SafetyState.DISARMED and not s.armed
    assert s.update(OK) is False
    s.enable()
    assert s.armed


def test_fault_latches_names_the_cause_once_and_refuses_rearm() -> None:
    s = SafetyMonitor()
    s.enable()
    with capture_logs() as logs:
        assert s.update({FaultCause.WRENCH_LIMIT: {"force": 200.0}}) is True
        # Still present next cycle: no second stop request, no second fault event.
        assert s.update({FaultCause.WRENCH_LIMIT: {"force": 201.0}}) is False
    faults = [e for e in logs if e["event"] == "fault"]
    assert len(faults) == 1
    assert faults[0]["cause"] == "wrench_limit" and faults[0]["force"] == 200.0
    assert faults[0]["log_level"] == "error"
    assert s.state is SafetyState.FAULT and s.latched is FaultCause.WRENCH_LIMIT
    with pytest.raises(EnableRefused, match="wrench_limit"):
        s.enable()
    assert s.state is SafetyState.FAULT
    # Cause gone: still latched until the operator enables.
    s.update(OK)
    assert s.state is SafetyState.FAULT and s.as_dict()["fault"] == "wrench_limit"
    s.enable()
    assert s.armed and s.latched is None and s.faults == 1


def test_disarmed_records_conditions_without_faulting() -> None:
    s = SafetyMonitor()
    with capture_logs() as logs:
        assert s.update({FaultCause.SENSOR_STALE: {}}) is False
    assert s.state is SafetyState.DISARMED
    assert s.as_dict()["conditions"] == ["sensor_stale"]
    assert [e["event"] for e in logs] == ["fault_conditions"]
    with pytest.raises(EnableRefused) as info:
        s.enable()
    assert info.value.causes == [FaultCause.SENSOR_STALE]


def test_trip_and_disable() -> None:
    s = SafetyMonitor()
    assert s.trip(FaultCause.INTERNAL, error="x") is False  # disarmed: nothing to stop
    s.enable()
    assert s.trip(FaultCause.INTERNAL, error="x") is True
    assert s.state is SafetyState.FAULT
    assert s.disable() is False and s.state is SafetyState.DISARMED
    s.enable()
    assert s.disable() is True


@settings(max_examples=60, deadline=None)
@given(st.lists(st.one_of(st.just("enable"), st.just("disable"), st.just("ok"),
                          st.sampled_from(list(FaultCause))), max_size=40))
def test_never_armed_while_a_condition_is_present(events: list) -> None:
    s = SafetyMonitor()
    for ev in events:
        if ev == "enable":
            try:
                s.enable()
            except EnableRefused:
                assert s.active
        elif ev == "disable":
            s.disable()
        elif ev == "ok":
            s.update(OK)
        else:
            was_armed = s.armed
            assert s.update({ev: {}}) is was_armed
        assert not (s.armed and s.active)
