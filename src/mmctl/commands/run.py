"""Run the control daemon (foreground; Ctrl-C or `mmctl stop` ends it).

Without --config it uses $MMCTL_CONFIG, else ./config/sim.yaml: the simulated robot
(fake UR controller, CAN sensor, CANopen drives and a simulated person pushing the
handle), in a process of its own (`mmctl sim`): this command attaches to one that
answers, or starts its own before the daemon connects and stops it after the robot
stopped (the daemon itself never starts or stops a simulation).  It arms itself, so
the robot moves within seconds.  With config/robot.yaml it drives the real robot and
starts DISARMED: `mmctl enable`.

On a terminal a live block shows state, mode, fault, wrench, speeds, kinetic energy
and loop timing, with the log lines scrolling above it (--no-live: plain lines).
Elsewhere (a pipe, journald) a ``summary`` event every --summary-every seconds says
the same in one line.  A start that fails ends with ``daemon_stopped`` naming the
error, and leaves no live block behind.
Push the simulated handle yourself from another terminal: `mmctl sim push 30 0 0`.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mmctl.runtime.daemon import Daemon


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE", help="YAML config (default: config/sim.yaml)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="stop after this many seconds (default: run until stopped)")
    p.add_argument("--socket", metavar="PATH", help="control socket (overrides daemon.socket_path)")
    p.add_argument("--sim-log", metavar="DIR",
                   help="simulation: write the fakes' command logs to DIR on shutdown")
    p.add_argument("--log-level", choices=("debug", "info", "warning", "error"),
                   help="override daemon.log_level")
    p.add_argument("--log-json", action="store_true", help="JSON log lines even on a TTY")
    p.add_argument("--viewer", action="store_true", help="telemetry: spawn a local rerun viewer")
    p.add_argument("--connect", metavar="ADDR",
                   help="telemetry: stream to a running rerun viewer (HOST:PORT or URL)")
    p.add_argument("--record", metavar="FILE", help="telemetry: save a .rrd recording")
    p.add_argument("--ros2", action="store_true",
                   help="publish the robot to ROS 2 (ros2.enabled; the mmctl[ros2] extra; "
                        "docs/ros2.md)")
    p.add_argument("--record-inputs", metavar="DIR",
                   help="write every cycle's readings, operator commands and the update's "
                        "commands to the new folder DIR (for `mmctl replay DIR`; about 1 GB "
                        "an hour at 500 Hz)")
    p.add_argument("--no-live", action="store_true",
                   help="no live status block on a terminal (plain log lines)")
    p.add_argument("--summary-every", type=float, default=5.0, metavar="S",
                   help="where no live block shows (a pipe, journald, --no-live): log a "
                        "one-line summary (state, mode, speeds, E_K, misses) every S "
                        "seconds (default 5; 0: none)")


def run(args: argparse.Namespace) -> int:
    import faulthandler

    faulthandler.enable()  # a crash in a C extension leaves every thread's stack in the log
    try:
        return _run(args)
    except KeyboardInterrupt:  # Ctrl-C before the daemon took the signals over: no devices
        return 130


def _run(args: argparse.Namespace) -> int:
    import math
    import sys
    from pathlib import Path

    from mmctl.errors import MmctlError
    from mmctl.runtime.client import load
    from mmctl.runtime.factory import create_daemon
    from mmctl.runtime.ipc import resolve_socket_path
    from mmctl.runtime.logging import setup_logging

    cfg = load(args.config)
    if args.ros2:
        import dataclasses

        from mmctl.extras import require

        require("ros2", "--ros2")
        plain: Any = cfg  # (a config section is a dataclass mypy does not see as one)
        cfg = dataclasses.replace(plain, ros2=dataclasses.replace(plain.ros2, enabled=True))
    setup_logging(args.log_level or cfg.daemon.log_level, json=True if args.log_json else None)
    socket_path = Path(args.socket) if args.socket else resolve_socket_path(cfg.daemon.socket_path)
    from mmctl.telemetry.service import TelemetryService, destinations_from

    destinations = destinations_from(cfg, viewer=args.viewer, connect=args.connect,
                                     record=args.record)
    if destinations.any:  # before anything starts: a missing extra is one line
        from mmctl.extras import require

        require("telemetry", "telemetry (--viewer, --connect, --record)")
    telemetry = TelemetryService(cfg, destinations)
    input_log = None
    if args.record_inputs:
        from mmctl.runtime.inputlog import InputLog

        input_log = InputLog(args.record_inputs, cfg)
        input_log.open()  # before anything starts: a folder in use is one line
    from mmctl.runtime.factory import sim_link

    # the simulated robot is this command's, never the daemon's: opened before the
    # daemon connects to it, closed after the daemon stopped (on the robot: none)
    sim = sim_link(cfg, Path(args.sim_log) if args.sim_log else None)
    if not (args.summary_every >= 0 and math.isfinite(args.summary_every)):
        raise MmctlError(f"--summary-every {args.summary_every!r}: seconds >= 0 (0: none)")
    view = summary = None
    ran = False
    try:
        daemon = create_daemon(cfg, socket_path, sim=sim, telemetry=telemetry,
                               input_log=input_log)
        daemon.install_signals()  # a signal while the simulation starts is a stop too
        if sys.stdout.isatty() and not args.log_json and not args.no_live:
            from mmctl.runtime.liveview import LiveView

            view = LiveView(daemon.live, stderr=True).start()  # before any child: theirs too
        elif args.summary_every > 0:
            import structlog

            from mmctl.runtime.liveview import SummaryLog

            summary = SummaryLog(daemon.live, args.summary_every,
                                 structlog.get_logger("mmctl.daemon")).start()
        if sim is not None:
            sim.start(lambda: daemon.stopping)
        on_ready = auto_enable if sim is not None and cfg.sim.auto_enable else None
        code = daemon.run(duration=args.duration, install_signals=False, on_ready=on_ready)
        ran = True
        return code
    finally:
        if summary is not None:
            summary.stop()
        if view is not None:
            view.stop(keep_block=ran)  # a start that failed: no block of a robot never run
        if sim is not None:
            sim.close()
        if input_log is not None:
            input_log.close()  # (idempotent: the daemon's shutdown closes it too)


def auto_enable(daemon: Daemon) -> None:
    """Simulation only, once the daemon is ready: tare, arm, and let the simulated
    person start (within sim.ready_timeout: a starved machine's tare takes its 100
    samples slowly).  A failure is logged, not fatal: the operator can `mmctl enable`."""
    import structlog

    from mmctl.errors import MmctlError

    log = structlog.get_logger("mmctl.daemon")
    cfg = daemon.cfg
    try:
        daemon.tare_and_enable(cfg.sim.ready_timeout)
    except MmctlError as exc:
        log.warning("auto_enable_failed", error=str(exc))
        return
    log.info("auto_enabled", mode=daemon.core.mode)
    if cfg.sim.human and daemon.sim is not None:  # (else a push set meanwhile stays)
        daemon.sim.start_human()
