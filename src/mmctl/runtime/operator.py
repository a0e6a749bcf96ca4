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
from mmctl.errors import FaultCause, IpcError, MmctlError, SafetyFault, TransportError
from mmctl.runtime.ipc import Peer

log = structlog.get_logger("mmctl.daemon")

_BASE_CAUSES = frozenset({FaultCause.DRIVE_FAULT, FaultCause.DRIVE_HEARTBEAT,
                          FaultCause.BASE_LINK})
_ARM_RECONNECT_CAUSES = frozenset({FaultCause.ARM_DISCONNECTED, FaultCause.ARM_STALE,
                                   FaultCause.ARM_NOT_PLAYING})
#: [s] the least an enable's last step (on the loop thread) is given to be taken.
_FINISH_MIN = 0.5


if TYPE_CHECKING:
    from mmctl.runtime.daemon import SampleHook
    from mmctl.runtime.parts import DaemonParts as _Parts
else:
    _Parts = object


class OperatorCommands(_Parts):
    """The operator's commands (see the module docstring)."""

    def submit(self, fn: Callable[[], Any]) -> Future[Any]:
        """Run ``fn`` on the loop thread at the start of the next cycle."""
        fut: Future[Any] = Future()
        self._commands.put((fn, fut))
        return fut

    def call(self, cmd: str, **args: Any) -> Any:
        """Run one control command (same names as the socket's) and wait for its result."""
        return self.handle({"cmd": cmd, **args}, None)

    def _on_loop(self, fn: Callable[[], Any], timeout: float | None = None) -> Any:
        """Run ``fn`` on the loop thread and wait; without a loop thread (tests stepping
        the daemon with :meth:`step_once`) run it right here.

        A command the loop has not started within ``timeout`` [s] (default
        ``daemon.command_timeout``) is cancelled, so a command reported as failed never
        takes effect later; one it has started is waited for (the loop runs nothing
        that blocks: an arm reconnect runs on the caller's thread) and reported as it
        ended.
        """
        if not self.loop.running:
            if self.loop.error is not None or self._stop_requested.is_set():
                raise IpcError("the control loop is not running")
            return fn()
        fut = self.submit(fn)
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
            "disable": lambda req: self._then_status(self._on_loop(self._disable)),
            "mode": self._cmd_mode,
            "profile": self._cmd_profile,
            "switch": self._cmd_switch,
            "tare": self._cmd_tare,
            "stop": self._cmd_stop,
            "trial": self._cmd_trial,
            "calibrate": self._cmd_calibrate,
            "set": self._cmd_set,
            "get": self._cmd_get,
        }

    def _cmd_mode(self, req: Mapping[str, Any]) -> Any:
        mode = _arg(req, "mode", str)
        return self._then_status(self._on_loop(lambda: self._set_mode(mode)))

    def _cmd_profile(self, req: Mapping[str, Any]) -> Any:
        profile = _arg(req, "profile", str)
        return self._then_status(self._on_loop(lambda: self._set_profile(profile)))

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
            self._on_loop(lambda: self.core.install(cfg, controller, key))
        new = get_value(cfg, key)
        log.info("param_set", key=key, old=old, new=new)
        return {"key": key, "old": old, "value": new, "status": self.status_snapshot()}

    def _cmd_get(self, req: Mapping[str, Any]) -> Any:
        key = _arg(req, "key", str)
        return {"key": key, "value": get_value(self.core.cfg, key),
                "settable": key in SETTABLE, "changed": key in self.core.changed}

    def _cmd_switch(self, req: Mapping[str, Any]) -> Any:
        which = _arg(req, "to", str)
        return self._then_status(self._on_loop(lambda: self._set_switch(which)))

    def _cmd_tare(self, req: Mapping[str, Any]) -> Any:
        self._hands_off_for_tare()
        return self._on_loop(self._tare)

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
        if self.sim is None or self.safety.armed:
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

        1. when the arm's link or program is lost, the arm reconnects on *this* thread
           (it takes seconds) while the loop leaves the arm alone;
        2. the loop checks every condition but the base's (:meth:`_enable_check`:
           refused at once when one is present);
        3. the base enables on *this* thread (SDO round trips; a wheel still ramping
           down on the last stop is waited for), the loop leaving the base alone;
        4. the loop checks again and arms (:meth:`_enable_finish`), or refuses and stops.

        An enable reported as failed (refused, the reconnect failed, the budget ran out)
        never takes effect later: a base enabled for an enable that then failed is
        disabled again."""
        deadline = time.monotonic() + budget
        if self._on_loop(self._begin_enable, budget):
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
            if not self._on_loop(self._enable_check, left):
                return self._then_status(None)  # armed already
            try:
                failure = self._enable_base()
            finally:
                self._base_busy = False
            try:
                # the drives' command watchdog runs from the enable: the loop arms (and
                # sends targets) in its next cycle, whatever is left of the budget
                self._on_loop(lambda: self._enable_finish(failure),
                              max(deadline - time.monotonic(), _FINISH_MIN))
            except BaseException:
                if failure is None and not self.safety.armed:
                    self._disable_base_after_failed_enable()
                raise
        return self._then_status(None)

    def _then_status(self, _done: None) -> dict[str, Any]:
        """A command's reply: the status, built on the caller's thread (never on the
        loop's: building it costs a share of a cycle) once the command has run."""
        return self.status_snapshot()

    def _begin_enable(self) -> bool:
        """Loop thread: whether the enable must reconnect the arm first (then the loop
        leaves the arm to the reconnect from now on): an arm link or program condition
        present, or one latched (a link that failed once is not trusted because its
        reads look fine again: a dead controller's last sample can linger in the arm's
        process for up to ``arm.stale_cycles``)."""
        if self.safety.armed:
            return False
        if not (self.safety.active.keys() & _ARM_RECONNECT_CAUSES
                or self.safety.latched in _ARM_RECONNECT_CAUSES):
            return False
        self._arm_busy = True
        return True

    def _other_conditions(self) -> dict[FaultCause, dict[str, Any]]:
        """Loop thread: the conditions an enable must find gone, but the base's (its
        faults are latched until its own enable resets them); the arm judged on a fresh
        read."""
        other = {c: d for c, d in self.safety.active.items()
                 if c not in _BASE_CAUSES and not c.value.startswith("arm_")}
        if self.loop.consecutive_misses == 0:
            other.pop(FaultCause.LOOP_OVERRUN, None)  # on time again; counters reset below
        try:
            self.devices.arm.read_state()
        except SafetyFault as exc:
            other[exc.cause] = {"device": "arm", **exc.details}
        except TransportError as exc:
            other[FaultCause.ARM_DISCONNECTED] = {"device": "arm", "error": str(exc)}
        return other

    def _enable_check(self) -> bool:
        """Loop thread, before the base's enable: False when armed already; refused
        (EnableRefused naming them) while a condition but the base's is present; else
        the loop leaves the base to the enable from now on (True)."""
        if self.safety.armed:
            return False
        if self.cycles == 0:
            raise MmctlError("refused to enable: no control cycle has run yet")
        if self.core.taring:
            raise MmctlError("refused to enable: a tare is in progress (the handle must not "
                             "be touched until it ends)")
        other = self._other_conditions()
        if other:
            self.safety.enable(other)  # raises EnableRefused naming them
        self._base_busy = True
        return True

    def _enable_base(self) -> BaseException | None:
        """The caller's thread: enable the base and check its health; what went wrong,
        for :meth:`_enable_finish` to refuse with (the base disables itself again when
        its enable fails)."""
        try:
            self.devices.base.enable()
            self.devices.base.check()
        except (MmctlError, OSError) as exc:
            return exc
        return None

    def _enable_finish(self, failure: BaseException | None) -> None:
        """Loop thread, after the base's enable: refuse (and stop) when the base failed
        or another condition came up meanwhile; else arm."""
        if self.safety.armed:
            return
        if failure is None:
            try:
                self.devices.base.check()
            except (MmctlError, OSError) as exc:
                failure = exc
        if isinstance(failure, SafetyFault):
            self.devices.stop(self.cfg.arm.stop_deceleration, wait=False)
            self.safety.enable({failure.cause: {"device": "base", **failure.details}})
        if failure is not None:
            self.devices.stop(self.cfg.arm.stop_deceleration, wait=False)
            try:
                self.devices.base.check()  # name the cause if the base knows it
            except SafetyFault as fault:
                self.safety.enable({fault.cause: {"device": "base", "error": str(failure),
                                                  **fault.details}})  # refused
            except (MmctlError, OSError):
                pass
            raise MmctlError(f"refused to enable: the base did not enable ({failure})")
        other = self._other_conditions()
        if other:  # came up while the base was enabled
            self.devices.stop(self.cfg.arm.stop_deceleration, wait=False)
            self.safety.enable(other)  # raises EnableRefused naming them
        self.safety.enable({})
        self.core.reset()
        self.loop.reset_misses()
        self._update_status()

    def _disable_base_after_failed_enable(self) -> None:
        """The base was enabled for an enable that did not arm: switch it off again."""
        try:
            self.devices.base.disable(wait=False)
        except (MmctlError, OSError) as exc:
            log.warning("base_enable_undo_failed", error=str(exc))

    def _reconnect_arm(self) -> None:
        """Enable after a lost link / stopped program (off the loop thread, the loop
        leaving the arm alone): reconnect, which re-uploads the control script (~1-2 s;
        ur_rtde's constructors and destructors hold the GIL for parts of it)."""
        log.info("arm_reconnecting",
                 causes=sorted(c.value for c in self.safety.active if c.value.startswith("arm_")))
        try:
            self.devices.arm.reconnect()
        except (MmctlError, OSError) as exc:
            log.warning("arm_reconnect_failed", error=str(exc))
            raise MmctlError(f"refused to enable: the arm did not reconnect ({exc})") from None
        log.info("arm_reconnected")

    def _disable(self) -> None:
        if self.safety.disable():
            self._send_stop()
        self._update_status()

    def _set_mode(self, mode: str) -> None:
        old = self.core.mode
        self.core.set_mode(mode)
        log.info("mode", old=old, new=self.core.mode)
        self._update_status()

    def _set_profile(self, profile: str) -> None:
        old = self.core.profile
        self.core.set_profile(profile)
        log.info("profile", old=old, new=self.core.profile, caps=self.core.caps)
        self._update_status()

    def _set_switch(self, which: str) -> None:
        if self.core.mode != "switch":
            raise MmctlError(f"`switch` needs mode 'switch' (current mode: {self.core.mode}); "
                             "run `mmctl mode switch` first")
        old = self.core.switch
        self.core.set_switch(which)
        log.info("switch", old=old, new=self.core.switch)
        self._update_status()

    def _tare(self) -> dict[str, Any]:
        if self.safety.armed:
            raise MmctlError("refusing to tare while armed: `mmctl disable` first "
                             "(a tare must not absorb the operator's push)")
        self.core.start_tare()
        return {"taring": True, "samples": self.cfg.sensor.wrench.tare_samples}


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
