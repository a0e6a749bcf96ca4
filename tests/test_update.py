"""The pure update (`mmctl.control.update`): every per-cycle decision on scripted
readings and a scripted clock -- the safety latch, the operator's commands, the arm hold,
the enabling switch, the button, the base divider.  No threads, no devices, no sleeps."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from mmctl.config import Config, config_from_dict
from mmctl.control.cycle import CycleChain
from mmctl.control.safety import ConditionsChanged, EnableRefused, FaultRaised, SafetyState
from mmctl.control.update import (
    BeginEnable,
    Changed,
    Command,
    Commands,
    Disable,
    EnableCheck,
    EnableFinish,
    Readings,
    Release,
    Reply,
    SetMode,
    SetSwitch,
    Switched,
    Tare,
    Update,
    UpdateState,
)
from mmctl.errors import FaultCause, MmctlError, SafetyFault
from mmctl.types import ArmState, Odometry, Vec, Wrench

DT = 0.002
PUSH = np.array([20.0, 0.0, 0.0])


def make_config(**extra: Any) -> Config:
    return config_from_dict({"sensor": {"wrench": {"stale_timeout": 0.01, "tare_samples": 5}},
                             **extra})


@dataclass
class Rig:
    """The update and its state, with a robot at rest and a sensor pushed as scripted."""

    update: Update
    state: UpdateState
    t: float = 50.0
    index: int = 0
    seq: int = 0
    controller_time: float = 0.0
    inputs: int = 0
    force: Vec = field(default_factory=lambda: np.zeros(3))
    events: list[Any] = field(default_factory=list)

    @property
    def chain(self) -> CycleChain:
        return self.update.chain

    def readings(self, fresh_arm: bool = True, conditions: dict[FaultCause, Any] | None = None,
                 overrun: tuple[int, int] | None = None, calibrating: bool = False,
                 base_read: bool = True, arm_busy: bool = False) -> Readings:
        q = np.array([0.0, -1.2, 1.5, -1.9, -1.57, 0.0])
        r = self.chain.model.fk_base(np.concatenate((q, np.zeros(3))), "sensor").rotation
        raw = self.chain.wrench.gravity_wrench(r)
        raw[:3] += self.force
        self.seq += 1
        if fresh_arm:
            self.controller_time += DT
        arm = ArmState(q, np.zeros(6), self.controller_time, 2, 1)
        return Readings(self.index, self.t, DT, arm, Wrench(raw[:3], raw[3:], self.t, self.seq),
                        Odometry(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.t) if base_read else None,
                        self.inputs,
                        conditions or {}, overrun, 0 if overrun is None else overrun[0],
                        arm_busy=arm_busy, calibrating=calibrating)

    def step(self, inbox: list[Command] | None = None, **kw: Any) -> Commands:
        self.t += DT
        self.index += 1
        self.state, cmds, events = self.update(self.state, self.readings(**kw), inbox or [])
        self.events.extend(events)
        return cmds

    def replies(self) -> list[Reply]:
        return [e for e in self.events if isinstance(e, Reply)]

    def enable(self) -> None:
        """The enable's steps as the runtime sends them (no reconnect needed; the base's
        lease given back with the last)."""
        for cmds in ([BeginEnable()], [EnableCheck()], [Release("base"), EnableFinish()]):
            self.events.clear()
            self.step(list(cmds))
            for reply in self.replies():
                if reply.error is not None:
                    raise reply.error


def peak_of(cmds: Commands) -> float:
    """The largest joint speed of a cycle's speedJ [rad/s]."""
    assert cmds.qd_arm is not None, cmds
    return float(np.abs(cmds.qd_arm).max())


def rig(**extra: Any) -> Rig:
    cfg = make_config(**extra)
    update = Update(cfg, CycleChain(cfg))
    return Rig(update, update.initial_state())


def test_starts_disarmed_and_sends_no_motion() -> None:
    r = rig()
    cmds = r.step()
    assert r.state.safety.state is SafetyState.DISARMED
    assert cmds.qd_arm is None and cmds.twist is None and not cmds.stop and cmds.kick


def test_enable_then_a_push_moves_and_a_fault_stops_in_its_own_cycle() -> None:
    r = rig()
    r.step()
    r.enable()
    assert r.state.safety.armed
    r.force = PUSH.copy()
    for _ in range(20):
        cmds = r.step()
    assert cmds.qd_arm is not None and np.abs(cmds.qd_arm).max() > 0
    r.events.clear()
    cmds = r.step(conditions={FaultCause.DRIVE_FAULT: {"wheel": "FL"}})
    assert cmds.stop and cmds.qd_arm is None and cmds.twist is None
    assert r.state.safety.state is SafetyState.FAULT
    assert [e.cause for e in r.events if isinstance(e, FaultRaised)] == [FaultCause.DRIVE_FAULT]
    cmds = r.step(conditions={FaultCause.DRIVE_FAULT: {"wheel": "FL"}})
    assert not cmds.stop and cmds.qd_arm is None  # latched: one stop, no motion


def test_enable_is_refused_while_a_condition_is_present_and_accepted_once_gone() -> None:
    r = rig()
    r.step(conditions={FaultCause.SENSOR_STALE: {"age_ms": 30.0}})
    with pytest.raises(EnableRefused, match="sensor_stale"):
        for cmd in (BeginEnable(), EnableCheck()):
            r.events.clear()
            r.step([cmd], conditions={FaultCause.SENSOR_STALE: {"age_ms": 30.0}})
            (reply,) = r.replies()
            if reply.error is not None:
                raise reply.error
    assert r.state.safety.state is SafetyState.DISARMED
    r.step()
    r.enable()
    assert r.state.safety.armed


def test_the_base_failing_its_enable_refuses_with_its_cause_and_stops() -> None:
    r = rig()
    r.step()
    r.step([EnableCheck()])
    r.events.clear()
    fault = SafetyFault(FaultCause.DRIVE_FAULT, node_id=1)
    cmds = r.step([EnableFinish(fault)])
    (reply,) = r.replies()
    assert isinstance(reply.error, EnableRefused) and reply.error.causes == [FaultCause.DRIVE_FAULT]
    assert cmds.stop and not r.state.safety.armed


def test_an_enable_leases_the_links_it_works_on_until_their_release() -> None:
    """The links an enable's device work holds are the update's state, not flags set
    from other threads: BeginEnable leases the links to reconnect, EnableCheck the base;
    each Release gives one back; while the arm is leased no watchdog kick goes out."""
    r = rig()
    r.step()
    assert r.state.leased == frozenset()
    lost = {FaultCause.SENSOR_LINK: {"device": "sensor"},
            FaultCause.ARM_DISCONNECTED: {"device": "arm"}}
    r.step(conditions=lost)
    r.events.clear()
    r.step([BeginEnable()], conditions=lost)
    (reply,) = r.replies()
    assert reply.value == ("arm", "sensor") and r.state.leased == {"arm", "sensor"}
    cmds = r.step()
    assert r.state.leased == {"arm", "sensor"}
    r.events.clear()
    cmds = r.step([Release("sensor")], arm_busy=True)
    assert r.state.leased == {"arm"} and not cmds.kick  # the arm reconnects: left alone
    r.step([Release("arm")], arm_busy=True)
    assert r.state.leased == frozenset()
    r.events.clear()
    r.step([EnableCheck()])
    assert r.replies()[0].value is True and r.state.leased == {"base"}
    r.events.clear()
    r.step([Release("base"), EnableFinish()])
    assert [x.value for x in r.replies()] == [None, "armed"]
    assert r.state.leased == frozenset() and r.state.safety.armed
    r.events.clear()
    r.step([Release("wheels")])
    (reply,) = r.replies()
    assert isinstance(reply.error, MmctlError) and "must be one of" in str(reply.error)


def test_disable_while_armed_sends_the_stop_that_cycle() -> None:
    r = rig()
    r.step()
    r.enable()
    cmds = r.step([Disable()])
    assert cmds.stop and r.state.safety.state is SafetyState.DISARMED
    cmds = r.step([Disable()])
    assert not cmds.stop  # disarmed already: nothing to stop


def test_operator_commands_are_values_answered_by_replies() -> None:
    r = rig()
    r.step([SetSwitch("locomotion")])
    (reply,) = r.replies()
    assert isinstance(reply.error, MmctlError) and "needs mode 'switch'" in str(reply.error)
    r.events.clear()
    r.step([SetMode("switch"), SetSwitch("locomotion")])
    assert [x.error for x in r.replies()] == [None, None]
    assert [(e.what, e.new) for e in r.events if isinstance(e, Changed)] == [
        ("mode", "switch"), ("switch", "locomotion")]
    assert r.state.chain.controller.switch.value == "locomotion"
    r.enable()
    r.events.clear()
    r.step([Tare()])
    (reply,) = r.replies()
    assert isinstance(reply.error, MmctlError) and "while armed" in str(reply.error)


def test_a_tare_runs_while_disarmed_and_refuses_enable_until_done() -> None:
    r = rig()
    r.step([Tare()])
    assert r.replies()[0].value == {"taring": True, "samples": 5}
    r.events.clear()
    r.step([EnableCheck()])
    (reply,) = r.replies()
    assert reply.error is not None and "tare is in progress" in str(reply.error)
    for _ in range(5):
        r.step()
    r.enable()
    assert r.state.safety.armed


def test_a_tare_finishes_while_the_base_is_not_read_and_then_enable_goes_on() -> None:
    """A faulted drive (or a lost base link) leaves no odometry: the tare still runs on
    the arm's pose and the sensor's samples, so the enable that resets the drive is not
    refused for good by a tare that can never end."""
    r = rig()
    drive = {FaultCause.DRIVE_FAULT: {"wheel": "FL"}}
    r.step(base_read=False, conditions=drive)
    r.step([Tare()], base_read=False, conditions=drive)
    n = r.update.cfg.sensor.wrench.tare_samples
    for _ in range(n + 5):
        cmds = r.step(base_read=False, conditions=drive)
        assert cmds.result is None and cmds.qd_arm is None and cmds.twist is None
    assert r.state.chain.wrench.tare_left == 0  # the tare finished
    r.step()  # the drive reset by the base's enable: read again
    r.enable()
    assert r.state.safety.armed


def test_the_arm_hold_brings_the_command_to_rest_on_a_repeated_sample() -> None:
    r = rig()
    hold = r.update.hold_cycles
    r.step()
    r.enable()
    r.force = PUSH.copy()
    for _ in range(50):
        moving = r.step()
    assert moving.qd_arm is not None
    peak = peak_of(moving)
    for _ in range(hold - 1):  # the same sample: not yet held
        cmds = r.step(fresh_arm=False)
    assert r.state.arm_repeats == hold - 1
    assert peak_of(cmds) >= 0.9 * peak
    for _ in range(400):  # held: decelerates to rest on the acceleration limits
        cmds = r.step(fresh_arm=False)
    assert cmds.qd_arm is not None and peak_of(cmds) < 1e-6
    assert r.state.safety.armed  # a hold, not a fault (the arm's link says stale)
    for _ in range(50):
        cmds = r.step()  # fresh samples again: motion again
    assert peak_of(cmds) > 0.5 * peak


def test_the_enabling_switch_released_rests_and_contacts_that_disagree_fault() -> None:
    r = rig(enabling={"inputs": [8, 9], "discrepancy_time": 0.05})
    both = (1 << 8) | (1 << 9)
    r.inputs = both
    r.step()
    assert r.state.enabling.held is True
    r.enable()
    r.force = PUSH.copy()
    for _ in range(50):
        cmds = r.step()
    assert cmds.qd_arm is not None and peak_of(cmds) > 0
    r.inputs = 0  # released: comes to rest, still armed
    for _ in range(400):
        cmds = r.step()
    assert r.state.safety.armed and peak_of(cmds) < 1e-6
    assert r.state.enabling.held is False
    r.inputs = 1 << 8  # one contact: disagree; a fault after discrepancy_time
    n = 0
    while r.state.safety.armed:
        n += 1
        r.step()
        assert n < 100
    assert r.state.safety.latched is FaultCause.ENABLING_DEVICE
    # the first cycle whose time since the contacts first disagreed exceeds 50 ms
    assert 0.05 < (n - 1) * DT + 1e-9 <= 0.05 + DT
    assert r.state.safety.latched_details["levels"] == [1, 0]


def test_the_button_toggles_switch_mode_on_its_rising_edge_only() -> None:
    r = rig(daemon={"switch_input": 3})
    r.step()
    r.inputs = 1 << 3  # pressed in min-energy: nothing
    r.step()
    assert not [e for e in r.events if isinstance(e, Switched)]
    r.inputs = 0
    r.step([SetMode("switch")])
    before = r.state.chain.controller.switch.value
    r.inputs = 1 << 3
    r.step()
    r.step()  # held down: one toggle
    switched = [e for e in r.events if isinstance(e, Switched)]
    assert len(switched) == 1 and switched[0].source == "button"
    assert r.state.chain.controller.switch.value != before


def test_the_base_twist_goes_every_divider_th_cycle_or_at_once_on_a_jump() -> None:
    r = rig(loop={"base_divider": 4, "base_jump": 0.05})
    r.step()
    r.enable()
    r.force = PUSH.copy()
    last = r.state.twist_sent  # the enable's own cycle commanded one
    multiples = jumps = 0
    for _ in range(60):
        cmds = r.step()
        assert cmds.result is not None
        t = cmds.result.twist
        twist = (float(t[0]), float(t[1]), float(t[2]))
        jumped = last is None or max(abs(a - b) for a, b in zip(twist, last)) > 0.05
        if r.index % 4 == 0 or jumped:
            assert cmds.twist == twist, (r.index, last, twist)
            last = twist
            multiples += r.index % 4 == 0
            jumps += r.index % 4 != 0
        else:
            assert cmds.twist is None, (r.index, last, twist)
    assert multiples == 15 and last is not None
    r.events.clear()
    # a stop forgets the last twist: the first after a re-enable goes at once
    r.step([Disable()])
    assert r.state.twist_sent is None


def test_while_a_calibration_runs_the_arm_command_is_the_routines_and_the_base_rests() -> None:
    """The update holds the controller and sends no speedJ of its own (the routine's
    goes out instead, :mod:`mmctl.runtime.calibrate`), and the base gets a zero twist on
    the divider's grid, at once when the last twist sent was not zero: all decided in
    the update, so the runtime changes none of its state."""
    r = rig(loop={"base_divider": 4, "base_jump": 0.05})
    r.step()
    r.enable()
    r.force = PUSH.copy()
    for _ in range(40):
        r.step()
    assert r.state.twist_sent is not None and any(r.state.twist_sent)  # the base moved
    r.force = np.zeros(3)
    cmds = r.step(calibrating=True)  # the first calibrating cycle: the rest goes at once
    assert cmds.qd_arm is None and cmds.kick and not cmds.stop
    assert cmds.twist == (0.0, 0.0, 0.0) and r.state.twist_sent == (0.0, 0.0, 0.0)
    sent = []
    for _ in range(12):
        cmds = r.step(calibrating=True)
        assert cmds.qd_arm is None and cmds.result is not None
        sent.append(cmds.twist)
        assert r.state.safety.armed
    assert sent.count((0.0, 0.0, 0.0)) == 3 and sent.count(None) == 9


def test_a_loop_overrun_is_a_fault_and_enable_waits_for_a_cycle_on_time() -> None:
    r = rig()
    r.step()
    r.enable()
    cmds = r.step(overrun=(3, 3))
    assert cmds.stop and r.state.safety.latched is FaultCause.LOOP_OVERRUN
    r.events.clear()
    r.step([EnableCheck()], overrun=(4, 4))
    assert isinstance(r.replies()[0].error, EnableRefused)
    r.step()
    r.enable()
    assert r.state.safety.armed


def test_conditions_while_disarmed_are_events_only_when_they_change() -> None:
    r = rig()
    stale = {FaultCause.SENSOR_STALE: {"age_ms": 20.0}}
    for _ in range(5):
        r.step(conditions=stale)
    r.step()
    changes = [e for e in r.events if isinstance(e, ConditionsChanged)]
    assert [c.present for c in changes] == [("sensor_stale",), ()]


def test_the_update_is_a_function_of_its_inputs() -> None:
    """The same readings and inbox from the same state give the same commands."""
    a, b = rig(), rig()
    for x in (a, b):
        x.step()
        x.enable()
        x.force = PUSH.copy()
    for _ in range(30):
        ca, cb = a.step(), b.step()
        np.testing.assert_array_equal(ca.qd_arm, cb.qd_arm)
        assert ca.twist == cb.twist


def test_the_writes_outcome_goes_through_the_updates_own_transitions() -> None:
    """A failed command and a cycle that raised are the update's pure transitions (the
    runtime changes no state itself): the fault latches in that cycle, the stop goes
    out once, the twist is forgotten; a failing cycle while disarmed is a condition."""
    r = rig()
    r.step()
    r.enable()
    r.force = PUSH.copy()
    for _ in range(20):
        cmds = r.step()
    assert r.state.twist_sent is not None
    s, events = r.update.write_failed(r.state, FaultCause.ARM_DISCONNECTED, {"device": "arm"})
    assert s.safety.latched is FaultCause.ARM_DISCONNECTED and s.twist_sent is None
    assert [e.cause for e in events if isinstance(e, FaultRaised)] == [
        FaultCause.ARM_DISCONNECTED]
    again, events = r.update.write_failed(s, FaultCause.ARM_DISCONNECTED, {"device": "arm"})
    assert again.safety == s.safety and not events  # latched already: no second fault
    s, stop, events = r.update.cycle_failed(r.state, "ZeroDivisionError()")
    assert stop and s.safety.latched is FaultCause.INTERNAL
    r.state = s
    cmds = r.step([Disable()])
    s, stop, _ = r.update.cycle_failed(r.state, "ZeroDivisionError()")
    assert not stop and FaultCause.INTERNAL in s.safety.active
    assert not cmds.stop
