"""The daemon: devices + control core + safety + loop + control socket + systemd notify.

One cycle (:meth:`Daemon.cycle`, on the loop thread):

1. take operator commands queued by the control socket (enable, disable, mode, ...);
2. read the arm, the sensor and the base; every SPEC §5 condition found goes into this
   cycle's condition set (a device raising :class:`SafetyFault` names its cause);
3. when ARMED, run the pure control step (wrench processing, admittance, IDK, limits);
   its fault (non-finite, singular) joins the set;
4. feed the set to the :class:`~mmctl.runtime.safety.SafetyMonitor`: a new fault sends
   speedStop and zero base velocity *in this same cycle*, then disables the base;
5. the optional per-cycle sample hook (telemetry: one row into the sample ring);
6. ARMED: send speedJ and the base twist;
7. systemd watchdog ping.

The daemon always starts DISARMED.  Shutdown (SIGTERM/SIGINT, ``mmctl stop``, the
duration elapsing, or any exception) always ends with the stop commands sent, then the
devices closed.
"""

from __future__ import annotations

import gc
import math
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import structlog

from mmctl.config import Config
from mmctl.errors import FaultCause, IpcError, MmctlError, SafetyFault, TransportError
from mmctl.runtime.core import ControlCore, CycleResult
from mmctl.runtime.devices import Devices
from mmctl.runtime.ipc import ControlServer, Peer
from mmctl.runtime.logging import RateLimiter
from mmctl.runtime.loop import CycleLoop, Tick, Wait

if TYPE_CHECKING:
    from mmctl.runtime.sim_link import SimLink
    from mmctl.telemetry.service import TelemetryService
from mmctl.runtime.notify import Notifier
from mmctl.runtime.pmqos import CpuLatencyRequest
from mmctl.runtime.safety import SafetyMonitor, SafetyState
from mmctl.runtime.timing import TimingRing

log = structlog.get_logger("mmctl.daemon")

#: The hook telemetry attaches: called on the loop thread once per cycle as
#: ``hook(result, cycle, t, safety)`` (the cycle's CycleResult, its index, its deadline
#: since the origin [s], the safety state's name); must not block.
SampleHook = Callable[[CycleResult, int, float, str], None]

#: Signals that end the daemon by default and are turned into a stop instead: the
#: service manager's (TERM), a terminal's (INT: Ctrl-C, QUIT: Ctrl-\, HUP: the ssh
#: session closed), the user signals, resource limits (XCPU, XFSZ) and a power failure
#: (PWR).  SIGKILL and a crash (SEGV, ABRT, BUS) cannot be caught: then the devices'
#: own watchdogs stop the robot (the arm's RTDE watchdog, the drives' command watchdog).
STOP_SIGNALS = tuple(getattr(signal, name) for name in (
    "SIGTERM", "SIGINT", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM",
    "SIGXCPU", "SIGXFSZ", "SIGPWR", "SIGVTALRM") if hasattr(signal, name))

_BASE_CAUSES = frozenset({FaultCause.DRIVE_FAULT, FaultCause.DRIVE_HEARTBEAT,
                          FaultCause.BASE_LINK})
_ARM_RECONNECT_CAUSES = frozenset({FaultCause.ARM_DISCONNECTED, FaultCause.ARM_STALE,
                                   FaultCause.ARM_NOT_PLAYING})
_LINK_CAUSE = {"arm": FaultCause.ARM_DISCONNECTED, "sensor": FaultCause.SENSOR_LINK,
               "base": FaultCause.BASE_LINK}


#: The device phases of a cycle timed in :attr:`Daemon.phase_ns` (rows, in this order).
PHASES = ("arm_read", "sensor_read", "base_read", "arm_send", "base_send", "sensor_request")


class StartAborted(Exception):
    """A stop request arrived while :meth:`Daemon.open` was still starting."""


class Daemon:
    """Composition root of the running daemon (see the module docstring).

    cfg: the configuration; devices: not yet connected; core: the control chain;
    socket_path: where to serve the control socket (None = no socket, for in-process
    tests); notifier: systemd notify (default: from the environment); sim: the link
    to the simulated robot's own process (a :class:`~mmctl.runtime.sim_link.SimLink`:
    ``start(should_stop)``, ``start_human()``, ``hold(seconds)``, ``status()``,
    ``close()``), or None; telemetry: a
    :class:`~mmctl.telemetry.service.TelemetryService` (its hook becomes
    :attr:`sample_hook`, ``trial`` requests go to it), or None; loop_wait: the loop's
    wait for each deadline (default: sleep, then spin; benchmarks give their own).
    """

    def __init__(self, cfg: Config, devices: Devices, core: ControlCore, *,
                 socket_path: Path | None = None, notifier: Notifier | None = None,
                 sim: SimLink | None = None, telemetry: TelemetryService | None = None,
                 loop_wait: Wait | None = None):
        self.cfg = cfg
        self.devices = devices
        self.core = core
        self.safety = SafetyMonitor()
        self.notifier = notifier if notifier is not None else Notifier()
        self.sim = sim
        self.telemetry = telemetry
        self.ring = TimingRing(cfg.loop.timing_samples)
        #: time spent in the pure control chain (ControlCore.step) per cycle, indexed by
        #: cycle % size [ns]: the part of the compute time that is not device I/O
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
        )
        self.period = 1.0 / cfg.loop.rate_hz
        self.server = (ControlServer(socket_path, self.handle, cfg.daemon.socket_mode)
                       if socket_path is not None else None)
        self._commands: queue.SimpleQueue[tuple[Callable[[], Any], Future[Any]]] = (
            queue.SimpleQueue())
        self._stop_requested = threading.Event()
        self._healthy_cycle = threading.Event()
        self.stop_reason = ""
        self.sample_hook: SampleHook | None = None
        self.cycles = 0
        self.last: CycleResult | None = None
        self.last_conditions: dict[FaultCause, dict[str, Any]] = {}
        self._button_was = False
        self._arm_busy = False
        """An arm reconnect runs off the loop thread (set and cleared around it): the
        loop then leaves the arm alone and counts it as disconnected."""
        self._arm_reconnect = threading.Lock()
        self._started = time.monotonic()
        self._t0_ns = 0
        self._status_text = ""
        self.commands_sent = {"speed_j": 0, "stop": 0, "twist": 0}
        self._limiter = RateLimiter(1.0)
        self.cpu_latency = (CpuLatencyRequest(cfg.loop.cpu_dma_latency)
                            if cfg.loop.cpu_dma_latency >= 0 else None)
        #: a request/reply sensor's "ask for the next sample" (CAN), sent at the end of
        #: each cycle so the answer comes in the loop's idle time; None: it streams
        self._sensor_request: Callable[[], None] | None = getattr(
            devices.sensor, "request_next", None)
        self._request_at_start = cfg.loop.sensor_request == "start"
        #: the newest base twist sent (None: none since the last stop)
        self._twist_sent: tuple[float, float, float] | None = None
        self._handlers = self._command_table()

    # ------------------------------------------------------------------ lifecycle --
    def open(self) -> None:
        """Claim the control socket, connect the devices (in that order)."""
        if self.server is not None:
            self.server.open()
        try:
            if self.sim is not None:
                self.sim.start(self._stop_requested.is_set)
                if self._stop_requested.is_set():
                    raise StartAborted("stopped while the simulated robot started")
            self.devices.connect()
        except BaseException:
            if self.server is not None:
                self.server.close()
            if self.sim is not None:
                self.sim.close()
            raise
        self.notifier.connect()

    def start(self) -> None:
        """Start the loop and the control socket."""
        sys.setswitchinterval(self.cfg.loop.switch_interval)
        if self.cpu_latency is not None:
            self.cpu_latency.acquire()  # best effort: a warning when not permitted
        gc.collect()
        gc.freeze()  # start-up objects (models, fakes) out of every later collection
        self._t0_ns = time.perf_counter_ns()
        if self.telemetry is not None:
            self.telemetry.start(ring=self.ring)
            self.sample_hook = self.telemetry.hook(self.core)
        self.loop.start()
        if self.server is not None:
            self.server.start()

    @property
    def origin_ns(self) -> int:
        """perf_counter_ns of t = 0 (set by :meth:`start`); a sample's ``t`` counts from it."""
        return self._t0_ns

    def run(self, duration: float | None = None, install_signals: bool = True) -> int:
        """open, start, wait for a stop (signal, ``mmctl stop``, duration), shut down.

        Returns the process exit status (0 clean, 1 if the loop died of an error).
        """
        if install_signals:
            self._install_signals()
        try:
            self.open()
            self.start()
            self._wait_ready()
            if (self.cfg.sim.enabled and self.cfg.sim.auto_enable and self.sim is not None
                    and not self._stop_requested.is_set()):
                self._auto_enable()
            deadline = None if duration is None else time.monotonic() + duration
            while not self._stop_requested.is_set():
                if not self.loop.running:
                    self.stop_reason = self.stop_reason or "loop_ended"
                    break
                left = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
                if left <= 0:
                    self.stop_reason = "duration"
                    break
                self._stop_requested.wait(left)
        except StartAborted:
            pass  # a signal during start-up: nothing moved; shut down what was opened
        except BaseException as exc:
            self.stop_reason = self.stop_reason or f"error: {exc}"
            raise
        finally:
            self.shutdown()
        return 1 if self.loop.error is not None else 0

    def request_stop(self, reason: str = "requested") -> None:
        """Ask :meth:`run` to shut down (any thread, signal handler)."""
        self.stop_reason = self.stop_reason or reason
        self._stop_requested.set()

    def shutdown(self) -> None:
        """Stop the loop, send the stop commands, close devices, socket and sim (idempotent)."""
        self.notifier.stopping(f"stopping ({self.stop_reason or 'shutdown'})")
        log.info("daemon_stopping", reason=self.stop_reason or "shutdown")
        self.loop.stop()
        self.loop.wait(5.0)
        if self.devices.connected:
            self.devices.stop(self.cfg.arm.stop_deceleration, arm=not self._arm_busy)
            self.commands_sent["stop"] += 1
            if self.safety.state is SafetyState.ARMED:
                self.safety.disable()
        if self.server is not None:
            try:
                self.server.close()
            except OSError as exc:
                log.error("socket_close_failed", error=str(exc))
        if self.telemetry is not None:
            self.telemetry.close()
        reconnect_done = self._arm_reconnect.acquire(timeout=3 * self.cfg.arm.connect_timeout + 2)
        if not reconnect_done:  # never close the arm under a reconnect in progress
            log.error("arm_reconnect_still_running", why="the arm is not closed")
            self.devices.connected.clear()
        self.devices.close(arm=reconnect_done)
        if reconnect_done:
            self._arm_reconnect.release()
        if self.sim is not None:
            self.sim.close()
        if self.cpu_latency is not None:
            self.cpu_latency.release()
        self.notifier.close()
        log.info("daemon_stopped", cycles=self.cycles, error=repr(self.loop.error)
                 if self.loop.error else None)

    def _install_signals(self) -> None:
        """Every signal whose default would end the process is a stop: the stop commands
        go out, then the devices close (:data:`STOP_SIGNALS`).  The handler only sets
        the stop request, so a second signal during the shutdown changes nothing."""
        def on_signal(signum: int, _frame: Any) -> None:
            self.request_stop(signal.Signals(signum).name)

        for signum in STOP_SIGNALS:
            signal.signal(signum, on_signal)

    def _wait_ready(self) -> None:
        deadline = time.monotonic() + self.cfg.daemon.ready_timeout
        healthy = False
        while not self._stop_requested.is_set() and self.loop.running:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            healthy = self._healthy_cycle.wait(min(left, 0.05))  # a stop is seen at once
            if healthy:
                break
        if not healthy:
            log.warning("ready_without_healthy_cycle",
                        conditions=sorted(c.value for c in self.last_conditions))
        self.notifier.ready(self._status())
        log.info("daemon_ready", state=self.safety.state.value, mode=self.core.mode,
                 socket=str(self.server.path) if self.server else None)

    def _auto_enable(self) -> None:
        """Simulation only: tare, arm, and let the simulated person start."""
        deadline = time.monotonic() + self.cfg.daemon.ready_timeout
        try:
            self.call("tare")
            while self.core.taring and time.monotonic() < deadline and self.loop.running:
                time.sleep(0.01)
            while True:  # a condition may flicker while the fakes settle: retry a while
                try:
                    self.call("enable")
                    break
                except MmctlError:
                    if time.monotonic() > deadline or self._stop_requested.is_set():
                        raise
                    time.sleep(0.1)
        except MmctlError as exc:
            log.warning("auto_enable_failed", error=str(exc))
            return
        log.info("auto_enabled", mode=self.core.mode)
        if self.cfg.sim.human and self.sim is not None:  # (else a push set meanwhile stays)
            self.sim.start_human()

    # ---------------------------------------------------------- operator commands --
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
            return fut.result(self.cfg.daemon.command_timeout if timeout is None else timeout)
        except FutureTimeout:
            if fut.cancel():
                raise IpcError("the control loop did not take the command in time "
                               "(not applied)") from None
        return fut.result()  # started: ends within its cycle

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
            "status": lambda req: self.status(),
            "enable": lambda req: self._enable_request(
                _budget(req, self.cfg.daemon.command_timeout)),
            "disable": lambda req: self._on_loop(self._disable),
            "mode": self._cmd_mode,
            "switch": self._cmd_switch,
            "tare": self._cmd_tare,
            "stop": self._cmd_stop,
            "trial": self._cmd_trial,
        }

    def _cmd_mode(self, req: Mapping[str, Any]) -> Any:
        mode = _arg(req, "mode", str)
        return self._on_loop(lambda: self._set_mode(mode))

    def _cmd_switch(self, req: Mapping[str, Any]) -> Any:
        which = _arg(req, "to", str)
        return self._on_loop(lambda: self._set_switch(which))

    def _cmd_tare(self, req: Mapping[str, Any]) -> Any:
        self._hands_off_for_tare()
        return self._on_loop(self._tare)

    def _cmd_stop(self, req: Mapping[str, Any]) -> Any:
        self.request_stop("mmctl stop")
        return {"stopping": True}

    def _cmd_trial(self, req: Mapping[str, Any]) -> Any:
        if self.telemetry is None:
            raise MmctlError("'trial' needs the telemetry service")
        return self.telemetry.command(req, self._on_loop, self)

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
        """Operator re-arm within ``budget`` [s]: the checks and the arming run on the
        loop thread (:meth:`_enable`); when the arm's link or program is lost, the arm
        reconnects first on *this* thread (it takes seconds), while the loop keeps its
        period and leaves the arm alone.  An enable reported as failed (refused, the
        reconnect failed, the budget ran out) never takes effect later."""
        deadline = time.monotonic() + budget
        if self._on_loop(self._begin_enable, budget):
            with self._arm_reconnect:
                try:
                    self._reconnect_arm()
                finally:
                    self._arm_busy = False
        left = deadline - time.monotonic()
        if left <= 0:
            raise MmctlError(f"refused to enable: the arm's reconnect took longer than "
                             f"{budget:g} s (daemon.command_timeout or the client's timeout)")
        return cast("dict[str, Any]", self._on_loop(self._enable, left))

    def _begin_enable(self) -> bool:
        """Loop thread: whether the enable must reconnect the arm first (then the loop
        leaves the arm to the reconnect from now on)."""
        if self.safety.armed or not (self.safety.active.keys() & _ARM_RECONNECT_CAUSES):
            return False
        self._arm_busy = True
        return True

    def _enable(self) -> dict[str, Any]:
        """Operator re-arm (loop thread).

        Conditions other than the base's must be gone (else EnableRefused); the arm is
        judged on a fresh read.  The base latches its faults until ``enable()`` resets
        them, so it is enabled first and its health re-checked: a drive still faulty or
        silent refuses the enable.
        """
        if self.safety.armed:
            return self.status()
        if self.cycles == 0:
            raise MmctlError("refused to enable: no control cycle has run yet")
        if self.core.taring:
            raise MmctlError("refused to enable: a tare is in progress (the handle must not "
                             "be touched until it ends)")
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
        if other:
            self.safety.enable(other)  # raises EnableRefused naming them
        try:
            self.devices.base.enable()
            self.devices.base.check()
        except SafetyFault as exc:
            self.devices.stop(self.cfg.arm.stop_deceleration, wait=False)
            self.safety.enable({exc.cause: {"device": "base", **exc.details}})  # refused
        except (MmctlError, OSError) as exc:
            self.devices.stop(self.cfg.arm.stop_deceleration, wait=False)
            try:
                self.devices.base.check()  # name the cause if the base knows it
            except SafetyFault as fault:
                self.safety.enable({fault.cause: {"device": "base", "error": str(exc),
                                                  **fault.details}})  # refused
            except (MmctlError, OSError):
                pass
            raise MmctlError(f"refused to enable: the base did not enable ({exc})") from None
        self.safety.enable({})
        self.core.reset()
        self.loop.reset_misses()
        self._update_status()
        return self.status()

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

    def _disable(self) -> dict[str, Any]:
        if self.safety.disable():
            self._send_stop()
        self._update_status()
        return self.status()

    def _set_mode(self, mode: str) -> dict[str, Any]:
        old = self.core.mode
        self.core.set_mode(mode)
        log.info("mode", old=old, new=self.core.mode)
        self._update_status()
        return self.status()

    def _set_switch(self, which: str) -> dict[str, Any]:
        if self.core.mode != "switch":
            raise MmctlError(f"`switch` needs mode 'switch' (current mode: {self.core.mode}); "
                             "run `mmctl mode switch` first")
        old = self.core.switch
        self.core.set_switch(which)
        log.info("switch", old=old, new=self.core.switch)
        self._update_status()
        return self.status()

    def _tare(self) -> dict[str, Any]:
        if self.safety.armed:
            raise MmctlError("refusing to tare while armed: `mmctl disable` first "
                             "(a tare must not absorb the operator's push)")
        self.core.start_tare()
        return {"taring": True, "samples": self.cfg.sensor.wrench.tare_samples}

    # ------------------------------------------------------------------ the cycle --
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
            if self.safety.trip(FaultCause.INTERNAL, error=repr(exc)):
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
        odom = self._read("base", dev.base.read_odometry, conditions)
        t2 = clock()
        wrench = self._read("sensor", dev.sensor.read, conditions)
        t3 = clock()
        phase[0, row], phase[2, row], phase[1, row] = t1 - t0, t2 - t1, t3 - t2
        if tick.overrun:
            conditions[FaultCause.LOOP_OVERRUN] = {
                "consecutive": tick.consecutive_misses, "total": tick.total_misses}
        self._poll_button()
        result: CycleResult | None = None
        if arm is not None and wrench is not None and odom is not None:
            t0 = time.perf_counter_ns()
            result = self.core.step(arm, wrench, odom, tick.period, active=self.safety.armed)
            self.step_ns[self.cycles % self.step_ns.shape[0]] = time.perf_counter_ns() - t0
            if result.fault is not None:
                conditions.setdefault(result.fault, dict(result.fault_details))
            self.last = result
        stop_now = self.safety.update(conditions)
        self.last_conditions = conditions
        if stop_now:
            self._send_stop()
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

    # -------------------------------------------------------------------- status --
    def _status(self) -> str:
        s = self.safety
        fault = f" fault={s.latched.value}" if s.latched else ""
        return f"state={s.state.value} mode={self.core.mode}{fault}"

    def _update_status(self) -> None:
        text = self._status()
        if text != self._status_text:
            self._status_text = text
            self.notifier.status(text)

    def status(self) -> dict[str, Any]:
        """Plain-JSON snapshot for ``mmctl status`` (any thread)."""
        stats = self.ring.stats(min(self.ring.size, int(self.cfg.loop.rate_hz * 5)))
        out: dict[str, Any] = {
            **self.safety.as_dict(),
            "mode": self.core.mode,
            "switch": self.core.switch,
            "taring": self.core.taring,
            "cycles": self.cycles,
            "uptime_s": round(time.monotonic() - self._started, 3),
            "loop": {"rate_hz": self.cfg.loop.rate_hz, "running": self.loop.running,
                     "total_misses": self.loop.total_misses, **stats.as_dict()},
            "commands": dict(self.commands_sent),
            "config": self.cfg.name,
        }
        last = self.last
        if last is not None:
            out["robot"] = {"q": _round(last.q), "ee_position": _round(last.p),
                            "v_d": _round(last.v_d), "f_h": _round(last.f_h),
                            "energy_J": round(float(last.energy.total), 6)}
        if self.sim is not None:
            out["sim"] = self.sim.status()
        if self.telemetry is not None:
            out["telemetry"] = self.telemetry.status()
        out["process"] = {
            "pid": os.getpid(), "threads": sorted(t.name for t in threading.enumerate()),
            # on the robot and on the simulated robot alike: no simulation code in here
            "simulation_loaded": any(m in sys.modules for m in ("mmctl.sim", "mmctl.study")),
        }
        return out


    def live(self) -> dict[str, Any]:
        """The live terminal view's snapshot (:mod:`mmctl.runtime.liveview`; any thread,
        a few times a second: the last second of loop timing, the newest cycle)."""
        stats = self.ring.stats(min(self.ring.size, int(self.cfg.loop.rate_hz)))
        out: dict[str, Any] = {
            "state": self.safety.state.value, "mode": self.core.mode,
            "fault": self.safety.as_dict().get("fault"), "taring": self.core.taring,
            "cycles": self.cycles, "uptime_s": time.monotonic() - self._started,
            "loop": {"rate_hz": self.cfg.loop.rate_hz, "total_misses": self.loop.total_misses,
                     **stats.as_dict()},
        }
        last = self.last
        if last is not None:
            out.update(f_h=[float(x) for x in last.f_h],
                       ee_speed=float(np.linalg.norm(last.v_d[:3])),
                       base_speed=float(np.hypot(last.qd[6], last.qd[7])),
                       base_yaw_rate=float(last.qd[8]),
                       energy_arm=float(last.energy.arm), energy_base=float(last.energy.base))
        if self.sim is not None and self.sim.closed:
            out["sim"] = {"person": "stopped"}
        elif self.sim is not None:
            try:
                st = self.sim.call("status", timeout=0.5)
                out["sim"] = {"person": st.get("person"), "faults": st.get("faults")}
            except MmctlError as exc:
                out["sim"] = {"person": f"unreachable ({exc})"}
        if self.sim is not None:
            out["hint"] = ("mmctl sim push 30 0 0 · mmctl sim person off|on · "
                           "mmctl sim fault --list · Ctrl-C stops")
        else:
            out["hint"] = "mmctl status · mmctl disable · Ctrl-C stops"
        return out


def _round(v: Any, nd: int = 5) -> list[float]:
    return [round(float(x), nd) if math.isfinite(float(x)) else float("nan")
            for x in np.asarray(v).ravel()]


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
