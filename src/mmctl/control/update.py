"""One control period as one pure function: ``update(state, readings, inbox)`` ->
``(state, commands, events)``.

The loop thread does read -> update -> write and nothing else (SPEC §7): it copies the
devices' newest samples into :class:`Readings`, calls :meth:`Update.__call__`, sends
:class:`Commands` and logs the events.  Every per-cycle decision is made here, on
values only (no I/O, no clock, no logging):

- the operator's commands, typed values drained from a bounded inbox
  (:data:`Command`), each answered by a :class:`Reply` event;
- the switch-mode button (a rising edge of its digital input toggles the sub-mode);
- the arm hold: a repeated RTDE sample (same controller time) for ``arm.hold_cycles``
  cycles brings the command to rest (the stale fault comes later, from the arm's link);
- the enabling (hold-to-run) switch, its contacts read from the arm sample's digital
  inputs, and their discrepancy fault;
- the control chain (:meth:`~mmctl.control.cycle.CycleChain.cycle`: wrench, admittance,
  IDK, limits, energy) and its faults;
- the safety state machine and its latch (:mod:`mmctl.control.safety`);
- the commands: speedJ, or a watchdog kick when none goes out, or the stop; the base
  twist every ``loop.base_divider``-th cycle or at once when it jumped by more than
  ``loop.base_jump``.

The study, the scripted fault tests and the daemon run this same function.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np

from mmctl.config import Config
from mmctl.control import safety as sm
from mmctl.control.cycle import CycleChain, CycleResult, CycleState
from mmctl.control.cycle import Readings as ChainReadings
from mmctl.control.safety import Conditions, EnableRefused, Safety, SafetyEvent
from mmctl.control.step import Controller
from mmctl.errors import FaultCause, MmctlError, SafetyFault
from mmctl.types import ArmState, Odometry, Vec, Wrench

#: Causes the base's own enable resets (its drives latch them until then).
BASE_CAUSES = frozenset({FaultCause.DRIVE_FAULT, FaultCause.DRIVE_HEARTBEAT,
                         FaultCause.BASE_LINK})
#: Causes after which an enable reconnects the arm first.
ARM_RECONNECT_CAUSES = frozenset({FaultCause.ARM_DISCONNECTED, FaultCause.ARM_STALE,
                                  FaultCause.ARM_NOT_PLAYING})
#: Causes an enable judges on this cycle's reads only (a link it may have just
#: reconnected): the arm's and the sensor's link.
_FRESH_CAUSES = frozenset(
    {c for c in FaultCause if c.value.startswith("arm_")} | {FaultCause.SENSOR_LINK})
_Z3 = np.zeros(3)
_NO_CONDITIONS: Conditions = MappingProxyType({})


# -- the inbox: one value per operator command -----------------------------------------

class Disable(NamedTuple):
    """Disarm (the stop goes out this cycle when armed)."""


class SetMode(NamedTuple):
    """Another IDK strategy (cross-faded: no velocity jump)."""

    mode: str


class SetSwitch(NamedTuple):
    """Switch mode's sub-mode: ``manipulation`` or ``locomotion``."""

    to: str


class SetProfile(NamedTuple):
    """The limits' profile: ``normal`` or ``reduced``."""

    profile: str


class Tare(NamedTuple):
    """Average the next ``sensor.wrench.tare_samples`` fresh samples into the bias."""


class Install(NamedTuple):
    """A run-time parameter change (`mmctl set`): the configuration with ``key`` changed
    and a controller built from it off the loop; the controller takes over the current
    state (no velocity jump)."""

    cfg: Config
    controller: Controller
    key: str


class BeginEnable(NamedTuple):
    """An enable's first step: replies the links to reconnect first (``"arm"``: an arm
    link or program condition present or latched; ``"sensor"``: the sensor's link lost,
    present or latched), a tuple of names, empty when none; they are leased to the
    enable (:attr:`UpdateState.leased`) until its :class:`Release`."""


class EnableCheck(NamedTuple):
    """An enable's check before the base's own enable: replies False when armed already;
    refused (EnableRefused) while a condition but the base's is present; else True, and
    the base is leased to the enable (the loop leaves it alone) until its
    :class:`Release`."""


class Release(NamedTuple):
    """A link an enable leased (:class:`BeginEnable`: the arm's or the sensor's, to
    reconnect it; :class:`EnableCheck`: the base's, to enable it) is the loop's again:
    its work ended, whatever its outcome.  The loop reads it again from the next cycle."""

    link: str


class EnableFinish(NamedTuple):
    """An enable's last step, after the base's enable: ``failure`` is what the base's
    enable raised (None: it enabled), ``fault`` the cause the base named when asked
    after a failure (its ``check``).  Arms, or refuses and stops."""

    failure: BaseException | None = None
    fault: SafetyFault | None = None


Command = (Disable | SetMode | SetSwitch | SetProfile | Tare | Install | BeginEnable
           | EnableCheck | Release | EnableFinish)

#: The links an enable may lease (:attr:`UpdateState.leased`).
LINKS = ("arm", "sensor", "base")


# -- readings, commands, events --------------------------------------------------------

class Readings(NamedTuple):
    """One cycle's inputs, as the loop read them.

    index: the cycle's index (the base divider counts it); now: the time [s] on the
    readings' clock (``time.monotonic``), staleness is judged against it; dt: the
    period [s]; arm, wrench, odom: the devices' newest samples (None: not read, its
    condition says why); inputs: the arm sample's digital inputs (bit i = input i);
    conditions: the fault conditions the reads raised; overrun: (consecutive, total)
    misses when the loop's miss budget is exhausted, else None; misses: the cycles in a
    row that overran until this one (0: on time); arm_busy: a reconnect
    owns the arm's link (no arm command may go out); calibrating: a tool-load
    calibration moves the arm this cycle (the controller idles).
    """

    index: int  # type: ignore[assignment]  # shadows tuple.index
    now: float
    dt: float
    arm: ArmState | None
    wrench: Wrench | None
    odom: Odometry | None
    inputs: int = 0
    conditions: Conditions = _NO_CONDITIONS
    overrun: tuple[int, int] | None = None
    misses: int = 0
    arm_busy: bool = False
    calibrating: bool = False


class Commands(NamedTuple):
    """What the write step sends this cycle.

    stop: the stop commands (base zero, speedStop, base disable); qd_arm: (6,) speedJ
    [rad/s] (None: none this cycle); twist: (vx, vy [m/s], wz [rad/s]) for the base
    (None: none this cycle); kick: feed the arm's RTDE watchdog (no speedJ goes out);
    result: the chain's numbers of this cycle (None: a device was not read).
    """

    stop: bool
    qd_arm: Vec | None
    twist: tuple[float, float, float] | None
    kick: bool
    result: CycleResult | None


class Reply(NamedTuple):
    """The answer to ``inbox[index]``: ``value``, or ``error`` (then raised to the
    operator)."""

    index: int  # type: ignore[assignment]  # shadows tuple.index
    value: Any = None
    error: MmctlError | None = None


class Switched(NamedTuple):
    """Switch mode's sub-mode changed (``source``: ``button``)."""

    new: str
    source: str


class Changed(NamedTuple):
    """An operator's command took effect: ``what`` (mode, profile, switch, param) went
    from ``old`` to ``new``."""

    what: str
    old: Any
    new: Any


Event = SafetyEvent | Reply | Switched | Changed


class Enabling(NamedTuple):
    """The enabling switch as the last cycle read it: ``held`` (None: not read yet, or
    its contacts disagree); ``disagree_since`` [s]: when they started to disagree."""

    held: bool | None = None
    disagree_since: float | None = None


class UpdateState(NamedTuple):
    """What one cycle hands to the next."""

    chain: CycleState
    safety: Safety
    cycles: int = 0
    arm_time: float = float("nan")
    arm_repeats: int = 0
    speed_scaling: float = 1.0
    enabling: Enabling = Enabling()
    button: bool = False
    twist_sent: tuple[float, float, float] | None = None
    last: CycleResult | None = None
    #: the links an enable's device work holds (:data:`LINKS`): the loop neither reads
    #: them nor sends them commands until their :class:`Release`
    leased: frozenset[str] = frozenset()


class Update:
    """The pure update's fixed parts (see the module docstring): the chain and the
    configuration's per-cycle rules."""

    def __init__(self, cfg: Config, chain: CycleChain):
        self.chain = chain
        self.cfg = cfg
        e = cfg.enabling
        self.enabling_inputs = tuple(e.inputs)
        self.enabling_level = not e.active_low
        self.discrepancy_time = e.discrepancy_time
        self.button_input = cfg.daemon.switch_input
        self.hold_cycles = cfg.arm.hold_cycles
        self.divider = cfg.loop.base_divider
        self.jump = cfg.loop.base_jump

    @property
    def held_inputs(self) -> int:
        """The arm's digital-inputs word with the enabling switch held: each contact
        at its held level (no switch configured: 0).  What a scripted hand sends."""
        return sum(1 << i for i in self.enabling_inputs) if self.enabling_level else 0

    def initial_state(self) -> UpdateState:
        """Disarmed, at rest, in ``idk.strategy``."""
        return UpdateState(self.chain.initial_state(), Safety())

    # -- the update ---------------------------------------------------------------------
    def __call__(self, s: UpdateState, r: Readings, inbox: Sequence[Command] = ()
                 ) -> tuple[UpdateState, Commands, tuple[Event, ...]]:
        events: list[Event] = []
        conditions = self._conditions(r)
        stop = False
        for i, cmd in enumerate(inbox):
            s, halt = self._apply(s, r, i, cmd, conditions, events)
            stop = stop or halt
        s = self._button(s, r, events)
        arm = r.arm
        if arm is not None:
            if arm.controller_time != s.arm_time:
                s = s._replace(arm_time=arm.controller_time, arm_repeats=0,
                               speed_scaling=arm.speed_scaling)
            else:
                s = s._replace(arm_repeats=s.arm_repeats + 1, speed_scaling=arm.speed_scaling)
        s, held = self._enabling(s, r, conditions)
        held = held and s.arm_repeats < self.hold_cycles
        result: CycleResult | None = None
        if arm is not None and r.wrench is not None and r.odom is not None:
            active = s.safety.armed and not r.calibrating
            chain, result = self.chain.cycle(
                s.chain, ChainReadings(arm, r.wrench, r.odom, r.dt, active, held), r.now)
            s = s._replace(chain=chain, last=result)
            if result.fault is not None:
                conditions.setdefault(result.fault, dict(result.fault_details))
        elif arm is not None and r.wrench is not None and not s.safety.armed:
            # the base not read (a faulted drive, its link lost) while disarmed: the
            # sensor's part of the chain still runs, with the base at rest at the origin
            # (the wrench's processing needs only the arm's pose in the base's frame),
            # so a tare finishes (enable waits for it, and a faulted drive is reset only
            # by an enable) and the sensor's conditions are still seen.  No result: the
            # base's motion is not measured.
            odom = Odometry(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, r.now)
            chain, idle = self.chain.cycle(
                s.chain, ChainReadings(arm, r.wrench, odom, r.dt, False, held), r.now)
            s = s._replace(chain=chain)
            if idle.fault is not None:
                conditions.setdefault(idle.fault, dict(idle.fault_details))
        safety, stop_now, sev = sm.observe(s.safety, conditions)
        events.extend(sev)
        stop = stop or stop_now
        s = s._replace(safety=safety, cycles=s.cycles + 1)
        qd_arm: Vec | None = None
        twist: tuple[float, float, float] | None = None
        if stop:
            s = s._replace(twist_sent=None)
        elif safety.armed and result is not None:
            if r.calibrating:  # the routine's speedJ goes out instead; the base rests
                tw = (0.0, 0.0, 0.0)
            else:
                qd_arm = result.qd_arm
                t = result.twist
                tw = (float(t[0]), float(t[1]), float(t[2]))
            if self._base_due(r.index, tw, s.twist_sent):
                twist = tw
                s = s._replace(twist_sent=tw)
        kick = qd_arm is None and not r.arm_busy
        return s, Commands(stop, qd_arm, twist, kick, result), tuple(events)

    # -- the write's outcome: the update's two other transitions ------------------------
    def write_failed(self, s: UpdateState, cause: FaultCause, details: Mapping[str, Any]
                     ) -> tuple[UpdateState, tuple[Event, ...]]:
        """A command the write step could not send (its device raised): the fault
        latches in this same cycle, the base's last twist is forgotten; the write sends
        the stop.  A pure transition like the update, recorded as its input (the input
        log's ``write_failed``) and replayed through this same function."""
        safety, _, events = sm.trip(s.safety, cause, details)
        return s._replace(safety=safety, twist_sent=None), tuple(events)

    def cycle_failed(self, s: UpdateState, error: str
                     ) -> tuple[UpdateState, bool, tuple[Event, ...]]:
        """A cycle that raised (a bug): ``internal_error`` is this cycle's condition, as
        any other (enable is refused while cycles keep failing); returns whether the
        stop goes out.  Recorded and replayed as :meth:`write_failed` is."""
        safety, stop, events = sm.observe(s.safety, {FaultCause.INTERNAL: {"error": error}})
        return s._replace(safety=safety), stop, tuple(events)

    def apply(self, s: UpdateState, r: Readings, inbox: Sequence[Command]
              ) -> tuple[UpdateState, bool, tuple[Event, ...]]:
        """The inbox alone, judged on the readings ``r`` (a cycle's), without a control
        step: the next state, whether the stop goes out, the events (replies among
        them).  For a runtime that steps its cycles by hand (tests, tools)."""
        events: list[Event] = []
        conditions = self._conditions(r)
        stop = False
        for i, cmd in enumerate(inbox):
            s, halt = self._apply(s, r, i, cmd, conditions, events)
            stop = stop or halt
        if stop:
            s = s._replace(twist_sent=None)
        return s, stop, tuple(events)

    @staticmethod
    def _conditions(r: Readings) -> dict[FaultCause, Mapping[str, Any]]:
        conditions = dict(r.conditions)
        if r.overrun is not None:
            conditions[FaultCause.LOOP_OVERRUN] = {"consecutive": r.overrun[0],
                                                   "total": r.overrun[1]}
        return conditions

    # -- the parts ----------------------------------------------------------------------
    def _button(self, s: UpdateState, r: Readings, events: list[Event]) -> UpdateState:
        if self.button_input < 0 or r.arm is None:
            return s
        now = bool((r.inputs >> self.button_input) & 1)
        ctl = s.chain.controller
        if now and not s.button and ctl.mode.value == "switch":
            nxt = self.chain.controller.toggle_switch(ctl)
            s = s._replace(chain=s.chain._replace(controller=nxt))
            events.append(Switched(nxt.switch.value, "button"))
        return s._replace(button=now)

    def _enabling(self, s: UpdateState, r: Readings,
                  conditions: dict[FaultCause, Mapping[str, Any]]) -> tuple[UpdateState, bool]:
        """Whether the enabling switch is held (True without one; not held without an
        arm sample: the arm's own condition says why)."""
        if not self.enabling_inputs:
            return s, True
        if r.arm is None:
            return s, False
        levels = [bool((r.inputs >> i) & 1) for i in self.enabling_inputs]
        held = [lvl == self.enabling_level for lvl in levels]
        if all(held) or not any(held):
            return s._replace(enabling=Enabling(held[0], None)), held[0]
        since = s.enabling.disagree_since
        if since is None:
            since = r.now
        s = s._replace(enabling=Enabling(None, since))
        apart = r.now - since
        if apart > self.discrepancy_time:
            conditions.setdefault(FaultCause.ENABLING_DEVICE, {
                "device": "enabling", "inputs": list(self.enabling_inputs),
                "levels": [int(v) for v in levels], "disagree_for": round(apart, 4),
                "why": "the switch's contacts disagree (a broken wire or a welded contact)"})
        return s, False

    def _base_due(self, index: int, twist: tuple[float, float, float],
                  last: tuple[float, float, float] | None) -> bool:
        """Every ``loop.base_divider``-th cycle, or at once when the twist jumped by more
        than ``loop.base_jump`` since the last one sent (a new push)."""
        if index % self.divider == 0 or last is None:
            return True
        j = self.jump
        return (abs(twist[0] - last[0]) > j or abs(twist[1] - last[1]) > j
                or abs(twist[2] - last[2]) > j)

    # -- the operator's commands --------------------------------------------------------
    def _apply(self, s: UpdateState, r: Readings, i: int, cmd: Command,
               conditions: Conditions, events: list[Event]) -> tuple[UpdateState, bool]:
        """One inbox command: the next state and whether the stop goes out now; its
        answer (or error) joins ``events`` as a :class:`Reply`."""
        try:
            s, value, stop = self._command(s, r, cmd, conditions, events)
        except MmctlError as exc:
            stop = isinstance(exc, _RefusedAndStop)
            events.append(Reply(i, None, exc.refused if isinstance(exc, _RefusedAndStop)
                                else exc))
            return s, stop
        events.append(Reply(i, value))
        return s, stop

    def _command(self, s: UpdateState, r: Readings, cmd: Command, conditions: Conditions,
                 events: list[Event]) -> tuple[UpdateState, Any, bool]:
        ctl_now = s.chain.controller
        controller = self.chain.controller
        match cmd:
            case Disable():
                safety, stop, sev = sm.disable(s.safety)
                events.extend(sev)
                return s._replace(safety=safety), None, stop
            case SetMode(mode=mode):
                nxt = controller.set_mode(ctl_now, mode)
                events.append(Changed("mode", ctl_now.mode.value, nxt.mode.value))
                return self._with_controller(s, nxt), None, False
            case SetProfile(profile=profile):
                nxt = controller.set_profile(ctl_now, profile)
                events.append(Changed("profile", _profile(ctl_now.reduced),
                                      _profile(nxt.reduced)))
                return self._with_controller(s, nxt), None, False
            case SetSwitch(to=which):
                if ctl_now.mode.value != "switch":
                    raise MmctlError(f"`switch` needs mode 'switch' (current mode: "
                                     f"{ctl_now.mode.value}); run `mmctl mode switch` first")
                nxt = controller.set_switch(ctl_now, which)
                events.append(Changed("switch", ctl_now.switch.value, nxt.switch.value))
                return self._with_controller(s, nxt), None, False
            case Tare():
                if s.safety.armed:
                    raise MmctlError("refusing to tare while armed: `mmctl disable` first "
                                     "(a tare must not absorb the operator's push)")
                w = self.chain.wrench.start_tare(s.chain.wrench)
                return (s._replace(chain=s.chain._replace(wrench=w)),
                        {"taring": True, "samples": self.cfg.sensor.wrench.tare_samples}, False)
            case Install(cfg=cfg, controller=new):
                self.cfg = cfg
                self.chain.cfg = cfg
                self.chain.controller = new
                return s, None, False
            case BeginEnable():
                if s.safety.armed:
                    return s, (), False
                sf = s.safety
                present = sf.active.keys() | conditions.keys()  # this cycle's reads too
                links = []
                if present & ARM_RECONNECT_CAUSES or sf.latched in ARM_RECONNECT_CAUSES:
                    links.append("arm")
                if FaultCause.SENSOR_LINK in present or sf.latched is FaultCause.SENSOR_LINK:
                    links.append("sensor")
                return s._replace(leased=s.leased | set(links)), tuple(links), False
            case EnableCheck():
                if s.safety.armed:
                    return s, False, False
                if s.cycles == 0:
                    raise MmctlError("refused to enable: no control cycle has run yet")
                if s.chain.wrench.tare_left > 0:
                    raise MmctlError("refused to enable: a tare is in progress (the handle "
                                     "must not be touched until it ends)")
                other = self._other_conditions(s, r, conditions, base=False)
                if other:
                    s = s._replace(safety=dataclasses.replace(s.safety, active=other))
                    raise EnableRefused(list(other), other)
                return s._replace(leased=s.leased | {"base"}), True, False
            case Release(link=link):
                if link not in LINKS:
                    raise MmctlError(f"release: link {link!r}: must be one of {LINKS}")
                return s._replace(leased=s.leased - {link}), None, False
            case EnableFinish(failure=failure, fault=fault):
                return self._enable_finish(s, r, conditions, failure, fault, events)
        raise MmctlError(f"unknown command {cmd!r}")  # pragma: no cover

    def _enable_finish(self, s: UpdateState, r: Readings, conditions: Conditions,
                       failure: BaseException | None, fault: SafetyFault | None,
                       events: list[Event]) -> tuple[UpdateState, Any, bool]:
        if s.safety.armed:
            return s, None, False
        if failure is not None:  # refused; the cause the base names, if it does
            refused: MmctlError
            if isinstance(failure, SafetyFault):
                refused = EnableRefused([failure.cause], {
                    failure.cause: {"device": "base", **failure.details}})
            elif fault is not None:
                refused = EnableRefused([fault.cause], {fault.cause: {
                    "device": "base", "error": str(failure), **fault.details}})
            else:
                refused = MmctlError(f"refused to enable: the base did not enable ({failure})")
            raise _RefusedAndStop(refused)
        other = self._other_conditions(s, r, conditions, base=False)
        if other:  # came up while the base was enabled
            s = s._replace(safety=dataclasses.replace(s.safety, active=other))
            raise _RefusedAndStop(EnableRefused(list(other), other))
        safety, sev = sm.enable(dataclasses.replace(s.safety, active={}))
        events.extend(sev)
        return (s._replace(safety=safety, chain=self.chain.at_rest(s.chain)), "armed", False)

    def _other_conditions(self, s: UpdateState, r: Readings, conditions: Conditions,
                          base: bool) -> dict[FaultCause, Mapping[str, Any]]:
        """The conditions an enable must find gone: the last cycle's but the links' and
        the base's (the base latches its faults until its own enable resets them); the
        arm's and the sensor's link (:data:`_FRESH_CAUSES`) and (``base``) the base's
        from this cycle's reads; a loop on time again (no miss in a row) is no longer an
        overrun."""
        other: dict[FaultCause, Mapping[str, Any]] = {
            c: d for c, d in s.safety.active.items()
            if c not in BASE_CAUSES and c not in _FRESH_CAUSES}
        if r.misses == 0:
            other.pop(FaultCause.LOOP_OVERRUN, None)
        for c, d in conditions.items():
            if c in _FRESH_CAUSES or (base and c in BASE_CAUSES):
                other.setdefault(c, d)
        return other

    def _with_controller(self, s: UpdateState, ctl: Any) -> UpdateState:
        return s._replace(chain=s.chain._replace(controller=ctl))


class _RefusedAndStop(MmctlError):
    """An enable refused after the base was enabled: the stop goes out this cycle."""

    def __init__(self, refused: MmctlError):
        super().__init__(str(refused))
        self.refused = refused


def _profile(reduced: bool) -> str:
    return "reduced" if reduced else "normal"


#: An operator's enable with no device work to do (a study's plant, a benchmark): the
#: runtime's sequence (runtime/operator.py), the base's lease given back at once.
ENABLE_WITHOUT_DEVICES: tuple[Command, ...] = (
    BeginEnable(), EnableCheck(), Release("base"), EnableFinish())

__all__ = [
    "ARM_RECONNECT_CAUSES",
    "BASE_CAUSES",
    "ENABLE_WITHOUT_DEVICES",
    "LINKS",
    "_Z3",
    "BeginEnable",
    "Changed",
    "Command",
    "Commands",
    "Disable",
    "EnableCheck",
    "EnableFinish",
    "Enabling",
    "Event",
    "Install",
    "Readings",
    "Release",
    "Reply",
    "SetMode",
    "SetProfile",
    "SetSwitch",
    "Switched",
    "Tare",
    "Update",
    "UpdateState",
]
