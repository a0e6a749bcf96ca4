"""`mmctl sim`: the simulated robot as a process of its own, with its own control socket.

It runs a :class:`~mmctl.sim.world.SimWorld` (the fake UR controller process, the fake
sensor and drives on python-can's virtual bus, served over socketcand, the simulated
person) and answers on ``sim.socket_path`` (one JSON object per line, the daemon's
protocol, :mod:`mmctl.runtime.ipc`).  Requests:

``status``; ``push`` (``force`` [fx, fy, fz] N in the world frame or null to end it,
``seconds``); ``person`` (``on`` true/false, ``hold`` seconds: let go while the
daemon tares); ``press`` (the handle button); ``fault`` (``name``, ``on``); ``log``
(the fakes' command logs and the sensor's push steps from ``since`` on: what the
benchmarks read); ``stop``.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import structlog

from mmctl.config import Config
from mmctl.errors import MmctlError
from mmctl.runtime.ipc import ControlServer, Peer
from mmctl.runtime.sim_link import sim_socket_path
from mmctl.sim.world import FAULTS, SimWorld

log = structlog.get_logger("mmctl.sim")

#: What ends `mmctl sim` (stop the fakes, write the logs, remove the socket).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGQUIT)


class SimService:
    """The simulated robot and its control socket (see the module docstring)."""

    def __init__(self, cfg: Config, log_dir: Path | None = None,
                 exit_with_parent: bool = False):
        self.cfg = cfg
        self.world = SimWorld(cfg, log_dir=log_dir)
        self.path = sim_socket_path(cfg)
        self.server = ControlServer(self.path, self.handle, mode=cfg.daemon.socket_mode)
        self._stop = threading.Event()
        self.stop_reason = ""
        self._parent = os.getppid() if exit_with_parent else None
        self._handlers = self._command_table()

    def request_stop(self, reason: str) -> None:
        self.stop_reason = self.stop_reason or reason
        self._stop.set()

    def run(self, install_signals: bool = True) -> int:
        """Serve until a stop (signal, ``stop`` request, the parent gone); 0 when clean."""
        if install_signals:
            for sig in STOP_SIGNALS:
                signal.signal(sig, lambda n, _f: self.request_stop(signal.Signals(n).name))
        self.server.open()  # refuses when another simulation answers on the socket
        try:
            self.world.start()
            self.server.start()
            log.info("sim_ready", socket=str(self.path), pid=os.getpid(),
                     hint="mmctl sim status | push FX FY FZ | person on|off | fault NAME")
            while not self._stop.wait(0.25):
                if self._parent is not None and os.getppid() != self._parent:
                    self.request_stop("parent_exited")
        finally:
            log.info("sim_stopping", reason=self.stop_reason or "error")
            try:
                self.server.close()
            finally:
                self.world.close()
        return 0

    # -- requests -----------------------------------------------------------------------
    def handle(self, req: Mapping[str, Any], _peer: Peer) -> Any:
        """Dispatch one request (see the module docstring)."""
        cmd = req.get("cmd")
        handler = self._handlers.get(cmd) if isinstance(cmd, str) else None
        if handler is None:
            raise MmctlError(f"unknown command {cmd!r}; known: {', '.join(self._handlers)}")
        return handler(req)

    def _command_table(self) -> dict[str, Callable[[Mapping[str, Any]], Any]]:
        return {
            "status": lambda req: {**self._then_status(), "pid": os.getpid(),
                                   "config": self.cfg.name, "faults_known": FAULTS},
            "push": self._cmd_push,
            "person": self._cmd_person,
            "press": self._cmd_press,
            "fault": self._cmd_fault,
            "log": self._log,
            "stop": self._cmd_stop,
        }

    def _then_status(self) -> dict[str, Any]:
        """The world's status (taken once) and what the person does."""
        st = self.world.status()
        return {**st, "person": _person(st)}

    def _cmd_press(self, req: Mapping[str, Any]) -> Any:
        self.world.press()
        return self._then_status()

    def _cmd_push(self, req: Mapping[str, Any]) -> Any:
        self.world.set_push(req.get("force"), req.get("seconds"))
        return self._then_status()

    def _cmd_person(self, req: Mapping[str, Any]) -> Any:
        w = self.world
        if "on" in req:
            w.set_push(None)
            w.human_on = bool(req["on"]) and self.cfg.sim.human
        if "hold" in req:
            hold = req["hold"]
            if not isinstance(hold, (int, float)) or isinstance(hold, bool):
                raise MmctlError(f"hold needs seconds (a number), got {hold!r}")
            w.hold(float(hold))
        return self._then_status()

    def _cmd_fault(self, req: Mapping[str, Any]) -> Any:
        name = req.get("name")
        if not isinstance(name, str):
            raise MmctlError(f"fault needs a name; known: {', '.join(FAULTS)}")
        self.world.inject(name, bool(req.get("on", True)))
        return self._then_status()

    def _cmd_stop(self, req: Mapping[str, Any]) -> Any:
        self.request_stop("requested")
        return {"stopping": True}

    def _log(self, req: Mapping[str, Any]) -> dict[str, Any]:
        """The fakes' logs from ``since`` on (CLOCK_MONOTONIC [s], ``time.monotonic()``
        of any process here): UR commands as [seq, kind, received, qd], per drive
        [received, target counts/s], and the sensor's push steps [step, the time of the
        first sample that carried it]."""
        since = req.get("since", 0.0)
        if not isinstance(since, (int, float)) or isinstance(since, bool):
            raise MmctlError(f"log needs 'since' (CLOCK_MONOTONIC seconds), got {since!r}")
        w = self.world
        cmds = w.ur.commands()
        ur = [[c.seq, c.kind.value, c.received, None if c.qd is None else list(c.qd)]
              for c in cmds if c.received is not None and c.received >= since]
        ids = self.cfg.base.canopen.node_ids
        drives = {str(nid): [e for e in w.drives.command_log(nid) if e[0] >= since]
                  for nid in ids}
        return {"ur": ur, "drives": drives,
                "steps": [s for s in w.step_samples if s[1] >= since]}


def _person(st: Mapping[str, Any]) -> str:
    """holding / push / on / off, from the world's status."""
    if st["holding"]:
        return "holding"
    if st["push"] is not None:
        return "push"
    return "on" if st["human"] else "off"
