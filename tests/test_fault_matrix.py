"""Every SPEC §5 fault condition at the daemon-cycle level, deterministically.

The daemon runs on scripted device peers (:class:`ScriptedArm`, :class:`ScriptedSensor`,
:class:`ScriptedBase`: the transports' protocols, raising exactly what the real
transports raise for each condition) and a scripted clock that only the test advances,
one period per cycle; the test steps it with ``Daemon.step_once``.  No threads (but the
loop's own in the overrun tests, which runs the daemon's cycle on the scripted clock and
ends by itself), no sleeps, no retries: every count below is exact.

Each condition: armed and pushed (speedJ and base twists flow), the condition injected
before cycle ``k``, detected in cycle ``k`` (or, for the time-based ones, in the first
cycle past the configured timeout, computed from the configuration); that cycle sends
no motion (but the cases where the send itself fails, after that cycle's own speedJ /
twist), and it sends the stop: base zero, arm stop with ``arm.stop_deceleration``, base
disable, in that order; one ``fault`` event names the cause; enabling is refused while
the condition persists, the fault stays latched after it clears, and the operator's
enable is accepted then.  The end-to-end tests through the simulated robot's fakes are
in ``test_daemon_faults.py``.
"""

from __future__ import annotations

import itertools
import math
import threading
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import pytest
from structlog.testing import capture_logs

from mmctl.config import Config, config_from_dict
from mmctl.errors import FaultCause, MmctlError, SafetyFault, TransportError
from mmctl.model.robot import RobotModel
from mmctl.runtime import loop as loop_module
from mmctl.runtime.core import ControlCore
from mmctl.runtime.daemon import Daemon
from mmctl.runtime.devices import Devices
from mmctl.runtime.notify import Notifier
from mmctl.runtime.safety import EnableRefused, SafetyState
from mmctl.transports.sensor.can_ft import check_status
from mmctl.transports.sensor.protocol import SensorStats
from mmctl.transports.ur_rtde_arm import EMERGENCY_BITS, PLAYING, PROTECTIVE_BITS
from mmctl.types import ArmState, Odometry, Twist, Vec, Wrench

if TYPE_CHECKING:
    from typing_extensions import Self

HOST = "scripted-ur"
PUSH = np.array([20.0, 0.0, 0.0])  # [N] sensor frame: above the dead band, below the limit
Q_SINGULAR = np.array([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0])  # stretched up
#: folded down: the handle inside the base's deck (`mmctl model distances --q ...`)
Q_SELF_COLLISION = np.array([0.0, -1.2, 2.7, -1.0, 1.57, 0.0])
ENABLING = {"enabling": {"inputs": [8, 9], "discrepancy_time": 0.021}}  # off the 2 ms grid
HELD = 1 << 8 | 1 << 9  # both contacts of the enabling switch closed
STOPPED = 1  # RTDE runtime state: the program is stopped
NORMAL_MODE = 1  # RTDE safety status bit 0


def base_config(extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """The defaults (500 Hz), with the time-based thresholds off the 2 ms grid, so the
    float rounding of the scripted clock cannot move a detection by a cycle; the base
    twist every cycle; a stop deceleration that is no transport's default."""
    cfg: dict[str, Any] = {
        "name": "fault-matrix",
        "arm": {"stop_deceleration": 7.5},
        "sensor": {"wrench": {"stale_timeout": 0.011}},
        "base": {"canopen": {"heartbeat_timeout": 0.021},
                 "serial": {"link_timeout": 0.031}},
        "loop": {"base_divider": 1},
    }
    for key, value in (extra or {}).items():
        cfg[key] = {**cfg.get(key, {}), **value}
    return cfg


# -- scripted time and command log -------------------------------------------------------

class Clock:
    """Monotonic time that only the test moves: integer nanoseconds (the loop's
    ``perf_counter_ns`` in the overrun tests); called, seconds (the devices' stamps and
    the control core's ``now``)."""

    def __init__(self) -> None:
        self.ns = 1_000_000_000_000

    def __call__(self) -> float:
        return self.ns * 1e-9


class Command(NamedTuple):
    """One command a peer received: the daemon cycle it came in (None: outside a
    cycle, e.g. an operator's enable), device, name, arguments."""

    cycle: int | None
    device: str
    name: str
    args: tuple[Any, ...] = ()


@dataclass
class Recorder:
    """Every command of every peer, in order."""

    cycle: int | None = None
    log: list[Command] = field(default_factory=list)

    def add(self, device: str, name: str, *args: Any) -> None:
        self.log.append(Command(self.cycle, device, name, args))


# -- scripted peers ----------------------------------------------------------------------

class ScriptedArm:
    """:class:`~mmctl.transports.arm.Arm` as the daemon's arm link
    (:class:`~mmctl.transports.ur_rtde_process.UrRtdeProcessArm` running
    :class:`~mmctl.transports.ur_rtde_arm.UrRtdeArm`) behaves: holds still at ``q``;
    ``read_state`` raises in UrRtdeArm's order (emergency, protective, not PLAYING,
    timestamp stale, non-finite); after ARM_STALE or ARM_DISCONNECTED the link is gone
    (the arm's process ends itself) and every call raises ARM_DISCONNECTED until a
    reconnect, which fails while the controller is unreachable, streams nothing or
    refuses the control script."""

    def __init__(self, rec: Recorder, clock: Clock, q: Vec, stale_cycles: int):
        self.rec = rec
        self.clock = clock
        self.q = q.copy()
        self.stale_cycles = stale_cycles
        self.safety_bits = NORMAL_MODE
        self.runtime_state = PLAYING
        self.frozen = False  # the controller's timestamp stops advancing
        self.reachable = True  # the controller answers (False: it died)
        self.script_refused = False  # the controller will not run the control script
        self.checks_finite = True  # UrRtdeArm raises NON_FINITE on a non-finite sample
        self.die_at_send = False  # the link breaks under the next speed_j
        self.inputs = HELD  # its digital inputs: the enabling switch held
        self.gone = False
        self._t = clock()
        self._last_t = math.nan
        self._stale = 0

    def connect(self) -> None:
        self.rec.add("arm", "connect")

    def read_state(self) -> ArmState:
        if self.gone or not self.reachable:
            raise self._lost("the arm process ended (exit code 0)")
        if not self.frozen:
            self._t = self.clock()
        t = self._t
        if t != self._last_t:
            self._last_t, self._stale = t, 0
        else:
            self._stale += 1
        bits = self.safety_bits
        if bits & EMERGENCY_BITS:
            raise SafetyFault(FaultCause.ARM_EMERGENCY_STOP, safety_status_bits=bits,
                              controller_time=t)
        if bits & PROTECTIVE_BITS:
            raise SafetyFault(FaultCause.ARM_PROTECTIVE_STOP, safety_status_bits=bits,
                              controller_time=t)
        if self.runtime_state != PLAYING:
            raise SafetyFault(FaultCause.ARM_NOT_PLAYING, runtime_state=self.runtime_state,
                              controller_time=t)
        if self._stale >= self.stale_cycles:
            raise self._lost(None, FaultCause.ARM_STALE, cycles=self._stale, controller_time=t)
        if self.checks_finite and not np.isfinite(self.q).all():
            raise SafetyFault(FaultCause.NON_FINITE, source="arm state", controller_time=t)
        return ArmState(self.q.copy(), np.zeros(6), t, self.runtime_state, bits)

    def speed_j(self, qd: Vec, acceleration: float | None = None,
                dt: float | None = None) -> bool:
        self.rec.add("arm", "speed_j", tuple(float(x) for x in qd), acceleration, dt)
        if self.gone:
            raise self._lost("the arm process ended (exit code 0)")
        if self.die_at_send:
            self.die_at_send, self.reachable = False, False
            raise self._lost("the arm process ended (exit code -11)")
        return True

    def digital_input(self, index: int) -> bool:
        if self.gone or not self.reachable:
            raise self._lost("the arm process ended (exit code 0)")
        return bool((self.inputs >> index) & 1)

    def kick_watchdog(self) -> None:
        self.rec.add("arm", "kick_watchdog")
        if self.gone:
            raise self._lost("the arm process ended (exit code 0)")

    def stop(self, deceleration: float | None = None) -> None:
        self.rec.add("arm", "stop", deceleration)  # never raises (logged when not sent)

    def reconnect(self) -> None:
        self.rec.add("arm", "reconnect")
        if not self.reachable:
            raise TransportError(f"{HOST}: nothing answers on the dashboard port 29999")
        if self.frozen:
            raise TransportError(f"{HOST}: the RTDE port accepts but sends no data")
        if self.script_refused:
            raise TransportError(f"{HOST}: ur_rtde control interface: the control script "
                                 "did not start")
        self.gone = False
        self.runtime_state = PLAYING  # the control script uploaded again, running
        self._last_t, self._stale = math.nan, 0

    def close(self) -> None:
        self.rec.add("arm", "close")

    def _lost(self, why: str | None, cause: FaultCause = FaultCause.ARM_DISCONNECTED,
              **details: Any) -> SafetyFault:
        self.gone = True
        return SafetyFault(cause, host=HOST, **({"why": why} if why else {}), **details)


class ScriptedSensor:
    """:class:`~mmctl.transports.sensor.protocol.ForceSensor` as the CAN transport
    behaves: a fresh sample stamped by the clock each read (the handle's weight at the
    held pose, plus ``force``); its status word and gauges checked by the transport's
    own :func:`check_status`; ``silent``: the last sample again until it is older than
    ``sensor.wrench.stale_timeout``, then SENSOR_STALE (``judges_staleness`` False: a
    transport that repeats it forever, left to the daemon's own check); ``error``:
    raised by every read (a link error, a bug)."""

    link = "scripted:sensor@0x20"

    def __init__(self, rec: Recorder, clock: Clock, rest: Vec, stale_timeout: float):
        self.rec = rec
        self.clock = clock
        self.rest = rest
        self.stale_timeout = stale_timeout
        self.force = np.zeros(3)
        self.status = 0
        self.gauges = np.zeros(6)
        self.silent = False
        self.judges_staleness = True
        self.error: Exception | None = None
        self.seq = 0
        self._last: Wrench | None = None
        self._last_fresh = math.nan

    def connect(self) -> None:
        self.rec.add("sensor", "connect")

    def read(self) -> Wrench:
        if self.error is not None:
            raise self.error
        now = self.clock()
        if self.silent and self._last is not None:
            age = now - self._last_fresh
            if self.judges_staleness and age > self.stale_timeout:
                raise SafetyFault(FaultCause.SENSOR_STALE, age_ms=round(age * 1e3, 2),
                                  lost=self.seq, link=self.link)
            return self._last
        check_status(self.status, self.gauges)
        self.seq += 1
        raw = self.rest.copy()
        raw[:3] += self.force
        self._last = Wrench(raw[:3], raw[3:], now, self.seq)
        self._last_fresh = now
        return self._last

    def stats(self) -> SensorStats:
        return SensorStats(self.seq, 0, 0)

    def reconnect(self) -> None:
        """The link again: fails while the scripted error persists."""
        if self.error is not None:
            raise TransportError(f"{self.link}: reconnect failed: {self.error}")

    def close(self) -> None:
        self.rec.add("sensor", "close")

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ScriptedBase:
    """:class:`~mmctl.transports.base.protocol.Base` as the CANopen (or, configured so,
    the serial) transport behaves: at rest at the origin; health checked by both
    per-cycle calls; a fault latched until ``enable()``, which fails while the drive is
    still in FAULT (SafetyFault) or silent (TransportError, then ``check()`` names it);
    ``send_twist`` commands zero before it raises."""

    def __init__(self, rec: Recorder, clock: Clock, cfg: Config):
        self.rec = rec
        self.clock = clock
        if cfg.base.transport == "canopen":
            self.silent_cause = FaultCause.DRIVE_HEARTBEAT
            self.silent_timeout = cfg.base.canopen.heartbeat_timeout
        else:
            self.silent_cause = FaultCause.BASE_LINK
            self.silent_timeout = cfg.base.serial.link_timeout
        self.drive_fault = False  # drive 1 (FL) in FAULT
        self.fault_at_send = False  # drive 1 faults between the read and the next send
        self.silent = False  # its heartbeat (the bridge's frames) stops
        self.link_error: TransportError | None = None
        self.odometry_nan = False
        self.enabled = False
        self._fault: SafetyFault | None = None
        self._heard = clock()

    def connect(self) -> None:
        self.rec.add("base", "connect")

    def reconnect(self) -> None:
        """Nothing to do: the scripted link itself never drops (its errors are scripted
        on enable and on the per-cycle calls)."""

    def enable(self) -> None:
        self.rec.add("base", "enable")
        self._fault = None
        if self.link_error is not None:
            raise self.link_error
        if self.silent:
            raise TransportError("drive 1 (FL) cannot be enabled: SDO timeout")
        if self.drive_fault:
            self._fault = SafetyFault(FaultCause.DRIVE_FAULT, node_id=1, wheel="FL",
                                      state="FAULT", why="stays in FAULT after the reset")
            raise self._fault
        self.enabled = True

    def send_twist(self, vx: float, vy: float, wz: float) -> Twist:
        self.rec.add("base", "send_twist", vx, vy, wz)
        if not self.enabled:
            raise TransportError("send_twist() before enable()")
        if self.fault_at_send:
            self.fault_at_send, self.drive_fault = False, True
        fault = self._health()
        if fault is not None:
            self.rec.add("base", "zero_wheels")
            raise fault
        return Twist(vx, vy, wz)

    def read_odometry(self) -> Odometry:
        fault = self._health()
        if fault is not None:
            raise fault
        v = math.nan if self.odometry_nan else 0.0
        return Odometry(v, 0.0, 0.0, 0.0, 0.0, 0.0, self.clock())

    def check(self) -> None:
        fault = self._health()
        if fault is not None:
            raise fault

    def drive_status(self) -> list[Any]:
        return []

    def stop(self) -> None:
        self.rec.add("base", "stop")
        if self.link_error is not None:
            raise self.link_error

    def disable(self, wait: bool = True) -> None:
        self.rec.add("base", "disable", wait)
        self.enabled = False
        if self.link_error is not None:
            raise self.link_error

    def close(self) -> None:
        self.rec.add("base", "close")

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _health(self) -> SafetyFault | None:
        if self.link_error is not None:  # the link itself: no fault to latch, an error
            raise self.link_error
        if self._fault is not None:
            return self._fault
        now = self.clock()
        if not self.silent:
            self._heard = now
        age = now - self._heard
        if age > self.silent_timeout:
            self._fault = SafetyFault(self.silent_cause, node_id=1, wheel="FL",
                                      silent_for=round(age, 4))
        elif self.enabled and self.drive_fault:
            self._fault = SafetyFault(FaultCause.DRIVE_FAULT, node_id=1, wheel="FL",
                                      state="FAULT", statusword="0x0008")
        return self._fault


# -- the rig -------------------------------------------------------------------------

class Rig:
    """A daemon on scripted peers and a scripted clock, stepped by the test."""

    def __init__(self, cfg: Config, model: RobotModel):
        self.cfg = cfg
        self.model = model
        self.clock = Clock()
        self.rec = Recorder()
        q = np.array(cfg.robot.q_des[:6], dtype=float)
        rest = self._core().wrench.gravity_wrench(
            model.fk_base(np.concatenate((q, np.zeros(3))), "sensor").rotation)
        self.arm = ScriptedArm(self.rec, self.clock, q, cfg.arm.stale_cycles)
        self.sensor = ScriptedSensor(self.rec, self.clock, rest,
                                     cfg.sensor.wrench.stale_timeout)
        self.base = ScriptedBase(self.rec, self.clock, cfg)
        self.daemon = self.start_daemon()

    def _core(self) -> ControlCore:
        return ControlCore(self.cfg, self.model, clock=self.clock)

    def start_daemon(self) -> Daemon:
        """A new daemon process on these devices (built and opened, not started)."""
        d = Daemon(self.cfg, Devices(self.arm, self.sensor, self.base),  # type: ignore[arg-type]
                   self._core(), notifier=Notifier({}))
        self.rec.cycle = None
        self._since = len(self.rec.log)  # this daemon's commands (its cycles count from 0)
        d.open()
        return d

    @property
    def period_ns(self) -> int:
        return self.daemon.loop.period_ns

    def step(self, n: int = 1, overrun: bool = False) -> list[Command]:
        """``n`` cycles, each one period after the last; the last cycle's commands."""
        for _ in range(n):
            self.clock.ns += self.period_ns
            cycle = self.rec.cycle = self.daemon.cycles
            self.daemon.step_once(overrun=overrun)
            self.rec.cycle = None
        return self.commands(cycle)

    def commands(self, cycle: int) -> list[Command]:
        return [c for c in self.rec.log[self._since:] if c.cycle == cycle]

    def enable(self) -> None:
        self.daemon.call("enable")

    def arm_and_push(self) -> None:
        """Healthy cycles, enable, then a push: speedJ and twists with motion flow."""
        self.step(3)
        assert self.daemon.safety.state is SafetyState.DISARMED
        self.enable()
        assert self.daemon.safety.armed
        self.sensor.force = PUSH.copy()
        for _ in range(3):
            assert_moves(self.step())

    @property
    def state(self) -> SafetyState:
        return self.daemon.safety.state


def names(cmds: list[Command]) -> list[str]:
    return [f"{c.device}.{c.name}" for c in cmds]


def assert_moves(cmds: list[Command]) -> None:
    """A cycle that commanded motion: a non-zero speedJ, then the twist, nothing else."""
    assert names(cmds) == ["arm.speed_j", "base.send_twist"], cmds
    assert np.abs(cmds[0].args[0]).max() > 0.0, cmds


def assert_brakes(cmds: list[Command]) -> None:
    """A cycle of an armed robot coming to rest: speedJ and the twist (maybe zero)."""
    assert names(cmds) == ["arm.speed_j", "base.send_twist"], cmds


def assert_still(cmds: list[Command]) -> None:
    """A cycle of a robot that is not armed: the arm's watchdog kicked, nothing else."""
    assert names(cmds) == ["arm.kick_watchdog"], cmds


def stop_commands(cfg: Config) -> list[tuple[str, str, tuple[Any, ...]]]:
    """The stop, in order: base zero, arm stop, base disable (never waiting on the loop)."""
    return [("base", "stop", ()), ("arm", "stop", (cfg.arm.stop_deceleration,)),
            ("base", "disable", (False,))]


def late(timeout: float, period: float) -> int:
    """Cycles after the last fresh one until ``age > timeout``: the detection is in
    cycle ``k + late`` when cycle ``k`` is the first without news."""
    ratio = timeout / period
    assert abs(ratio - round(ratio)) > 0.01, "a timeout on the period grid: rounding decides"
    return math.floor(ratio)


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel(config_from_dict(base_config()).robot)


@pytest.fixture
def make_rig(model: RobotModel) -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def make(extra: dict[str, Any] | None = None) -> Rig:
        rig = Rig(config_from_dict(base_config(extra)), model)
        rigs.append(rig)
        return rig

    yield make
    for rig in rigs:
        rig.daemon.shutdown()


# -- the matrix --------------------------------------------------------------------------

Action = Callable[[Rig], None]


def _set(device: str, **attrs: Any) -> Action:
    def act(rig: Rig) -> None:
        for key, value in attrs.items():
            setattr(getattr(rig, device), key, value)
    return act


def _nan_q(rig: Rig) -> None:
    rig.arm.q[2] = math.nan


def _q_des(rig: Rig) -> None:
    rig.arm.q = np.array(rig.cfg.robot.q_des[:6], dtype=float)


@dataclass(frozen=True)
class Case:
    """One condition: its injection, its removal, its cause.

    late: cycles between the injection and the detection, from the configuration;
    found_by: the send that finds it ("arm": speedJ, "base": the twist) after the
    cycle's own motion commands (None: a read finds it); reconnect: the enable
    reconnects the arm first, and while the condition lasts that reconnect fails;
    refusal: the refusal's message when it is not an EnableRefused naming the cause
    (a failed reconnect, a base link that fails the enable); extra: configuration.
    """

    id: str
    cause: FaultCause
    inject: Action
    clear: Action
    late: Callable[[Config], int] = lambda cfg: 0
    found_by: str | None = None
    reconnect: bool = False
    refusal: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    meanwhile: Callable[[list[Command]], None] = field(default=lambda cmds: assert_moves(cmds))
    """What the cycles before the detection send (default: motion)."""


def _stale_sensor(cfg: Config) -> int:
    return late(cfg.sensor.wrench.stale_timeout, 1.0 / cfg.loop.rate_hz)


CASES = [
    # the sensor
    Case("sensor_silent", FaultCause.SENSOR_STALE, _set("sensor", silent=True),
         _set("sensor", silent=False), late=_stale_sensor),
    Case("sensor_repeats_its_sample", FaultCause.SENSOR_STALE,  # the daemon's own check
         _set("sensor", silent=True, judges_staleness=False), _set("sensor", silent=False),
         late=_stale_sensor),
    Case("sensor_status_error", FaultCause.SENSOR_STATUS, _set("sensor", status=0xC000),
         _set("sensor", status=0)),
    Case("sensor_gauge_saturated", FaultCause.SENSOR_SATURATION,
         _set("sensor", gauges=np.array([0, 0, 32767, 0, 0, 0])),
         _set("sensor", gauges=np.zeros(6))),
    Case("wrench_beyond_the_sensing_range", FaultCause.SENSOR_SATURATION,
         _set("sensor", force=np.array([0.0, 0.0, 1000.0])), _set("sensor", force=PUSH)),
    Case("sensor_link_lost", FaultCause.SENSOR_LINK,
         _set("sensor", error=TransportError("CAN receive failed on 'mmctl-sensor'")),
         _set("sensor", error=None),
         refusal="refused to enable: the sensor did not reconnect [(].*reconnect failed"),
    Case("wrench_over_the_limit", FaultCause.WRENCH_LIMIT,
         _set("sensor", force=np.array([0.0, 0.0, 200.0])), _set("sensor", force=PUSH)),
    Case("nan_in_the_wrench", FaultCause.NON_FINITE,
         _set("sensor", force=np.array([math.nan, 0.0, 0.0])), _set("sensor", force=PUSH)),
    # the arm
    Case("arm_disconnected", FaultCause.ARM_DISCONNECTED, _set("arm", reachable=False),
         _set("arm", reachable=True), reconnect=True),
    Case("arm_link_lost_under_speed_j", FaultCause.ARM_DISCONNECTED,
         _set("arm", die_at_send=True), _set("arm", reachable=True), found_by="arm",
         reconnect=True),
    Case("arm_not_playing", FaultCause.ARM_NOT_PLAYING,
         _set("arm", runtime_state=STOPPED, script_refused=True),
         _set("arm", script_refused=False), reconnect=True),
    Case("arm_protective_stop", FaultCause.ARM_PROTECTIVE_STOP,
         _set("arm", safety_bits=NORMAL_MODE | 1 << 2), _set("arm", safety_bits=NORMAL_MODE)),
    Case("arm_emergency_stop", FaultCause.ARM_EMERGENCY_STOP,
         _set("arm", safety_bits=NORMAL_MODE | 1 << 7), _set("arm", safety_bits=NORMAL_MODE)),
    Case("arm_timestamp_frozen", FaultCause.ARM_STALE, _set("arm", frozen=True),
         _set("arm", frozen=False), late=lambda cfg: cfg.arm.stale_cycles - 1, reconnect=True),
    Case("nan_in_q_found_by_the_arm_link", FaultCause.NON_FINITE, _nan_q, _q_des),
    Case("nan_in_q_found_by_the_cycle", FaultCause.NON_FINITE,
         lambda rig: (_set("arm", checks_finite=False)(rig), _nan_q(rig)), _q_des),
    Case("singular_configuration", FaultCause.SINGULAR, _set("arm", q=Q_SINGULAR), _q_des),
    Case("self_collision", FaultCause.SELF_COLLISION, _set("arm", q=Q_SELF_COLLISION), _q_des),
    # the base
    Case("drive_fault", FaultCause.DRIVE_FAULT, _set("base", drive_fault=True),
         _set("base", drive_fault=False)),
    Case("drive_fault_under_the_twist", FaultCause.DRIVE_FAULT,
         _set("base", fault_at_send=True), _set("base", drive_fault=False), found_by="base"),
    Case("drive_heartbeat_lost", FaultCause.DRIVE_HEARTBEAT, _set("base", silent=True),
         _set("base", silent=False),
         late=lambda cfg: late(cfg.base.canopen.heartbeat_timeout, 1.0 / cfg.loop.rate_hz)),
    Case("base_bridge_silent", FaultCause.BASE_LINK, _set("base", silent=True),
         _set("base", silent=False),
         late=lambda cfg: late(cfg.base.serial.link_timeout, 1.0 / cfg.loop.rate_hz),
         extra={"base": {"transport": "serial"}}),
    Case("base_link_error", FaultCause.BASE_LINK,
         _set("base", link_error=TransportError("CAN receive thread died")),
         _set("base", link_error=None),
         refusal="refused to enable: the base did not enable [(]CAN receive thread died"),
    Case("nan_in_the_odometry", FaultCause.NON_FINITE, _set("base", odometry_nan=True),
         _set("base", odometry_nan=False)),
    # the enabling switch: one contact opens (a broken wire); timed from the first cycle
    # that sees the contacts disagree (released meanwhile: the robot decelerates)
    Case("enabling_contacts_disagree", FaultCause.ENABLING_DEVICE,
         _set("arm", inputs=1 << 8), _set("arm", inputs=HELD),
         late=lambda cfg: late(cfg.enabling.discrepancy_time, 1.0 / cfg.loop.rate_hz) + 1,
         extra=ENABLING, meanwhile=lambda cmds: assert_brakes(cmds)),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_a_fault_stops_in_its_cycle_latches_and_refuses_until_gone(
        make_rig: Callable[..., Rig], case: Case) -> None:
    rig = make_rig(case.extra)
    cfg, d = rig.cfg, rig.daemon
    rig.arm_and_push()
    k = d.cycles
    n = case.late(cfg)
    with capture_logs() as logs:
        case.inject(rig)
        for _ in range(n):  # not yet past the timeout: still armed, still moving
            case.meanwhile(rig.step())
            assert rig.state is SafetyState.ARMED, d.safety.as_dict()
        cmds = rig.step()  # cycle k + n
        assert d.cycles - 1 == k + n
        assert rig.state is SafetyState.FAULT and d.safety.latched is case.cause, (
            d.safety.as_dict())
        got = [(c.device, c.name, c.args) for c in cmds]
        if case.found_by is None:  # found while reading: no motion at all, then the stop
            assert got == [*stop_commands(cfg), ("arm", "kick_watchdog", ())], got
        elif case.found_by == "arm":  # speedJ failed: the stop follows it
            assert names(cmds[:1]) == ["arm.speed_j"]
            assert got[1:] == [*stop_commands(cfg), ("arm", "kick_watchdog", ())], got
        else:  # speedJ went out, the twist found the drive faulty (and sent zero)
            assert names(cmds[:3]) == ["arm.speed_j", "base.send_twist", "base.zero_wheels"]
            assert got[3:] == stop_commands(cfg), got
        for _ in range(3):  # the condition persists: nothing moves, nothing more is sent
            assert_still(rig.step())
        assert rig.state is SafetyState.FAULT
    faults = [e for e in logs if e["event"] == "fault"]
    assert [e["cause"] for e in faults] == [case.cause.value], faults
    assert faults[0]["log_level"] == "error"

    # refused while the condition persists
    if case.reconnect:
        with pytest.raises(MmctlError, match="refused to enable: the arm did not reconnect"):
            rig.enable()
        assert rig.rec.log[-1] == Command(None, "arm", "reconnect")
    elif case.refusal is not None:
        with pytest.raises(MmctlError, match=case.refusal):
            rig.enable()
    else:
        with pytest.raises(EnableRefused, match=case.cause.value) as refused:
            rig.enable()
        assert case.cause in refused.value.causes
    assert rig.state is SafetyState.FAULT and d.safety.latched is case.cause
    assert "arm.speed_j" not in names([c for c in rig.rec.log if c.cycle is None])
    assert_still(rig.step())

    # latched after it clears, until the operator's enable
    case.clear(rig)
    for _ in range(3):
        assert_still(rig.step())
    assert rig.state is SafetyState.FAULT and d.safety.latched is case.cause
    before = len(rig.rec.log)
    rig.enable()
    assert d.safety.armed and d.safety.latched is None
    enabling = names(rig.rec.log[before:])
    assert enabling == ["arm.reconnect", "base.enable"] if case.reconnect else ["base.enable"]
    assert_moves(rig.step())


# -- beyond the matrix ---------------------------------------------------------------

@pytest.mark.parametrize("before", ["armed", "fault"])
def test_a_restarted_daemon_starts_disarmed(make_rig: Callable[..., Rig], before: str) -> None:
    """The previous daemon armed (it died without a stop) or latched on a fault: the
    new one commands nothing, whatever the handle says, until an operator enables."""
    rig = make_rig()
    rig.arm_and_push()
    if before == "fault":
        rig.sensor.force = np.array([0.0, 0.0, 200.0])
        rig.step()
        assert rig.daemon.safety.latched is FaultCause.WRENCH_LIMIT
        rig.sensor.force = PUSH.copy()
    assert rig.daemon.safety.state.value == before
    rig.daemon = rig.start_daemon()  # the old one never shut down
    assert rig.state is SafetyState.DISARMED and rig.daemon.safety.latched is None
    for _ in range(10):
        assert_still(rig.step())
    assert rig.state is SafetyState.DISARMED
    rig.enable()
    assert_moves(rig.step())


def test_an_overrun_tick_stops_in_its_cycle(make_rig: Callable[..., Rig]) -> None:
    """``step_once(overrun=True)``: the loop's miss budget exhausted in this cycle."""
    rig = make_rig()
    rig.arm_and_push()
    with capture_logs() as logs:
        cmds = rig.step(overrun=True)
    assert rig.daemon.safety.latched is FaultCause.LOOP_OVERRUN
    got = [(c.device, c.name, c.args) for c in cmds]
    assert got == [*stop_commands(rig.cfg), ("arm", "kick_watchdog", ())]
    assert [e["cause"] for e in logs if e["event"] == "fault"] == ["loop_overrun"]


def run_loop(rig: Rig, cycles: int, slow: Callable[[int], bool],
             monkeypatch: pytest.MonkeyPatch) -> int:
    """The daemon's own :class:`~mmctl.runtime.loop.CycleLoop` for ``cycles`` cycles on
    the scripted clock: each deadline is met at once (the wait moves the clock to it),
    and loop cycle ``i`` takes 1.5 periods when ``slow(i)``: one deadline missed.
    Returns the daemon cycle of loop cycle 0."""
    loop = rig.daemon.loop
    first = rig.daemon.cycles
    period = loop.period_ns

    def wait(deadline: int) -> int:
        rig.clock.ns = max(rig.clock.ns, deadline)
        if loop.cycles == cycles - 1:
            loop.stop()  # after this cycle
        rig.rec.cycle = rig.daemon.cycles
        return rig.clock.ns

    def hook(*_: Any) -> None:
        if slow(loop.cycles):
            rig.clock.ns += period * 3 // 2

    monkeypatch.setattr(loop_module, "time", types.SimpleNamespace(
        perf_counter_ns=lambda: rig.clock.ns))
    loop.wait_for_deadline = wait
    rig.daemon.sample_hook = hook
    loop.start()
    assert loop.wait(60.0), "the scripted loop did not end"
    rig.rec.cycle = None
    rig.daemon.sample_hook = None
    assert loop.error is None and loop.cycles == cycles
    return first


@pytest.mark.parametrize("budget", ["consecutive", "total"])
def test_the_loops_miss_budget_on_a_scripted_clock(make_rig: Callable[..., Rig],
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   budget: str) -> None:
    """The real loop and its miss budget (``loop.max_consecutive_misses``, 3 here, or
    ``loop.max_total_misses``, 4 here, in every other cycle): the cycle after the budget
    is spent faults and stops; enabling is refused while the loop still overruns."""
    rig = make_rig({"loop": {"max_consecutive_misses": 3, "max_total_misses": 4}})
    rig.arm_and_push()
    s = 4  # the first slow loop cycle
    if budget == "consecutive":
        trip = s + rig.cfg.loop.max_consecutive_misses
    else:
        trip = s + 2 * rig.cfg.loop.max_total_misses - 1

    def slow(i: int) -> bool:
        """Every cycle from ``s`` on; for the total budget every other one until the
        trip (never two in a row), then every one."""
        return i >= s and (budget == "consecutive" or (i - s) % 2 == 0 or i > trip)
    with capture_logs() as logs:
        first = run_loop(rig, trip + 3, slow, monkeypatch)
    d = rig.daemon
    for i in range(trip):
        assert_moves(rig.commands(first + i))
    got = [(c.device, c.name, c.args) for c in rig.commands(first + trip)]
    assert got == [*stop_commands(rig.cfg), ("arm", "kick_watchdog", ())]
    for i in range(trip + 1, trip + 3):
        assert_still(rig.commands(first + i))
    faults = [e for e in logs if e["event"] == "fault"]
    assert [e["cause"] for e in faults] == ["loop_overrun"]
    if budget == "consecutive":
        assert faults[0]["consecutive"] == 3 and faults[0]["total"] == 3
    else:
        assert faults[0]["consecutive"] == 1 and faults[0]["total"] == 4
    # the loop ended still overrunning: refused; one cycle on time: accepted
    assert d.loop.consecutive_misses > 0
    with pytest.raises(EnableRefused, match="loop_overrun"):
        rig.enable()
    assert_still(rig.step())
    assert d.safety.latched is FaultCause.LOOP_OVERRUN
    rig.enable()
    assert_moves(rig.step())


def test_an_exception_in_a_cycle_stops_in_its_cycle(make_rig: Callable[..., Rig]) -> None:
    """A bug (an exception no transport raises on purpose) in a cycle: INTERNAL, the
    stop in that cycle; latched until an enable after it is gone."""
    rig = make_rig()
    rig.arm_and_push()
    with capture_logs() as logs:
        rig.sensor.error = ValueError("a decoding bug")
        cmds = rig.step()
        assert rig.daemon.safety.latched is FaultCause.INTERNAL
        got = [(c.device, c.name, c.args) for c in cmds]
        assert got == stop_commands(rig.cfg)  # the cycle ended there: no watchdog kick
        for _ in range(3):
            assert rig.step() == []  # every cycle fails before any command
    faults = [e for e in logs if e["event"] == "fault"]
    assert [e["cause"] for e in faults] == ["internal_error"]
    assert "a decoding bug" in faults[0]["error"]
    rig.sensor.error = None
    for _ in range(3):
        assert_still(rig.step())
    assert rig.daemon.safety.latched is FaultCause.INTERNAL
    rig.enable()
    assert_moves(rig.step())


def test_enable_is_refused_while_the_cycle_keeps_failing(
        make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.arm_and_push()
    rig.sensor.error = ValueError("a decoding bug")
    rig.step(3)
    with pytest.raises(EnableRefused, match="internal_error"):
        rig.enable()
    assert rig.daemon.safety.state is SafetyState.FAULT
    rig.sensor.error = None
    assert_still(rig.step())
    rig.enable()  # one good cycle: the condition is gone
    assert_moves(rig.step())


def test_a_latched_arm_link_fault_reconnects_even_when_reads_look_fine(
        make_rig: Callable[..., Rig]) -> None:
    """A link lost under speedJ, then reads that look fine again (a dead controller's
    last sample lingering in the arm's process): the enable still reconnects first, and
    a reconnect that fails refuses it."""
    rig = make_rig()
    rig.arm_and_push()
    rig.arm.die_at_send = True
    rig.step()
    assert rig.daemon.safety.latched is FaultCause.ARM_DISCONNECTED
    rig.arm.gone, rig.arm.reachable = False, True  # reads answer again ...
    rig.arm.script_refused = True  # ... but the controller runs no control script
    assert_still(rig.step())
    assert not rig.daemon.safety.active  # nothing present: only the latch remembers
    with pytest.raises(MmctlError, match="refused to enable: the arm did not reconnect"):
        rig.enable()
    assert rig.rec.log[-1] == Command(None, "arm", "reconnect")
    assert rig.state is SafetyState.FAULT
    rig.arm.script_refused = False
    rig.enable()
    assert rig.daemon.safety.armed


def _arm_speeds(rig: Rig, cycles: int) -> list[float]:
    """The largest joint speed of each cycle's speedJ (every cycle must send one)."""
    speeds = []
    for _ in range(cycles):
        cmds = rig.step()
        assert names(cmds)[:1] == ["arm.speed_j"], cmds
        speeds.append(float(np.abs(cmds[0].args[0]).max()))
    return speeds


def test_released_the_armed_robot_comes_to_rest_and_stays_armed(
        make_rig: Callable[..., Rig]) -> None:
    """The enabling switch released under a push: no fault; the speedJ commands fall to
    zero on the acceleration limits (the arm's and the base's commands keep flowing, so
    the controller's watchdog is fed); held again, the robot follows the push again."""
    rig = make_rig(ENABLING)
    rig.arm_and_push()
    assert rig.daemon.status()["enabling"] == "held"
    rig.arm.inputs = 0
    speeds = _arm_speeds(rig, 400)
    assert rig.daemon.safety.armed and rig.daemon.safety.faults == 0
    assert rig.daemon.status()["enabling"] == "released"
    assert speeds[0] > 0.0 and speeds[-1] == 0.0
    assert all(b <= a for a, b in itertools.pairwise(speeds))  # it only slows down
    rig.arm.inputs = HELD
    for _ in range(5):
        assert_moves(rig.step())
    assert rig.daemon.status()["enabling"] == "held"


def test_no_motion_on_a_stale_arm_pose(make_rig: Callable[..., Rig]) -> None:
    """The arm's stream stops (a frozen controller, a starved arm process): from
    ``arm.hold_cycles`` cycles without a new sample on, the command decelerates to rest,
    long before the stale fault (here 1000 cycles: a load-proof configuration) — the
    soak saw a wrist driven blind into its joint limit for those 2 s.  A new sample
    lets the robot follow the push again."""
    rig = make_rig({"arm": {"stale_cycles": 1000, "hold_cycles": 10}})
    rig.arm_and_push()
    for _ in range(200):
        assert_moves(rig.step())  # pushed up to speed
    rig.arm.frozen = True
    speeds = _arm_speeds(rig, 400)
    assert rig.daemon.safety.armed and rig.daemon.safety.faults == 0
    assert speeds[0] > 0.0 and speeds[-1] == 0.0
    first_slower = next(i for i, (a, b) in enumerate(itertools.pairwise(speeds)) if b < a)
    # the first frozen cycle already repeats the sample: the 10th repeat (cycle index 9)
    # is the first command that slows down
    assert first_slower + 1 == 9
    assert all(b <= a for a, b in itertools.pairwise(speeds[first_slower:]))
    rig.arm.frozen = False
    for _ in range(5):
        assert_moves(rig.step())


def test_the_loop_cycles_on_while_the_base_enables(make_rig: Callable[..., Rig]) -> None:
    """The base's enable waits for SDO answers and for wheels still ramping down on the
    last stop (up to ``base.canopen.stop_timeout``).  On the loop thread it stalled the
    loop, long enough for the arm's RTDE watchdog to stop the control script (the soak's
    ``arm_not_playing`` right after an enable).  It runs on the enabling thread now:
    the loop cycles on and feeds the arm's watchdog, leaves the base alone, and arms
    once the base is enabled."""
    rig = make_rig()
    rig.step(3)
    entered, release = threading.Event(), threading.Event()
    scripted_enable = rig.base.enable
    reads: list[int] = []
    scripted_read = rig.base.read_odometry

    def slow_enable() -> None:
        entered.set()
        assert release.wait(60.0)
        scripted_enable()

    def counted_read() -> Odometry:
        reads.append(rig.daemon.cycles)
        return scripted_read()

    rig.base.enable = slow_enable  # type: ignore[method-assign]
    rig.base.read_odometry = counted_read  # type: ignore[method-assign]
    outcome: list[object] = []

    def operator() -> None:
        try:
            outcome.append(rig.daemon.call("enable")["state"])
        except Exception as exc:  # noqa: BLE001 -- asserted below
            outcome.append(exc)

    t = threading.Thread(target=operator)
    t.start()
    try:
        assert entered.wait(60.0)
        for _ in range(5):  # cycles while the base is enabling
            assert names(rig.step()) == ["arm.kick_watchdog"]
        assert rig.daemon.safety.state is SafetyState.DISARMED
        # the base is not read meanwhile: not a fault condition (nothing to report)
        assert rig.daemon.safety.active == {}
        assert reads == []  # the enabling thread has the base
    finally:
        release.set()
        t.join(60.0)
    assert outcome == ["armed"]
    rig.sensor.force = PUSH.copy()
    assert_moves(rig.step(2))
    assert reads  # the loop reads the base again


def test_the_sample_hook_runs_after_the_stop_and_before_the_motion(
        make_rig: Callable[..., Rig]) -> None:
    """Telemetry goes after a stop (never delays it) and before speedJ and the twist
    (whose frames wake the device threads)."""
    rig = make_rig()
    rig.arm_and_push()
    seen: list[tuple[list[str], str]] = []
    rig.daemon.sample_hook = lambda r, cycle, t, safety: seen.append(
        (names(rig.commands(cycle)), safety))
    assert_moves(rig.step())
    rig.sensor.force = np.array([0.0, 0.0, 200.0])
    rig.step()
    assert seen == [([], "armed"), (["base.stop", "arm.stop", "base.disable"], "fault")]


def test_a_cycle_that_fails_after_its_update_keeps_the_leases_answer(
        make_rig: Callable[..., Rig]) -> None:
    """A cycle that raises after its update ran (a condition: enable is refused while
    cycles fail): the update's lease of a link to the enable's thread is answered as
    such (the caller does the link's work and gives it back: the link is not left
    unread for good); every other command in that cycle fails with the cycle's error."""
    from mmctl.control.update import EnableCheck, Release, SetMode

    rig = make_rig()
    rig.step(3)
    assert rig.daemon.safety.state is SafetyState.DISARMED
    rt = rig.daemon.runtime

    def broken(*_: Any) -> None:
        raise RuntimeError("a telemetry bug")

    rig.daemon.sample_hook = broken
    check, mode = rt.submit(EnableCheck()), rt.submit(SetMode("locomotion"))
    rig.step()
    rig.daemon.sample_hook = None
    assert check.result(0) is True and rt.base_busy  # the base: leased to the enable
    with pytest.raises(RuntimeError, match="a telemetry bug"):
        mode.result(0)
    assert FaultCause.INTERNAL in rig.daemon.last_conditions  # (enable: refused meanwhile)
    done = rt.submit(Release("base"))
    rig.step()
    done.result(0)
    assert not rt.base_busy  # given back: the loop reads the base again


def test_the_fault_matrix_in_the_docs_is_current() -> None:
    """docs/fault-matrix.md is what tools/fault_matrix.py measures on these peers."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "tools" / "fault_matrix.py"
    spec = importlib.util.spec_from_file_location("fault_matrix_tool", path)
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    assert tool.DOC.read_text() == tool.generate(), (
        "docs/fault-matrix.md is stale: run `python tools/fault_matrix.py --write`")
