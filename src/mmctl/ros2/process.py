"""The ROS 2 bridge's child process, fed from a sample ring of its own.

The loop's telemetry hook copies each cycle's row into this ring (a few microseconds;
:class:`~mmctl.telemetry.service.TelemetryService`); the child maps the ring, takes
what is queued at ``ros2.rate`` and publishes the newest row, and every
``1 / ros2.diagnostics_rate`` the loop's timing over the rows since the last
diagnostics.  It runs as background work (SCHED_IDLE, off the loop's CPUs: the
telemetry child's :func:`~mmctl.telemetry.process_publisher._background`).
"""

from __future__ import annotations

import math
import os
import signal
import time
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import structlog

from mmctl.config import Config
from mmctl.errors import MmctlError
from mmctl.runtime.spawn import spawn_ready
from mmctl.telemetry import ring as tr
from mmctl.telemetry.ring import SampleRing

log = structlog.get_logger("mmctl.ros2")

#: rows held between the loop and the bridge (8 s at 500 Hz: the child takes them at
#: ros2.rate, so a full ring means a stalled child; the loop then drops and counts)
RING_SIZE = 4096


class Ros2Error(MmctlError):
    """The ROS 2 bridge could not start, or failed."""


class Ros2Process:
    """The bridge's parent side: the ring the loop writes, the child that publishes.

    cfg: the daemon's configuration (``ros2``, ``robot``, ``limits``); timing: the loop's
    TimingRing (each row carries the previous cycle's timing); avoid_cpus: the loop's
    CPUs, which the child stays off while another is allowed; origin_wall: the wall
    clock [s] at the loop's origin (the messages' stamps are the rows' times after it).
    """

    def __init__(self, cfg: Config, timing: Any = None, avoid_cpus: tuple[int, ...] = (),
                 origin_wall: float = 0.0, start_timeout: float = 60.0,
                 close_timeout: float = 10.0):
        self.cfg = cfg
        self.origin_wall = origin_wall
        self.timing = timing
        self.avoid_cpus = tuple(avoid_cpus)
        self.start_timeout = start_timeout
        self.close_timeout = close_timeout
        self.ring: SampleRing | None = None
        self.error: BaseException | None = None
        self.child_stats: dict[str, Any] = {}
        self._conn: Connection | None = None
        self._proc: Any = None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def start(self) -> None:
        """Create the ring, start the child, wait until its participant is up."""
        if self._proc is not None:
            raise RuntimeError("the ROS 2 bridge is already started")
        ring = SampleRing.create_file(RING_SIZE, timing=self.timing)
        try:
            self._proc, self._conn = spawn_ready(
                _serve, (ring.path, RING_SIZE, self.cfg, self.avoid_cpus, self.origin_wall),
                name="mmctl-ros2", who="the ROS 2 bridge", start_timeout=self.start_timeout,
                error=Ros2Error)
        finally:
            ring.unlink()  # mapped by both sides by now (or not needed any more)
        proc = self._proc
        self.ring = ring
        log.info("ros2_bridge_started", pid=proc.pid, domain_id=self.cfg.ros2.domain_id,
                 discovery_range=self.cfg.ros2.discovery_range,
                 topic_prefix=self.cfg.ros2.topic_prefix or "/")

    def stats(self) -> dict[str, Any]:
        """For ``mmctl status``: the ring's counters and the child."""
        ring = self.ring
        return {"process": self.pid, "accepted": ring.accepted if ring else 0,
                "dropped": ring.dropped if ring else 0, "taken": ring.published if ring else 0,
                "error": repr(self.error) if self.error is not None else None}

    def close(self) -> None:
        """End the child (idempotent): its participant leaves the graph cleanly."""
        conn, proc = self._conn, self._proc
        if proc is None or conn is None:
            return
        try:
            conn.send(("close",))
            if conn.poll(self.close_timeout):
                reply = conn.recv()
                if reply[0] == "closed":
                    self.child_stats = dict(reply[1])
                elif reply[0] == "error":
                    self.error = Ros2Error(str(reply[1]))
        except (EOFError, OSError) as exc:
            self.error = Ros2Error(f"the ROS 2 bridge went away ({exc!r})")
        finally:
            proc.join(5.0)
            self._kill()
        log.info("ros2_bridge_stopped", **self.child_stats,
                 error=repr(self.error) if self.error else None)

    def _kill(self) -> None:
        proc, self._proc = self._proc, None
        conn, self._conn = self._conn, None
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(5.0)
        if conn is not None:
            conn.close()


def loop_timing(rows: np.ndarray) -> dict[str, float]:
    """The loop's timing over ``rows`` (each carries its previous cycle's): compute
    p50/p99 [us] and the misses, for /diagnostics."""
    compute = rows[:, tr.PREV_COMPUTE]
    compute = compute[np.isfinite(compute)] / 1e3
    missed = rows[:, tr.PREV_MISSED]
    missed = missed[np.isfinite(missed)]
    return {"cycles": float(len(rows)),
            "compute_p50_us": float(np.percentile(compute, 50)) if len(compute) else math.nan,
            "compute_p99_us": float(np.percentile(compute, 99)) if len(compute) else math.nan,
            "misses": float(np.sum(missed > 0)) if len(missed) else 0.0}


def _serve(conn: Connection, ring_path: str, size: int, cfg: Config,
           avoid_cpus: tuple[int, ...], origin_wall: float) -> None:
    """The child: map the ring, open the bridge, publish until told to close."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    bridge = None
    try:
        from mmctl.ros2.bridge import Ros2Bridge
        from mmctl.telemetry.process_publisher import _background

        ring = SampleRing.attach_file(ring_path, size)
        bridge = Ros2Bridge(cfg, origin_wall)
        _background(avoid_cpus)
        conn.send(("ready",))
        period = 1.0 / cfg.ros2.rate
        diag_period = 1.0 / cfg.ros2.diagnostics_rate
        next_tick = time.monotonic()
        next_diag = next_tick + diag_period
        pending: list[np.ndarray] = []
        published = 0
        while True:
            next_tick += period
            wait = next_tick - time.monotonic()
            if wait < -period:  # fell behind (a busy machine): no catching up
                next_tick = time.monotonic()
                wait = 0.0
            if conn.poll(max(0.0, wait)):
                msg = conn.recv()
                if msg[0] == "close":
                    bridge.close()
                    conn.send(("closed", {"published": published, "pid": os.getpid()}))
                    return
                raise Ros2Error(f"unknown message {msg[0]!r}")
            rows = ring.take()
            if len(rows):
                ring.mark_published(len(rows))
                bridge.publish(rows[-1])
                published += 1
                pending.append(rows)
            if time.monotonic() >= next_diag:
                next_diag += diag_period
                if pending:
                    block = np.concatenate(pending)
                    pending = []
                    bridge.publish_diagnostics(block[-1], loop_timing(block))
    except EOFError:  # the parent is gone
        pass
    except Exception as exc:  # noqa: BLE001 -- reported to the parent, then exit
        try:
            conn.send(("error", repr(exc)))
        except OSError:
            pass
    finally:
        if bridge is not None:
            try:
                bridge.close()
            except Exception:  # noqa: BLE001, S110 -- leaving anyway
                pass
        conn.close()
