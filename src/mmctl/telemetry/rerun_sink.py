"""The rerun side of the publisher: the only module that logs to rerun.

rerun is imported in :meth:`RerunSink.open`, never at module import, so a daemon with
telemetry off never loads it.  Column data goes out as ``rerun.chunk.Chunk``s built
straight from numpy/pyarrow arrays and sent together with one ``send_chunks`` call per
flush (about 40 us per entity, a third of ``rr.send_columns`` with archetype
helpers); the 3-D scene and events use ``RecordingStream.log``.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import structlog

from mmctl.config.base import MecanumConfig
from mmctl.errors import MmctlError
from mmctl.telemetry import layout
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


class _Column:
    """A ready-made component column (duck-types ``rerun.ComponentColumn``)."""

    __slots__ = ("_array", "_desc")

    def __init__(self, desc: Any, array: Any):
        self._desc = desc
        self._array = array

    def component_descriptor(self) -> Any:
        return self._desc

    def as_arrow_array(self) -> Any:
        return self._array


class _Index:
    """A ready-made index column (a ``rerun.TimeColumnLike``)."""

    __slots__ = ("_array", "_name")

    def __init__(self, name: str, array: Any):
        self._name = name
        self._array = array

    def timeline_name(self) -> str:
        return self._name

    def as_arrow_array(self) -> Any:
        return self._array


def _scene_descriptors(rr: Any) -> dict[str, Any]:
    """Component descriptors of the 3-D archetypes, taken from rerun's own column helpers."""
    z = np.zeros((1, 3))
    cols = [*rr.Transform3D.columns(translation=z, quaternion=[[0.0, 0.0, 0.0, 1.0]]),
            *rr.Points3D.columns(positions=z), *rr.LineStrips3D.columns(strips=[z]),
            *rr.Arrows3D.columns(vectors=z, origins=z)]
    out = {}
    for c in cols:
        desc = c.component_descriptor()
        out[desc.component.split(":")[-1]] = desc
    return out


class RerunSink:
    """Logs columns, scene frames and events to one rerun recording stream.

    destinations: where the stream goes; recording_name: a label shown by the viewer;
    static: name -> value logged once under ``telemetry/info`` (rates, period...);
    mecanum: base geometry for the drawn footprint.  Call :meth:`open` first (imports
    rerun, opens the sinks); :meth:`close` flushes and is idempotent.
    """

    def __init__(self, destinations: Destinations, recording_name: str = "mmctl",
                 static: dict[str, float | int | str] | None = None,
                 mecanum: MecanumConfig | None = None):
        self.destinations = destinations
        self.recording_name = recording_name
        self.static = dict(static or {})
        self.mecanum = mecanum if mecanum is not None else MecanumConfig()
        self.viewer: subprocess.Popen[bytes] | None = None
        self._rec: Any = None
        self._rr: Any = None
        self._pa: Any = None
        self._chunk: Any = None
        self._desc: Any = None
        self._scene_desc: dict[str, Any] = {}
        self._fsl_type: dict[int, Any] = {}
        self._strip_type: Any = None
        self._path: list[np.ndarray] = []

    # -- lifecycle ------------------------------------------------------------------
    def open(self) -> None:
        """Import rerun, open the destinations, log the static parts and the blueprint."""
        import pyarrow as pa
        import rerun as rr
        from rerun.chunk import Chunk

        self._rr, self._pa, self._chunk = rr, pa, Chunk
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
        self._desc = next(iter(rr.Scalars.columns(scalars=np.zeros((1, 1))))).component_descriptor()
        self._scene_desc = _scene_descriptors(rr)
        item = pa.field("item", pa.float32(), nullable=False)
        self._fsl_type = {3: pa.list_(item, 3), 4: pa.list_(item, 4)}
        self._strip_type = pa.list_(pa.field("item", self._fsl_type[3], nullable=False))
        self._log_static()

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
    def write_columns(self, columns: Sequence[Columns]) -> None:
        """Send several column batches as chunks in one call (empty ones are skipped)."""
        pa, chunk_cls, desc = self._pa, self._chunk, self._desc
        chunks = []
        for cols in columns:
            n = len(cols)
            if n == 0:
                continue
            index = self._index(cols.cycle, cols.time_ns)
            for path, values in cols.values.items():
                k = values.shape[1]
                offsets = pa.array(np.arange(0, n * k + 1, k, dtype=np.int32))
                arr = pa.ListArray.from_arrays(offsets, pa.array(values.reshape(-1)))
                chunks.append(chunk_cls.from_columns(path, index, [_Column(desc, arr)]))
        if chunks:
            self._rec.send_chunks(chunks)

    def write_scene(self, cycle: int, t: float, frame: SceneFrame) -> None:
        """Send one 3-D frame at ``cycle`` / ``t`` [s] (one ``send_chunks``; the styles
        were logged once as static data)."""
        self._path.append(frame.base_translation)
        if len(self._path) > 600:
            del self._path[:100]
        d, vec3, quat = self._scene_desc, self._vec3_rows, self._quat_row
        pts = frame.arm_points
        parts: list[tuple[str, list[_Column]]] = [
            (layout.BASE, [_Column(d["translation"], vec3([frame.base_translation[None]])),
                           _Column(d["quaternion"], quat(frame.base_quaternion))]),
            (layout.ARM, [_Column(d["strips"], self._strips_row([pts]))]),
            (layout.ARM_JOINTS, [_Column(d["positions"], vec3([pts]))]),
            (layout.HANDLE, [_Column(d["translation"], vec3([frame.handle_translation[None]])),
                             _Column(d["quaternion"], quat(frame.handle_quaternion))]),
            (layout.TWIST_ARROW, [_Column(d["vectors"], vec3([frame.twist_vector[None]])),
                                  _Column(d["origins"], vec3([frame.handle_translation[None]]))]),
            (layout.FORCE_ARROW, [_Column(d["vectors"], vec3([frame.force_vector[None]])),
                                  _Column(d["origins"], vec3([frame.handle_translation[None]]))]),
            (layout.P_DES, [_Column(d["positions"], vec3([frame.p_des[None]]))]),
        ]
        if len(self._path) >= 2:
            parts.append((layout.BASE_PATH, [_Column(d["strips"],
                                                     self._strips_row([np.array(self._path)]))]))
        index = self._index(np.array([cycle], np.int64), time_ns(np.array([t])))
        self._rec.send_chunks([self._chunk.from_columns(path, index, cols)
                               for path, cols in parts])

    def write_event(self, event: Event) -> None:
        """Log a text line and/or a row of named values at the event's cycle."""
        rr, rec = self._rr, self._rec
        self._set_time(event.cycle, event.t)
        if event.text:
            rec.log(layout.EVENTS, rr.TextLog(event.text, level=event.level))
        if event.values:
            rec.log(event.entity, rr.AnyValues(**dict(event.values)))

    # -- internals ------------------------------------------------------------------------
    def _index(self, cycle: np.ndarray, t_ns: np.ndarray) -> list[_Index]:
        pa = self._pa
        return [_Index(layout.TIMELINE_CYCLE, pa.array(cycle, pa.int64())),
                _Index(layout.TIMELINE_TIME,
                       pa.array(t_ns.astype("timedelta64[ns]"), pa.duration("ns")))]

    def _fsl(self, values: np.ndarray, width: int) -> Any:
        """(n, width) -> FixedSizeList<float32 not null>[width] (rerun's vector layout)."""
        pa = self._pa
        flat = pa.array(np.ascontiguousarray(values, dtype=np.float32).reshape(-1))
        return pa.FixedSizeListArray.from_arrays(flat, type=self._fsl_type[width])

    def _vec3_rows(self, rows: list[np.ndarray]) -> Any:
        """One row per (k_i, 3) array -> list<vec3> column."""
        pa = self._pa
        offsets = np.zeros(len(rows) + 1, np.int32)
        offsets[1:] = np.cumsum([len(r) for r in rows])
        return pa.ListArray.from_arrays(pa.array(offsets), self._fsl(np.concatenate(rows), 3))

    def _quat_row(self, q: np.ndarray) -> Any:
        """One (x, y, z, w) quaternion -> a one-row list<vec4> column."""
        pa = self._pa
        return pa.ListArray.from_arrays(pa.array(np.array([0, 1], np.int32)),
                                        self._fsl(q[None], 4))

    def _strips_row(self, strips: list[np.ndarray]) -> Any:
        """One row holding several (k_i, 3) line strips -> list<list<vec3>> column."""
        pa = self._pa
        inner = np.zeros(len(strips) + 1, np.int32)
        inner[1:] = np.cumsum([len(s) for s in strips])
        points = self._fsl(np.concatenate(strips), 3)
        strip_arr = pa.ListArray.from_arrays(pa.array(inner), points, type=self._strip_type)
        return pa.ListArray.from_arrays(pa.array(np.array([0, len(strips)], np.int32)),
                                        strip_arr)

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
