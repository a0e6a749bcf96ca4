"""The cycle driver: one control period on the loop thread is read -> update -> write.

- :meth:`LoopRuntime._read` copies the devices' newest samples (timed per device,
  :data:`PHASES`) and the conditions their reads raised into
  :class:`~mmctl.control.update.Readings`;
- :class:`~mmctl.control.update.Update` (pure) makes every per-cycle decision: the
  operator's commands taken from the inbox, the button, the arm hold, the enabling
  switch, the control chain, the safety latch, the commands;
- :meth:`LoopRuntime._write` sends the commands (a command that fails stops the robot at
  once, and its condition reaches the next update), then the events are logged and the
  inbox's replies handed to the waiting callers.

:class:`LoopRuntime` owns what the loop thread works on: the update's state, the newest
readings and result, the inbox, the timing rows.  The operator
(:class:`~mmctl.runtime.operator.Operator`) and the tool-load calibration
(:class:`~mmctl.runtime.calibrate.Calibrations`) hold it and reach the loop only through
:meth:`LoopRuntime.on_loop` (a command into the inbox, its reply back);
:class:`~mmctl.runtime.daemon.Daemon` composes the three with the lifecycle.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, NamedTuple, TypeVar, overload

import numpy as np
import structlog

from mmctl.control.safety import FaultRaised, Safety, StateChanged
from mmctl.control.update import (
    BeginEnable,
    Changed,
    Command,
    Commands,
    Disable,
    EnableCheck,
    EnableFinish,
    Install,
    Readings,
    Release,
    Reply,
    SetMode,
    SetProfile,
    SetSwitch,
    Switched,
    Tare,
    Update,
    UpdateState,
)
from mmctl.errors import FaultCause, IpcError, MmctlError, SafetyFault, TransportError
from mmctl.runtime.core import ControlCore, CycleResult
from mmctl.runtime.devices import Devices
from mmctl.runtime.logging import RateLimiter
from mmctl.runtime.loop import CycleLoop, GcInSlack, Tick, Wait
from mmctl.runtime.notify import Notifier
from mmctl.runtime.safety import log_events
from mmctl.runtime.timing import TimingRing
from mmctl.types import Wrench

log = structlog.get_logger("mmctl.daemon")

_LINK_CAUSE = {"arm": FaultCause.ARM_DISCONNECTED, "sensor": FaultCause.SENSOR_LINK,
               "base": FaultCause.BASE_LINK}

#: The device phases of a cycle timed in :attr:`Daemon.phase_ns` (rows, in this order).
PHASES = ("arm_read", "sensor_read", "base_read", "arm_send", "base_send", "sensor_request")

_Z3 = np.zeros(3)
#: The commands that lease links to an enable's thread or give them back
LEASING = (BeginEnable, EnableCheck, Release)

if TYPE_CHECKING:
    from mmctl.config import Config
    from mmctl.control.calibration import ToolCalibration
    from mmctl.runtime.inputlog import InputLog

Conditions = dict[FaultCause, Mapping[str, object]]
T = TypeVar("T")

#: The hook telemetry attaches: called on the loop thread once per cycle as
#: ``hook(result, cycle, t, safety)`` (the cycle's CycleResult, its index, its deadline
#: since the origin [s], the safety state's name); must not block.
SampleHook = Callable[[CycleResult, int, float, str], None]

#: A running tool-load calibration's part of a cycle (:meth:`Calibrations.cycle
#: <mmctl.runtime.calibrate.Calibrations.cycle>`): the routine, the controller's result,
#: the sensor's sample, how many cycles the arm's pose has been repeated -> the result
#: with the routine's command in place of the controller's.
CalibrationCycle = Callable[["ToolCalibration", CycleResult | None, Wrench | None, int],
                            CycleResult | None]

#: The update's commands a caller may queue (anything else is a :class:`RunOnLoop`).
COMMAND_TYPES = (BeginEnable, Disable, EnableCheck, EnableFinish, Install, Release,
                 SetMode, SetProfile, SetSwitch, Tare)


class RunOnLoop(NamedTuple):
    """A runtime-side operation run on the loop thread before the update (a trial's
    telemetry hook, a tool-load calibration's start or abort): not a control decision."""

    fn: Callable[[], object]


class LoopRuntime:
    """The loop thread's cycle and what it works on (see the module docstring).

    cfg: the configuration; devices: the device links (connected by the daemon); core:
    the control chain; notifier: systemd notify (status line, watchdog); stop_requested:
    set once the daemon is stopping (a command is then refused, never queued);
    input_log: every cycle's readings, inbox and commands (None: not recorded);
    loop_wait: the loop's wait for each deadline (default: sleep, then spin).
    """

    def __init__(self, cfg: Config, devices: Devices, core: ControlCore, *,
                 notifier: Notifier, stop_requested: threading.Event,
                 input_log: InputLog | None = None, loop_wait: Wait | None = None):
        self.cfg = cfg
        self.devices = devices
        self.core = core
        self.notifier = notifier
        self.stop_requested = stop_requested
        #: the pure update (every per-cycle decision) and the state it hands on
        self.update = Update(cfg, core.chain)
        self.ustate: UpdateState = self.update.initial_state()
        #: [commands] the most the update takes from the inbox in one cycle
        self.inbox_size = 16
        #: the arm's digital inputs a cycle reads: the enabling contacts, the button
        self._inputs = tuple(cfg.enabling.inputs) + (
            (cfg.daemon.switch_input,) if cfg.daemon.switch_input >= 0 else ())
        self.input_log = input_log
        #: this cycle's update events not yet answered (a cycle that fails after its
        #: update ran still gives the inbox's callers the update's own replies)
        self._unanswered: tuple[object, ...] = ()
        #: the last cycle's readings (None: no cycle yet)
        self.readings: Readings | None = None
        self.ring = TimingRing(cfg.loop.timing_samples)
        #: time spent in the pure update per cycle, indexed by cycle % size [ns]: the
        #: part of the compute time that is not device I/O
        self.step_ns = np.zeros(cfg.loop.timing_samples, np.int64)
        #: time spent in the telemetry sample hook (write the cycle's row) per cycle,
        #: indexed like ``step_ns`` [ns]; 0 when no hook ran: telemetry's own loop cost
        self.hook_ns = np.zeros(cfg.loop.timing_samples, np.int64)
        #: per device phase (:data:`PHASES`) and cycle, indexed like ``step_ns`` [ns]; 0
        #: when the phase did not run: where the compute time goes (`mmctl bench loop`)
        self.phase_ns = np.zeros((len(PHASES), cfg.loop.timing_samples), np.int64)
        self.loop = CycleLoop(
            self.cycle, rate_hz=cfg.loop.rate_hz, spin_margin=cfg.loop.spin_margin,
            max_consecutive_misses=cfg.loop.max_consecutive_misses,
            max_total_misses=cfg.loop.max_total_misses, ring=self.ring,
            rt_priority=cfg.loop.rt_priority, cpu_affinity=cfg.loop.cpu_affinity,
            wait=loop_wait,
            gc_slack=GcInSlack(cfg.loop.gc_every, round(cfg.loop.gc_margin * 1e9),
                               cfg.loop.rate_hz) if cfg.loop.gc_in_slack else None,
        )
        self.period = 1.0 / cfg.loop.rate_hz
        self._commands: queue.SimpleQueue[tuple[Command | RunOnLoop, Future[object]]] = \
            queue.SimpleQueue()
        #: set by the first cycle that finds no condition (readiness)
        self.healthy_cycle = threading.Event()
        self.sample_hook: SampleHook | None = None
        self.cycles = 0
        self.last: CycleResult | None = None
        #: the cycle that produced :attr:`last`
        self.last_cycle = 0
        #: perf_counter_ns of t = 0 (set when the daemon starts the loop)
        self.t0_ns = 0
        self._status_text = ""
        self.commands_sent = {"speed_j": 0, "stop": 0, "twist": 0}
        self.limiter = RateLimiter(1.0)
        #: a request/reply sensor's "ask for the next sample" (CAN), sent at the end of
        #: each cycle so the answer comes in the loop's idle time; None: it streams
        self._sensor_request: Callable[[], None] | None = getattr(
            devices.sensor, "request_next", None)
        self._request_at_start = cfg.loop.sensor_request == "start"
        #: a sensor in a process of its own: told the loop's grid in the first cycle
        self._phase_sensor: Callable[[int, float], None] | None = getattr(
            devices.sensor, "set_phase", None)
        #: the newest tool-load calibration (`mmctl calibrate tool`) and its part of
        #: each cycle while it runs (set by :class:`~mmctl.runtime.calibrate.Calibrations`)
        self.calibration: ToolCalibration | None = None
        self.calibration_cycle: CalibrationCycle | None = None

    @property
    def safety(self) -> Safety:
        """The safety state machine's value as the last cycle left it."""
        return self.ustate.safety

    @property
    def speed_scaling(self) -> float:
        """The arm's speed scaling in the last sample (speed slider x reduced mode)."""
        return self.ustate.speed_scaling

    def enabling_state(self) -> str | None:
        """The enabling switch as the last cycle read it: "held", "released",
        "disagree" (its contacts differ), or None (no enabling switch configured)."""
        if not self.cfg.enabling.inputs:
            return None
        return {True: "held", False: "released", None: "disagree"}[self.ustate.enabling.held]

    def status_line(self) -> str:
        """The one-line status systemd shows (``state=... mode=... [fault=...]``)."""
        s = self.safety
        fault = f" fault={s.latched.value}" if s.latched else ""
        return f"state={s.state.value} mode={self.core.mode}{fault}"

    def update_status(self) -> None:
        """Tell systemd the status line when it changed."""
        text = self.status_line()
        if text != self._status_text:
            self._status_text = text
            self.notifier.status(text)

    # -- the inbox ----------------------------------------------------------------------
    # a device whose link the operator's enable is reconnecting (the arm, the sensor)
    # or enabling (the base) off the loop thread: the loop leaves it alone and counts
    # it as not read.  The update's own state says so (UpdateState.leased: its
    # BeginEnable and EnableCheck lease a link, the enable's Release gives it back);
    # no flag crosses threads.
    @property
    def arm_busy(self) -> bool:
        return "arm" in self.ustate.leased

    @property
    def sensor_busy(self) -> bool:
        return "sensor" in self.ustate.leased

    @property
    def base_busy(self) -> bool:
        return "base" in self.ustate.leased

    def submit(self, cmd: Command | RunOnLoop) -> Future[object]:
        """Queue ``cmd`` for the loop's next cycle (the update's inbox)."""
        fut: Future[object] = Future()
        self._commands.put((cmd, fut))
        return fut

    @overload
    def on_loop(self, cmd: Command | RunOnLoop, timeout: float | None = None) -> object: ...

    @overload
    def on_loop(self, cmd: Callable[[], T], timeout: float | None = None) -> T: ...

    def on_loop(self, cmd: Command | RunOnLoop | Callable[[], object],
                timeout: float | None = None) -> object:
        """Hand ``cmd`` to the loop's next cycle and wait for its reply (a plain function
        is a :class:`RunOnLoop`); without a loop thread (tests stepping the daemon with
        :meth:`step_once`) apply it right here.

        A command the loop has not taken within ``timeout`` [s] (default
        ``daemon.command_timeout``) is cancelled, so a command reported as failed never
        takes effect later; one it has taken is waited for (it ends within its cycle).
        """
        if not isinstance(cmd, (RunOnLoop, *COMMAND_TYPES)):
            cmd = RunOnLoop(cmd)
        if not self.loop.running:
            if self.loop.error is not None or self.stop_requested.is_set():
                raise IpcError("the control loop is not running")
            if isinstance(cmd, RunOnLoop):
                return cmd.fn()
            return self.apply_now(cmd)
        fut = self.submit(cmd)
        try:
            try:
                return fut.result(self.cfg.daemon.command_timeout if timeout is None else timeout)
            except FutureTimeout:
                if fut.cancel():
                    raise IpcError("the control loop did not take the command in time "
                                   "(not applied)") from None
            return fut.result()  # started: ends within its cycle
        finally:
            # the future holds the command's exception, whose traceback holds this frame:
            # without this, that cycle keeps the caller's frames (a control connection's
            # socket among them) until a full garbage collection
            del fut

    @property
    def last_conditions(self) -> Mapping[FaultCause, Mapping[str, object]]:
        """The conditions the newest update saw (a read-only view of its safety state)."""
        return self.ustate.safety.active

    def step_once(self, overrun: bool = False) -> None:
        """Run one cycle on the calling thread (tests and tools that drive the daemon
        without the loop thread); ``overrun`` pretends the miss budget is exhausted."""
        now = time.perf_counter_ns()
        self.cycle(Tick(self.cycles, now, now, self.loop.period_ns, 0, 0, overrun))

    def cycle(self, tick: Tick) -> None:
        """One control period (loop thread)."""
        inbox: list[tuple[Command, Future[object]]] = []
        try:
            inbox = self._take_inbox()
            self._cycle(tick, inbox)
        except Exception as exc:  # any bug in a cycle: stop the robot, log, go on
            error = repr(exc)
            # a condition like any other: enable is refused while cycles keep failing
            self.ustate, stop, events = self.update.cycle_failed(self.ustate, error)
            if self.input_log is not None:
                self.input_log.outcome(tick.index, "cycle_failed", {"error": error})
            log_events(events, self.limiter)
            if stop:
                self.send_stop()
                self.update_status()
            self._answer_after_failure(inbox, exc)
            suppressed = self.limiter.allow("cycle_failed")
            if suppressed is not None:
                log.exception("cycle_failed", error=error, suppressed=suppressed)
        self.cycles += 1
        if self.notifier.watchdog_interval is not None:
            self.notifier.watchdog_tick(tick.wake_ns)

    def _answer_after_failure(self, inbox: list[tuple[Command, Future[object]]],
                              exc: Exception) -> None:
        """A failed cycle's inbox: a lease its update gave or took back stands, so
        that command keeps the update's reply (the caller then does the link's work and
        gives the link back, as after any cycle); every other command fails with
        ``exc``.  No caller is left waiting."""
        events, self._unanswered = self._unanswered, ()
        for ev in events:
            if (isinstance(ev, Reply) and isinstance(inbox[ev.index][0], LEASING)
                    and not inbox[ev.index][1].done()):
                try:
                    self._reply(inbox[ev.index], ev)
                except Exception:
                    log.exception("reply_failed", command=type(inbox[ev.index][0]).__name__)
        for _, fut in inbox:
            if not fut.done():
                fut.set_exception(exc)

    def _take_inbox(self) -> list[tuple[Command, Future[object]]]:
        """The update's commands queued since the last cycle (at most ``inbox_size``);
        the runtime's own (:class:`RunOnLoop`: a trial's hook, a calibration's start or
        abort) run here, first."""
        out: list[tuple[Command, Future[object]]] = []
        while len(out) < self.inbox_size:
            try:
                cmd, fut = self._commands.get_nowait()
            except queue.Empty:
                break
            if not fut.set_running_or_notify_cancel():
                continue
            if isinstance(cmd, RunOnLoop):
                try:
                    fut.set_result(cmd.fn())
                except Exception as exc:  # noqa: BLE001 -- handed to the waiting client
                    fut.set_exception(exc)
                finally:  # the exception's traceback holds this frame: no cycle through it
                    del fut
                continue
            out.append((cmd, fut))
        return out

    # -- read ---------------------------------------------------------------------------
    def _read_one(self, name: str, fn: Callable[[], T], conditions: Conditions) -> T | None:
        try:
            return fn()
        except SafetyFault as exc:
            conditions.setdefault(exc.cause, {"device": name, **exc.details})
        except TransportError as exc:
            conditions.setdefault(_LINK_CAUSE[name], {"device": name, "error": str(exc)})
        return None

    def _read(self, tick: Tick, row: int) -> Readings:
        conditions: Conditions = {}
        dev = self.devices
        clock = time.perf_counter_ns
        phase = self.phase_ns
        if self._request_at_start:  # the sensor answers while the arm and the base are read
            self._request_sensor(row)
        t0 = clock()
        arm = None
        inputs = 0
        if self.arm_busy:
            conditions[FaultCause.ARM_DISCONNECTED] = {"device": "arm", "why": "reconnecting"}
        else:
            arm = self._read_one("arm", dev.arm.read_state, conditions)
            if arm is not None and self._inputs:
                try:
                    for i in self._inputs:
                        if dev.arm.digital_input(i):
                            inputs |= 1 << i
                except (SafetyFault, TransportError) as exc:
                    conditions.setdefault(FaultCause.ARM_DISCONNECTED,
                                          {"device": "arm", "error": str(exc)})
                    arm = None
        t1 = clock()
        odom = None if self.base_busy else self._read_one("base", dev.base.read_odometry,
                                                           conditions)
        t2 = clock()
        wrench = None
        if self.sensor_busy:
            conditions[FaultCause.SENSOR_LINK] = {"device": "sensor", "why": "reconnecting"}
        else:
            wrench = self._read_one("sensor", dev.sensor.read, conditions)
        t3 = clock()
        phase[0, row], phase[2, row], phase[1, row] = t1 - t0, t2 - t1, t3 - t2
        calib = self.calibration
        self.readings = Readings(
            tick.index, self.core.clock(), tick.period, arm, wrench, odom, inputs, conditions,
            (tick.consecutive_misses, tick.total_misses) if tick.overrun else None,
            tick.consecutive_misses, self.arm_busy, calib is not None and calib.running)
        return self.readings

    # -- the cycle ----------------------------------------------------------------------
    def _cycle(self, tick: Tick, inbox: list[tuple[Command, Future[object]]]) -> None:
        row = self.cycles % self.phase_ns.shape[1]
        phase = self.phase_ns
        phase[3, row] = phase[4, row] = phase[5, row] = 0
        if self._phase_sensor is not None:  # once: the sensor's process polls on our grid
            self._phase_sensor(tick.deadline_ns, tick.period)
            self._phase_sensor = None
        readings = self._read(tick, row)
        t0 = time.perf_counter_ns()
        taken = [c for c, _ in inbox]
        state, commands, events = self.update(self.ustate, readings, taken)
        self.step_ns[self.cycles % self.step_ns.shape[0]] = time.perf_counter_ns() - t0
        if events:  # logged before the new state is seen: a fault seen has its event
            log_events(events, self.limiter)
        self.ustate = state
        self._unanswered = events
        if self.input_log is not None:
            self.input_log.append(readings, taken, commands)
        self.core.cstate = state.chain
        result = commands.result
        if result is not None:  # this cycle's numbers (none: a device was not read)
            self.last, self.last_cycle = result, self.cycles
        calib = self.calibration
        if readings.calibrating and calib is not None:
            commands = self._calibration_commands(calib, commands, readings)
            result = commands.result
            if result is not None:
                self.last, self.last_cycle = result, self.cycles
        if commands.stop:  # never delayed by telemetry
            self.send_stop()
            self.update_status()
            commands = commands._replace(stop=False)
        # telemetry before the motion commands: their CAN frames wake the device threads,
        # which then want the GIL
        hook = self.sample_hook
        if hook is not None and result is not None:
            t0 = time.perf_counter_ns()
            hook(result, tick.index, (tick.deadline_ns - self.t0_ns) * 1e-9,
                 self.ustate.safety.state.value)
            self.hook_ns[self.cycles % self.hook_ns.shape[0]] = time.perf_counter_ns() - t0
        self._write(commands, row)
        self._unanswered = ()
        self._after(events, inbox)
        if (not state.safety.active and self.devices.connected
                and not self.healthy_cycle.is_set()):
            self.healthy_cycle.set()  # once: Event.set takes a lock and notifies
        if not self._request_at_start:
            self._request_sensor(row)

    def _calibration_commands(self, calib: ToolCalibration, c: Commands,
                              r: Readings) -> Commands:
        """A tool-load calibration's cycle: its speedJ in place of the controller's (the
        update holds the controller and the base at rest while it runs), or the stop
        when it aborts (its disarm reaches the next update as a Disable command)."""
        if self.calibration_cycle is None:
            return c
        result = self.calibration_cycle(calib, c.result, r.wrench, self.ustate.arm_repeats)
        if c.stop or not self.ustate.safety.armed or result is None or c.result is None:
            return c._replace(result=result)
        if not calib.running:  # aborted in this cycle: the stop went out, no motion
            return Commands(False, None, None, False, result)
        return Commands(False, result.qd_arm, c.twist, False, result)

    # -- write --------------------------------------------------------------------------
    def _write(self, c: Commands, row: int) -> None:
        clock = time.perf_counter_ns
        if c.stop:
            self.send_stop()
            self.update_status()
        elif c.qd_arm is not None:
            t0 = clock()
            try:
                self.devices.arm.speed_j(c.qd_arm, self.cfg.arm.speedj_acceleration,
                                         self.period)
                self.commands_sent["speed_j"] += 1
            except (SafetyFault, TransportError) as exc:
                self._write_failed("arm", FaultCause.ARM_DISCONNECTED, exc)
                self._kick_arm_watchdog()  # no speedJ went out: the watchdog as ever
                return
            t1 = clock()
            self.phase_ns[3, row] = t1 - t0
            if c.twist is not None:
                try:
                    self.devices.base.send_twist(*c.twist)
                    self.commands_sent["twist"] += 1
                    self.phase_ns[4, row] = clock() - t1
                except (SafetyFault, TransportError) as exc:
                    self._write_failed("base", FaultCause.BASE_LINK, exc)
        if c.kick:
            t0 = clock()
            self._kick_arm_watchdog()
            self.phase_ns[3, row] = clock() - t0

    def _write_failed(self, device: str, default: FaultCause,
                      exc: SafetyFault | TransportError) -> None:
        """A command that failed: the write's one reflex.  The fault latches in this
        cycle (the update's own pure transition,
        :meth:`~mmctl.control.update.Update.write_failed`) and the stop goes out at
        once; the next reads find the cause if it persists.  The input log records the
        failure as the transition's input (replay runs the same transition)."""
        cause = exc.cause if isinstance(exc, SafetyFault) else default
        details = {"device": device,
                   **(exc.details if isinstance(exc, SafetyFault) else {"error": str(exc)})}
        self.ustate, events = self.update.write_failed(self.ustate, cause, details)
        if self.input_log is not None:
            self.input_log.outcome(self.readings.index if self.readings else self.cycles,
                                   "write_failed", {"cause": cause.value, "details": details})
        log_events(events, self.limiter)
        self.send_stop()

    def _kick_arm_watchdog(self) -> None:
        """A cycle without speedJ still feeds the controller's RTDE watchdog: only a
        daemon that stops cycling gets the arm stopped by the controller."""
        try:
            self.devices.arm.kick_watchdog()
        except (SafetyFault, TransportError) as exc:  # the next read names the cause
            suppressed = self.limiter.allow("arm_watchdog_kick_failed")
            if suppressed is not None:
                log.warning("arm_watchdog_kick_failed", error=str(exc), suppressed=suppressed)

    def send_stop(self) -> None:
        """The stop commands, from the loop thread: never waits for the wheels to rest
        (each drive ramps down before its power stage goes off, 0x605B)."""
        self.devices.stop(self.cfg.arm.stop_deceleration, disable_base=True,
                          arm=not self.arm_busy, wait=False)
        self.commands_sent["stop"] += 1

    def _request_sensor(self, row: int) -> None:
        """Ask a request/reply sensor for its next sample (``loop.sensor_request``)."""
        if self._sensor_request is None or self.sensor_busy:
            return
        t0 = time.perf_counter_ns()
        try:
            self._sensor_request()
        except TransportError as exc:  # the next read finds no reply: stale, a fault
            suppressed = self.limiter.allow("sensor_request_failed")
            if suppressed is not None:
                log.warning("sensor_request_failed", error=str(exc), suppressed=suppressed)
        self.phase_ns[5, row] = time.perf_counter_ns() - t0

    def apply_now(self, cmd: Command, fresh: bool = True) -> object:
        """Without a loop thread (tests and tools stepping the daemon by hand): the
        update takes ``cmd`` at once (no control step), judged on a fresh arm and sensor
        sample (``fresh``; else the last cycle's) and the last cycle's other readings,
        and the stop goes out when it says so; returns the reply (or raises its error)."""
        if self.readings is None:
            raise MmctlError("refused: no control cycle has run yet")
        if not fresh or isinstance(cmd, Release):  # a Release is judged on nothing
            return self._apply_on(self.readings, cmd)
        # the arm and the sensor read again (a reconnect may have just brought them back),
        # the rest as the last cycle saw it
        conditions: Conditions = {c: d for c, d in self.readings.conditions.items()
                                  if not c.value.startswith(("arm_", "sensor_"))}
        arm = None if self.arm_busy else self._read_one("arm", self.devices.arm.read_state,
                                                         conditions)
        wrench = None
        if not self.sensor_busy:
            try:
                wrench = self._read_one("sensor", self.devices.sensor.read, conditions)
            except Exception as exc:  # noqa: BLE001 -- as a cycle would: a condition
                conditions[FaultCause.INTERNAL] = {"error": repr(exc)}
        readings = self.readings._replace(arm=arm, wrench=wrench, conditions=conditions,
                                          misses=self.loop.consecutive_misses)
        return self._apply_on(readings, cmd)

    def _apply_on(self, readings: Readings, cmd: Command) -> object:
        fut: Future[object] = Future()
        fut.set_running_or_notify_cancel()
        state, stop, events = self.update.apply(self.ustate, readings, [cmd])
        log_events(events, self.limiter)
        self.ustate = state
        self.core.cstate = state.chain
        if stop:
            self.send_stop()
        self._after(events, [(cmd, fut)])
        try:
            return fut.result(0)
        finally:
            del fut

    # -- after the write: events and replies --------------------------------------------
    def _after(self, events: tuple[object, ...], inbox: list[tuple[Command, Future[object]]]) -> None:
        if not events:
            return
        status = False
        for ev in events:
            if isinstance(ev, Reply):
                self._reply(inbox[ev.index], ev)
            elif isinstance(ev, Switched):
                log.info("switch", new=ev.new, source=ev.source)
                status = True
            elif isinstance(ev, Changed):
                self._log_changed(ev)
                status = True
            elif isinstance(ev, (FaultRaised, StateChanged)):
                status = True
        if status:
            self.update_status()

    def _log_changed(self, ev: Changed) -> None:
        if ev.what == "profile":
            log.info("profile", old=ev.old, new=ev.new, caps=self.core.caps)
        else:
            log.info(ev.what, old=ev.old, new=ev.new)

    def _reply(self, item: tuple[Command, Future[object]], ev: Reply) -> None:
        """Hand one command's answer to its caller, after the runtime's part of it (on
        the loop thread, so the loop's next read already sees it)."""
        cmd, fut = item
        if ev.error is None:
            match cmd:
                case EnableFinish() if ev.value == "armed":
                    self.loop.reset_misses()
                case Install(cfg=cfg, controller=controller, key=key):
                    self.core.installed(cfg, controller, key)
                case _:
                    pass
            fut.set_result(ev.value)
        else:
            fut.set_exception(ev.error)
