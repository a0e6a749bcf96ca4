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

Every request is validated as a whole before anything is applied, like the
configuration: an unknown field, a wrong type (a bool must be a JSON ``true``/``false``,
a number a finite JSON number) or a value out of range is one error reply naming the
command, the field, the value and what is allowed, and nothing changes.
"""

from __future__ import annotations

import math
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
from mmctl.sim.fake_ur.log import CommandKind
from mmctl.sim.world import FAULTS, SimWorld

log = structlog.get_logger("mmctl.sim")

#: What ends `mmctl sim` (stop the fakes, write the logs, remove the socket).
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGQUIT)

#: Fields of the control protocol itself, in any request (:mod:`mmctl.runtime.ipc`).
ENVELOPE = frozenset({"cmd", "timeout_s"})
#: A push per axis at most [N]: beyond the Axia80's largest range (900 N along z).
MAX_PUSH_FORCE = 1000.0
#: The longest push [s] (a soak runs for hours with pushes of seconds).
MAX_PUSH_SECONDS = 3600.0
#: The longest the person lets go for a tare [s] (:meth:`SimWorld.hold`'s own range).
MAX_HOLD_SECONDS = 60.0
#: Each command's fields (besides :data:`ENVELOPE`) and what they take.
FIELDS: dict[str, dict[str, str]] = {
    "status": {},
    "push": {"force": f"[fx, fy, fz] N (world frame, each |f| <= {MAX_PUSH_FORCE:g}) or null "
                      "to end the push",
             "seconds": f"how long the push lasts: 0 < s <= {MAX_PUSH_SECONDS:g}, or null "
                        "(until ended)"},
    "person": {"on": "true or false", "hold": f"0 <= s <= {MAX_HOLD_SECONDS:g}"},
    "press": {},
    "enabling": {"held": "true or false"},
    "slider": {"fraction": "the pendant's speed slider, 0 <= f <= 1"},
    "fault": {"name": "one of the known faults (mmctl sim fault --list)",
              "on": "true or false (default true)"},
    "log": {"since": "CLOCK_MONOTONIC seconds >= 0 (default 0)"},
    "stop": {},
}


class BadRequest(MmctlError):
    """A simulation request with an unknown field, a wrong type or a value out of range:
    ``<cmd>: <field> = <value>: <what is allowed>``."""

    def __init__(self, cmd: str, field: str, value: Any, allowed: str):
        self.cmd, self.field, self.value = cmd, field, value
        super().__init__(f"{cmd}: {field} = {value!r}: {allowed}")


def check_fields(cmd: str, req: Mapping[str, Any]) -> None:
    """Every field of ``req`` is one ``cmd`` takes (or the protocol's own)."""
    known = FIELDS[cmd]
    for key in req:
        if key not in known and key not in ENVELOPE:
            allowed = ", ".join(known) or "(none)"
            raise BadRequest(cmd, str(key), req[key], f"unknown field; {cmd} takes: {allowed}")


def json_bool(cmd: str, req: Mapping[str, Any], field: str, default: bool) -> bool:
    """A JSON true/false (never a string, a number or null)."""
    value = req.get(field, default)
    if not isinstance(value, bool):
        raise BadRequest(cmd, field, value, "must be true or false (a JSON boolean)")
    return value


def json_number(cmd: str, field: str, value: Any, lo: float, hi: float, unit: str,
                lo_open: bool = False) -> float:
    """A finite JSON number in [lo, hi] (or (lo, hi] with ``lo_open``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BadRequest(cmd, field, value, f"must be a number [{unit}]")
    x = float(value)
    if not math.isfinite(x):
        raise BadRequest(cmd, field, value, f"must be a finite number [{unit}]")
    if (x <= lo if lo_open else x < lo) or x > hi:
        upper = f" and <= {hi:g}" if math.isfinite(hi) else ""
        raise BadRequest(cmd, field, value,
                         f"must be {'>' if lo_open else '>='} {lo:g}{upper} [{unit}]")
    return x


def push_force(req: Mapping[str, Any]) -> list[float] | None:
    """``push``'s ``force``: three numbers [N] or null (required)."""
    if "force" not in req:
        raise BadRequest("push", "force", None, "is required: " + FIELDS["push"]["force"])
    force = req["force"]
    if force is None:
        return None
    if not isinstance(force, list) or len(force) != 3:
        raise BadRequest("push", "force", force, "must be a list of 3 numbers [N] or null")
    return [json_number("push", f"force[{i}]", f, -MAX_PUSH_FORCE, MAX_PUSH_FORCE, "N")
            for i, f in enumerate(force)]


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
            "status": self._cmd_status,
            "push": self._cmd_push,
            "person": self._cmd_person,
            "press": self._cmd_press,
            "enabling": self._cmd_enabling,
            "slider": self._cmd_slider,
            "fault": self._cmd_fault,
            "log": self._log,
            "stop": self._cmd_stop,
        }

    def _then_status(self) -> dict[str, Any]:
        """The world's status (taken once) and what the person does."""
        st = self.world.status()
        return {**st, "person": _person(st)}

    def _cmd_press(self, req: Mapping[str, Any]) -> Any:
        check_fields("press", req)
        self.world.press()
        return self._then_status()

    def _cmd_enabling(self, req: Mapping[str, Any]) -> Any:
        check_fields("enabling", req)
        if "held" not in req:
            raise BadRequest("enabling", "held", None, "is required: true or false")
        self.world.set_enabling(json_bool("enabling", req, "held", True))
        return self._then_status()

    def _cmd_slider(self, req: Mapping[str, Any]) -> Any:
        check_fields("slider", req)
        if "fraction" not in req:
            raise BadRequest("slider", "fraction", None, "is required: 0 <= f <= 1")
        self.world.set_speed_slider(json_number("slider", "fraction", req["fraction"],
                                                0.0, 1.0, ""))
        return self._then_status()

    def _cmd_push(self, req: Mapping[str, Any]) -> Any:
        check_fields("push", req)
        force = push_force(req)
        seconds = req.get("seconds")
        if seconds is not None:
            if force is None:
                raise BadRequest("push", "seconds", seconds,
                                 "must be null when force is null (ending a push)")
            seconds = json_number("push", "seconds", seconds, 0.0, MAX_PUSH_SECONDS, "s",
                                  lo_open=True)
        self.world.set_push(force, seconds)
        return self._then_status()

    def _cmd_person(self, req: Mapping[str, Any]) -> Any:
        check_fields("person", req)
        on = json_bool("person", req, "on", False) if "on" in req else None
        hold = (json_number("person", "hold", req["hold"], 0.0, MAX_HOLD_SECONDS, "s")
                if "hold" in req else None)
        w = self.world
        if on is not None:
            w.set_push(None)
            w.human_on = on and self.cfg.sim.human
        if hold is not None:
            w.hold(hold)
        return self._then_status()

    def _cmd_fault(self, req: Mapping[str, Any]) -> Any:
        check_fields("fault", req)
        name = req.get("name")
        if not isinstance(name, str) or name not in FAULTS:
            raise BadRequest("fault", "name", name, f"must be one of: {', '.join(FAULTS)}")
        self.world.inject(name, json_bool("fault", req, "on", True))
        return self._then_status()

    def _cmd_status(self, req: Mapping[str, Any]) -> Any:
        check_fields("status", req)
        return {**self._then_status(), "pid": os.getpid(), "config": self.cfg.name,
                "faults_known": FAULTS}

    def _cmd_stop(self, req: Mapping[str, Any]) -> Any:
        check_fields("stop", req)
        self.request_stop("requested")
        return {"stopping": True}

    def _log(self, req: Mapping[str, Any]) -> dict[str, Any]:
        """The fakes' logs from ``since`` on (CLOCK_MONOTONIC [s], ``time.monotonic()``
        of any process here): UR commands as [seq, kind, received, qd], the UR's
        program events as [controller time, text] (started, stopped and why, paused by
        its RTDE watchdog: all of them, they are few), per drive [received, target
        counts/s], and the sensor's push steps [step, the time of the first sample that
        carried it]."""
        check_fields("log", req)
        since = json_number("log", "since", req.get("since", 0.0), 0.0, math.inf, "s")
        w = self.world
        cmds = w.ur.commands()
        ur = [[c.seq, c.kind.value, c.received, None if c.qd is None else list(c.qd)]
              for c in cmds if c.received is not None and c.received >= since]
        program = [[c.controller_time, c.text] for c in cmds if c.kind is CommandKind.PROGRAM]
        ids = self.cfg.base.canopen.node_ids
        drives = {str(nid): [e for e in w.drives.command_log(nid) if e[0] >= since]
                  for nid in ids}
        return {"ur": ur, "program": program, "drives": drives,
                "steps": [s for s in w.step_samples if s[1] >= since]}


def _person(st: Mapping[str, Any]) -> str:
    """holding / push / on / off, from the world's status."""
    if st["holding"]:
        return "holding"
    if st["push"] is not None:
        return "push"
    return "on" if st["human"] else "off"
