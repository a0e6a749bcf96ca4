"""ProcessSink: the rerun side in a child process -- a recording read back, start-up
errors named, a dead child reported (never a hang)."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from mmctl.config import default_config
from mmctl.telemetry import layout
from mmctl.telemetry.process_sink import ProcessSink
from mmctl.telemetry.publisher import Publisher
from mmctl.telemetry.recording import load_recording
from mmctl.telemetry.rerun_sink import Destinations, TelemetryError
from mmctl.telemetry.scene import SceneBuilder
from mmctl.telemetry.synthetic import synthetic_samples

N = 600


def test_publisher_through_a_child_process_writes_the_recording(tmp_path: Path) -> None:
    path = tmp_path / "child.rrd"
    sink = ProcessSink(Destinations(record=str(path)), recording_name="test",
                       static={"period_s": 0.002, "loop_rate_hz": 500.0})
    pub = Publisher(sink, scene_rate_hz=50.0, scene=SceneBuilder(default_config().robot))
    pub.start()
    child = sink.pid
    assert child is not None and child != os.getpid()
    for s in synthetic_samples(N):
        pub.put(s)
    assert pub.wait_published(N, 60.0)
    pub.close()
    assert sink.pid is None  # the child ended after the last flush
    rec = load_recording(path)
    assert len(rec.cycle) == N and rec.period == 0.002
    sent = [s.e_total for s in synthetic_samples(N)]
    assert rec.series[layout.ENERGY.path][:, 0].tolist() == sent


def test_an_unusable_destination_is_a_named_error_at_open(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    sink = ProcessSink(Destinations(record=str(blocker / "x.rrd")))
    with pytest.raises(TelemetryError):
        sink.open()
    assert sink.pid is None


def test_a_dead_child_is_reported_by_the_next_write(tmp_path: Path) -> None:
    sink = ProcessSink(Destinations(record=str(tmp_path / "dead.rrd")), close_timeout=5.0)
    sink.open()
    pid = sink.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    sink._proc.join(10.0)
    with pytest.raises(TelemetryError, match="went away|telemetry process"):
        for _ in range(50):  # a pipe may take a few writes to break
            sink.write([], None)
    with pytest.raises(TelemetryError):
        sink.close()
    assert sink.pid is None
