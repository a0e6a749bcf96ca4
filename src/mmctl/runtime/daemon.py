"""The daemon: devices + control core + safety + loop + control socket + systemd notify.

This module is the lifecycle (open, start, run, shutdown, signals, readiness) and the
status; :class:`Daemon` composes it with the operator's commands
(:mod:`mmctl.runtime.operator`) and the cycle driver (:mod:`mmctl.runtime.driver`).

One cycle (:meth:`Daemon.cycle`, on the loop thread):

1. take operator commands queued by the control socket (enable, disable, mode, ...);
2. read the arm, the sensor and the base; every SPEC §5 condition found goes into this
   cycle's condition set (a device raising :class:`SafetyFault` names its cause);
3. when ARMED, run the pure control step (wrench processing, admittance, IDK, limits);
   its fault (non-finite, singular) joins the set (while a tool-load calibration runs,
   :mod:`mmctl.runtime.calibrate`, the controller idles and the calibration's motion
   goes out instead);
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
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from mmctl.config import Config
from mmctl.control import safety as sm
from mmctl.control.safety import Safety
from mmctl.control.update import Readings, Update, UpdateState
from mmctl.errors import MmctlError
from mmctl.runtime.calibrate import CalibrationCommands
from mmctl.runtime.core import ControlCore, CycleResult
from mmctl.runtime.devices import Devices
from mmctl.runtime.ipc import Handler
from mmctl.runtime.ipc_process import ProcessControlServer
from mmctl.runtime.logging import RateLimiter
from mmctl.runtime.loop import CycleLoop, GcInSlack, Wait

if TYPE_CHECKING:
    from mmctl.control.calibration import ToolCalibration, ToolLoadFit
    from mmctl.model.robot import RobotModel
    from mmctl.runtime.inputlog import InputLog
    from mmctl.runtime.sim_link import SimLink
    from mmctl.telemetry.service import TelemetryService
from mmctl.runtime.driver import PHASES, CycleDriver
from mmctl.runtime.notify import Notifier
from mmctl.runtime.operator import OperatorCommands
from mmctl.runtime.pmqos import CpuLatencyRequest
from mmctl.runtime.safety import SafetyState, log_events
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

#: [s] the longest a control-socket ``status`` reply is older than the daemon's state
#: (:meth:`Daemon.status_snapshot`): a flood of status requests costs at most ten
#: rebuilds a second
STATUS_MAX_AGE = 0.1
#: [s] the longest the loop's timing figures in ``status`` (5 s percentiles) are reused
STATS_MAX_AGE = 1.0
#: [s] the window of the loop's timing figures and window miss rate (status, live view)
STATS_WINDOW = 5.0
#: [cycles] the oldest a cycle's measured motion may be and still be shown as now (a
#: device not read since: shown as unknown, never as the motion it last had)
MEASURED_MAX_AGE = 5


def _control_server(cfg: Config, path: Path, handler: Handler) -> ProcessControlServer:
    """The control socket, in a process of its own (:mod:`mmctl.runtime.ipc_process`: it
    hands the daemon only complete, rate-limited requests): ``status`` from the snapshot
    (inline), ``stop`` and ``disable`` never queued behind other clients' requests (see
    :mod:`mmctl.runtime.ipc`)."""
    kw: dict[str, Any] = {"inline": ("status",), "urgent": ("stop", "disable")}
    from mmctl.runtime import logging as mmctl_logging

    cpus: tuple[int, ...] = ()
    loop_cpus = set(cfg.loop.cpu_affinity)
    if loop_cpus and hasattr(os, "sched_getaffinity"):
        cpus = tuple(sorted(os.sched_getaffinity(0) - loop_cpus))  # off the loop's CPUs
    return ProcessControlServer(path, handler, cfg.daemon.socket_mode,
                                log_setup=mmctl_logging.CURRENT, cpus=cpus, **kw)


class StartAborted(Exception):
    """A stop request arrived while :meth:`Daemon.open` was still starting."""


class Daemon(OperatorCommands, CycleDriver, CalibrationCommands):
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
                 loop_wait: Wait | None = None, input_log: InputLog | None = None):
        self.cfg = cfg
        self.devices = devices
        self.core = core
        #: the pure update (every per-cycle decision) and the state it hands on
        self.update = Update(cfg, core.chain)
        self.ustate: UpdateState = self.update.initial_state()
        #: [commands] the most the update takes from the inbox in one cycle
        self.inbox_size = 16
        #: the arm's digital inputs a cycle reads: the enabling contacts, the button
        self._inputs = tuple(cfg.enabling.inputs) + (
            (cfg.daemon.switch_input,) if cfg.daemon.switch_input >= 0 else ())
        #: every cycle's readings, inbox and commands (None: not recorded)
        self.input_log = input_log
        #: the update's state as the update left it this cycle (the runtime's own
        #: changes after it go into the input log as patches)
        self._updated: UpdateState = self.ustate
        #: the last cycle's readings (None: no cycle yet)
        self.readings: Readings | None = None
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
            gc_slack=GcInSlack(cfg.loop.gc_every, round(cfg.loop.gc_margin * 1e9),
                               cfg.loop.rate_hz) if cfg.loop.gc_in_slack else None,
        )
        self.period = 1.0 / cfg.loop.rate_hz
        # status: a snapshot (inline, on the socket's selector thread); stop and disable
        # never queue behind other clients' requests (see mmctl.runtime.ipc)
        self.server = (_control_server(cfg, socket_path, self.handle)
                       if socket_path is not None else None)
        self._snapshot: tuple[float, tuple[Any, ...], dict[str, Any]] | None = None
        self._snapshot_lock = threading.RLock()  # (status() in it asks for loop_stats)
        self._loop_stats: tuple[float, dict[str, Any]] | None = None
        self._commands: queue.SimpleQueue[tuple[Any, Future[Any]]] = queue.SimpleQueue()
        self._stop_requested = threading.Event()
        self._param_lock = threading.Lock()  # `mmctl set`: one change at a time
        self._healthy_cycle = threading.Event()
        self.stop_reason = ""
        self.sample_hook: SampleHook | None = None
        self.cycles = 0
        self.last: CycleResult | None = None
        #: the cycle that produced :attr:`last`
        self.last_cycle = 0
        self._arm_busy = False
        """An arm reconnect runs off the loop thread (set and cleared around it): the
        loop then leaves the arm alone and counts it as disconnected."""
        self._arm_reconnect = threading.Lock()
        self._sensor_busy = False
        """A sensor reconnect runs off the loop thread: the loop leaves the sensor alone."""
        self._base_busy = False
        """The base's enable runs off the loop thread (it waits for SDO answers and for
        a wheel still ramping down): the loop then leaves the base alone."""
        self._base_enable = threading.Lock()
        """Held by an enable from its checks to its end: one enable at a time, and the
        shutdown waits for it before it stops the devices."""
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
        #: a sensor in a process of its own: told the loop's grid in the first cycle
        self._phase_sensor: Callable[[int, float], None] | None = getattr(
            devices.sensor, "set_phase", None)
        #: the newest tool-load calibration (`mmctl calibrate tool`) and its fit
        self.calibration: ToolCalibration | None = None
        self.calibration_fit: ToolLoadFit | None = None
        self._planner: RobotModel | None = None
        self._planner_lock = threading.Lock()
        self._handlers = self._command_table()

    @property
    def safety(self) -> Safety:
        """The safety state machine's value as the last cycle left it."""
        return self.ustate.safety

    @property
    def speed_scaling(self) -> float:
        """The arm's speed scaling in the last sample (speed slider x reduced mode)."""
        return self.ustate.speed_scaling

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
        co = self.cfg.base.canopen
        enable_done = self._base_enable.acquire(timeout=co.stop_timeout + 4 * co.sdo_timeout + 2)
        if not enable_done:
            log.error("base_enable_still_running", why="stopping the devices anyway")
        if self.devices.connected:
            self.devices.stop(self.cfg.arm.stop_deceleration, arm=not self._arm_busy)
            self.commands_sent["stop"] += 1
            if self.safety.state is SafetyState.ARMED:  # (the loop has ended)
                safety, _, events = sm.disable(self.safety)
                self.ustate = self.ustate._replace(safety=safety)
                log_events(events, self._limiter)
        if enable_done:
            self._base_enable.release()
        if self.server is not None:
            try:
                self.server.close()
            except OSError as exc:
                log.error("socket_close_failed", error=str(exc))
        if self.telemetry is not None:
            self.telemetry.close()
        if self.input_log is not None:
            self.input_log.close()
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
        """Simulation only: tare, arm, and let the simulated person start (within
        sim.ready_timeout: a starved machine's tare takes its 100 samples slowly)."""
        deadline = time.monotonic() + self.cfg.sim.ready_timeout
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

    def status_snapshot(self) -> dict[str, Any]:
        """The control socket's ``status``: :meth:`status`, rebuilt at most every
        :data:`STATUS_MAX_AGE` however many clients ask, and at once when the safety
        state, the fault, the conditions' count, the mode or the tare changed (so a
        status right after a command shows its effect).  The loop's state is read, not
        locked; the dict returned is never changed afterwards (a new one each rebuild)."""
        s, core = self.safety, self.core
        calib = self.calibration
        key = (s.state, s.latched, len(s.active), core.mode, core.switch, core.taring,
               self.enabling_state(), core.profile, len(core.changed), id(core.cfg),
               None if calib is None else (calib.phase, calib.index, calib.closed))
        with self._snapshot_lock:
            snap = self._snapshot
            now = time.monotonic()
            if snap is None or now - snap[0] > STATUS_MAX_AGE or snap[1] != key:
                snap = self._snapshot = (now, key, self.status())
        return snap[2]

    def loop_stats(self) -> dict[str, Any]:
        """The loop's timing over the last 5 s, recomputed at most every
        :data:`STATS_MAX_AGE` (percentiles over 2 500 cycles: about a millisecond of the
        interpreter the loop shares, the largest part of a status by far)."""
        with self._snapshot_lock:
            cached = self._loop_stats
            now = time.monotonic()
            if cached is None or now - cached[0] > STATS_MAX_AGE:
                stats = self.ring.stats(min(self.ring.size,
                                            int(self.cfg.loop.rate_hz * STATS_WINDOW)))
                cached = self._loop_stats = (now, stats.as_dict())
        return cached[1]

    def status(self) -> dict[str, Any]:
        """Plain-JSON snapshot for ``mmctl status`` (any thread)."""
        out: dict[str, Any] = {
            **self.safety.as_dict(),
            "mode": self.core.mode,
            "switch": self.core.switch,
            "taring": self.core.taring,
            "enabling": self.enabling_state(),
            "profile": self.core.profile,
            "caps": self.core.caps,
            "changed": dict(self.core.changed),
            "cycles": self.cycles,
            "uptime_s": round(time.monotonic() - self._started, 3),
            "loop": self._loop_block(self.loop_stats(), running=self.loop.running),
            "commands": dict(self.commands_sent),
            "config": self.cfg.name,
        }
        last = self.last
        if last is not None:
            out["robot"] = {"q": _round(last.q), "ee_position": _round(last.p),
                            "f_h": _round(last.f_h),
                            **self._measured(last),
                            "desired": {"v_d": _round(last.v_d),
                                        "ee_speed_m_s": round(float(
                                            np.linalg.norm(last.v_d[:3])), 4)},
                            "speed_scaling": round(float(self.speed_scaling), 4),
                            "limit": last.out.limit if last.out is not None else ""}
        if self.calibration is not None:
            out["calibration"] = self.calibration.progress()
        if self.sim is not None:
            out["sim"] = self.sim.status()
        if self.telemetry is not None:
            out["telemetry"] = self.telemetry.status()
        out["process"] = {
            "pid": os.getpid(), "threads": sorted(t.name for t in threading.enumerate()),
            # on the robot and on the simulated robot alike: no simulation code in here
            "simulation_loaded": any(m in sys.modules for m in ("mmctl.sim", "mmctl.study")),
            # the device links' own processes (None: in this process, or not running)
            "links": {name: getattr(getattr(self.devices, name), "pid", None)
                      for name in ("arm", "sensor", "base")},
        }
        if isinstance(self.server, ProcessControlServer):
            # the control socket's own process (None between a crash and its restart)
            out["process"]["socket_process"] = {"pid": self.server.pid,
                                                "starts": self.server.started}
        return out


    def _loop_block(self, stats: dict[str, Any], **extra: Any) -> dict[str, Any]:
        """The loop's figures as status and the live view show them: timing over the
        last :data:`STATS_WINDOW` s, and misses with one definition (deadlines missed /
        (cycles run + deadlines missed)), over that window and since the start."""
        loop = self.loop
        since = loop.missed_since_start
        return {"rate_hz": self.cfg.loop.rate_hz, **extra, **stats,
                "window_s": STATS_WINDOW,
                "misses": {"window": stats.get("missed", 0),
                           "window_pct": round(100.0 * float(stats.get("miss_rate", 0.0)), 3),
                           "since_start": since,
                           "since_start_pct": round(100.0 * since / max(loop.cycles + since, 1),
                                                    3)},
                "budget_misses": loop.total_misses,
                **({} if loop.gc_slack is None else {"gc_in_slack": {
                    "collections": list(loop.gc_slack.collections),
                    "worst_us": round(loop.gc_slack.worst_ns / 1e3, 1)}})}

    def _measured(self, last: CycleResult) -> dict[str, Any]:
        """The robot's motion as measured (end-effector and base speed, E_K from the
        measured velocities; zero at rest), or None where the newest cycle could not
        read a device (``measured_age_cycles`` says how old the numbers are)."""
        age = self.cycles - self.last_cycle
        if age > MEASURED_MAX_AGE:
            return {"ee_speed_m_s": None, "base_speed_m_s": None, "base_yaw_rate": None,
                    "energy_J": None, "energy_arm_J": None, "energy_base_J": None,
                    "measured_age_cycles": age}
        return {"ee_speed_m_s": round(float(np.linalg.norm(last.v[:3])), 4),
                "base_speed_m_s": round(float(np.hypot(last.qd[6], last.qd[7])), 4),
                "base_yaw_rate": round(float(last.qd[8]), 4),
                "energy_J": round(float(last.energy.total), 6),
                "energy_arm_J": round(float(last.energy.arm), 6),
                "energy_base_J": round(float(last.energy.base), 6),
                "measured_age_cycles": age}

    def enabling_state(self) -> str | None:
        """The enabling switch as the last cycle read it: "held", "released",
        "disagree" (its contacts differ), or None (no enabling switch configured)."""
        if not self.cfg.enabling.inputs:
            return None
        return {True: "held", False: "released", None: "disagree"}[self.ustate.enabling.held]

    def live(self) -> dict[str, Any]:
        """The live terminal view's snapshot (:mod:`mmctl.runtime.liveview`; any thread,
        a few times a second: the last second of loop timing, the newest cycle)."""
        out: dict[str, Any] = {
            "state": self.safety.state.value, "mode": self.core.mode,
            "fault": self.safety.as_dict().get("fault"), "taring": self.core.taring,
            "enabling": self.enabling_state(),
            "cycles": self.cycles, "uptime_s": time.monotonic() - self._started,
            "loop": self._loop_block(self.loop_stats()),
        }
        last = self.last
        if last is not None:
            m = self._measured(last)
            out.update(f_h=[float(x) for x in last.f_h], ee_speed=m["ee_speed_m_s"],
                       base_speed=m["base_speed_m_s"], base_yaw_rate=m["base_yaw_rate"],
                       energy_arm=m["energy_arm_J"], energy_base=m["energy_base_J"],
                       ee_speed_desired=float(np.linalg.norm(last.v_d[:3])))
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
