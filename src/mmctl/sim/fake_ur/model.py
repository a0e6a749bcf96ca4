"""The simulated UR controller without its sockets: clock, safety, program, joints.

One :meth:`ControllerModel.step` is one controller period (2 ms, 500 Hz on e-Series).
The network side (:mod:`mmctl.sim.fake_ur.server`) writes input registers, calls
``step`` and reads output variables through :meth:`ControllerModel.getter`.

Safety model (kept simple, each fault injectable on its own): a protective or an
emergency stop sets its safety status bits, brakes the joints at
:data:`SAFETY_STOP_DECELERATION` and ignores speed commands until it is cleared; the
program keeps its runtime state (stopping the program is a separate injection).  A
program cannot be started while a safety stop is active or in local control.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from enum import IntEnum

from mmctl.sim.fake_ur.log import CommandKind, CommandLog
from mmctl.sim.fake_ur.program import (
    SPEED_STOP,
    SPEEDJ,
    STOP_SCRIPT,
    Registers,
    RtdeControlProgram,
    register_offset,
    watchdog_actions,
)
from mmctl.sim.joints import JointPlant, Motion

PERIOD = 0.002
"""[s] controller period (500 Hz)."""
SAFETY_STOP_DECELERATION = 20.0
"""[rad/s^2] how the joints brake on a protective or emergency stop."""
PROGRAM_STOP_DECELERATION = 10.0
"""[rad/s^2] how the joints stop when the program ends or is stopped."""
DEFAULT_VERSION = (5, 11, 0, 108249)
DEFAULT_SERIAL = "20205500042"


class RuntimeState(IntEnum):
    """RTDE ``runtime_state``."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


class SafetyBit(IntEnum):
    """Bit numbers of RTDE ``safety_status_bits``."""

    NORMAL_MODE = 0
    REDUCED_MODE = 1
    PROTECTIVE_STOPPED = 2
    RECOVERY_MODE = 3
    SAFEGUARD_STOPPED = 4
    SYSTEM_EMERGENCY_STOPPED = 5
    ROBOT_EMERGENCY_STOPPED = 6
    EMERGENCY_STOPPED = 7
    VIOLATION = 8
    FAULT = 9
    STOPPED_DUE_TO_SAFETY = 10


ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL = 1
SAFETY_MODE_PROTECTIVE_STOP = 3
SAFETY_MODE_ROBOT_EMERGENCY_STOP = 7
JOINT_MODE_RUNNING = 253


class ControllerModel:
    """Clock, registers, program, safety flags and joints of one fake controller."""

    def __init__(self, q_init: Sequence[float], log: CommandLog,
                 version: tuple[int, int, int, int] = DEFAULT_VERSION,
                 serial: str = DEFAULT_SERIAL):
        self.log = log
        self.version = version
        self.serial = serial
        self.time = 0.0
        self.steps = 0
        self.regs = Registers()
        self.plant = JointPlant(list(q_init))
        self.program: RtdeControlProgram | None = None
        self.program_name = "<unnamed>"
        self.protective_stop = False
        self.emergency_stop = False
        self.remote_control = True
        self.frozen = False
        self.paused = False
        """The program was paused (its RTDE watchdog with action "pause")."""
        self.digital_inputs = 0

    # -- state seen by clients -------------------------------------------------------

    @property
    def runtime_state(self) -> int:
        if self.program is None:
            return RuntimeState.STOPPED
        return RuntimeState.PAUSED if self.paused else RuntimeState.PLAYING

    @property
    def safety_status_bits(self) -> int:
        bits = 0
        if self.protective_stop:
            bits |= 1 << SafetyBit.PROTECTIVE_STOPPED
        if self.emergency_stop:
            bits |= (1 << SafetyBit.ROBOT_EMERGENCY_STOPPED) | (1 << SafetyBit.EMERGENCY_STOPPED)
        if bits:
            bits |= 1 << SafetyBit.STOPPED_DUE_TO_SAFETY
        else:
            bits = 1 << SafetyBit.NORMAL_MODE
        return bits

    @property
    def safety_mode(self) -> int:
        if self.emergency_stop:
            return SAFETY_MODE_ROBOT_EMERGENCY_STOP
        if self.protective_stop:
            return SAFETY_MODE_PROTECTIVE_STOP
        return SAFETY_MODE_NORMAL

    @property
    def safety_status_name(self) -> str:
        if self.emergency_stop:
            return "ROBOT_EMERGENCY_STOP"
        if self.protective_stop:
            return "PROTECTIVE_STOP"
        return "NORMAL"

    @property
    def robot_status_bits(self) -> int:
        return 1 | (2 if self.program is not None else 0)  # power on, program running

    @property
    def version_text(self) -> str:
        return ".".join(str(v) for v in self.version)

    # -- events ------------------------------------------------------------------------

    def motion_allowed(self) -> bool:
        return not (self.protective_stop or self.emergency_stop)

    def start_program(self, name: str, text: str) -> None:
        """A program arrived on the script port: it replaces the running one."""
        if self.program is not None:
            self.stop_program("replaced")
        if not self.remote_control:
            self.log.add(self.time, CommandKind.PROGRAM, text=f"rejected: local control ({name})")
            return
        if not self.motion_allowed():
            self.log.add(self.time, CommandKind.PROGRAM,
                         text=f"rejected: {self.safety_status_name} ({name})")
            return
        if name != "rtde_control":
            self.log.add(self.time, CommandKind.PROGRAM, text=f"rejected: unsupported ({name})")
            return
        self.program = RtdeControlProgram(self.regs, self.plant, register_offset(text),
                                          watchdog_actions(text), lambda: self.time)
        self.program.motion_allowed = self.motion_allowed
        self.program_name = name
        self.log.add(self.time, CommandKind.PROGRAM, text=f"started ({name})")

    def stop_program(self, why: str) -> None:
        """End the running program (stopScript, dashboard ``stop``, its RTDE watchdog, a
        test); its watchdogs go with it."""
        if self.program is None:
            return
        self.program = None
        self.paused = False
        self.plant.stop(PROGRAM_STOP_DECELERATION)
        self.log.add(self.time, CommandKind.PROGRAM, text=f"stopped ({why})")

    def _check_watchdog(self, program: RtdeControlProgram) -> None:
        """The program's RTDE watchdog: a late input update pauses or stops it."""
        wd = program.watchdog
        if wd is None or not wd.expired(self.time):
            return
        why = (f"rtde watchdog: input_int_register_{wd.register} not updated for "
               f"{self.time - wd.last_update:.3f} s (min frequency {wd.min_frequency:g} Hz)")
        if wd.action == "stop":
            self.stop_program(why)
        elif wd.action == "pause":
            program.watchdog = None
            self.paused = True
            self.plant.stop(PROGRAM_STOP_DECELERATION)
            self.log.add(self.time, CommandKind.PROGRAM, text=f"paused ({why})")
        else:  # "ignore": reported once, as the controller's log does
            program.watchdog = None
            self.log.add(self.time, CommandKind.PROGRAM, text=f"ignored ({why})")

    def set_protective_stop(self, on: bool) -> None:
        self.protective_stop = bool(on)
        if on:
            self.plant.stop(SAFETY_STOP_DECELERATION)

    def set_emergency_stop(self, on: bool) -> None:
        self.emergency_stop = bool(on)
        if on:
            self.plant.stop(SAFETY_STOP_DECELERATION)

    def input_written(self, cmd_register: int) -> None:
        """Log the command a client has just written (called per received data package)."""
        program = self.program
        off = program.offset if program is not None else 0
        if program is not None and program.watchdog is not None \
                and cmd_register == program.watchdog.register:
            program.watchdog.last_update = self.time
        if cmd_register != off:
            return
        cmd = self.regs.in_int[off]
        d = self.regs.in_double
        if cmd == SPEEDJ:
            self.log.add(self.time, CommandKind.SPEEDJ, qd=tuple(d[off:off + 6]),
                         acceleration=d[off + 6], time=d[off + 7])
        elif cmd == SPEED_STOP:
            self.log.add(self.time, CommandKind.SPEED_STOP, deceleration=d[off])
        elif cmd == STOP_SCRIPT:
            self.log.add(self.time, CommandKind.STOP_SCRIPT)
        elif cmd != 0:
            self.log.add(self.time, CommandKind.RTDE_COMMAND, code=cmd)

    def step(self, dt: float = PERIOD) -> None:
        """One controller period."""
        program = self.program
        if program is not None and not self.paused:
            program.cycle()
            if not program.running:
                self.stop_program("stopScript")
            else:
                self._check_watchdog(program)
        if not self.motion_allowed() and self.plant.motion is Motion.SPEED:
            self.plant.stop(SAFETY_STOP_DECELERATION)
        self.plant.step(dt)
        if self.plant.limit_hit:
            self.plant.limit_hit = False
            self.set_protective_stop(True)
            self.log.add(self.time, CommandKind.PROGRAM, text="protective stop: joint limit")
        self.steps += 1
        self.time = self.steps * dt

    # -- output variables ----------------------------------------------------------------

    def getter(self, name: str) -> Callable[[], object] | None:
        """A function returning the current value of output variable ``name`` (a scalar or
        a list), or None for variables the fake reports as constant zero."""
        p = self.plant
        regs = self.regs
        table: dict[str, Callable[[], object]] = {
            "timestamp": lambda: self.time,
            "actual_q": lambda: p.q, "target_q": lambda: p.q,
            "actual_qd": lambda: p.qd, "target_qd": lambda: p.qd,
            "actual_qdd": lambda: p.qdd, "target_qdd": lambda: p.qdd,
            "runtime_state": lambda: self.runtime_state,
            "robot_mode": lambda: ROBOT_MODE_RUNNING,
            "safety_mode": lambda: self.safety_mode,
            "safety_status": lambda: self.safety_mode,
            "safety_status_bits": lambda: self.safety_status_bits,
            "robot_status_bits": lambda: self.robot_status_bits,
            "speed_scaling": lambda: 1.0, "target_speed_fraction": lambda: p.scale,
            "joint_mode": lambda: [JOINT_MODE_RUNNING] * 6,
            "joint_temperatures": lambda: [30.0] * 6,
            "actual_main_voltage": lambda: 48.0, "actual_robot_voltage": lambda: 48.0,
            "actual_joint_voltage": lambda: [48.0] * 6,
            "actual_digital_input_bits": lambda: self.digital_inputs,
        }
        if name in table:
            return table[name]
        for prefix, array in (("output_int_register_", regs.out_int),
                              ("output_double_register_", regs.out_double),
                              ("input_int_register_", regs.in_int),
                              ("input_double_register_", regs.in_double)):
            if name.startswith(prefix) and name[len(prefix):].isdigit():
                index = int(name[len(prefix):])
                return lambda: array[index]
        return None
