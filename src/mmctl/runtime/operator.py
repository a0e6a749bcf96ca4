"""The operator's side of the daemon: the control socket's commands (a table of
handlers), enable with its arm reconnect, disable, mode, switch, tare, and running a
command on the loop thread (:meth:`OperatorCommands._on_loop`).  A part of
:class:`~mmctl.runtime.daemon.Daemon`, which composes it with the lifecycle and the
cycle driver (:mod:`mmctl.runtime.driver`)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, Any

import structlog

from mmctl.control.params import SETTABLE, get_value
from mmctl.control.update import (
    BeginEnable,
    Command,
    Disable,
    EnableCheck,
    EnableFinish,
    Install,
    SetMode,
    SetProfile,
    SetSwitch,
    Tare,
)
from mmctl.errors import IpcError, MmctlError, SafetyFault
from mmctl.runtime.driver import RunOnLoop
from mmctl.runtime.ipc import Peer

log = structlog.get_logger("mmctl.daemon")

COMMAND_TYPES = (BeginEnable, Disable, EnableCheck, EnableFinish, Install, SetMode,
                 SetProfile, SetSwitch, Tare)
#: [s] the least an enable's last step (on the loop thread) is given to be taken.
_FINISH_MIN = 0.5


if TYPE_CHECKING:
    from mmctl.runtime.daemon import SampleHook
    from mmctl.runtime.parts import DaemonParts as _Parts
else:
    _Parts = object


class OperatorCommands(_Parts):
    """The operator's commands (see the module docstring)."""

    def submit(self, cmd: Command | RunOnLoop) -> Future[Any]:
        """Queue ``cmd`` for the loop's next cycle (the update's inbox)."""
        fut: Future[Any] = Future()
        self._commands.put((cmd, fut))
        return fut

    def call(self, cmd: str, **args: Any) -> Any:
        """Run one control command (same names as the socket's) and wait for its result."""
        return self.handle({"cmd": cmd, **args}, None)

    def _on_loop(self, cmd: Command | RunOnLoop | Callable[[], Any],
                 timeout: float | None = None) -> Any:
        """Hand ``cmd`` to the loop's next cycle and wait for its reply (a plain function
        is a :class:`RunOnLoop`); without a loop thread (tests stepping the daemon with
        :meth:`step_once`) queue it and run one cycle right here.

        A command the loop has not taken within ``timeout`` [s] (default
        ``daemon.command_timeout``) is cancelled, so a command reported as failed never
        takes effect later; one it has taken is waited for (it ends within its cycle).
        """
        if not isinstance(cmd, (RunOnLoop, *COMMAND_TYPES)):
            cmd = RunOnLoop(cmd)
        if not self.loop.running:
            if self.loop.error is not None or self._stop_requested.is_set():
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

    def handle(self, req: Mapping[str, Any], peer: Peer | None) -> Any:
        """Dispatch one control-socket request (see :mod:`mmctl.runtime.ipc`)."""
        cmd = req["cmd"]
        handler = self._handlers.get(cmd)
        if handler is None:
            raise MmctlError(f"unknown command {cmd!r}; known: {', '.join(self._handlers)}")
        return handler(req)

    def _command_table(self) -> dict[str, Callable[[Mapping[str, Any]], Any]]:
        """The control socket's commands: name -> handler of the request."""
        return {
            "status": lambda req: self.status_snapshot(),
            "enable": lambda req: self._enable_request(
                _budget(req, self.cfg.daemon.command_timeout)),
            "disable": lambda req: self._then_status(self._on_loop(Disable())),
            "mode": lambda req: self._then_status(self._on_loop(SetMode(_arg(req, "mode", str)))),
            "profile": lambda req: self._then_status(
                self._on_loop(SetProfile(_arg(req, "profile", str)))),
            "switch": lambda req: self._then_status(self._on_loop(SetSwitch(_arg(req, "to", str)))),
            "tare": self._cmd_tare,
            "stop": self._cmd_stop,
            "trial": self._cmd_trial,
            "calibrate": self._cmd_calibrate,
            "set": self._cmd_set,
            "get": self._cmd_get,
        }

    def _cmd_set(self, req: Mapping[str, Any]) -> Any:
        """A run-time parameter change (:mod:`mmctl.control.params`): validated and
        built on this worker, installed on the loop (no velocity jump), logged."""
        key = _arg(req, "key", str)
        if "value" not in req:
            raise MmctlError("'set' needs a 'value'")
        value = req["value"]
        with self._param_lock:  # one change at a time: none is lost to another
            old = get_value(self.core.cfg, key)
            cfg, controller = self.core.prepare(key, value)
            self._on_loop(Install(cfg, controller, key))
        new = get_value(cfg, key)
        log.info("param_set", key=key, old=old, new=new)
        return {"key": key, "old": old, "value": new, "status": self.status_snapshot()}

    def _cmd_get(self, req: Mapping[str, Any]) -> Any:
        key = _arg(req, "key", str)
        return {"key": key, "value": get_value(self.core.cfg, key),
                "settable": key in SETTABLE, "changed": key in self.core.changed}

    def _cmd_tare(self, req: Mapping[str, Any]) -> Any:
        self._hands_off_for_tare()
        return self._on_loop(Tare())

    def _cmd_stop(self, req: Mapping[str, Any]) -> Any:
        self.request_stop("mmctl stop")
        return {"stopping": True}

    def _cmd_trial(self, req: Mapping[str, Any]) -> Any:
        if self.telemetry is None:
            raise MmctlError("'trial' needs the telemetry service")
        return self.telemetry.command(req, self._on_loop, self._install_hook, self.core)

    def _install_hook(self, hook: SampleHook | None) -> None:
        """The loop's telemetry hook (loop thread: a trial started or stopped)."""
        self.sample_hook = hook

    def _hands_off_for_tare(self) -> None:
        """Simulated robot: the person lets go of the handle while the sensor is tared
        (an operator does; the tare must not absorb a push)."""
        if self.sim is None or self.ustate.safety.armed:
            return
        w = self.cfg.sensor.wrench
        seconds = 0.3 + 2.0 * w.tare_samples / self.cfg.loop.rate_hz
        try:
            self.sim.hold(seconds)
        except MmctlError as exc:
            log.warning("sim_hold_failed", error=str(exc))

    def _enable_request(self, budget: float) -> dict[str, Any]:
        """Operator re-arm within ``budget`` [s].  Neither step that waits for a device
        runs on the loop thread, which keeps its period meanwhile:

        1. when the sensor's link, or the arm's link or program, is lost
           (:class:`BeginEnable`), it reconnects on *this* thread (the arm's takes
           seconds) while the loop leaves that device alone;
        2. the update checks every condition but the base's (:class:`EnableCheck`:
           refused at once when one is present);
        3. the base reconnects its link if it was lost and enables on *this* thread
           (SDO round trips; a wheel still ramping down on the last stop is waited
           for), the loop leaving the base alone;
        4. the update checks again and arms (:class:`EnableFinish`), or refuses and stops.

        An enable reported as failed (refused, the reconnect failed, the budget ran out)
        never takes effect later: a base enabled for an enable that then failed is
        disabled again."""
        deadline = time.monotonic() + budget
        links = self._on_loop(BeginEnable(), budget)
        try:
            if "sensor" in links:
                self._reconnect_sensor()
        finally:
            self._sensor_busy = False
        if "arm" in links:
            with self._arm_reconnect:
                try:
                    self._reconnect_arm()
                finally:
                    self._arm_busy = False
        with self._base_enable:
            left = deadline - time.monotonic()
            if left <= 0:
                raise MmctlError(f"refused to enable: the arm's reconnect took longer than "
                                 f"{budget:g} s (daemon.command_timeout or the client's "
                                 "timeout)")
            if not self._on_loop(EnableCheck(), left):
                return self._then_status(None)  # armed already
            try:
                failure, fault = self._enable_base()
            finally:
                self._base_busy = False
            try:
                # the drives' command watchdog runs from the enable: the loop arms (and
                # sends targets) in its next cycle, whatever is left of the budget
                self._on_loop(EnableFinish(failure, fault),
                              max(deadline - time.monotonic(), _FINISH_MIN))
            except BaseException:
                if failure is None and not self.ustate.safety.armed:
                    self._disable_base_after_failed_enable()
                raise
        return self._then_status(None)

    def _then_status(self, _done: Any) -> dict[str, Any]:
        """A command's reply: the status, built on the caller's thread (never on the
        loop's: building it costs a share of a cycle) once the command has run."""
        return self.status_snapshot()

    def _enable_base(self) -> tuple[BaseException | None, SafetyFault | None]:
        """The caller's thread: enable the base and check its health.  Returns what went
        wrong and the cause the base names after it, for :class:`EnableFinish` to
        refuse with (the base disables itself again when its enable fails)."""
        try:
            self.devices.base.reconnect()  # a lost link: connect again (else nothing)
            self.devices.base.enable()
            self.devices.base.check()
        except (MmctlError, OSError) as exc:
            fault = exc if isinstance(exc, SafetyFault) else None
            if fault is None:
                try:
                    self.devices.base.check()  # name the cause if the base knows it
                except SafetyFault as named:
                    fault = named
                except (MmctlError, OSError):
                    pass
            return exc, fault
        return None, None

    def _disable_base_after_failed_enable(self) -> None:
        """The base was enabled for an enable that did not arm: switch it off again."""
        try:
            self.devices.base.disable(wait=False)
        except (MmctlError, OSError) as exc:
            log.warning("base_enable_undo_failed", error=str(exc))

    def _reconnect_sensor(self) -> None:
        """Enable after the sensor's link was lost (off the loop thread, the loop leaving
        the sensor alone): connect again (the transport re-reads its calibration)."""
        log.info("sensor_reconnecting")
        try:
            self.devices.sensor.reconnect()
        except (MmctlError, OSError) as exc:
            log.warning("sensor_reconnect_failed", error=str(exc))
            raise MmctlError(f"refused to enable: the sensor did not reconnect ({exc})") from None
        log.info("sensor_reconnected")

    def _reconnect_arm(self) -> None:
        """Enable after a lost link / stopped program (off the loop thread, the loop
        leaving the arm alone): reconnect, which re-uploads the control script (~1-2 s;
        ur_rtde's constructors and destructors hold the GIL for parts of it)."""
        log.info("arm_reconnecting", causes=sorted(
            c.value for c in self.ustate.safety.active if c.value.startswith("arm_")))
        try:
            self.devices.arm.reconnect()
        except (MmctlError, OSError) as exc:
            log.warning("arm_reconnect_failed", error=str(exc))
            raise MmctlError(f"refused to enable: the arm did not reconnect ({exc})") from None
        log.info("arm_reconnected")


def _budget(req: Mapping[str, Any], default: float) -> float:
    """How long [s] a command may take: ``default``, shortened to 80 % of the client's
    own ``timeout_s`` when it sends one (the rest is its margin for the reply), so a
    client never reports a failure that the daemon then carries out."""
    client = req.get("timeout_s")
    if isinstance(client, (int, float)) and not isinstance(client, bool) \
            and math.isfinite(client) and client > 0:
        return min(default, 0.8 * float(client))
    return default


def _arg(req: Mapping[str, Any], key: str, typ: type) -> Any:
    val = req.get(key)
    if not isinstance(val, typ):
        raise MmctlError(f"request {req.get('cmd')!r} needs {key!r} ({typ.__name__})")
    return val
