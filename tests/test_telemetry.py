"""Telemetry queue, batching and publisher thread, against fake sinks (no rerun)."""

from __future__ import annotations

import math
import subprocess
import sys
import threading

import numpy as np
import pytest

from mmctl.config.base import MecanumConfig
from mmctl.control.mecanum import wheel_matrix
from mmctl.runtime.loop import CycleLoop
from mmctl.runtime.timing import TimingRing
from mmctl.telemetry import layout
from mmctl.telemetry import ring as tr
from mmctl.telemetry.batch import (
    Columns,
    base_frame,
    full_rate,
    norm3,
    norm3_rows,
    plot_rate,
    plot_stride,
)
from mmctl.telemetry.events import Event
from mmctl.telemetry.publisher import Publisher
from mmctl.telemetry.queue import DropQueue
from mmctl.telemetry.ring import SampleRing, rows_of, sample_of
from mmctl.telemetry.synthetic import synthetic_sample, synthetic_samples

WAIT = 60.0  # generous: the machine is shared


class RecordingSink:
    """Keeps everything it is given; ``gate`` (if set) blocks write_columns until set."""

    def __init__(self, gate: threading.Event | None = None, fail_after: int | None = None):
        self.gate = gate
        self.fail_after = fail_after
        self.entered = threading.Event()
        self.columns: list[Columns] = []
        self.scenes: list[int] = []
        self.events: list[Event] = []
        self.opened = self.closed = 0

    def open(self) -> None:
        self.opened += 1

    def write(self, columns: list[Columns], scene: tuple[int, float, object] | None = None,
              pace: object = None) -> None:
        self.entered.set()
        if self.gate is not None:
            assert self.gate.wait(WAIT), "test gate never opened"
        if self.fail_after is not None and len(self.columns) >= self.fail_after:
            raise RuntimeError("sink broke")
        self.columns.extend(columns)
        if scene is not None:
            self.scenes.append(scene[0])

    def write_event(self, event: Event) -> None:
        self.events.append(event)

    def close(self) -> None:
        self.closed += 1

    def rows(self, path: str) -> tuple[np.ndarray, np.ndarray]:
        cyc = [c.cycle for c in self.columns if path in c.values]
        val = [c.values[path] for c in self.columns if path in c.values]
        if not cyc:
            return np.zeros(0, np.int64), np.zeros((0, 0))
        return np.concatenate(cyc), np.concatenate(val)


class CountScene:
    def frame(self, s: object) -> str:
        return "frame"


# -- the queue ----------------------------------------------------------------------------
def test_queue_drops_new_items_when_full_and_counts_them() -> None:
    q: DropQueue[int] = DropQueue(3)
    assert [q.put(i) for i in range(5)] == [True, True, True, False, False]
    assert (q.accepted, q.dropped, len(q)) == (3, 2, 3)
    assert q.drain(2) == [0, 1]
    assert q.put(9)
    assert q.drain() == [2, 9]
    assert (q.taken, len(q)) == (4, 0)
    with pytest.raises(ValueError):
        DropQueue(0)


# -- batching -----------------------------------------------------------------------------
def test_norm3_scalar_and_column_forms_are_bit_identical() -> None:
    a = np.random.default_rng(1).normal(scale=40.0, size=(2000, 6))
    assert np.array_equal(norm3_rows(a), np.array([norm3(r) for r in a]))
    assert norm3(np.array([3.0, 4.0, 12.0, 99.0])) == 13.0


def test_full_and_plot_rate_columns_hold_the_sample_values() -> None:
    samples = list(synthetic_samples(23, start=7))
    rows = rows_of(samples)
    cols = full_rate(rows)
    assert list(cols.cycle) == list(range(7, 30))
    assert cols.time_ns[1] - cols.time_ns[0] == 2_000_000
    e = cols.values[layout.ENERGY.path]
    assert e.shape == (23, 3)
    assert e[4, 0] == samples[4].e_total and e[4, 2] == samples[4].e_base
    f = cols.values[layout.FORCE_NORM.path]
    assert f[5, 0] == pytest.approx(np.linalg.norm(samples[5].f_h[:3]), rel=1e-15)
    assert cols.values[layout.SPEED.path][3, 1] == norm3(samples[3].v)
    # positions go out in the mobile base frame: the synthetic p_des is (0.9, 0, 1) there
    assert np.allclose(cols.values[layout.EE_POSITION_DES.path], [0.9, 0.0, 1.0], atol=1e-12)
    x, y, yaw = samples[9].base_pose
    dx, dy = samples[9].p[0] - x, samples[9].p[1] - y
    assert np.allclose(cols.values[layout.EE_POSITION.path][9],
                       [math.cos(yaw) * dx + math.sin(yaw) * dy,
                        -math.sin(yaw) * dx + math.cos(yaw) * dy, samples[9].p[2]], atol=1e-15)
    for s in layout.FULL_RATE:
        assert cols.values[s.path].shape == (23, len(s.names))

    stride = plot_stride(500.0, 100.0)
    assert stride == 5
    wheels = wheel_matrix(MecanumConfig())
    plot = plot_rate(rows, stride, wheels)
    assert list(plot.cycle) == [10, 15, 20, 25]
    assert np.allclose(plot.values[layout.WHEELS.path][0], wheels @ samples[3].qd_cmd[6:],
                       rtol=1e-15, atol=0)
    assert np.array_equal(plot.values[layout.BASE_TWIST.path][1], samples[8].qd_cmd[6:])
    for s in layout.PLOT_RATE:
        assert plot.values[s.path].shape == (4, len(s.names))


# -- the publisher --------------------------------------------------------------------------
def test_put_never_blocks_while_the_sink_is_stuck_and_drops_are_counted() -> None:
    gate = threading.Event()
    sink = RecordingSink(gate)
    pub = Publisher(sink, queue_size=50, scene_rate_hz=200.0)
    pub.start()
    try:
        assert pub.put(synthetic_sample(0))
        assert sink.entered.wait(WAIT)  # the publisher thread is now stuck inside the sink
        results = [pub.put(s) for s in synthetic_samples(500, start=1)]
        # Every put returned (we are here), the queue kept exactly its capacity:
        assert results.count(True) == 50 and results.count(False) == 450
        assert pub.ring.dropped == 450 and len(pub.ring) == 50
    finally:
        gate.set()
        pub.close()
    assert pub.published == 51 == pub.ring.accepted
    assert sink.closed == 1
    cycles, _ = sink.rows(layout.ENERGY.path)
    assert list(cycles) == list(range(51))
    _, dropped = sink.rows(layout.DROPPED.path)
    assert dropped[-1, 0] == 450


def test_the_loop_never_waits_on_a_stuck_publisher() -> None:
    """A real CycleLoop puts a sample every cycle into a publisher whose sink hangs:
    the loop keeps cycling and the queue counts what it could not hold."""
    gate = threading.Event()
    sink = RecordingSink(gate)
    pub = Publisher(sink, queue_size=64, scene_rate_hz=100.0)
    pub.start()
    loop = CycleLoop(lambda tick: pub.put(synthetic_sample(tick.index)), rate_hz=1000.0,
                     spin_margin=0.0)
    loop.start()
    try:
        assert sink.entered.wait(WAIT)
        target = 64 + 400
        done = threading.Event()

        def watch() -> None:
            while loop.cycles < target and loop.running:
                done.wait(0.01)
            done.set()

        threading.Thread(target=watch, daemon=True).start()
        assert done.wait(WAIT)
        assert loop.cycles >= target
        assert pub.ring.dropped > 0
        assert pub.ring.accepted + pub.ring.dropped >= target
        assert len(pub.ring) == 64
    finally:
        loop.join(WAIT)
        gate.set()
        pub.close()
    assert loop.error is None


def test_flush_sends_scene_events_timing_and_state_changes() -> None:
    ring = TimingRing(64)
    sink = RecordingSink()
    pub = Publisher(sink, timing=ring, scene=CountScene(), pace=False)
    sink.open()
    samples = list(synthetic_samples(10))
    samples[6] = samples[6]._replace(safety="fault")
    for i, s in enumerate(samples):
        if i:  # the loop records cycle i-1's timing before cycle i's sample is written
            ring.record(1_000_000 + (i - 1) * 2_000_000, 5_000 + i - 1, 100_000 + i - 1,
                        1_800_000, 0)
        pub.put(s)
    pub.post_event(Event(3, 0.006, "hello"))
    pub.flush()
    cyc, timing = sink.rows(layout.LOOP_TIMING.path)
    assert list(cyc) == list(range(9))  # the first row had no previous cycle
    assert timing[2].tolist() == [100.002, 1800.0, 5.002]
    tcols = next(c for c in sink.columns if layout.LOOP_TIMING.path in c.values)
    assert tcols.time_ns[3] == 6_000_000
    assert sink.scenes == [9]
    texts = [e.text for e in sink.events]
    assert texts[0] == "mode=min-energy safety=armed"
    assert "mode=min-energy safety=fault" in texts and "hello" in texts
    assert [e.cycle for e in sink.events if "safety" in e.text] == [0, 6, 7]
    pub.flush()  # nothing new: no duplicate timing rows, no scene
    assert len(sink.rows(layout.LOOP_TIMING.path)[0]) == 9 and sink.scenes == [9]


def test_the_binding_limit_is_plotted_and_named_when_it_changes_and_holds() -> None:
    """The limits' scale at the plot rate; an event when the binding limit changes and
    holds for LIMIT_HOLD rows, none for a limit that binds every other cycle."""
    from mmctl.telemetry.publisher import LIMIT_HOLD

    sink = RecordingSink()
    pub = Publisher(sink, pace=False)
    sink.open()
    samples = list(synthetic_samples(200))
    for i in range(200):
        if 40 <= i < 100:  # the energy cap binds for 60 cycles
            samples[i] = samples[i]._replace(limit="energy", limit_scale=0.5)
        elif i >= 140:  # the acceleration limit flickers
            samples[i] = samples[i]._replace(limit="acceleration" if i % 2 else "")
    for chunk in range(0, 200, 20):  # flushed in batches, as the publisher thread does
        for s in samples[chunk:chunk + 20]:
            pub.put(s)
        pub.flush()
    texts = [(e.cycle, e.text) for e in sink.events if e.text.startswith("limit=")]
    assert LIMIT_HOLD <= 40  # (the runs below are long enough)
    assert texts == [(40, "limit=energy"), (100, "limit=none")]
    cyc, scale = sink.rows(layout.LIMIT_SCALE.path)
    by_cycle = dict(zip(cyc.tolist(), scale[:, 0].tolist()))
    assert by_cycle[0] == 1.0 and by_cycle[50] == 0.5 and by_cycle[120] == 1.0


def test_timing_after_a_missed_deadline_lands_on_the_late_cycle() -> None:
    ring = TimingRing(8)
    sink = RecordingSink()
    pub = Publisher(sink, timing=ring, pace=False)
    ring.record(9_000_000, 4_000, 2_500_000, -500_000, 1)  # cycle 4 ran late: 1 skipped
    pub.put(synthetic_sample(5)._replace(t=0.012))  # cycle 5 is due one period later
    pub.flush()
    cyc, timing = sink.rows(layout.LOOP_TIMING.path)
    assert list(cyc) == [4] and timing[0].tolist() == [2500.0, -500.0, 4.0]
    tcols = next(c for c in sink.columns if layout.LOOP_TIMING.path in c.values)
    assert tcols.time_ns.tolist() == [8_000_000]


# -- the ring -------------------------------------------------------------------------------
def test_ring_rows_round_trip_and_a_full_ring_drops_new_rows() -> None:
    ring = SampleRing(4)
    sent = list(synthetic_samples(6))
    assert [ring.put(s) for s in sent] == [True] * 4 + [False] * 2
    assert (ring.accepted, ring.dropped, len(ring)) == (4, 2, 4)
    rows = ring.take(3)
    assert rows.shape == (3, tr.WIDTH) and len(ring) == 1
    back = sample_of(rows[1])
    for name, value in sent[1]._asdict().items():
        got = getattr(back, name)
        assert (np.array_equal(got, value) if isinstance(value, np.ndarray) else got == value), name
    assert ring.put(sent[4]) and ring.put(sent[5])  # room again, order kept across the wrap
    assert ring.take()[:, 0].tolist() == [3.0, 4.0, 5.0]
    assert sample_of(rows_of([sent[0]._replace(mode="bogus")])[0]).mode == "?"
    with pytest.raises(ValueError):
        SampleRing(0)


def test_a_ring_in_a_file_is_shared_by_two_mappings() -> None:
    writer = SampleRing.create_file(16)
    try:
        assert writer.path is not None
        reader = SampleRing.attach_file(writer.path, 16)
    finally:
        writer.unlink()
    assert writer.path is None
    for s in synthetic_samples(20):
        writer.put(s)
    rows = reader.take()
    assert rows[:, 0].tolist() == list(range(16)) and writer.dropped == 4
    reader.mark_published(16)
    assert writer.published == 16 and len(writer) == 0


def test_a_sink_error_is_stored_and_reraised_by_close_and_put_keeps_working() -> None:
    sink = RecordingSink(fail_after=0)
    pub = Publisher(sink, queue_size=8, scene_rate_hz=200.0)
    pub.start()
    pub.put(synthetic_sample(0))
    assert not pub.wait_published(1, WAIT)
    assert isinstance(pub.error, RuntimeError)
    assert all(isinstance(pub.put(s), bool) for s in synthetic_samples(20))
    assert pub.ring.dropped > 0
    with pytest.raises(RuntimeError, match="sink broke"):
        pub.close()
    pub.close()  # idempotent
    assert sink.closed == 1


def test_telemetry_off_imports_no_rerun() -> None:
    code = (
        "import sys\n"
        "from mmctl.config import default_config\n"
        "from mmctl.telemetry.service import TelemetryService, destinations_from\n"
        "import mmctl.telemetry.publisher, mmctl.telemetry.recording, mmctl.telemetry.trial\n"
        "svc = TelemetryService(default_config(), destinations_from(default_config()))\n"
        "svc.start()\n"
        "from mmctl.runtime.core import ControlCore\n"
        "assert svc.hook(ControlCore(default_config())) is None and svc.publisher is None\n"
        "assert 'rerun' not in sys.modules, 'rerun imported'\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


# -- the loop's row writer ------------------------------------------------------------------
def test_control_core_fills_a_row_in_the_base_frame() -> None:
    import time

    from mmctl.config import default_config
    from mmctl.runtime.core import ControlCore
    from mmctl.types import ArmState, Odometry, Wrench

    cfg = default_config()
    core = ControlCore(cfg)
    q_arm = np.asarray(cfg.robot.q_des, dtype=float)
    now = time.monotonic()
    arm = ArmState(q_arm.copy(), np.zeros(6), 0.0, 2, 0)
    odom = Odometry(0.4, -0.2, 0.5, 0.0, 0.0, 0.0, now)
    for k in range(20):  # a push along y: the admittance speeds up
        r = core.step(arm, Wrench(np.array([0.0, 15.0, 0.0]), np.zeros(3), now, k), odom,
                      0.002, active=True, now=now)
    core.set_mode("switch")
    row = np.full(tr.WIDTH, np.nan)
    core.fill_row(r, 7, 0.014, "armed", (150_000, 310_000, 1_500_000, 0), row)
    assert row[tr.CYCLE] == 7 and row[tr.T] == 0.014
    assert tr.label(tr.MODES, row[tr.MODE]) == f"switch/{core.switch}"
    assert tr.label(tr.SAFETY_STATES, row[tr.SAFETY]) == "armed"
    assert list(row[tr.PREV_LATENCY:tr.PREV_MISSED + 1]) == [150_000, 310_000, 1_500_000, 0]
    assert np.array_equal(row[tr.Q_A], r.q[:6]) and np.array_equal(row[tr.BASE_POSE], r.q[6:])
    assert np.array_equal(row[tr.F_H], r.f_h) and np.array_equal(row[tr.V_D], r.v_d)
    assert r.out is not None and np.array_equal(row[tr.V], r.out.v)
    assert np.linalg.norm(row[tr.V_D][:3]) > 0.01
    assert np.array_equal(row[tr.QD_CMD], r.qd_cmd)
    assert np.array_equal(row[tr.BASE_TWIST], r.twist)
    assert row[tr.E_TOTAL] == r.energy.total
    assert np.array_equal(row[tr.P], r.p) and np.array_equal(row[tr.P_DES], r.p_des)
    assert tr.label(tr.LIMITS, row[tr.LIMIT]) == r.out.limit
    assert row[tr.LIMIT_SCALE] == r.out.scale
    # the consumer's world -> mobile base frame: rotate the offset from the base by -yaw
    c, s = math.cos(0.5), math.sin(0.5)
    for world, cols in ((r.p, tr.P), (r.p_des, tr.P_DES)):
        dx, dy = world[0] - 0.4, world[1] + 0.2
        assert np.allclose(base_frame(row[None], cols)[0],
                           [c * dx + s * dy, -s * dx + c * dy, world[2]], atol=1e-15)


def test_a_row_of_an_idle_cycle_holds_the_measured_end_effector_speed() -> None:
    """Not commanding (disarmed, stopped): the cycle measures v = J(q) q̇ and E_K from
    the measured velocities (exactly 0 at rest), and the row holds them."""
    import time

    from mmctl.config import default_config
    from mmctl.runtime.core import ControlCore
    from mmctl.types import ArmState, Odometry, Wrench

    cfg = default_config()
    core = ControlCore(cfg)
    q_arm = np.asarray(cfg.robot.q_des, dtype=float)
    now = time.monotonic()
    wrench = Wrench(np.zeros(3), np.zeros(3), now, 0)
    row = np.full(tr.WIDTH, np.nan)
    still = core.step(ArmState(q_arm.copy(), np.zeros(6), 0.0, 2, 0), wrench,
                      Odometry(0.4, -0.2, 0.5, 0.0, 0.0, 0.0, now), 0.002, active=False,
                      now=now)
    qd_arm = np.array([0.1, -0.2, 0.3, 0.0, 0.05, -0.1])
    moving = core.step(ArmState(q_arm.copy(), qd_arm, 0.0, 2, 0), wrench,
                       Odometry(0.4, -0.2, 0.5, 0.02, 0.0, 0.1, now), 0.002, active=False,
                       now=now)
    assert still.out is None and moving.out is None
    expected = core.model.jacobian(moving.q) @ moving.qd
    # the cycle measured it (the row only copies it: no Jacobian on the telemetry path)
    assert np.array_equal(still.v, np.zeros(6)) and still.energy.total == 0.0
    assert np.allclose(moving.v, expected, rtol=0, atol=1e-12)
    assert moving.energy.total > 0.0  # coasting: E_K from the measured velocities
    core.fill_row(still, 1, 0.002, "disarmed", (0, 0, 0, 0), row)
    assert np.array_equal(row[tr.V], np.zeros(6))
    core.fill_row(moving, 2, 0.004, "disarmed", (0, 0, 0, 0), row)
    assert np.linalg.norm(expected) > 0.1
    assert np.allclose(row[tr.V], expected, rtol=0, atol=1e-12)


def test_base_frame_of_one_row_is_bit_identical_to_the_same_row_among_many() -> None:
    """The trial tracker converts its last row alone; the recording converts batches."""
    rows = rows_of(list(synthetic_samples(97, start=3)))
    rows[:, tr.BASE_YAW] = np.random.default_rng(7).uniform(-4.0, 4.0, len(rows))
    for cols in (tr.P, tr.P_DES):
        many = base_frame(rows, cols)
        for i in (0, 1, 13, 96):
            assert np.array_equal(base_frame(rows[i:i + 1], cols)[0], many[i])
    # and it is the rotation of the offset from the base by -yaw
    x, y, yaw = rows[5, tr.BASE_POSE]
    px, py, pz = rows[5, tr.P]
    c, s = math.cos(yaw), math.sin(yaw)
    assert np.allclose(base_frame(rows, tr.P)[5],
                       [c * (px - x) + s * (py - y), -s * (px - x) + c * (py - y), pz],
                       rtol=0, atol=1e-15)


def test_the_scene_draws_p_des_where_the_plotted_series_has_it() -> None:
    """The 3-D point and the full-rate series are the same base-frame position (one
    conversion, batch.base_frame), bit for bit; synthetic p_des is (0.9, 0, 1) there."""
    from mmctl.config import default_config
    from mmctl.telemetry.batch import full_rate
    from mmctl.telemetry.scene import SceneBuilder

    scene = SceneBuilder(default_config().robot)
    samples = list(synthetic_samples(40, start=3))
    series = full_rate(rows_of(samples)).values[layout.EE_POSITION_DES.path]
    for s, plotted in zip(samples, series, strict=True):
        drawn = scene.frame(s).p_des
        assert np.array_equal(drawn, plotted)
        assert np.allclose(drawn, [0.9, 0.0, 1.0], atol=1e-12)
