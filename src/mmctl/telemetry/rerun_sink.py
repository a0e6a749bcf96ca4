"""The rerun side of the publisher: the only module that logs to rerun.

rerun is imported in :meth:`RerunSink.open`, never at module import, so a daemon with
telemetry off never loads it.  Series and the 3-D frame go out as rerun-tagged Arrow
record batches (:mod:`mmctl.telemetry.arrow_batch`), one ``Chunk.from_record_batch``
per batch and one ``send_chunks`` per flush; only the rare events use
``RecordingStream.log``.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import structlog

from mmctl.config.base import MecanumConfig
from mmctl.errors import MmctlError
from mmctl.telemetry import layout
from mmctl.telemetry.arrow_batch import ArrowEncoder
from mmctl.telemetry.batch import Columns, time_ns
from mmctl.telemetry.events import Event
from mmctl.telemetry.scene import SceneFrame, footprint_box

log = structlog.get_logger("mmctl.telemetry")

DEFAULT_VIEWER_PORT = 9876
DEFAULT_URL = f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"


class TelemetryError(MmctlError):
    """A telemetry destination could not be opened (viewer, address, file)."""


class Destinations(NamedTuple):
    """Where telemetry goes; several at once are fine.

    viewer: spawn a local rerun viewer (bound to 127.0.0.1) and stream to it;
    connect: address of a running viewer (``HOST:PORT``, ``PORT`` or a ``rerun+http://``
    URL; "" = the loopback default) or None; record: ``.rrd`` path or None.
    """

    viewer: bool = False
    connect: str | None = None
    record: str | None = None

    @property
    def any(self) -> bool:
        return self.viewer or self.connect is not None or self.record is not None


def grpc_url(address: str) -> str:
    """``HOST:PORT`` / ``PORT`` / URL -> the viewer's gRPC proxy URL (loopback default)."""
    a = address.strip()
    if not a:
        return DEFAULT_URL
    if "://" in a:
        return a
    if a.isdigit():
        return f"rerun+http://127.0.0.1:{a}/proxy"
    host, sep, port = a.rpartition(":")
    if not sep or not port.isdigit():
        raise TelemetryError(f"--connect {address!r}: expected HOST:PORT, PORT or a "
                             "rerun+http://HOST:PORT/proxy URL")
    return f"rerun+http://{host or '127.0.0.1'}:{port}/proxy"


def rerun_executable() -> str:
    """The ``rerun`` viewer binary: next to this Python (the venv), else on PATH."""
    here = Path(sys.executable).parent / "rerun"
    if here.exists():
        return str(here)
    found = shutil.which("rerun")
    if found is None:
        raise TelemetryError("the rerun viewer executable was not found (pip install rerun-sdk)")
    return found


def spawn_viewer(port: int = DEFAULT_VIEWER_PORT, timeout: float = 15.0) -> subprocess.Popen[bytes]:
    """Start a detached rerun viewer listening on 127.0.0.1:``port``; wait until it does.

    Raises :class:`TelemetryError` if it exits first (e.g. no display) or never listens.
    """
    cmd = [rerun_executable(), "--port", str(port), "--bind", "127.0.0.1"]
    env = dict(os.environ, RERUN_APP_ONLY="true")
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, env=env, start_new_session=True)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
            last = next((ln for ln in reversed(err.splitlines()) if ln.strip()), "")
            raise TelemetryError(f"the rerun viewer exited at start ({last.strip() or proc.returncode}); "
                                 "without a display use --record FILE.rrd or --connect ADDR")
        with socket.socket() as s:
            s.settimeout(0.2)
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return proc
        time.sleep(0.1)
    proc.terminate()
    raise TelemetryError(f"the rerun viewer did not listen on 127.0.0.1:{port} within {timeout:g} s")


class RerunSink:
    """Logs columns, scene frames and events to one rerun recording stream.

    destinations: where the stream goes; recording_name: a label shown by the viewer;
    static: name -> value logged once under ``telemetry/info`` (rates, period...);
    mecanum: base geometry for the drawn footprint; robot_urdf: the robot as URDF text
    (:func:`mmctl.model.urdf.urdf`), drawn from its shapes and turned by the scene
    frames' joints (None: the stick figure only).  Call :meth:`open` first (imports
    rerun, opens the sinks); :meth:`close` flushes and is idempotent.
    """

    def __init__(self, destinations: Destinations, recording_name: str = "mmctl",
                 static: dict[str, float | int | str] | None = None,
                 mecanum: MecanumConfig | None = None, robot_urdf: str | None = None):
        self.destinations = destinations
        self.recording_name = recording_name
        self.static = dict(static or {})
        self.mecanum = mecanum if mecanum is not None else MecanumConfig()
        self.robot_urdf = robot_urdf
        self.viewer: subprocess.Popen[bytes] | None = None
        self._rec: Any = None
        self._rr: Any = None
        self._chunk: Any = None
        self._enc: Any = None
        self._path: list[np.ndarray] = []

    # -- lifecycle ------------------------------------------------------------------
    def open(self) -> None:
        """Import rerun, open the destinations, log the static parts and the blueprint."""
        import pyarrow as pa
        import rerun as rr
        from rerun.chunk import Chunk

        self._rr, self._chunk = rr, Chunk
        d = self.destinations
        sinks: list[Any] = []
        if d.record is not None:
            Path(d.record).expanduser().parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(Path(d.record).expanduser())))
        if d.viewer:
            self.viewer = spawn_viewer()
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"))
        if d.connect is not None:
            url = grpc_url(d.connect)
            if d.viewer and url.endswith(f":{DEFAULT_VIEWER_PORT}/proxy"):
                url = ""  # the spawned viewer already gets the stream
            if url:
                sinks.append(rr.GrpcSink(url))
        rec = rr.RecordingStream("mmctl", recording_id=None, send_properties=True)
        if sinks:
            rec.set_sinks(*sinks, default_blueprint=layout.blueprint())
        self._rec = rec
        rec.send_recording_name(self.recording_name)
        joints = None if self.robot_urdf is None else self._robot_joints(self.robot_urdf)
        self._enc = ArrowEncoder(rr, pa, joints=joints)
        self._log_static()
        if self.robot_urdf is not None:
            self._log_robot(self.robot_urdf)

    def close(self) -> None:
        """Flush everything to the destinations and close them (idempotent)."""
        rec, self._rec = self._rec, None
        if rec is None:
            return
        try:
            rec.flush(timeout_sec=10.0)
        finally:
            rec.disconnect()

    # -- what the publisher calls -------------------------------------------------------
    def write(self, columns: Sequence[Columns],
              scene: tuple[int, float, SceneFrame] | None = None,
              pace: Callable[[], None] | None = None) -> None:
        """Send column batches and (optionally) one 3-D frame ``(cycle, t [s], frame)``,
        one record batch at a time; the 3-D styles were logged once as static data.

        pace: called between the steps (each ~0.1-0.3 ms of interpreter time) so the
        caller can keep them in the control loop's idle time.
        """
        enc = self._enc
        pace = pace if pace is not None else _no_pace
        for c in columns:
            pace()
            self._send(enc.columns(c), pace)
        if scene is not None:
            cycle, t, frame = scene
            self._path.append(frame.base_translation)
            if len(self._path) > 600:
                del self._path[:100]
            path = np.array(self._path) if len(self._path) % 3 == 1 else None
            pace()
            self._send(enc.scene(cycle, int(time_ns(np.array([t]))[0]), frame, path), pace)

    def _send(self, batches: list[Any], pace: Callable[[], None]) -> None:
        """Record batches -> chunks -> the stream, with a pacing point before each call."""
        for batch in batches:
            pace()
            chunks = self._chunk.from_record_batch(batch)
            pace()
            self._rec.send_chunks(chunks)

    def write_event(self, event: Event) -> None:
        """Log a text line and/or a row of named values at the event's cycle."""
        rr, rec = self._rr, self._rec
        self._set_time(event.cycle, event.t)
        if event.text:
            rec.log(layout.EVENTS, rr.TextLog(event.text, level=event.level))
        if event.values:
            rec.log(event.entity, rr.AnyValues(**dict(event.values)))

    # -- internals ------------------------------------------------------------------------
    def _set_time(self, cycle: int, t: float) -> None:
        rec = self._rec
        rec.set_time(layout.TIMELINE_CYCLE, sequence=int(cycle))
        t_ns = int(time_ns(np.array([t]))[0])
        rec.set_time(layout.TIMELINE_TIME, duration=np.timedelta64(t_ns, "ns"))

    def _log_static(self) -> None:
        rr, rec = self._rr, self._rec
        for s in layout.ALL_SERIES:
            rec.log(s.path, rr.SeriesLines(names=list(s.names), widths=1.5), static=True)
        rec.log(layout.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        center, half = footprint_box(self.mecanum)
        rec.log(layout.BASE_FOOTPRINT, rr.Boxes3D(centers=[center], half_sizes=[half],
                                                  colors=[(120, 120, 120)]), static=True)
        rec.log(layout.HANDLE, rr.TransformAxes3D(0.15), static=True)
        styles = [
            (layout.ARM, rr.LineStrips3D.from_fields(radii=0.03, colors=[(90, 150, 230)])),
            (layout.ARM_JOINTS, rr.Points3D.from_fields(radii=0.045, colors=[(40, 60, 90)])),
            (layout.TWIST_ARROW, rr.Arrows3D.from_fields(radii=0.012, colors=[(40, 200, 80)],
                                                         labels=["v_d"])),
            (layout.FORCE_ARROW, rr.Arrows3D.from_fields(radii=0.012, colors=[(230, 60, 60)],
                                                         labels=["f_h"])),
            (layout.P_DES, rr.Points3D.from_fields(radii=0.035, colors=[(240, 180, 0)],
                                                   labels=["p_des"])),
            (layout.BASE_PATH, rr.LineStrips3D.from_fields(radii=0.01, colors=[(150, 150, 150)])),
        ]
        for path, style in styles:
            rec.log(path, style, static=True)
        if self.static:
            rec.log("telemetry/info", rr.AnyValues(**self.static), static=True)


    def _robot_joints(self, text: str) -> list[tuple[str, str, str, tuple[float, ...]]]:
        """The arm's six joints as rerun's URDF parser reads ``text``: (entity, parent
        link, child link, origin translation), in :data:`layout.ARM_JOINT_ENTITIES`'
        order."""
        import rerun.urdf as ru

        with tempfile.TemporaryDirectory(prefix="mmctl-urdf-") as tmp:
            path = Path(tmp) / "mmctl.urdf"
            path.write_text(text)
            tree = ru.UrdfTree.from_file_path(path)
        out = []
        for entity in layout.ARM_JOINT_ENTITIES:
            joint = tree.get_joint_by_name(entity.rsplit("/", 1)[1])
            if joint is None:
                raise TelemetryError(f"the robot's URDF has no joint {entity.rsplit('/', 1)[1]!r}")
            out.append((entity, joint.parent_link, joint.child_link, tuple(joint.origin_xyz)))
        return out

    def _log_robot(self, text: str) -> None:
        """The URDF through rerun's own loader (its shapes, and its joints as static
        named-frame transforms at zero), and its root link on the base's frame; each
        scene frame then sends the arm's six joints' transforms (as rerun's URDF
        how-to does)."""
        rr, rec = self._rr, self._rec
        rec.log_file_from_contents("mmctl.urdf", text.encode(),
                                   entity_path_prefix=layout.ROBOT, static=True)
        rec.log(f"{layout.ROBOT_JOINTS}/root",
                rr.Transform3D(parent_frame=f"tf#/{layout.BASE}", child_frame="base_link"),
                static=True)


def _no_pace() -> None:
    """No pacing: run every step at once."""
