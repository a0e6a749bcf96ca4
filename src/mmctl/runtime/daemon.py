"""The daemon: devices + control core + safety + loop + control socket + systemd notify.

This module is the lifecycle (open, start, run, shutdown, signals, readiness) and the
status.  :class:`Daemon` holds three parts, none of which knows the daemon:

- :class:`~mmctl.runtime.driver.LoopRuntime`: the loop thread's cycle (read -> pure
  update -> write) and what it works on;
- :class:`~mmctl.runtime.operator.Operator`: the control socket's commands, which reach
  the loop as values in its inbox, and an enable's device work off the loop thread;
- :class:`~mmctl.runtime.calibrate.Calibrations`: `mmctl calibrate tool`.

One cycle (:meth:`LoopRuntime.cycle <mmctl.runtime.driver.LoopRuntime.cycle>`, on the
loop thread):

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
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog
from numpy.typing import ArrayLike

from mmctl.config import Config
from mmctl.control import safety as sm
from mmctl.control.safety import Safety
from mmctl.control.update import UpdateState
from mmctl.errors import FaultCause, MmctlError
from mmctl.runtime.calibrate import Calibrations
from mmctl.runtime.core import ControlCore, CycleResult
from mmctl.runtime.devices import Devices
from mmctl.runtime.driver import PHASES, LoopRuntime, SampleHook
from mmctl.runtime.ipc import Handler, Peer
from mmctl.runtime.ipc_process import ProcessControlServer
from mmctl.runtime.loop import Tick, Wait
from mmctl.runtime.notify import Notifier
from mmctl.runtime.operator import Operator
from mmctl.runtime.pmqos import CpuLatencyRequest
from mmctl.runtime.safety import SafetyState, log_events

if TYPE_CHECKING:
    from mmctl.control.calibration import ToolCalibration
    from mmctl.runtime.inputlog import InputLog
    from mmctl.runtime.sim_link import SimLink
    from mmctl.telemetry.service import TelemetryService

__all__ = ["PHASES", "STOP_SIGNALS", "Daemon", "SampleHook", "StartAborted"]

log = structlog.get_logger("mmctl.daemon")

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
    from mmctl.runtime import logging as mmctl_logging

    cpus: tuple[int, ...] = ()
    loop_cpus = set(cfg.loop.cpu_affinity)
    if loop_cpus and hasattr(os, "sched_getaffinity"):
        cpus = tuple(sorted(os.sched_getaffinity(0) - loop_cpus))  # off the loop's CPUs
    return ProcessControlServer(path, handler, cfg.daemon.socket_mode,
                                log_setup=mmctl_logging.CURRENT, cpus=cpus,
                                inline=("status",), urgent=("stop", "disable"))


class StartAborted(Exception):
    """A stop request arrived while :meth:`Daemon.open` was still starting."""


class Daemon:
    """Composition root of the running daemon (see the module docstring).

    cfg: the configuration; devices: not yet connected; core: the control chain;
    socket_path: where to serve the control socket (None = no socket, for in-process
    tests); notifier: systemd notify (default: from the environment); sim: the link to
    the simulated robot's own process, already opened by whoever runs the daemon (a
    :class:`~mmctl.runtime.sim_link.SimLink`: the daemon asks it for its status and
    lets the person's hands go for a tare, never starts or stops it), or None;
    telemetry: a :class:`~mmctl.telemetry.service.TelemetryService` (its hook becomes
    the loop's sample hook, ``trial`` requests go to it), or None; loop_wait: the loop's
    wait for each deadline (default: sleep, then spin; benchmarks give their own);
    input_log: every cycle's readings, inbox and commands are written into it.
    """

    def __init__(self, cfg: Config, devices: Devices, core: ControlCore, *,
                 socket_path: Path | None = None, notifier: Notifier | None = None,
                 sim: SimLink | None = None, telemetry: TelemetryService | None = None,
                 loop_wait: Wait | None = None, input_log: InputLog | None = None):
        self.cfg = cfg
        self.devices = devices
        self.core = core
        self.notifier = notifier if notifier is not None else Notifier()
        self.sim = sim
        self.telemetry = telemetry
        self.input_log = input_log
        self._stop_requested = threading.Event()
        #: the loop thread's cycle and what it works on
        self.runtime = LoopRuntime(cfg, devices, core, notifier=self.notifier,
                                   stop_requested=self._stop_requested,
                                   input_log=input_log, loop_wait=loop_wait)
        #: `mmctl calibrate tool`'s requests and the routine's part of each cycle
        self.calibrations = Calibrations(self.runtime)
        #: the control socket's commands
        self.operator = Operator(self.runtime, self.calibrations,
                                 status=self.status_snapshot, request_stop=self.request_stop,
                                 sim=sim, telemetry=telemetry)
        rt = self.runtime
        self.loop = rt.loop
        self.ring, self.step_ns, self.hook_ns, self.phase_ns = (
            rt.ring, rt.step_ns, rt.hook_ns, rt.phase_ns)
        self.period = rt.period
        # status: a snapshot (inline, on the socket's selector thread); stop and disable
        # never queue behind other clients' requests (see mmctl.runtime.ipc)
        self.server = (_control_server(cfg, socket_path, self.operator.handle)
                       if socket_path is not None else None)
        self._snapshot: tuple[float, tuple[object, ...], dict[str, object]] | None = None
        self._snapshot_lock = threading.RLock()  # (status() in it asks for loop_stats)
        self._loop_stats: tuple[float, dict[str, float | int]] | None = None
        self.stop_reason = ""
        #: what ended :meth:`run` early (a device that did not connect, ...), else None
        self.error: BaseException | None = None
        self._started = time.monotonic()
        self.cpu_latency = (CpuLatencyRequest(cfg.loop.cpu_dma_latency)
                            if cfg.loop.cpu_dma_latency >= 0 else None)

    # -- the parts' state, as tools and tests read it -------------------------------
    @property
    def safety(self) -> Safety:
        """The safety state machine's value as the last cycle left it."""
        return self.runtime.safety

    @property
    def speed_scaling(self) -> float:
        """The arm's speed scaling in the last sample (speed slider x reduced mode)."""
        return self.runtime.speed_scaling

    @property
    def ustate(self) -> UpdateState:
        """The update's state as the last cycle left it."""
        return self.runtime.ustate

    @property
    def cycles(self) -> int:
        """Cycles run since the start."""
        return self.runtime.cycles

    @property
    def last(self) -> CycleResult | None:
        """The newest cycle's numbers (None: no device read yet)."""
        return self.runtime.last

    @property
    def last_conditions(self) -> Mapping[FaultCause, Mapping[str, object]]:
        """The conditions the newest update saw."""
        return self.runtime.last_conditions

    @property
    def commands_sent(self) -> dict[str, int]:
        """Commands sent to the devices since the start, by kind."""
        return self.runtime.commands_sent

    @property
    def calibration(self) -> ToolCalibration | None:
        """The newest tool-load calibration (running or ended), or None."""
        return self.runtime.calibration

    @property
    def sample_hook(self) -> SampleHook | None:
        """The loop's per-cycle telemetry hook (set it before the loop starts)."""
        return self.runtime.sample_hook

    @sample_hook.setter
    def sample_hook(self, hook: SampleHook | None) -> None:
        self.runtime.sample_hook = hook

    def cycle(self, tick: Tick) -> None:
        """One control period (:meth:`LoopRuntime.cycle`)."""
        self.runtime.cycle(tick)

    def step_once(self, overrun: bool = False) -> None:
        """One cycle on the calling thread (tests and tools without the loop thread)."""
        self.runtime.step_once(overrun)

    def call(self, cmd: str, **args: object) -> Any:
        """Run one control command (same names as the socket's) and wait for its result."""
        return self.operator.call(cmd, **args)

    def handle(self, req: Mapping[str, object], peer: Peer | None = None) -> object:
        """One control-socket request (:meth:`Operator.handle`)."""
        return self.operator.handle(req, peer)

    # ------------------------------------------------------------------ lifecycle --
    def open(self) -> None:
        """Claim the control socket, connect the devices (in that order).  The simulated
        robot, if any, is already up: its owner (`mmctl run`) opened it first."""
        if self.server is not None:
            self.server.open()
        try:
            if self._stop_requested.is_set():
                raise StartAborted("stopped before the devices were connected")
            self.devices.connect()
        except BaseException:
            if self.server is not None:
                self.server.close()
            raise
        self.notifier.connect()

    def start(self) -> None:
        """Start the loop and the control socket."""
        sys.setswitchinterval(self.cfg.loop.switch_interval)
        if self.cpu_latency is not None:
            self.cpu_latency.acquire()  # best effort: a warning when not permitted
        gc.collect()
        gc.freeze()  # start-up objects (models, fakes) out of every later collection
        self.runtime.t0_ns = time.perf_counter_ns()
        if self.telemetry is not None:
            self.telemetry.start(ring=self.ring, origin_ns=self.runtime.t0_ns)
            self.runtime.sample_hook = self.telemetry.hook(self.core)
        self.loop.start()
        if self.server is not None:
            self.server.start()

    @property
    def origin_ns(self) -> int:
        """perf_counter_ns of t = 0 (set by :meth:`start`); a sample's ``t`` counts from it."""
        return self.runtime.t0_ns

    @property
    def stopping(self) -> bool:
        """True once a stop was asked for (signal, ``mmctl stop``, :meth:`request_stop`)."""
        return self._stop_requested.is_set()

    def run(self, duration: float | None = None, install_signals: bool = True,
            on_ready: Callable[[Daemon], None] | None = None) -> int:
        """open, start, wait for a stop (signal, ``mmctl stop``, duration), shut down.

        on_ready: called once the daemon is ready (on this thread, before the wait; `mmctl
        run` arms the simulated robot with it).  Returns the process exit status (0
        clean, 1 if the loop died of an error).
        """
        if install_signals:
            self.install_signals()
        try:
            self.open()
            self.start()
            self._wait_ready()
            if on_ready is not None and not self._stop_requested.is_set():
                on_ready(self)
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
            self.error = exc
            raise
        finally:
            self.shutdown()
        return 1 if self.loop.error is not None else 0

    def tare_and_enable(self, timeout: float) -> None:
        """Tare (hands off), then arm, within ``timeout`` [s]: ``enable`` is retried
        while a condition flickers (fakes settling at start-up); MmctlError when it is
        still refused at the end, or the daemon stops meanwhile (`mmctl run`'s
        auto-enable on the simulated robot, the benchmarks)."""
        deadline = time.monotonic() + timeout
        self.call("tare")
        while self.core.taring and time.monotonic() < deadline and self.loop.running:
            time.sleep(0.01)
        while True:
            try:
                self.call("enable")
                return
            except MmctlError:
                if time.monotonic() > deadline or self.stopping:
                    raise
                time.sleep(0.1)

    def request_stop(self, reason: str = "requested") -> None:
        """Ask :meth:`run` to shut down (any thread, signal handler)."""
        self.stop_reason = self.stop_reason or reason
        self._stop_requested.set()

    def shutdown(self) -> None:
        """Stop the loop, send the stop commands, close devices and socket (idempotent)."""
        self.notifier.stopping(f"stopping ({self.stop_reason or 'shutdown'})")
        log.info("daemon_stopping", reason=self.stop_reason or "shutdown")
        self.loop.stop()
        self.loop.wait(5.0)
        co = self.cfg.base.canopen
        enable_done = self.operator.base_enable.acquire(timeout=co.stop_timeout + 4 * co.sdo_timeout + 2)
        if not enable_done:
            log.error("base_enable_still_running", why="stopping the devices anyway")
        if self.devices.connected:
            self.devices.stop(self.cfg.arm.stop_deceleration, arm=not self.runtime.arm_busy)
            self.commands_sent["stop"] += 1
            if self.safety.state is SafetyState.ARMED:  # (the loop has ended)
                rt = self.runtime
                safety, _, events = sm.disable(rt.safety)
                rt.ustate = rt.ustate._replace(safety=safety)
                log_events(events, self.runtime.limiter)
        if enable_done:
            self.operator.base_enable.release()
        if self.server is not None:
            try:
                self.server.close()
            except OSError as exc:
                log.error("socket_close_failed", error=str(exc))
        if self.telemetry is not None:
            self.telemetry.close()
        if self.input_log is not None:
            self.input_log.close()
        reconnect_done = self.operator.arm_reconnect.acquire(timeout=3 * self.cfg.arm.connect_timeout + 2)
        if not reconnect_done:  # never close the arm under a reconnect in progress
            log.error("arm_reconnect_still_running", why="the arm is not closed")
            self.devices.connected.clear()
        self.devices.close(arm=reconnect_done)
        if reconnect_done:
            self.operator.arm_reconnect.release()
        if self.cpu_latency is not None:
            self.cpu_latency.release()
        self.notifier.close()
        error = self.loop.error or self.error
        (log.error if error is not None else log.info)(
            "daemon_stopped", cycles=self.cycles,
            error=None if error is None else str(error) or repr(error))

    def install_signals(self) -> None:
        """Every signal whose default would end the process is a stop: the stop commands
        go out, then the devices close (:data:`STOP_SIGNALS`).  The handler only sets
        the stop request, so a second signal during the shutdown changes nothing."""
        def on_signal(signum: int, _frame: FrameType | None) -> None:
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
            healthy = self.runtime.healthy_cycle.wait(min(left, 0.05))  # a stop is seen at once
            if healthy:
                break
        if not healthy:
            log.warning("ready_without_healthy_cycle",
                        conditions=sorted(c.value for c in self.last_conditions))
        self.notifier.ready(self.runtime.status_line())
        log.info("daemon_ready", state=self.safety.state.value, mode=self.core.mode,
                 socket=str(self.server.path) if self.server else None)

    # -------------------------------------------------------------------- status --
    def status_snapshot(self) -> dict[str, object]:
        """The control socket's ``status``: :meth:`status`, rebuilt at most every
        :data:`STATUS_MAX_AGE` however many clients ask, and at once when the safety
        state, the fault, the conditions' count, the mode or the tare changed (so a
        status right after a command shows its effect).  The loop's state is read, not
        locked; the dict returned is never changed afterwards (a new one each rebuild)."""
        s, core = self.safety, self.core
        calib = self.calibration
        key = (s.state, s.latched, len(s.active), core.mode, core.switch, core.taring,
               self.runtime.enabling_state(), core.profile, len(core.changed), id(core.cfg),
               None if calib is None else (calib.phase, calib.index, calib.closed))
        with self._snapshot_lock:
            snap = self._snapshot
            now = time.monotonic()
            if snap is None or now - snap[0] > STATUS_MAX_AGE or snap[1] != key:
                snap = self._snapshot = (now, key, self.status())
        return snap[2]

    def loop_stats(self) -> dict[str, float | int]:
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

    def status(self) -> dict[str, object]:
        """Plain-JSON snapshot for ``mmctl status`` (any thread)."""
        out: dict[str, object] = {
            **self.safety.as_dict(),
            "mode": self.core.mode,
            "switch": self.core.switch,
            "taring": self.core.taring,
            "enabling": self.runtime.enabling_state(),
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
                            "limit": last.out.limit if last.out is not None else "",
                            "nearest_parts": _nearest(last)}
        if self.calibration is not None:
            out["calibration"] = self.calibration.progress()
        if self.sim is not None:
            out["sim"] = self.sim.status()
        if self.telemetry is not None:
            out["telemetry"] = self.telemetry.status()
        process: dict[str, object] = {
            "pid": os.getpid(), "threads": sorted(t.name for t in threading.enumerate()),
            # on the robot and on the simulated robot alike: no simulation code in here
            "simulation_loaded": any(m in sys.modules for m in ("mmctl.sim", "mmctl.study")),
            # the device links' own processes (None: in this process, or not running)
            "links": {name: getattr(getattr(self.devices, name), "pid", None)
                      for name in ("arm", "sensor", "base")},
        }
        if isinstance(self.server, ProcessControlServer):
            # the control socket's own process (None between a crash and its restart)
            process["socket_process"] = {"pid": self.server.pid,
                                         "starts": self.server.started}
        out["process"] = process
        return out


    def _loop_block(self, stats: Mapping[str, float | int], **extra: object
                    ) -> dict[str, object]:
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

    def _measured(self, last: CycleResult) -> dict[str, object]:
        """The robot's motion as measured (end-effector and base speed, E_K from the
        measured velocities; zero at rest), or None where the newest cycle could not
        read a device (``measured_age_cycles`` says how old the numbers are)."""
        age = self.cycles - self.runtime.last_cycle
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

    def live(self) -> dict[str, object]:
        """The live terminal view's snapshot (:mod:`mmctl.runtime.liveview`; any thread,
        a few times a second: the last second of loop timing, the newest cycle)."""
        out: dict[str, object] = {
            "state": self.safety.state.value, "mode": self.core.mode,
            "fault": self.safety.as_dict().get("fault"), "taring": self.core.taring,
            "enabling": self.runtime.enabling_state(),
            "cycles": self.cycles, "uptime_s": time.monotonic() - self._started,
            "loop": self._loop_block(self.loop_stats()),
        }
        last = self.last
        if last is not None:
            m = self._measured(last)
            out.update(f_h=[float(x) for x in last.f_h], ee_speed=m["ee_speed_m_s"],
                       base_speed=m["base_speed_m_s"], base_yaw_rate=m["base_yaw_rate"],
                       energy_arm=m["energy_arm_J"], energy_base=m["energy_base_J"],
                       ee_speed_desired=float(np.linalg.norm(last.v_d[:3])),
                       limit=last.out.limit if last.out is not None else "",
                       nearest_parts=_nearest(last))
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


def _nearest(last: CycleResult) -> dict[str, object] | None:
    """The robot's two nearest parts and their distance (the self-collision check's),
    or None when the controller did not run the check."""
    body = last.out.body if last.out is not None else None
    if body is None:
        return None
    return {"pair": "-".join(body[0]), "distance_m": round(body[1], 4)}


def _round(v: ArrayLike, nd: int = 5) -> list[float]:
    return [round(float(x), nd) if math.isfinite(float(x)) else float("nan")
            for x in np.asarray(v).ravel()]
