"""The publisher in a child process, fed through a ring in shared memory.

A :class:`~mmctl.telemetry.publisher.Publisher` thread in the daemon holds the
interpreter lock while it batches, encodes and hands chunks to rerun (20-400 us per
call); on the simulated robot the fake devices need that lock in the loop's idle time
too, and on a 2-core machine the loop's compute p99 grew by 15-30 % with it.  Here the
daemon's only telemetry work is the loop's :meth:`SampleRing.put
<mmctl.telemetry.ring.SampleRing.put>` into a memory-mapped ring; a child process
(``spawn``: a fresh interpreter, at ``SCHED_IDLE``) maps the same ring and runs the whole
publisher there: batching, the 3-D frame (its own Pinocchio model), Arrow, rerun.

The ring file is created in /dev/shm (else the temp directory) and unlinked as soon as
the child has mapped it.  Protocol on the pipe (parent -> child): ``("event", event)``
(trial brackets, sent by a parent thread that sleeps until there is one),
``("close",)``; child -> parent: ``("ready",)`` once the destinations are open,
``("closed", stats)`` after the last flush, or ``("error", text)`` (then it exits).
The child ignores SIGINT/SIGTERM (a Ctrl-C or systemd's stop reaches the whole process
group): the daemon closes it after its own stop commands, so the recording is complete;
when the parent goes away it flushes and exits by itself.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

import structlog

from mmctl.config.base import MecanumConfig
from mmctl.config.robot import RobotConfig
from mmctl.errors import again
from mmctl.runtime.spawn import spawn_ready
from mmctl.telemetry.events import Event
from mmctl.telemetry.publisher import EVENT_QUEUE_SIZE
from mmctl.telemetry.queue import DropQueue
from mmctl.telemetry.rerun_sink import Destinations, TelemetryError
from mmctl.telemetry.ring import SampleRing

log = structlog.get_logger("mmctl.telemetry")

NICE = 10  #: the child's niceness increment where SCHED_IDLE is refused


class ProcessPublisher:
    """The publisher's face (``start``, ``put``, ``post_event``, ``stats``,
    ``wait_published``, ``close``) with the work in a child process.

    destinations, recording_name, static, mecanum: as for
    :class:`~mmctl.telemetry.rerun_sink.RerunSink`; robot: the model for the 3-D view
    (None: no 3-D view); robot_urdf: as for the sink (the robot drawn from its URDF); rates and queue_size: as for
    :class:`~mmctl.telemetry.publisher.Publisher`; timing: the loop's TimingRing (the
    rows' previous-cycle timing); avoid_cpus: CPUs the child stays off (the loop's
    ``loop.cpu_affinity``) while another is allowed; start_timeout / close_timeout
    [s]: how long :meth:`start` waits for the child to open the destinations and
    :meth:`close` for its last flush.
    """

    busy = None  #: no work intervals in this process (the bench's overlap count is n/a)

    def __init__(self, destinations: Destinations, *, recording_name: str = "mmctl",
                 static: dict[str, float | int | str] | None = None,
                 mecanum: MecanumConfig | None = None, robot: RobotConfig | None = None,
                 robot_urdf: str | None = None, loop_rate_hz: float = 500.0, plot_rate_hz: float = 100.0,
                 scene_rate_hz: float = 15.0, queue_size: int = 4096, timing: Any = None,
                 avoid_cpus: tuple[int, ...] = (), start_timeout: float = 60.0,
                 close_timeout: float = 30.0):
        self.destinations = destinations
        self._child_args: dict[str, Any] = {
            "destinations": destinations, "recording_name": recording_name,
            "static": dict(static or {}), "mecanum": mecanum, "robot": robot,
            "robot_urdf": robot_urdf,
            "loop_rate_hz": loop_rate_hz, "plot_rate_hz": plot_rate_hz,
            "scene_rate_hz": scene_rate_hz, "avoid_cpus": tuple(avoid_cpus)}
        self.queue_size = queue_size
        self.timing = timing
        self.start_timeout = start_timeout
        self.close_timeout = close_timeout
        self.ring: SampleRing | None = None
        self.events: DropQueue[Event] = DropQueue(EVENT_QUEUE_SIZE)
        self.error: BaseException | None = None
        self.child_stats: dict[str, Any] = {}
        self._conn: Connection | None = None
        self._proc: Any = None
        self._wake = threading.Event()
        self._closing = False
        self._forwarder: threading.Thread | None = None

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    @property
    def published(self) -> int:
        return self.ring.published if self.ring is not None else 0

    @property
    def flush_ns_max(self) -> int:
        return int(1e3 * float(self.child_stats.get("flush_max_us", 0.0)))

    def put(self, sample: Any) -> bool:
        """The loop's hot path (replaced by the ring's own ``put`` once started)."""
        raise TelemetryError("the telemetry process is not running")

    # -- lifecycle ------------------------------------------------------------------
    def start(self) -> None:
        """Create the ring, start the child, wait until it has opened the destinations."""
        if self._proc is not None:
            raise RuntimeError("publisher already started")
        ring = SampleRing.create_file(self.queue_size, timing=self.timing)
        try:
            self._proc, self._conn = spawn_ready(
                _serve, (ring.path, self.queue_size), kwargs=self._child_args,
                name="mmctl-telemetry", who="the telemetry process",
                start_timeout=self.start_timeout, error=TelemetryError)
        finally:
            ring.unlink()  # mapped by both sides by now (or not needed any more)
        self.ring = ring
        self.put = ring.put  # type: ignore[method-assign,assignment]
        self._forwarder = threading.Thread(target=self._forward, name="mmctl-telemetry-events",
                                           daemon=True)
        self._forwarder.start()

    def close(self) -> None:
        """Last flush in the child, then end it (idempotent); a child error re-raised."""
        if self._closing:
            return
        self._closing = True
        self._wake.set()
        if self._forwarder is not None:
            self._forwarder.join(10.0)
        conn, proc = self._conn, self._proc
        if proc is None or conn is None:
            return
        error = None
        try:
            if self.error is None:
                conn.send(("close",))
                # the child drains the ring before its reply: while it makes progress
                # (a loaded machine slows it), wait on; a child stuck for close_timeout
                # is an error
                progress = (len(self.ring), self.published) if self.ring is not None else None
                while True:
                    if not conn.poll(self.close_timeout):
                        now = (len(self.ring), self.published) if self.ring is not None else None
                        if now is not None and now != progress:
                            progress = now
                            continue
                        error = f"no last flush within {self.close_timeout:g} s"
                        break
                    reply = conn.recv()
                    if reply[0] == "closed":
                        self.child_stats = dict(reply[1])
                        break
                    if reply[0] == "error":
                        error = str(reply[1])
                        break
        except (EOFError, OSError) as exc:
            error = f"the telemetry process went away ({exc!r}, code {proc.exitcode})"
        finally:
            proc.join(5.0)
            self._kill()
        if error is not None and self.error is None:
            self.error = TelemetryError(f"telemetry process: {error}")
        if self.error is not None:
            raise again(self.error)

    def _kill(self) -> None:
        proc, self._proc = self._proc, None
        conn, self._conn = self._conn, None
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(5.0)
        if conn is not None:
            conn.close()

    def __enter__(self) -> ProcessPublisher:  # noqa: PYI034
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- producer side (any thread, never blocks) -----------------------------------------
    def post_event(self, event: Event) -> bool:
        """Queue an event for the child; False if the event queue was full."""
        kept = self.events.put(event)
        self._wake.set()
        return kept

    def stats(self) -> dict[str, Any]:
        """Counters for ``status`` (the ring's; the child's flush figures once closed)."""
        ring = self.ring
        return {
            "accepted": ring.accepted if ring is not None else 0,
            "dropped": ring.dropped if ring is not None else 0,
            "queued": len(ring) if ring is not None else 0,
            "published": self.published,
            "batches": self.child_stats.get("batches"),
            "flush_max_us": self.child_stats.get("flush_max_us"),
            "events_dropped": self.events.dropped,
            "process": self.pid,
            "error": repr(self.error) if self.error is not None else None,
        }

    def wait_published(self, count: int, timeout: float) -> bool:
        """Until at least ``count`` samples reached the sink (or the child failed)."""
        deadline = time.monotonic() + timeout
        while self.published < count:
            if (self.error is not None or time.monotonic() > deadline
                    or self._proc is None or not self._proc.is_alive()):
                return self.published >= count
            time.sleep(0.02)
        return True

    # -- the parent's thread: events down, failures up --------------------------------------
    def _forward(self) -> None:
        conn = self._conn
        assert conn is not None
        try:
            while True:
                self._wake.wait(0.5)
                self._wake.clear()
                for event in self.events.drain():
                    conn.send(("event", event))
                if self._closing:
                    return
                if conn.poll():
                    reply = conn.recv()
                    text = reply[1] if len(reply) > 1 else repr(reply)
                    raise TelemetryError(f"telemetry process: {text}")
        except (EOFError, OSError) as exc:
            self.error = TelemetryError(f"the telemetry process went away ({exc!r})")
        except TelemetryError as exc:
            self.error = exc
        log.error("telemetry_process_failed", error=repr(self.error))


def _background(avoid_cpus: tuple[int, ...] = ()) -> None:
    """Make this process background work, every thread of it (Linux applies affinity,
    scheduling class and nice per thread): off the CPUs in ``avoid_cpus`` (the loop's,
    when it is pinned: its caches stay its own) as long as another CPU is allowed, and
    SCHED_IDLE (it runs only on a CPU nothing else wants, and any waking thread of the
    daemon -- one that may hold the daemon's interpreter lock the loop needs -- preempts
    it at once), else ``nice +10``."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    for tid in tids:
        try:
            _background_thread(tid, avoid_cpus)
        except ProcessLookupError:  # the thread ended since the listing (rerun's
            pass                    # short-lived loader threads do)


def _background_thread(tid: int, avoid_cpus: tuple[int, ...]) -> None:
    if avoid_cpus and hasattr(os, "sched_setaffinity"):
        others = os.sched_getaffinity(tid) - set(avoid_cpus)
        if others:
            os.sched_setaffinity(tid, others)
    if hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            return
        except ProcessLookupError:
            raise
        except OSError:
            pass
    os.setpriority(os.PRIO_PROCESS, tid, NICE)


def _foreground(nice: int) -> None:
    """Undo :func:`_background` for every thread (back to SCHED_OTHER at ``nice``), as
    far as this process may (raising the priority needs CAP_SYS_NICE, which the systemd
    unit grants): the loop has ended and the last flush should not wait behind every
    other process of a busy machine.  Affinity is left as it is."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        tids = [0]
    for tid in tids:
        try:
            if hasattr(os, "SCHED_OTHER"):
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, tid, nice)
        except OSError:
            pass


def _serve(conn: Connection, ring_path: str, size: int, *, destinations: Destinations,
           recording_name: str, static: dict[str, float | int | str],
           mecanum: MecanumConfig | None, robot: RobotConfig | None,
           robot_urdf: str | None, loop_rate_hz: float,
           plot_rate_hz: float, scene_rate_hz: float, avoid_cpus: tuple[int, ...] = ()) -> None:
    """The child: map the ring, open the sink, run the publisher until told to close."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    from mmctl.telemetry.publisher import Publisher
    from mmctl.telemetry.rerun_sink import RerunSink

    pub = None
    try:
        ring = SampleRing.attach_file(ring_path, size)
        scene = None
        if robot is not None:
            from mmctl.telemetry.scene import SceneBuilder

            scene = SceneBuilder(robot)
        sink = RerunSink(destinations, recording_name=recording_name, static=static,
                         mecanum=mecanum, robot_urdf=robot_urdf)
        pub = Publisher(sink, loop_rate_hz=loop_rate_hz, plot_rate_hz=plot_rate_hz,
                        scene_rate_hz=scene_rate_hz, ring=ring, scene=scene, pace=False,
                        mecanum=mecanum)
        pub.start()
        nice = os.getpriority(os.PRIO_PROCESS, 0)
        # start-up (imports, rerun's sinks) at normal priority: in the background class
        # from the start, a busy machine kept the child from ever getting ready
        _background(avoid_cpus)
        conn.send(("ready",))
        while True:
            if not conn.poll(0.5):
                if pub.error is not None:
                    raise pub.error
                continue
            try:
                msg = conn.recv()
            except EOFError:  # the parent is gone: flush what we have and leave
                pub.close()
                return
            if msg[0] == "event":
                pub.post_event(msg[1])
            elif msg[0] == "close":
                _foreground(nice)  # the loop has ended: the last flush needs a CPU share
                pub.close()
                conn.send(("closed", pub.stats()))
                return
            else:
                raise TelemetryError(f"unknown telemetry message {msg[0]!r}")
    except Exception as exc:  # noqa: BLE001 -- reported to the parent, then exit
        try:
            conn.send(("error", repr(exc)))
        except OSError:
            pass
        if pub is not None:
            try:
                pub.close()
            except Exception as close_exc:  # noqa: BLE001 -- the error above is the news
                log.warning("telemetry_child_close_failed", error=repr(close_exc))
    finally:
        conn.close()
