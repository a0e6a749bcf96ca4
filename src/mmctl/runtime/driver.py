"""The cycle driver: one control period on the loop thread (:meth:`CycleDriver.cycle`):
queued operator commands, the device reads (timed per device, :data:`PHASES`), the pure
control cycle, the safety monitor, the telemetry hook, the motion or stop commands.  A
part of :class:`~mmctl.runtime.daemon.Daemon`."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import structlog

from mmctl.errors import FaultCause, MmctlError, SafetyFault, TransportError
from mmctl.runtime.core import CycleResult
from mmctl.runtime.loop import Tick

log = structlog.get_logger("mmctl.daemon")

_LINK_CAUSE = {"arm": FaultCause.ARM_DISCONNECTED, "sensor": FaultCause.SENSOR_LINK,
               "base": FaultCause.BASE_LINK}

#: The device phases of a cycle timed in :attr:`Daemon.phase_ns` (rows, in this order).
PHASES = ("arm_read", "sensor_read", "base_read", "arm_send", "base_send", "sensor_request")


if TYPE_CHECKING:
    from mmctl.runtime.parts import DaemonParts as _Parts
else:
    _Parts = object


class CycleDriver(_Parts):
    """The loop thread's cycle (see the module docstring)."""

    def step_once(self, overrun: bool = False) -> None:
        """Run one cycle on the calling thread (tests and tools that drive the daemon
        without the loop thread); ``overrun`` pretends the miss budget is exhausted."""
        now = time.perf_counter_ns()
        self.cycle(Tick(self.cycles, now, now, self.loop.period_ns, 0, 0, overrun))

    def cycle(self, tick: Tick) -> None:
        """One control period (loop thread)."""
        try:
            self._drain_commands()
            self._cycle(tick)
        except Exception as exc:  # any bug in a cycle: stop the robot, log, go on
            # a condition like any other: enable is refused while cycles keep failing
            failed = {FaultCause.INTERNAL: {"error": repr(exc)}}
            self.last_conditions = failed
            if self.safety.update(failed):
                self._send_stop()
                self._update_status()
            suppressed = self._limiter.allow("cycle_failed")
            if suppressed is not None:
                log.exception("cycle_failed", error=repr(exc), suppressed=suppressed)
        self.cycles += 1
        if self.notifier.watchdog_interval is not None:
            self.notifier.watchdog_tick(tick.wake_ns)

    def _drain_commands(self) -> None:
        while True:
            try:
                fn, fut = self._commands.get_nowait()
            except queue.Empty:
                return
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn())
            except Exception as exc:  # noqa: BLE001 -- handed to the waiting client
                fut.set_exception(exc)
            finally:  # the exception's traceback holds this frame: no cycle through it
                del fut

    def _read(self, name: str, fn: Callable[[], Any],
              conditions: dict[FaultCause, dict[str, Any]]) -> Any:
        try:
            return fn()
        except SafetyFault as exc:
            conditions.setdefault(exc.cause, {"device": name, **exc.details})
        except TransportError as exc:
            conditions.setdefault(_LINK_CAUSE[name], {"device": name, "error": str(exc)})
        return None

    def _cycle(self, tick: Tick) -> None:
        conditions: dict[FaultCause, dict[str, Any]] = {}
        dev = self.devices
        clock = time.perf_counter_ns
        row = self.cycles % self.phase_ns.shape[1]
        phase = self.phase_ns
        phase[3, row] = phase[4, row] = phase[5, row] = 0
        request_first = self._request_at_start
        if request_first:  # the sensor answers while the arm and the base are read
            self._request_sensor(row)
        t0 = clock()
        if self._arm_busy:
            conditions[FaultCause.ARM_DISCONNECTED] = {"device": "arm", "why": "reconnecting"}
            arm = None
        else:
            arm = self._read("arm", dev.arm.read_state, conditions)
        t1 = clock()
        if self._base_busy:
            conditions[FaultCause.BASE_LINK] = {"device": "base", "why": "enabling"}
            odom = None
        else:
            odom = self._read("base", dev.base.read_odometry, conditions)
        t2 = clock()
        wrench = self._read("sensor", dev.sensor.read, conditions)
        t3 = clock()
        phase[0, row], phase[2, row], phase[1, row] = t1 - t0, t2 - t1, t3 - t2
        if tick.overrun:
            conditions[FaultCause.LOOP_OVERRUN] = {
                "consecutive": tick.consecutive_misses, "total": tick.total_misses}
        self._poll_button()
        if arm is not None:
            self.speed_scaling = arm.speed_scaling
            if arm.controller_time != self._arm_time:
                self._arm_time, self._arm_repeats = arm.controller_time, 0
            else:
                self._arm_repeats += 1
        # no motion on a pose that is no longer known: after arm.hold_cycles without a
        # new sample the command decelerates to rest (the stale fault comes later)
        held = (self._enabling_held(arm is not None, conditions)
                and self._arm_repeats < self.cfg.arm.hold_cycles)
        result: CycleResult | None = None
        # a tool-load calibration moves the arm instead of the controller, which idles
        # meanwhile (held at rest; every fault check as when disarmed)
        calib = self.calibration
        if calib is not None and not calib.running:
            calib = None
        if arm is not None and wrench is not None and odom is not None:
            t0 = time.perf_counter_ns()
            result = self.core.step(arm, wrench, odom, tick.period,
                                    active=self.safety.armed and calib is None, held=held)
            self.step_ns[self.cycles % self.step_ns.shape[0]] = time.perf_counter_ns() - t0
            if result.fault is not None:
                conditions.setdefault(result.fault, dict(result.fault_details))
            self.last = result
        stop_now = self.safety.update(conditions)
        self.last_conditions = conditions
        if stop_now:
            self._send_stop()
        if calib is not None:
            result = self._calibration_cycle(
                calib, result, wrench, self._arm_repeats < self.cfg.arm.hold_cycles)
            if result is not None:
                self.last = result
        # telemetry before the motion commands: their CAN frames wake the device threads,
        # which then want the GIL; a stop above is never delayed by it
        hook = self.sample_hook
        if hook is not None and result is not None:
            t0 = time.perf_counter_ns()
            hook(result, tick.index, (tick.deadline_ns - self._t0_ns) * 1e-9,
                 self.safety.state.value)
            self.hook_ns[self.cycles % self.hook_ns.shape[0]] = time.perf_counter_ns() - t0
        moved = False
        if not stop_now and self.safety.armed and result is not None:
            moved = self._send_motion(result, self._base_due(tick.index, result.twist))
        if not moved and not self._arm_busy:
            t0 = clock()
            self._kick_arm_watchdog()
            phase[3, row] = clock() - t0
        if not conditions and dev.connected and not self._healthy_cycle.is_set():
            self._healthy_cycle.set()  # once: Event.set takes a lock and notifies
        if stop_now:
            self._update_status()
        if not request_first:
            self._request_sensor(row)

    def _enabling_held(self, arm_read: bool, conditions: dict[FaultCause, dict[str, Any]]
                       ) -> bool:
        """Whether the enabling switch is held (True without one); its contacts are read
        from this cycle's arm sample (none: not held; the arm's own condition says why)."""
        switch = self.devices.enabling
        if switch is None:
            return True
        if not arm_read:
            return False
        try:
            return switch.held(self.core.clock())
        except SafetyFault as exc:
            conditions.setdefault(exc.cause, {"device": "enabling", **exc.details})
        except TransportError as exc:
            conditions.setdefault(FaultCause.ARM_DISCONNECTED, {"device": "arm",
                                                                "error": str(exc)})
        return False

    def _request_sensor(self, row: int) -> None:
        """Ask a request/reply sensor for its next sample (``loop.sensor_request``)."""
        if self._sensor_request is None:
            return
        t0 = time.perf_counter_ns()
        try:
            self._sensor_request()
        except TransportError as exc:  # the next read finds no reply: stale, a fault
            suppressed = self._limiter.allow("sensor_request_failed")
            if suppressed is not None:
                log.warning("sensor_request_failed", error=str(exc), suppressed=suppressed)
        self.phase_ns[5, row] = time.perf_counter_ns() - t0

    def _send_motion(self, r: CycleResult, base: bool = True) -> bool:
        """speedJ, then (every ``loop.base_divider``-th cycle: ``base``) the base twist
        (``send_twist`` re-checks the drives and sends zero itself when they fail; the
        cycle then stops the arm too, before it ends).  Returns whether speedJ went
        out (it feeds the controller's RTDE watchdog).

        speedJ goes first: the base's RPDOs + SYNC wake the CANopen threads, and a
        ur_rtde call made while they run waits for the GIL."""
        dev = self.devices
        row = self.cycles % self.phase_ns.shape[1]
        t0 = time.perf_counter_ns()
        try:
            dev.arm.speed_j(r.qd_arm, self.cfg.arm.speedj_acceleration, self.period)
            self.commands_sent["speed_j"] += 1
            t1 = time.perf_counter_ns()
            self.phase_ns[3, row] = t1 - t0
        except (SafetyFault, TransportError) as exc:
            cause = getattr(exc, "cause", FaultCause.ARM_DISCONNECTED)
            if self.safety.trip(cause, device="arm", **getattr(exc, "details", {})):
                self._send_stop()
            return False
        if not base:
            return True
        try:
            vx, vy, wz = float(r.twist[0]), float(r.twist[1]), float(r.twist[2])
            dev.base.send_twist(vx, vy, wz)
            self._twist_sent = (vx, vy, wz)
            self.commands_sent["twist"] += 1
            self.phase_ns[4, row] = time.perf_counter_ns() - t1
        except (SafetyFault, TransportError) as exc:
            cause = getattr(exc, "cause", FaultCause.BASE_LINK)
            if self.safety.trip(cause, device="base", **getattr(exc, "details", {})):
                self._send_stop()
        return True

    def _base_due(self, index: int, twist: Any) -> bool:
        """Every ``loop.base_divider``-th cycle, or at once when the twist jumped by more
        than ``loop.base_jump`` since the last one sent (a new push)."""
        last = self._twist_sent
        if index % self.cfg.loop.base_divider == 0 or last is None:
            return True
        jump = self.cfg.loop.base_jump
        jumped: bool = (abs(twist[0] - last[0]) > jump or abs(twist[1] - last[1]) > jump
                        or abs(twist[2] - last[2]) > jump)
        return jumped

    def _kick_arm_watchdog(self) -> None:
        """A cycle without speedJ still feeds the controller's RTDE watchdog: only a
        daemon that stops cycling gets the arm stopped by the controller."""
        try:
            self.devices.arm.kick_watchdog()
        except (SafetyFault, TransportError) as exc:  # the next read names the cause
            suppressed = self._limiter.allow("arm_watchdog_kick_failed")
            if suppressed is not None:
                log.warning("arm_watchdog_kick_failed", error=str(exc), suppressed=suppressed)

    def _send_stop(self) -> None:
        """The stop commands, from the loop thread: never waits for the wheels to rest
        (each drive ramps down before its power stage goes off, 0x605B)."""
        self.devices.stop(self.cfg.arm.stop_deceleration, disable_base=True,
                          arm=not self._arm_busy, wait=False)
        self._twist_sent = None
        self.commands_sent["stop"] += 1

    def _poll_button(self) -> None:
        button = self.devices.button
        if button is None:
            return
        try:
            now = button.pressed()
        except (MmctlError, OSError):
            return
        if now and not self._button_was and self.core.mode == "switch":
            self.core.toggle_switch()
            log.info("switch", new=self.core.switch, source="button")
        self._button_was = now

