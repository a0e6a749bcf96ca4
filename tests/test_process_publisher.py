"""ProcessPublisher: the whole publisher in a child process, fed through a ring in a
shared file -- a recording read back, trial events carried over, start-up errors named,
a dead child reported (never a hang, never a blocked producer)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import pytest

from mmctl.config import default_config
from mmctl.runtime.timing import TimingRing
from mmctl.telemetry import layout
from mmctl.telemetry.process_publisher import ProcessPublisher
from mmctl.telemetry.recording import load_recording
from mmctl.telemetry.rerun_sink import Destinations, TelemetryError
from mmctl.telemetry.synthetic import synthetic_samples
from mmctl.telemetry.trial import TrialTracker

N = 600
WAIT = 60.0


def test_the_child_writes_the_recording_from_the_shared_ring(tmp_path: Path) -> None:
    path = tmp_path / "child.rrd"
    timing = TimingRing(N + 1)
    mine = os.sched_getaffinity(0)
    loop_cpu = max(mine)  # as if the loop were pinned there (loop.cpu_affinity)
    pub = ProcessPublisher(Destinations(record=str(path)), recording_name="test",
                           static={"period_s": 0.002, "loop_rate_hz": 500.0},
                           robot=default_config().robot, scene_rate_hz=50.0, timing=timing,
                           avoid_cpus=(loop_cpu,))
    pub.start()
    child = pub.pid
    assert child is not None and child != os.getpid()
    # background work, every thread of it (the class and the affinity are per thread):
    # it only gets a CPU nothing else wants, and not the loop's
    tids = [int(t) for t in os.listdir(f"/proc/{child}/task")]
    assert len(tids) > 1  # the publisher's thread besides the main one
    for tid in tids:
        assert os.sched_getscheduler(tid) == os.SCHED_IDLE, tid
        assert os.sched_getaffinity(tid) == (mine - {loop_cpu} or mine), tid
    assert pub.ring is not None and pub.ring.path is None  # unlinked once mapped by both
    tracker = TrialTracker(0.002, pub.post_event)  # its events cross to the child
    rows = None
    for s in synthetic_samples(N):
        if s.cycle:
            timing.record(s.cycle * 2_000_000, 7_000, 300_000, 1_600_000, 0)
        if s.cycle == 100:
            tracker.start()
        tracker.observe(s)
        if s.cycle == 499:
            rows = tracker.stop()
        assert pub.put(s)
    assert rows is not None
    live = tracker.finish(rows)
    assert pub.wait_published(N, WAIT)
    pub.close()
    assert pub.pid is None  # the child ended after the last flush
    stats = pub.stats()
    assert stats["published"] == N and stats["dropped"] == 0 and stats["batches"] >= 1
    rec = load_recording(path)
    assert len(rec.cycle) == N and rec.period == 0.002
    sent = [s.e_total for s in synthetic_samples(N)]
    assert rec.series[layout.ENERGY.path][:, 0].tolist() == sent
    (trial,) = rec.trials
    assert (trial.start_cycle, trial.stop_cycle) == (100, 499)
    assert trial.logged is not None and trial.logged["E"] == live.as_dict()["E"]
    assert trial.logged["x_f"] == live.as_dict()["x_f"]


def test_an_unusable_destination_is_a_named_error_at_start(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    pub = ProcessPublisher(Destinations(record=str(blocker / "x.rrd")))
    with pytest.raises(TelemetryError):
        pub.start()
    assert pub.pid is None
    with pytest.raises(TelemetryError, match="not running"):
        pub.put(next(synthetic_samples(1)))


def test_a_dead_child_is_reported_and_the_producer_never_blocks(tmp_path: Path) -> None:
    pub = ProcessPublisher(Destinations(record=str(tmp_path / "dead.rrd")), queue_size=32,
                           close_timeout=5.0)
    pub.start()
    pid = pub.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    deadline = time.monotonic() + WAIT
    while pub.error is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert isinstance(pub.error, TelemetryError)
    kept = [pub.put(s) for s in synthetic_samples(100)]  # nobody reads: the ring fills up
    assert kept.count(True) == 32 and pub.stats()["dropped"] == 68
    assert not pub.wait_published(1, 1.0)
    with pytest.raises(TelemetryError):
        pub.close()
    assert pub.pid is None


def test_the_last_flush_runs_in_the_normal_class_again(tmp_path: Path) -> None:
    """The child works as background (SCHED_IDLE) while the loop runs; for its last flush
    it returns to the normal class at the nice it started with, every thread of it
    (a busy machine gave an idle-class flush no CPU for over 30 s)."""
    code = (
        "import os, sys, threading\n"
        "from mmctl.telemetry.process_publisher import _background, _foreground\n"
        "nice = os.getpriority(os.PRIO_PROCESS, 0)\n"
        "stop = threading.Event()\n"
        "t = threading.Thread(target=stop.wait); t.start()\n"
        "tids = [int(x) for x in os.listdir('/proc/self/task')]\n"
        "_background(())\n"
        "idle = {os.sched_getscheduler(x) for x in tids}\n"
        "_foreground(nice)\n"
        "back = {os.sched_getscheduler(x) for x in tids}\n"
        "nices = {os.getpriority(os.PRIO_PROCESS, x) for x in tids}\n"
        "stop.set(); t.join()\n"
        "print(len(tids), idle == {os.SCHED_IDLE}, back == {os.SCHED_OTHER}, nices == {nice})\n")
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout.split()
    # every thread (ours and any the imports started): idle class in the background;
    # the normal class and the nice after
    assert int(out[0]) >= 2 and out[1:] == ["True", "True", "True"], out


def test_a_stopped_child_is_an_error_at_close_not_a_hang(tmp_path: Path) -> None:
    """close waits on while the child drains the ring, but a child that makes no
    progress for close_timeout is an error (here: stopped by SIGSTOP)."""
    pub = ProcessPublisher(Destinations(record=str(tmp_path / "stopped.rrd")),
                           close_timeout=1.0)
    pub.start()
    pid = pub.pid
    assert pid is not None
    try:
        os.kill(pid, signal.SIGSTOP)
        for s in synthetic_samples(50):
            assert pub.put(s)
        t0 = time.monotonic()
        with pytest.raises(TelemetryError, match="no last flush within 1 s"):
            pub.close()
        assert time.monotonic() - t0 < WAIT
        assert pub.pid is None  # killed
    finally:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass
