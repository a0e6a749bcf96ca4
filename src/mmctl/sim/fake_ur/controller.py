"""The parent-side handle of a fake UR controller running in its own process.

ur_rtde's constructors hold the Python GIL while they block on the network, so the
fake can never share a process with the client: :class:`FakeURController` spawns it
(``spawn`` context), talks to it through a pipe (fault injection, the command log) and
reads its joint state from shared memory (:mod:`mmctl.sim.fake_ur.shared`).

    with FakeURController("127.0.0.5", q_init=q0) as fake:
        arm = UrRtdeArm(ArmConfig(host="127.0.0.5")); arm.connect()
        ...
        fake.set_protective_stop()          # inject a fault
        fake.commands(CommandKind.SPEEDJ)   # what the client sent
        fake.state().q                      # joint positions [rad]
"""

from __future__ import annotations

import multiprocessing
import os
import random
import signal
import threading
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from mmctl.config.robot import DEFAULT_Q_DES
from mmctl.errors import TransportError
from mmctl.sim.fake_ur import server, shared
from mmctl.sim.fake_ur.log import CommandKind, CommandLog, FakeCommand
from mmctl.types import ArmState

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing_extensions import Self

log = structlog.get_logger("mmctl.fake_ur")

#: Entries of the command log fetched from the process per request at most (a full ring
#: of 200 000 in one message held the parent's GIL for seconds, and its peak stayed in
#: the parent's RSS).
LOG_CHUNK = 10_000


class FakeURController:
    """A fake UR10e controller serving RTDE/dashboard/script on ``host`` (127.x.y.z).

    q_init: initial joint positions (6,) [rad] (default: the preferred configuration
    ``robot.q_des``); start_timeout [s]: how long :meth:`start` waits for the ports;
    request_timeout [s]: how long a fault injection waits for the process to answer;
    log_capacity: entries kept by the process's command log, and by this side's copy of
    it (fetched from the process by :meth:`commands`, :meth:`kill` and :meth:`stop`, at
    most ``log_chunk`` entries per request, and kept encoded: one small ``bytes`` per
    entry, :class:`~mmctl.sim.fake_ur.log.CommandLog`).
    """

    def __init__(self, host: str, q_init: Sequence[float] | None = None, *,
                 start_timeout: float = 30.0, request_timeout: float = 10.0,
                 log_capacity: int = 200_000, log_chunk: int = LOG_CHUNK):
        q = tuple(float(x) for x in (DEFAULT_Q_DES if q_init is None else q_init))
        if len(q) != 6 or not all(np.isfinite(q)):
            raise ValueError(f"q_init must be 6 finite joint angles [rad], got {q_init!r}")
        self.host = host
        self.q_init = q
        self.start_timeout = start_timeout
        self.request_timeout = request_timeout
        self.log_capacity = log_capacity
        if log_chunk < 1:
            raise ValueError(f"log_chunk must be >= 1, got {log_chunk!r}")
        self.log_chunk = log_chunk
        self._ctx = multiprocessing.get_context("spawn")
        self._block = shared.new_block(self._ctx)
        self._proc: Any = None
        self._conn: Any = None
        self._lock = threading.Lock()
        #: the process's command log as fetched so far (it outlives the process)
        self._log = CommandLog(log_capacity)

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> Self:
        """Spawn the process and wait until its three ports accept connections."""
        if self.alive:
            return self
        from mmctl.runtime import logging as mmctl_logging
        from mmctl.runtime.spawn import with_logging

        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(  # (its events in the format of the stdout it shares)
            target=with_logging, args=(mmctl_logging.CURRENT, server.run, self.host,
                                       self.q_init, self._block, child, self.log_capacity,
                                       self._log.next_seq),
            name=f"fake-ur-{self.host}", daemon=True)
        proc.start()
        child.close()
        if not parent.poll(self.start_timeout):
            _kill(proc)
            parent.close()
            raise TransportError(f"fake UR on {self.host} did not start within "
                                 f"{self.start_timeout} s")
        try:
            status, detail = parent.recv()
        except EOFError:
            status, detail = "error", f"process exited with code {proc.exitcode}"
        if status != "ready":
            _kill(proc)
            parent.close()
            raise TransportError(f"fake UR on {self.host}: {detail}")
        self._proc, self._conn = proc, parent
        log.debug("fake_ur_started", host=self.host, pid=proc.pid)
        return self

    def stop(self) -> None:
        """Ask the process to close its ports and exit (idempotent)."""
        proc = self._proc
        if proc is None:
            return
        if proc.is_alive():
            try:
                self._fetch_log()
                self._request("shutdown")
            except TransportError as exc:
                log.warning("fake_ur_stop_request_failed", host=self.host, error=str(exc))
            proc.join(5.0)
        _kill(proc)
        self._forget()

    def kill(self) -> None:
        """SIGKILL the process (a controller that vanishes: sockets reset, no goodbye).

        The command log received so far is fetched first; the joint state in shared
        memory keeps the last sample.
        """
        proc = self._proc
        if proc is None:
            return
        if proc.is_alive():
            try:
                self._fetch_log()
            except TransportError as exc:
                log.warning("fake_ur_log_lost", host=self.host, error=str(exc))
        _kill(proc)
        self._forget()

    def restart(self, q_init: Sequence[float] | None = None) -> Self:
        """Start a new process after :meth:`kill`/:meth:`stop` (a rebooted controller:
        no program running, controller time from 0), at ``q_init`` or the last pose."""
        self.stop()
        q = self.state().q.tolist() if q_init is None else [float(x) for x in q_init]
        if len(q) != 6:
            raise ValueError(f"q_init must be 6 joint angles [rad], got {q_init!r}")
        self.q_init = (q[0], q[1], q[2], q[3], q[4], q[5])
        return self.start()

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- observation ---------------------------------------------------------------------

    def state(self) -> ArmState:
        """The joints as the fake's process last published them (shared memory, no I/O).

        q (6,) [rad], qd (6,) [rad/s], controller_time [s], runtime_state (2 = PLAYING),
        safety_bits (RTDE safety status bits).  Before start: q_init at rest.
        """
        t, q, qd, runtime, safety = shared.read(self._block)
        if t == 0.0 and self._proc is None and not any(q):
            q = list(self.q_init)
        return ArmState(np.array(q), np.array(qd), t, runtime, safety)

    def commands(self, kind: CommandKind | None = None) -> list[FakeCommand]:
        """The command log so far (all kinds, or one), oldest first; see :class:`FakeCommand`."""
        if self.alive:
            self._fetch_log()
        return [c for c in self._log.since(0) if kind is None or c.kind is kind]

    # -- fault injection (each returns the controller time [s] at which it took effect:
    #    the first sample that shows it carries a later timestamp) ---------------------------

    def set_protective_stop(self, on: bool = True) -> float:
        """Protective stop: safety bits 2 and 10, joints brake, speed commands ignored."""
        return float(self._request("protective_stop", on))

    def set_emergency_stop(self, on: bool = True) -> float:
        """Emergency stop: safety bits 6, 7 and 10, joints brake, speed commands ignored."""
        return float(self._request("emergency_stop", on))

    def stop_program(self) -> float:
        """Stop the running program (runtime state STOPPED), like the pendant's stop."""
        return float(self._request("stop_program"))

    def freeze_stream(self, on: bool = True) -> float:
        """Stop (or resume) sending RTDE data packages; sockets stay open."""
        return float(self._request("freeze", on))

    def set_remote_control(self, on: bool) -> float:
        """Remote (True) or local (False) control, as the dashboard reports it."""
        return float(self._request("remote_control", on))

    def set_digital_input(self, index: int, on: bool) -> float:
        """Set bit ``index`` (0-17) of ``actual_digital_input_bits`` (a handle button)."""
        return self.set_digital_inputs({index: on})

    def set_digital_inputs(self, levels: Mapping[int, bool]) -> float:
        """Set several bits of ``actual_digital_input_bits`` at once: every RTDE sample
        has all of them or none (the contacts of one switch, which change together)."""
        for index in levels:
            if not 0 <= index < 64:
                raise ValueError(f"digital input index must be 0..63, got {index}")
        return float(self._request("digital_inputs",
                                   [(int(i), bool(on)) for i, on in levels.items()]))

    def set_speed_slider(self, fraction: float) -> float:
        """The pendant's speed slider (0..1, RTDE ``target_speed_fraction``): speedJ
        targets are followed at this fraction of their speeds."""
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"the speed slider is a fraction 0..1, got {fraction!r}")
        return float(self._request("speed_slider", fraction))

    def set_q(self, q: Sequence[float]) -> float:
        """Teleport the joints to ``q`` (6,) [rad], at rest."""
        values = [float(x) for x in q]
        if len(values) != 6 or not all(np.isfinite(values)):
            raise ValueError(f"q must be 6 finite joint angles [rad], got {q!r}")
        return float(self._request("set_q", values))

    # -- internals -----------------------------------------------------------------------

    def _request(self, op: str, *args: object) -> Any:
        with self._lock:
            conn = self._conn
            if conn is None or not self.alive:
                raise TransportError(f"fake UR on {self.host} is not running")
            try:
                conn.send((op, *args))
                if not conn.poll(self.request_timeout):
                    raise TransportError(f"fake UR on {self.host} did not answer {op!r}")
                status, t, payload = conn.recv()
            except (EOFError, OSError) as exc:
                raise TransportError(f"fake UR on {self.host} is gone ({exc})") from None
        if status != "ok":
            raise ValueError(payload)
        if op == "log":
            return payload
        return t

    def _fetch_log(self) -> None:
        """Copy the process's new log entries here, ``log_chunk`` at a time (the process
        numbers them on from this copy's last: :func:`server.run`'s ``first_seq``)."""
        while True:
            rows: list[bytes] = self._request("log", self._log.next_seq, self.log_chunk)
            self._log.extend(rows)
            if len(rows) < self.log_chunk:
                return

    def _forget(self) -> None:
        if self._conn is not None:
            self._conn.close()
        self._proc = None
        self._conn = None


def start_fake_ur(host: str, q_init: Sequence[float] | None = None, attempts: int = 8,
                  **options: Any) -> FakeURController:
    """A started :class:`FakeURController` on ``host``, or, if its ports are taken (another
    test run or simulation on this machine), on a random 127.x.y.z address; the address
    used is ``.host``."""
    candidates = [host] + [f"127.{random.randint(100, 254)}.{random.randint(0, 255)}."
                           f"{random.randint(2, 254)}" for _ in range(attempts - 1)]
    for candidate in candidates:
        fake = FakeURController(candidate, q_init, **options)
        try:
            return fake.start()
        except TransportError as exc:
            if "in use" not in str(exc):
                raise
            log.warning("fake_ur_address_taken", host=candidate)
    raise TransportError(f"no free loopback address for a fake UR after {attempts} attempts")


def _kill(proc: Any) -> None:
    if proc.is_alive():
        try:
            os.kill(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.join(5.0)
