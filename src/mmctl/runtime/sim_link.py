"""The daemon's link to the simulated robot, which runs in its own process (`mmctl sim`).

The daemon's process holds exactly what it holds on the robot: its transports reach
the fakes through the real protocols (RTDE, socketcand, RDT).  This module only finds
or starts that process and talks to its control socket; it imports nothing from
:mod:`mmctl.sim`.

:meth:`SimLink.start` attaches to a simulation that already answers on
``sim.socket_path`` (`mmctl sim` in another terminal); else it starts ``mmctl sim`` as
a child in its own session (a terminal's Ctrl-C reaches only the daemon, which stops
the robot first and the simulation after it, :meth:`SimLink.close`) and waits until
the child answers.  A child it started exits with the daemon even if the daemon is
killed (``--exit-with-parent``).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog
import yaml

from mmctl.config import Config, to_dict
from mmctl.errors import IpcError, MmctlError
from mmctl.runtime.ipc import request, resolve_socket_path

log = structlog.get_logger("mmctl.sim_link")

SIM_SOCKET_NAME = "mmctl-sim.sock"


def sim_socket_path(cfg: Config) -> Path:
    """Where the simulation's control socket is (``sim.socket_path`` or the default)."""
    return resolve_socket_path(cfg.sim.socket_path, name=SIM_SOCKET_NAME)


def absent_message(path: Path) -> str:
    return (f"no simulated robot answers on {path}; start one with `mmctl sim` "
            "(`mmctl run` on the simulated configuration starts its own)")


class SimLink:
    """Find or start the simulated robot; talk to it (see the module docstring).

    cfg: the daemon's configuration (the child gets the same one); log_dir: where the
    child writes the fakes' command logs when it ends (``mmctl sim --log``).
    """

    def __init__(self, cfg: Config, log_dir: Path | None = None):
        self.cfg = cfg
        self.log_dir = log_dir
        self.path = sim_socket_path(cfg)
        self.proc: subprocess.Popen[bytes] | None = None
        self.pid: int | None = None
        self._closed = False

    @property
    def owned(self) -> bool:
        """True when this daemon started the simulation (and stops it)."""
        return self.proc is not None

    # -- lifecycle ----------------------------------------------------------------------
    def start(self, should_stop: Callable[[], bool] = lambda: False) -> None:
        """Attach to a running simulation, or start one and wait until it answers.

        Raises :class:`MmctlError` when the child exits or does not answer within
        ``sim.ready_timeout``; returns early (nothing to stop) when ``should_stop()``.
        """
        try:
            st = self.call("status", timeout=2.0)
        except IpcError:
            st = self._wait_for_a_slow_one(should_stop)
            if st is None and should_stop():
                return
        if st is not None:
            self.pid = st.get("pid")
            log.info("sim_attached", socket=str(self.path), pid=self.pid)
            if self.log_dir is not None:
                log.warning("sim_log_ignored", why="the simulation was started elsewhere: "
                            "its own --log decides where its command logs go")
            return
        self._spawn()
        deadline = time.monotonic() + self.cfg.sim.ready_timeout
        assert self.proc is not None
        while True:
            if self.proc.poll() is not None:
                raise MmctlError(f"the simulated robot (mmctl sim, pid {self.proc.pid}) "
                                 f"exited with status {self.proc.returncode} before it was "
                                 "ready (its log lines are above)")
            try:
                self.call("status", timeout=2.0)
                break
            except IpcError:
                pass
            if should_stop():
                return
            if time.monotonic() > deadline:
                raise MmctlError(f"the simulated robot (mmctl sim, pid {self.proc.pid}) did "
                                 f"not answer on {self.path} within sim.ready_timeout = "
                                 f"{self.cfg.sim.ready_timeout:g} s")
            time.sleep(0.05)
        log.info("sim_started", socket=str(self.path), pid=self.pid)

    def _wait_for_a_slow_one(self, should_stop: Callable[[], bool]) -> dict[str, Any] | None:
        """A simulation that accepts connections on the socket but did not answer in
        time (a starved one: seen in CI with both cores busy, where the daemon then
        started a second simulation that could only fail on the socket in use): its
        status once it answers, within ``sim.ready_timeout``; None when nothing listens
        there (start one)."""
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        probe.settimeout(1.0)
        try:
            probe.connect(str(self.path))
        except OSError:
            return None  # no socket, or a stale one: nothing runs there
        finally:
            probe.close()
        log.warning("sim_slow_to_answer", socket=str(self.path))
        deadline = time.monotonic() + self.cfg.sim.ready_timeout
        while not should_stop():
            try:
                st: dict[str, Any] = self.call("status", timeout=5.0)
                return st
            except IpcError as exc:
                if time.monotonic() > deadline:
                    raise MmctlError(f"the simulated robot on {self.path} accepts connections "
                                     f"but did not answer within sim.ready_timeout = "
                                     f"{self.cfg.sim.ready_timeout:g} s ({exc})") from None
        return None

    def _spawn(self) -> None:
        from mmctl.runtime import logging as mmctl_logging

        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, cfg_file = tempfile.mkstemp(prefix="mmctl-sim-", suffix=".yaml",
                                        dir=self.path.parent)
        with os.fdopen(fd, "w") as f:
            yaml.safe_dump(to_dict(self.cfg), f)
        self._cfg_file = Path(cfg_file)
        level, json_logs = mmctl_logging.CURRENT
        cmd = [sys.executable, "-m", "mmctl.cli", "sim", "--config", cfg_file,
               "--exit-with-parent", "--log-level", level, "--delete-config"]
        cmd.append("--log-json" if json_logs else "--log-console")
        if self.log_dir is not None:
            cmd += ["--log", str(self.log_dir)]
        loop_cpus = set(self.cfg.loop.cpu_affinity)
        if loop_cpus and hasattr(os, "sched_getaffinity"):
            others = os.sched_getaffinity(0) - loop_cpus
            if others:  # the simulated devices stand in for hardware: off the loop's CPUs
                cmd += ["--cpus", ",".join(map(str, sorted(others)))]
        sys.stdout.flush()
        # its own session: a terminal's Ctrl-C (SIGINT to the foreground process group)
        # reaches only the daemon, which stops the robot before it stops the simulation
        self.proc = subprocess.Popen(cmd, start_new_session=True, stdin=subprocess.DEVNULL)
        self.pid = self.proc.pid
        log.info("sim_spawned", pid=self.pid, socket=str(self.path))

    def close(self, timeout: float = 20.0) -> None:
        """Stop the simulation if this daemon started it (after the stop commands went
        out); idempotent.  Asks it over its socket, then SIGTERM, then SIGKILL."""
        if self._closed:
            return
        self._closed = True
        proc = self.proc
        if proc is None:
            return
        if proc.poll() is None:
            try:
                self.call("stop", timeout=5.0)
            except IpcError as exc:
                log.warning("sim_stop_request_failed", error=str(exc))
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.error("sim_stop_timeout", pid=proc.pid, timeout_s=timeout)
                self._signal(proc, signal.SIGTERM)
                try:
                    proc.wait(5.0)
                except subprocess.TimeoutExpired:
                    self._signal(proc, signal.SIGKILL)
                    proc.wait(5.0)
        log.info("sim_stopped", pid=proc.pid, status=proc.returncode)
        cfg_file = getattr(self, "_cfg_file", None)
        if cfg_file is not None:
            cfg_file.unlink(missing_ok=True)

    @staticmethod
    def _signal(proc: subprocess.Popen[bytes], sig: int) -> None:
        try:
            os.killpg(proc.pid, sig)  # its session: the fake UR process with it
        except ProcessLookupError:
            pass

    # -- requests -----------------------------------------------------------------------
    def call(self, cmd: str, timeout: float = 5.0, **args: object) -> Any:
        """One request to the simulation's control socket (raises IpcError); replies up
        to 256 MB (``log``: the fakes' command logs)."""
        return request(self.path, cmd, timeout=timeout, absent=absent_message(self.path),
                       max_reply=1 << 28, **args)

    def start_human(self) -> None:
        """Let the simulated person start the task (``sim.human``)."""
        self.call("person", on=True)

    def hold(self, seconds: float) -> None:
        """The person lets go of the handle for ``seconds`` (the daemon tares)."""
        self.call("person", hold=seconds)

    @property
    def closed(self) -> bool:
        """True once :meth:`close` ran (a simulation this daemon started is gone)."""
        return self._closed

    def status(self) -> dict[str, object]:
        """What the daemon's status says about the link (no request: cheap)."""
        return {"socket": str(self.path), "pid": self.pid, "owned": self.owned}
