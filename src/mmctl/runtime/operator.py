"""The operator's side of the daemon: the control socket's commands (a table of
handlers), enable with its links' reconnects, disable, mode, switch, tare.  Every
decision is the update's (a command into the loop's inbox through
:meth:`LoopRuntime.on_loop <mmctl.runtime.driver.LoopRuntime.on_loop>`); what runs here,
on the request's thread, is the device work an enable needs, which must never run on
the loop thread.  :class:`~mmctl.runtime.daemon.Daemon` composes it with the lifecycle,
the loop's runtime (:mod:`mmctl.runtime.driver`) and the tool-load calibration
(:mod:`mmctl.runtime.calibrate`)."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING, Any, TypeVar

import structlog

from mmctl.control.params import SETTABLE, get_value
from mmctl.control.safety import EnableRefused, plain
from mmctl.control.update import (
    BeginEnable,
    Disable,
    EnableCheck,
    EnableFinish,
    Install,
    Release,
    SetMode,
    SetProfile,
    SetSwitch,
    Tare,
)
from mmctl.errors import MmctlError, SafetyFault
from mmctl.runtime.calibrate import Calibrations
from mmctl.runtime.driver import LoopRuntime, SampleHook
from mmctl.runtime.ipc import Peer

log = structlog.get_logger("mmctl.daemon")

#: [s] the least an enable's last step (on the loop thread) is given to be taken.
_FINISH_MIN = 0.5


T = TypeVar("T")

if TYPE_CHECKING:
    from mmctl.runtime.sim_link import SimLink
    from mmctl.telemetry.service import TelemetryService


class Operator:
    """The operator's commands (see the module docstring).

    runtime: the loop's; calibrations: the ``calibrate`` requests' handler; status: the
    control socket's status snapshot (a command's reply); request_stop: ask the daemon
    to shut down; sim: the simulated robot's link (the person lets go for a tare), or
    None; telemetry: the telemetry service (``trial``), or None.
    """

    def __init__(self, runtime: LoopRuntime, calibrations: Calibrations, *,
                 status: Callable[[], dict[str, object]], request_stop: Callable[[str], None],
                 sim: SimLink | None = None, telemetry: TelemetryService | None = None):
        self.rt = runtime
        self.cfg = runtime.cfg
        self.calibrations = calibrations
        self.status_snapshot = status
        self.request_stop = request_stop
        self.sim = sim
        self.telemetry = telemetry
        self._param_lock = threading.Lock()  # `mmctl set`: one change at a time
        #: held by an arm reconnect (the daemon's shutdown never closes the arm under it)
        self.arm_reconnect = threading.Lock()
        #: held by an enable from its checks to its end: one enable at a time, and the
        #: daemon's shutdown waits for it before it stops the devices
        self.base_enable = threading.Lock()
        self._handlers = self._command_table()

    def call(self, cmd: str, **args: object) -> Any:
        """Run one control command (same names as the socket's) and wait for its result."""
        return self.handle({"cmd": cmd, **args}, None)

    def handle(self, req: Mapping[str, object], peer: Peer | None = None) -> object:
        """Dispatch one control-socket request (see :mod:`mmctl.runtime.ipc`)."""
        cmd = str(req["cmd"])
        handler = self._handlers.get(cmd)
        if handler is None:
            raise MmctlError(f"unknown command {cmd!r}; known: {', '.join(self._handlers)}")
        return handler(req)

    def _command_table(self) -> dict[str, Callable[[Mapping[str, object]], object]]:
        """The control socket's commands: name -> handler of the request."""
        return {
            "status": lambda req: self.status_snapshot(),
            "enable": lambda req: self._enable_request(
                _budget(req, self.cfg.daemon.command_timeout)),
            "disable": lambda req: self._then_status(self.rt.on_loop(Disable())),
            "mode": lambda req: self._then_status(self.rt.on_loop(SetMode(_arg(req, "mode", str)))),
            "profile": lambda req: self._then_status(
                self.rt.on_loop(SetProfile(_arg(req, "profile", str)))),
            "switch": lambda req: self._then_status(self.rt.on_loop(SetSwitch(_arg(req, "to", str)))),
            "tare": self._cmd_tare,
            "stop": self._cmd_stop,
            "trial": self._cmd_trial,
            "calibrate": self.calibrations.command,
            "set": self._cmd_set,
            "get": self._cmd_get,
        }

    def _cmd_set(self, req: Mapping[str, object]) -> object:
        """A run-time parameter change (:mod:`mmctl.control.params`): validated and
        built on this worker, installed on the loop (no velocity jump), logged."""
        key = _arg(req, "key", str)
        if "value" not in req:
            raise MmctlError("'set' needs a 'value'")
        value = req["value"]
        with self._param_lock:  # one change at a time: none is lost to another
            old = get_value(self.rt.core.cfg, key)
            cfg, controller = self.rt.core.prepare(key, value)
            self.rt.on_loop(Install(cfg, controller, key))
        new = get_value(cfg, key)
        log.info("param_set", key=key, old=old, new=new)
        return {"key": key, "old": old, "value": new, "status": self.status_snapshot()}

    def _cmd_get(self, req: Mapping[str, object]) -> object:
        key = _arg(req, "key", str)
        return {"key": key, "value": get_value(self.rt.core.cfg, key),
                "settable": key in SETTABLE, "changed": key in self.rt.core.changed}

    def _cmd_tare(self, req: Mapping[str, object]) -> object:
        self._hands_off_for_tare()
        return self.rt.on_loop(Tare())

    def _cmd_stop(self, req: Mapping[str, object]) -> object:
        self.request_stop("mmctl stop")
        return {"stopping": True}

    def _cmd_trial(self, req: Mapping[str, object]) -> object:
        if self.telemetry is None:
            raise MmctlError("'trial' needs the telemetry service")
        return self.telemetry.command(req, self.rt.on_loop, self._install_hook, self.rt.core)

    def _install_hook(self, hook: SampleHook | None) -> None:
        """The loop's telemetry hook (loop thread: a trial started or stopped)."""
        self.rt.sample_hook = hook

    def _hands_off_for_tare(self) -> None:
        """Simulated robot: the person lets go of the handle while the sensor is tared
        (an operator does; the tare must not absorb a push)."""
        if self.sim is None or self.rt.ustate.safety.armed:
            return
        w = self.cfg.sensor.wrench
        seconds = 0.3 + 2.0 * w.tare_samples / self.cfg.loop.rate_hz
        try:
            self.sim.hold(seconds)
        except MmctlError as exc:
            log.warning("sim_hold_failed", error=str(exc))

    def _enable_request(self, budget: float) -> dict[str, object]:
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
        try:
            return self._enable(budget)
        except EnableRefused as exc:  # what the conditions say, for whoever reads the log
            log.warning("enable_refused", conditions={
                k: {d: plain(v) for d, v in det.items()} for k, det in exc.details.items()})
            raise

    def _enable(self, budget: float) -> dict[str, object]:
        deadline = time.monotonic() + budget
        links = self.rt.on_loop(BeginEnable(), budget)
        assert isinstance(links, tuple)  # (BeginEnable's reply: the links' names)
        try:  # every link leased is given back, whichever reconnect failed
            try:
                if "sensor" in links:
                    self._reconnect_sensor()
            finally:  # (before the arm's reconnect, which takes seconds)
                if "sensor" in links:
                    self._release("sensor")
            if "arm" in links:
                with self.arm_reconnect:
                    self._reconnect_arm()
        finally:
            if "arm" in links:
                self._release("arm")
        with self.base_enable:
            left = deadline - time.monotonic()
            if left <= 0:
                raise MmctlError(f"refused to enable: the arm's reconnect took longer than "
                                 f"{budget:g} s (daemon.command_timeout or the client's "
                                 "timeout)")
            if not self.rt.on_loop(EnableCheck(), left):
                return self._then_status(None)  # armed already
            try:
                failure, fault = self._enable_base()
            finally:
                # in the inbox before the EnableFinish: the same cycle takes both
                self._release("base", wait=False)
            try:
                # the drives' command watchdog runs from the enable: the loop arms (and
                # sends targets) in its next cycle, whatever is left of the budget
                self.rt.on_loop(EnableFinish(failure, fault),
                              max(deadline - time.monotonic(), _FINISH_MIN))
            except BaseException:
                if failure is None and not self.rt.ustate.safety.armed:
                    self._disable_base_after_failed_enable()
                raise
        return self._then_status(None)

    def _release(self, link: str, wait: bool = True) -> None:
        """Give ``link`` back to the loop once its work ended, and (``wait``) wait until
        the loop has taken it (its next cycle reads the link: the enable's check judges
        that read).  A loop that does not take it (stopping) is no error here: the
        enable's next step then fails with the reason."""
        if not self.rt.loop.running:  # stepped by hand: the update takes it at once
            try:
                self.rt.on_loop(Release(link))
            except MmctlError as exc:
                log.warning("link_release_not_taken", link=link, error=str(exc))
            return
        fut = self.rt.submit(Release(link))
        if not wait:
            return
        try:
            fut.result(self.cfg.daemon.command_timeout)
        except (FutureTimeout, MmctlError) as exc:
            log.warning("link_release_not_taken", link=link, error=str(exc))

    def _then_status(self, _done: object) -> dict[str, object]:
        """A command's reply: the status, built on the caller's thread (never on the
        loop's: building it costs a share of a cycle) once the command has run."""
        return self.status_snapshot()

    def _enable_base(self) -> tuple[BaseException | None, SafetyFault | None]:
        """The caller's thread: enable the base and check its health.  Returns what went
        wrong and the cause the base names after it, for :class:`EnableFinish` to
        refuse with (the base disables itself again when its enable fails)."""
        try:
            self.rt.devices.base.reconnect()  # a lost link: connect again (else nothing)
            self.rt.devices.base.enable()
            self.rt.devices.base.check()
        except (MmctlError, OSError) as exc:
            fault = exc if isinstance(exc, SafetyFault) else None
            if fault is None:
                try:
                    self.rt.devices.base.check()  # name the cause if the base knows it
                except SafetyFault as named:
                    fault = named
                except (MmctlError, OSError):
                    pass
            return exc, fault
        return None, None

    def _disable_base_after_failed_enable(self) -> None:
        """The base was enabled for an enable that did not arm: switch it off again."""
        try:
            self.rt.devices.base.disable(wait=False)
        except (MmctlError, OSError) as exc:
            log.warning("base_enable_undo_failed", error=str(exc))

    def _reconnect_sensor(self) -> None:
        """Enable after the sensor's link was lost (off the loop thread, the loop leaving
        the sensor alone): connect again (the transport re-reads its calibration)."""
        log.info("sensor_reconnecting")
        try:
            self.rt.devices.sensor.reconnect()
        except (MmctlError, OSError) as exc:
            log.warning("sensor_reconnect_failed", error=str(exc))
            raise MmctlError(f"refused to enable: the sensor did not reconnect ({exc})") from None
        log.info("sensor_reconnected")

    def _reconnect_arm(self) -> None:
        """Enable after a lost link / stopped program (off the loop thread, the loop
        leaving the arm alone): reconnect, which re-uploads the control script (~1-2 s;
        ur_rtde's constructors and destructors hold the GIL for parts of it)."""
        log.info("arm_reconnecting", causes=sorted(
            c.value for c in self.rt.ustate.safety.active if c.value.startswith("arm_")))
        try:
            self.rt.devices.arm.reconnect()
        except (MmctlError, OSError) as exc:
            log.warning("arm_reconnect_failed", error=str(exc))
            raise MmctlError(f"refused to enable: the arm did not reconnect ({exc})") from None
        log.info("arm_reconnected")


def _budget(req: Mapping[str, object], default: float) -> float:
    """How long [s] a command may take: ``default``, shortened to 80 % of the client's
    own ``timeout_s`` when it sends one (the rest is its margin for the reply), so a
    client never reports a failure that the daemon then carries out."""
    client = req.get("timeout_s")
    if isinstance(client, (int, float)) and not isinstance(client, bool) \
            and math.isfinite(client) and client > 0:
        return min(default, 0.8 * float(client))
    return default


def _arg(req: Mapping[str, object], key: str, typ: type[T]) -> T:
    val = req.get(key)
    if not isinstance(val, typ):
        raise MmctlError(f"request {req.get('cmd')!r} needs {key!r} ({typ.__name__})")
    return val
