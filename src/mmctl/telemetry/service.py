"""What the daemon owns for telemetry: the optional publisher, the trial tracker and
the per-cycle hook that feeds them.

The daemon calls :meth:`TelemetryService.start` once its loop origin is known, installs
:meth:`TelemetryService.hook` as its ``sample_hook``, forwards ``{"cmd": "trial"}``
requests to :meth:`TelemetryService.command` and calls :meth:`close` at shutdown.

Cost when off: with no destination the publisher, rerun and the scene model are never
created or imported, and the hook is None (the loop does no telemetry work at all)
except while a trial is bracketed, when it fills a scratch row for the tracker.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import structlog

from mmctl import __version__
from mmctl.config import Config
from mmctl.control.cycle import CycleResult
from mmctl.errors import MmctlError
from mmctl.telemetry import ring
from mmctl.telemetry.events import Event
from mmctl.telemetry.rerun_sink import Destinations
from mmctl.telemetry.trial import TrialTracker

if TYPE_CHECKING:
    from mmctl.ros2.process import Ros2Process
    from mmctl.runtime.timing import TimingRing
    from mmctl.telemetry.process_publisher import ProcessPublisher
    from mmctl.telemetry.publisher import Publisher

log = structlog.get_logger("mmctl.telemetry")

#: The loop's per-cycle hook: ``hook(result, cycle, t, safety)``.
Hook = Callable[[CycleResult, int, float, str], None]
#: Runs a function on the loop thread and returns its result.
OnLoop = Callable[[Callable[[], Any]], Any]


class RowFiller(Protocol):
    """Writes one cycle into a telemetry row (:meth:`mmctl.runtime.core.ControlCore.fill_row`)."""

    def fill_row(self, r: CycleResult, cycle: int, t: float, safety: str,
                 prev: tuple[float, ...], row: Any) -> None: ...


def destinations_from(cfg: Config, viewer: bool = False, connect: str | None = None,
                      record: str | None = None) -> Destinations:
    """Config ``telemetry:`` merged with the command-line flags (flags win).

    ``telemetry.enabled`` with no destination at all streams to the loopback viewer.
    """
    t = cfg.telemetry
    d = Destinations(
        viewer=viewer or t.viewer,
        connect=connect if connect is not None else (t.connect or None),
        record=record if record is not None else (t.record or None),
    )
    if t.enabled and not d.any:
        d = d._replace(connect="")
    return d


class TelemetryService:
    """Publisher (when any destination is set) + trial tracker + the loop hook.

    cfg: the daemon's configuration; destinations: where telemetry goes (nothing: no
    publisher).
    """

    def __init__(self, cfg: Config, destinations: Destinations | None = None):
        self.cfg = cfg
        self.destinations = destinations if destinations is not None else Destinations()
        self.publisher: Publisher | ProcessPublisher | None = None
        self.ros: Ros2Process | None = None  #: the ROS 2 bridge (``ros2.enabled``)
        self.tracker = TrialTracker(1.0 / cfg.loop.rate_hz, on_event=self._post)

    @property
    def enabled(self) -> bool:
        """True when samples go to rerun."""
        return self.destinations.any

    def start(self, ring: TimingRing | None = None, origin_ns: int | None = None) -> None:
        """Open the destinations and start the publisher (no-op when disabled).

        ring: the loop's TimingRing (loop timing in the rows; the thread publisher's
        pacing); origin_ns: the loop's origin (``time.perf_counter_ns``), for the ROS 2
        bridge's wall-clock stamps (None: now).
        """
        if self.cfg.ros2.enabled and self.ros is None:
            self._start_ros(ring, origin_ns)
        if not self.enabled or self.publisher is not None:
            return
        from mmctl.extras import require

        require("telemetry", "telemetry (--viewer, --connect, --record)")
        from mmctl.model.urdf import urdf
        from mmctl.telemetry.publisher import Publisher
        from mmctl.telemetry.rerun_sink import RerunSink
        from mmctl.telemetry.scene import SceneBuilder

        cfg, t = self.cfg, self.cfg.telemetry
        static: dict[str, float | int | str] = {"period_s": 1.0 / cfg.loop.rate_hz, "loop_rate_hz": cfg.loop.rate_hz,
                  "plot_rate_hz": t.plot_rate, "scene_rate_hz": t.scene_rate,
                  "queue_size": t.queue_size, "config": cfg.name, "mmctl": __version__}
        robot_urdf = urdf(cfg, collision=False)  # the 3-D view draws the robot from it
        if t.process:
            from mmctl.telemetry.process_publisher import ProcessPublisher

            self.publisher = ProcessPublisher(
                self.destinations, recording_name=cfg.name, static=static,
                mecanum=cfg.base.mecanum, robot=cfg.robot, robot_urdf=robot_urdf,
                loop_rate_hz=cfg.loop.rate_hz,
                plot_rate_hz=t.plot_rate, scene_rate_hz=t.scene_rate,
                queue_size=t.queue_size, timing=ring, avoid_cpus=tuple(cfg.loop.cpu_affinity))
        else:
            sink = RerunSink(self.destinations, recording_name=cfg.name, static=static,
                             mecanum=cfg.base.mecanum, robot_urdf=robot_urdf)
            self.publisher = Publisher(sink, loop_rate_hz=cfg.loop.rate_hz,
                                       plot_rate_hz=t.plot_rate, scene_rate_hz=t.scene_rate,
                                       queue_size=t.queue_size, timing=ring,
                                       scene=SceneBuilder(cfg.robot),
                                       spin_margin_s=cfg.loop.spin_margin,
                                       mecanum=cfg.base.mecanum)
        self.publisher.start()
        log.info("telemetry_started", viewer=self.destinations.viewer,
                 connect=self.destinations.connect, record=self.destinations.record)

    def _start_ros(self, ring: TimingRing | None, origin_ns: int | None) -> None:
        import time

        from mmctl.extras import require

        require("ros2", "the ROS 2 bridge (ros2.enabled)")
        from mmctl.ros2.process import Ros2Process

        now = time.perf_counter_ns()
        origin_wall = time.time() - (now - (now if origin_ns is None else origin_ns)) * 1e-9
        ros = Ros2Process(self.cfg, timing=ring, avoid_cpus=tuple(self.cfg.loop.cpu_affinity),
                          origin_wall=origin_wall)
        ros.start()
        self.ros = ros

    def hook(self, core: RowFiller) -> Hook | None:
        """The per-cycle callable for the loop, ``hook(result, cycle, t, safety)``
        (None: no telemetry work at all).

        core: the :class:`~mmctl.runtime.core.ControlCore` whose ``fill_row`` writes the
        cycle into a row: straight into the ring (a full ring: into a scratch row, so a
        trial still sees the cycle), then the trial tracker reads the row.
        """
        pub, tracker = self.publisher, self.tracker
        fill, observe = core.fill_row, tracker.observe_row
        scratch = np.full(ring.WIDTH, np.nan)
        if self.ros is not None and self.ros.ring is not None:
            return self._hook_with_ros(core, self.ros.ring)
        if pub is None:
            if not tracker.active:
                return None

            unknown = ring.NO_TIMING.newest

            def trial_only(r: CycleResult, cycle: int, t: float, safety: str) -> None:
                fill(r, cycle, t, safety, unknown, scratch)
                observe(scratch)

            return trial_only
        if pub.ring is None:
            raise MmctlError("the telemetry publisher is not started")
        claim, commit = pub.ring.claim, pub.ring.commit
        timing = pub.ring.timing  # the loop's TimingRing, or NO_TIMING

        def both(r: CycleResult, cycle: int, t: float, safety: str) -> None:
            row = claim()
            if row is None:  # full: dropped and counted by the ring
                fill(r, cycle, t, safety, timing.newest, scratch)
                observe(scratch)
                return
            fill(r, cycle, t, safety, timing.newest, row)
            observe(row)
            commit()

        return both

    def _hook_with_ros(self, core: RowFiller, ros: ring.SampleRing) -> Hook:
        """The hook with the ROS 2 bridge on: the row goes to the bridge's ring, and a
        copy to the publisher's (when there is one; a full ring drops and counts)."""
        pub, tracker = self.publisher, self.tracker
        fill, observe = core.fill_row, tracker.observe_row
        scratch = np.full(ring.WIDTH, np.nan)
        timing = ros.timing
        claim, commit = ros.claim, ros.commit
        other = pub.ring if pub is not None else None
        if pub is not None and other is None:
            raise MmctlError("the telemetry publisher is not started")

        def with_ros(r: CycleResult, cycle: int, t: float, safety: str) -> None:
            row = claim()
            target = scratch if row is None else row
            fill(r, cycle, t, safety, timing.newest, target)
            if row is not None:
                commit()
            if other is not None:
                copy = other.claim()
                if copy is not None:
                    copy[:] = target
                    other.commit()
            observe(target)  # (a no-op without a trial)

        return with_ros

    def command(self, req: Mapping[str, Any], on_loop: OnLoop,
                install: Callable[[Hook | None], None], core: RowFiller) -> dict[str, Any]:
        """``{"cmd": "trial", "action": "start" | "stop" | "status"}`` from the socket.

        on_loop runs a function on the loop thread and returns its result; there the
        loop's hook is rebuilt for ``core`` and handed to ``install`` (a trial needs
        samples even with telemetry off).
        """
        action = req.get("action")
        tracker = self.tracker
        if action == "start":
            def start() -> int:
                n = tracker.start()
                install(self.hook(core))
                return n
            return {"trial": on_loop(start), "started": True}
        if action == "stop":
            def stop() -> Any:
                rows = tracker.stop()
                install(self.hook(core))
                return rows
            return tracker.finish(on_loop(stop)).as_dict()
        if action == "status":
            return {"active": tracker.active, "trials": [r.as_dict() for r in tracker.results]}
        raise MmctlError(f"trial action {action!r}: expected start, stop or status")

    def status(self) -> dict[str, Any]:
        """For ``mmctl status``: destinations and publisher counters."""
        out: dict[str, Any] = {"enabled": self.enabled, "trial_active": self.tracker.active}
        if self.publisher is not None:
            out.update(self.publisher.stats())
            out["record"] = self.destinations.record
        if self.ros is not None:
            out["ros2"] = self.ros.stats()
        return out

    def close(self) -> None:
        """Flush and close the publisher (idempotent); a publisher error is logged."""
        ros, self.ros = self.ros, None
        if ros is not None:
            try:
                ros.close()
            except Exception as exc:  # noqa: BLE001 -- the bridge must not break shutdown
                log.error("ros2_close_failed", error=repr(exc))
        pub, self.publisher = self.publisher, None
        if pub is None:
            return
        try:
            pub.close()
        except Exception as exc:  # noqa: BLE001 -- telemetry must not break shutdown
            log.error("telemetry_close_failed", error=repr(exc))
        log.info("telemetry_stopped", **{k: v for k, v in pub.stats().items() if k != "error"})

    def _post(self, event: Event) -> None:
        pub = self.publisher
        if pub is not None:
            pub.post_event(event)

