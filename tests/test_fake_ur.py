"""The fake UR controller: plant, control-script handshake, RTDE bytes, dashboard, log,
and the process handle (start/stop/kill/restart, shared state, fault hooks)."""

from __future__ import annotations

import math
import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.errors import TransportError
from mmctl.sim.fake_ur import CommandKind, FakeURController, start_fake_ur
from mmctl.sim.fake_ur import dashboard as dash
from mmctl.sim.fake_ur.log import CommandLog
from mmctl.sim.fake_ur.model import ControllerModel, RuntimeState
from mmctl.sim.fake_ur.program import (
    DONE,
    READY,
    Registers,
    RtdeControlProgram,
    ScriptReceiver,
    register_offset,
    watchdog_actions,
)
from mmctl.sim.fake_ur.rtde_session import RtdeSession
from mmctl.sim.fake_ur.rtde_types import HEADER, OUTPUT_TYPES, MsgType, frame
from mmctl.sim.joints import JointPlant, Motion

DT = 0.002
Q0 = [0.1, -1.5, 1.2, -1.0, -1.57, 0.3]

# What ur_rtde 1.6 asks for: RTDEReceiveInterface's default output recipe (PolyScope
# 5.11) and RTDEControlInterface's output recipe.
UR_RTDE_OUTPUTS = [
    "timestamp", "target_q", "target_qd", "target_qdd", "target_current", "target_moment",
    "actual_q", "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
    "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
    "actual_digital_input_bits", "joint_temperatures", "actual_execution_time", "robot_mode",
    "joint_mode", "safety_mode", "actual_tool_accelerometer", "speed_scaling",
    "target_speed_fraction", "actual_momentum", "actual_main_voltage", "actual_robot_voltage",
    "actual_robot_current", "actual_joint_voltage", "actual_digital_output_bits",
    "runtime_state", "standard_analog_input0", "standard_analog_input1",
    "standard_analog_output0", "standard_analog_output1", "robot_status_bits",
    "safety_status_bits", "ft_raw_wrench", "payload", "payload_cog", "payload_inertia",
    "output_int_register_2", "actual_qdd", "actual_moment", "actual_current_as_torque",
    "elbow_position", "elbow_velocity",
    *[f"output_int_register_{i}" for i in range(12, 20)],
    *[f"output_double_register_{i}" for i in range(12, 20)],
    *[f"output_double_register_{i}" for i in range(6)],
]


# -- plant -----------------------------------------------------------------------------------

def test_speed_reaches_target_with_leading_axis_acceleration() -> None:
    plant = JointPlant(list(Q0))
    target = [0.4, -0.2, 0.0, 0.1, 0.0, 0.0]
    plant.speed(target, 4.0)
    steps = 0
    while plant.qd != target:
        before = list(plant.qd)
        plant.step(DT)
        steps += 1
        dv = [a - b for a, b in zip(plant.qd, before)]
        assert max(abs(x) for x in dv) <= 4.0 * DT + 1e-12
        # every joint changes in proportion: the velocity change keeps its direction
        assert dv[1] == pytest.approx(-0.5 * dv[0], abs=1e-12)
        assert steps < 100
    assert steps == math.ceil(0.4 / (4.0 * DT))


def test_stop_brings_joints_to_rest_and_position_integrates() -> None:
    plant = JointPlant([0.0] * 6)
    plant.speed([1.0, 0, 0, 0, 0, 0], 10.0)
    for _ in range(500):
        plant.step(DT)
    q_at_speed = plant.q[0]
    # 0.1 s ramp (0.05 rad) then 0.9 s at 1 rad/s
    assert q_at_speed == pytest.approx(0.05 + 0.9, abs=1e-9)
    plant.stop(5.0)
    for _ in range(200):
        plant.step(DT)
    assert plant.qd == [0.0] * 6 and plant.motion is Motion.IDLE
    assert plant.q[0] - q_at_speed == pytest.approx(1.0 / (2 * 5.0), abs=1e-9)


def test_joint_limit_stops_the_joint_and_is_reported() -> None:
    plant = JointPlant([2 * math.pi - 0.001, 0, 0, 0, 0, 0])
    plant.speed([1.0, 0, 0, 0, 0, 0], 40.0)
    for _ in range(10):
        plant.step(DT)
    assert plant.limit_hit and plant.q[0] == 2 * math.pi and plant.qd[0] == 0.0


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6),
       st.lists(st.floats(-3, 3), min_size=6, max_size=6), st.floats(0.01, 40))
def test_velocity_change_is_bounded_and_aimed_at_the_target(v0: list[float], target: list[float],
                                                           acc: float) -> None:
    plant = JointPlant([0.0] * 6)
    plant.speed(v0, 1e6)
    plant.step(DT)
    assert plant.qd == pytest.approx(v0)
    plant.speed(target, acc)
    before = np.array(plant.qd)
    plant.step(DT)
    dv = np.array(plant.qd) - before
    want = np.array(target) - before
    assert np.abs(dv).max() <= acc * DT * (1 + 1e-9) + 1e-12
    lead = np.abs(want).max()
    scale = np.abs(dv).max() / lead if lead > 0 else 0.0
    assert 0.0 <= scale <= 1.0 + 1e-9
    np.testing.assert_allclose(dv, scale * want, atol=1e-12)  # direction kept


# -- the ur_rtde control script's register handshake -------------------------------------------

def test_control_script_handshake() -> None:
    regs, plant = Registers(), JointPlant(list(Q0))
    prog = RtdeControlProgram(regs, plant)
    assert regs.out_int[0] == READY
    regs.in_int[0] = 9  # speedJ: real-time, answered "ready" every cycle
    regs.in_double[:8] = [0.1, 0, 0, 0, 0, 0, 2.0, DT]
    prog.cycle()
    assert regs.out_int[0] == READY and plant.motion is Motion.SPEED and plant.target[0] == 0.1
    regs.in_int[0] = 15  # speedStop: executed once, answered "done"
    regs.in_double[0] = 7.0
    prog.cycle()
    assert regs.out_int[0] == DONE and plant.motion is Motion.STOPPING
    assert plant.acceleration == 7.0
    plant.speed([1.0] * 6, 1.0)
    prog.cycle()  # still the same command: not executed again
    assert plant.motion is Motion.SPEED and regs.out_int[0] == DONE
    regs.in_int[0] = 0  # the client clears the command register
    prog.cycle()
    assert regs.out_int[0] == READY
    regs.in_int[0] = 255
    prog.cycle()
    assert not prog.running


def test_upper_register_range() -> None:
    regs, plant = Registers(), JointPlant(list(Q0))
    prog = RtdeControlProgram(regs, plant, offset=24)
    assert regs.out_int[24] == READY and regs.out_int[0] == 0
    regs.in_int[24] = 9
    regs.in_double[24:32] = [0, 0, 0, 0, 0, 0.2, 1.0, DT]
    prog.cycle()
    assert plant.target[5] == 0.2


def test_script_receiver_reassembles_chunked_programs() -> None:
    text = ("def rtde_control():\n    global reg_offset_float = # float register offset\n24\n"
            "    global reg_offset_int = # int register offset\n24\n    while True:\n"
            "        sync()\n    end\nend\n")
    rx = ScriptReceiver()
    got = []
    for i in range(0, len(text), 7):
        got += rx.feed(text[i:i + 7].encode())
    assert [name for name, _ in got] == ["rtde_control"]
    assert got[0][1] == text and register_offset(got[0][1]) == 24
    assert rx.feed(b"textmsg(1)\n") == [("", "textmsg(1)")]
    assert register_offset("def f():\nend\n") == 0


# -- RTDE bytes --------------------------------------------------------------------------------

def _messages(data: bytes) -> list[tuple[int, bytes]]:
    out = []
    while data:
        size, kind = HEADER.unpack_from(data)
        out.append((kind, data[HEADER.size:size]))
        data = data[size:]
    return out


def _session() -> tuple[ControllerModel, RtdeSession]:
    model = ControllerModel(Q0, CommandLog())
    s = RtdeSession(model, "test")
    [(kind, body)] = _messages(s.feed(frame(MsgType.REQUEST_PROTOCOL_VERSION, struct.pack(">H", 2))))
    assert kind == MsgType.REQUEST_PROTOCOL_VERSION and body == b"\x01"
    return model, s


def test_rtde_handshake_versions_and_recipes() -> None:
    model, s = _session()
    [(_, body)] = _messages(s.feed(frame(MsgType.GET_URCONTROL_VERSION)))
    assert struct.unpack(">IIII", body) == model.version and model.version[0] > 3
    names = ",".join(UR_RTDE_OUTPUTS).encode() + b","
    [(_, body)] = _messages(s.feed(frame(MsgType.CONTROL_PACKAGE_SETUP_OUTPUTS,
                                         struct.pack(">d", 500.0) + names)))
    types = body[1:].decode().split(",")
    assert body[0] == 1 and "NOT_FOUND" not in types and len(types) == len(UR_RTDE_OUTPUTS)
    assert types[UR_RTDE_OUTPUTS.index("actual_tool_accelerometer")] == "VECTOR3D"
    assert types[UR_RTDE_OUTPUTS.index("joint_mode")] == "VECTOR6INT32"
    assert types[UR_RTDE_OUTPUTS.index("runtime_state")] == "UINT32"
    [(_, body)] = _messages(s.feed(frame(MsgType.CONTROL_PACKAGE_SETUP_OUTPUTS,
                                         struct.pack(">d", 500.0) + b"actual_q,no_such_var")))
    assert body == b"\x00VECTOR6D,NOT_FOUND"
    for expected_id in (1, 2):
        [(_, body)] = _messages(s.feed(frame(
            MsgType.CONTROL_PACKAGE_SETUP_INPUTS,
            b"input_int_register_0,input_double_register_0,input_double_register_1,")))
        assert body == bytes([expected_id]) + b"INT32,DOUBLE,DOUBLE"


def test_rtde_data_packages_in_and_out() -> None:
    model, s = _session()
    s.feed(frame(MsgType.CONTROL_PACKAGE_SETUP_OUTPUTS,
                 struct.pack(">d", 250.0) + b"timestamp,actual_q,runtime_state,output_int_register_0"))
    s.feed(frame(MsgType.CONTROL_PACKAGE_SETUP_INPUTS,
                 b"input_int_register_0," + b",".join(
                     f"input_double_register_{i}".encode() for i in range(8))))
    assert s.data_packages(0) == b""  # not started
    [(kind, body)] = _messages(s.feed(frame(MsgType.CONTROL_PACKAGE_START)))
    assert kind == MsgType.CONTROL_PACKAGE_START and body == b"\x01"
    # speedJ as ur_rtde packs it: recipe id, int32 command, 8 doubles
    s.feed(frame(MsgType.DATA_PACKAGE, struct.pack(">Bi8d", 1, 9, 0.1, 0, 0, 0, 0, -0.1, 3.0, DT)))
    assert model.regs.in_int[0] == 9 and model.regs.in_double[5] == -0.1
    [entry] = model.log.since(0)
    assert entry.kind is CommandKind.SPEEDJ and entry.qd == (0.1, 0, 0, 0, 0, -0.1)
    assert (entry.acceleration, entry.time) == (3.0, DT)
    model.program = RtdeControlProgram(model.regs, model.plant)
    model.step()
    assert s.data_packages(1) == b""  # 250 Hz: every second period
    [(kind, body)] = _messages(s.data_packages(2))
    rid, t, *rest = struct.unpack(">Bd6dIi", body)
    assert kind == MsgType.DATA_PACKAGE and rid == 1 and t == model.time
    assert rest[:6] == pytest.approx(model.plant.q) and rest[6] == RuntimeState.PLAYING
    assert rest[7] == READY
    s.feed(frame(MsgType.DATA_PACKAGE, b"\x01\x00"))  # wrong size: ignored, logged
    assert model.regs.in_int[0] == 9
    [(kind, body)] = _messages(s.feed(frame(MsgType.CONTROL_PACKAGE_PAUSE)))
    assert body == b"\x01" and s.data_packages(4) == b""


def test_every_output_variable_packs() -> None:
    _, s = _session()
    names = list(OUTPUT_TYPES)
    for i in range(0, len(names), 40):
        s.feed(frame(MsgType.CONTROL_PACKAGE_SETUP_OUTPUTS,
                     struct.pack(">d", 500.0) + ",".join(names[i:i + 40]).encode()))
    s.feed(frame(MsgType.CONTROL_PACKAGE_START))
    packages = _messages(s.data_packages(0))
    assert len(packages) == math.ceil(len(names) / 40)
    assert [body[0] for _, body in packages] == list(range(1, len(packages) + 1))


# -- dashboard, log ---------------------------------------------------------------------------

def test_dashboard_answers() -> None:
    model = ControllerModel(Q0, CommandLog())
    assert dash.answer(model, "PolyscopeVersion")[0].startswith("URSoftware 5.11.0.108249")
    assert dash.answer(model, "get serial number")[0].isdigit()
    assert dash.answer(model, "is in remote control") == ("true", False)
    assert dash.answer(model, "robotmode")[0] == "Robotmode: RUNNING"
    model.set_protective_stop(True)
    assert dash.answer(model, "safetystatus")[0] == "Safetystatus: PROTECTIVE_STOP"
    assert dash.answer(model, "unlock protective stop")[0] == "Protective stop releasing"
    assert not model.protective_stop
    model.program = RtdeControlProgram(model.regs, model.plant)
    assert dash.answer(model, "programState")[0].startswith("PLAYING")
    assert dash.answer(model, "stop")[0] == "Stopped" and model.program is None
    model.remote_control = False
    assert dash.answer(model, "is in remote control")[0] == "false"
    assert "local control" in dash.answer(model, "power off")[0]
    assert dash.answer(model, "quit") == ("Disconnected", True)
    assert dash.answer(model, "fly")[0] == "could not understand: 'fly'"


def test_command_log_ring_drops_oldest() -> None:
    ring = CommandLog(capacity=3)
    for i in range(5):
        ring.add(i * DT, CommandKind.STOP_SCRIPT)
    assert [e.seq for e in ring.since(0)] == [2, 3, 4]
    assert [e.seq for e in ring.since(4)] == [4] and ring.since(5) == []


def test_program_refused_in_a_safety_stop_or_local_control() -> None:
    model = ControllerModel(Q0, CommandLog())
    model.set_emergency_stop(True)
    model.start_program("rtde_control", "def rtde_control():\nend\n")
    assert model.runtime_state == RuntimeState.STOPPED
    model.set_emergency_stop(False)
    model.remote_control = False
    model.start_program("rtde_control", "def rtde_control():\nend\n")
    assert model.runtime_state == RuntimeState.STOPPED
    texts = [e.text for e in model.log.since(0)]
    assert texts == ["rejected: ROBOT_EMERGENCY_STOP (rtde_control)",
                     "rejected: local control (rtde_control)"]


# What ur_rtde 1.6.5's control script does for setWatchdog (command 35), verbatim.
UR_RTDE_SET_WATCHDOG = """def rtde_control():
    global reg_offset_int = # int register offset
0
    while True:
        cmd = read_input_integer_reg(0)
        if cmd == 35:
            watchdog_min_frequency = read_input_float_reg(0)
            if reg_offset_int == 0:
                rtde_set_watchdog("input_int_register_0", watchdog_min_frequency, "stop")
            elif reg_offset_int == 24:
                rtde_set_watchdog("input_int_register_24", watchdog_min_frequency, "stop")
            else:
                rtde_set_watchdog("input_int_register_0", watchdog_min_frequency, "stop")
            end
        end
    end
end
"""


def _set_watchdog(model: ControllerModel, frequency: float) -> None:
    """What ur_rtde's setWatchdog does: command 35 with the frequency, then clear it."""
    model.regs.in_int[0], model.regs.in_double[0] = 35, frequency
    model.input_written(0)
    model.step()
    model.regs.in_int[0] = 0
    model.input_written(0)
    model.step()


def test_watchdog_actions_are_read_from_the_uploaded_script() -> None:
    assert watchdog_actions(UR_RTDE_SET_WATCHDOG) == {0: "stop", 24: "stop"}
    assert watchdog_actions("def p():\n  sync()\nend\n") == {}


def test_rtde_watchdog_stops_the_program_and_the_arm_when_the_input_goes_quiet() -> None:
    model = ControllerModel(Q0, CommandLog())
    model.start_program("rtde_control", UR_RTDE_SET_WATCHDOG)
    _set_watchdog(model, 10.0)  # 100 ms without an update of input_int_register_0: stop
    model.regs.in_int[0] = 9
    model.regs.in_double[:8] = [0.5, 0, 0, 0, 0, 0, 40.0, DT]
    for _ in range(200):  # 0.4 s of speedJ, one package per period: updates in time
        model.input_written(0)
        model.step()
    assert model.runtime_state == RuntimeState.PLAYING
    assert model.plant.qd[0] == pytest.approx(0.5)
    for _ in range(50):  # 100 ms of silence: not yet late
        model.step()
    assert model.runtime_state == RuntimeState.PLAYING
    model.step()  # one more period: late
    assert model.runtime_state == RuntimeState.STOPPED
    assert model.plant.motion is Motion.STOPPING
    for _ in range(100):
        model.step()
    assert model.plant.qd == [0.0] * 6
    texts = [e.text or "" for e in model.log.since(0)]
    assert any(t.startswith("stopped (rtde watchdog: input_int_register_0 not updated")
               for t in texts), texts


def test_rtde_watchdog_is_fed_by_any_package_with_the_register_and_ends_with_the_program(
        ) -> None:
    model = ControllerModel(Q0, CommandLog())
    model.start_program("rtde_control", UR_RTDE_SET_WATCHDOG)
    _set_watchdog(model, 10.0)
    for _ in range(500):  # kickWatchdog(): a package writing 0, every 50 ms
        if model.steps % 25 == 0:
            model.input_written(0)
        model.step()
    assert model.runtime_state == RuntimeState.PLAYING
    model.stop_program("a test")  # "All watchdogs are removed on program stop."
    model.start_program("rtde_control", UR_RTDE_SET_WATCHDOG)
    for _ in range(500):  # no setWatchdog on the new program: silence is allowed
        model.step()
    assert model.runtime_state == RuntimeState.PLAYING


def test_rtde_watchdog_pause_action_and_non_positive_frequency() -> None:
    model = ControllerModel(Q0, CommandLog())
    model.start_program("rtde_control", UR_RTDE_SET_WATCHDOG.replace('"stop"', '"pause"'))
    _set_watchdog(model, 0.0)  # no watchdog
    for _ in range(100):
        model.step()
    assert model.runtime_state == RuntimeState.PLAYING
    _set_watchdog(model, 50.0)
    for _ in range(20):
        model.step()
    assert model.runtime_state == RuntimeState.PAUSED


# -- the process ------------------------------------------------------------------------------

def _wait(predicate, timeout: float = 20.0) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not met before the timeout"
        time.sleep(0.005)


@pytest.mark.timeout(120)
def test_process_lifecycle_state_and_hooks(loopback_host: str) -> None:
    assert FakeURController(loopback_host, q_init=Q0).state().q.tolist() == Q0  # before start
    fake = start_fake_ur(loopback_host, q_init=Q0)
    with fake:
        _wait(lambda: fake.state().controller_time > 0.02)
        st0 = fake.state()
        assert st0.q.tolist() == pytest.approx(Q0) and st0.runtime_state == RuntimeState.STOPPED
        assert st0.safety_bits == 1
        with pytest.raises(TransportError, match="cannot listen"):
            FakeURController(fake.host).start()  # ports taken
        t = fake.set_protective_stop()
        _wait(lambda: fake.state().controller_time > t)
        assert fake.state().safety_bits == (1 << 2) | (1 << 10)
        fake.set_protective_stop(False)
        fake.set_emergency_stop()
        _wait(lambda: fake.state().safety_bits == (1 << 6) | (1 << 7) | (1 << 10))
        fake.set_emergency_stop(False)
        fake.set_q([0.0] * 6)
        assert fake.state().q.tolist() == [0.0] * 6
        with socket.create_connection((fake.host, 29999), timeout=5) as s, \
                s.makefile("rb") as reader:
            assert reader.readline() == b"Connected: Universal Robots Dashboard Server\n"
            fake.set_remote_control(False)
            s.sendall(b"is in remote control\n")
            assert reader.readline() == b"false\n"
        _wait(lambda: len(fake.commands(CommandKind.CONNECTION)) >= 2)
        [entry] = fake.commands(CommandKind.DASHBOARD)
        assert (entry.text, entry.reply) == ("is in remote control", "false")
        fake.kill()
        assert not fake.alive
        with pytest.raises(TransportError):
            fake.set_protective_stop()
        fake.restart()
        assert fake.alive and fake.state().q.tolist() == [0.0] * 6
        _wait(lambda: fake.state().controller_time > 0.0)
        assert fake.commands(CommandKind.DASHBOARD)[0].seq == entry.seq  # log kept
    assert not fake.alive
    fake.stop()  # idempotent


@pytest.mark.timeout(120)
def test_real_receive_interface_parses_every_default_variable(loopback_host: str) -> None:
    """ur_rtde's RTDEReceiveInterface with its default (all-variables) recipe."""
    with start_fake_ur(loopback_host, q_init=Q0) as fake:
        fake.set_digital_input(3, True)
        _check_receive_interface(fake.host, fake)


@pytest.mark.timeout(120)
def test_a_switchs_two_contacts_change_in_one_sample(loopback_host: str) -> None:
    """set_digital_inputs sets several inputs in one controller step (the contacts of
    one dual-channel switch change together; two requests to a starved controller once
    came 58 ms apart, which the daemon rightly called a discrepancy fault)."""
    import rtde_receive

    with start_fake_ur(loopback_host, q_init=Q0) as fake:
        recv = rtde_receive.RTDEReceiveInterface(fake.host)
        try:
            fake.set_digital_inputs({8: True, 9: True, 3: True})
            _wait(lambda: recv.getActualDigitalInputBits() == (1 << 8) | (1 << 9) | (1 << 3))
            fake.set_digital_inputs({8: False, 9: False})
            _wait(lambda: recv.getActualDigitalInputBits() == 1 << 3)
            with pytest.raises(ValueError, match="0..63"):
                fake.set_digital_inputs({64: True})
        finally:
            recv.disconnect()


def _check_receive_interface(host: str, fake: FakeURController) -> None:
    import rtde_receive

    recv = rtde_receive.RTDEReceiveInterface(host)  # destroyed when this returns
    assert recv.isConnected()
    _wait(lambda: recv.getTimestamp() > 0.05)
    assert recv.getActualQ() == pytest.approx(Q0)
    assert recv.getTargetQ() == pytest.approx(Q0)
    assert recv.getActualQd() == [0.0] * 6
    assert recv.getRobotMode() == 7 and recv.getSafetyMode() == 1
    assert recv.getSafetyStatusBits() == 1 and recv.getRuntimeState() == 1
    assert recv.getRobotStatus() == 1 and recv.getSpeedScaling() == 1.0
    assert recv.getActualDigitalInputBits() == 1 << 3
    assert recv.getJointMode() == [253] * 6
    assert 0.05 < recv.getTimestamp() <= fake.state().controller_time


def test_command_log_entries_are_not_tracked_by_the_garbage_collector() -> None:
    """A full ring of tracked entries made each full collection of the fake's process
    take ~60 ms: the daemon saw the controller's clock stall and faulted."""
    import gc

    ring = CommandLog(capacity=100)
    for i in range(150):
        ring.add(i * DT, CommandKind.SPEEDJ, qd=(0.1, 0.0, -0.1, 0.0, 0.0, 0.2),
                 acceleration=1.4, time=0.002)
    ring.add(150 * DT, CommandKind.DASHBOARD, text="play", reply="Starting program")
    gc.collect()
    assert not any(gc.is_tracked(e) for e in ring._ring)
    entries = ring.since(149)
    assert [e.seq for e in entries] == [149, 150]
    assert entries[0].kind is CommandKind.SPEEDJ and entries[0].qd == (0.1, 0.0, -0.1, 0.0, 0.0, 0.2)
    assert entries[0].acceleration == 1.4 and entries[0].deceleration is None
    assert entries[1].kind is CommandKind.DASHBOARD and entries[1].reply == "Starting program"
    with pytest.raises(TypeError, match="unknown command log fields"):
        ring.add(0.0, CommandKind.SPEEDJ, speed=1.0)
