"""Publisher -> real rerun .rrd file -> read back with rerun's own API."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.config import default_config
from mmctl.telemetry import layout
from mmctl.telemetry.publisher import Publisher
from mmctl.telemetry.recording import (
    RecordingError,
    column_name,
    entity_rows,
    load_recording,
    recording_metrics,
)
from mmctl.telemetry.rerun_sink import Destinations, RerunSink, TelemetryError, grpc_url
from mmctl.telemetry.scene import SceneBuilder
from mmctl.telemetry.synthetic import synthetic_samples
from mmctl.telemetry.trial import TrialTracker

N = 1200
WAIT = 60.0


def record(path: Path, n: int = N, queue_size: int = 4096, prefill: bool = False,
           trial: tuple[int, int] | None = (200, 899)) -> tuple[Publisher, list]:  # type: ignore[type-arg]
    """Publish n synthetic cycles to ``path``; returns the publisher and trial results.

    prefill: queue everything *before* the publisher starts (so a small queue drops).
    """
    sink = RerunSink(Destinations(record=str(path)), recording_name="test",
                     static={"period_s": 0.002, "loop_rate_hz": 500.0})
    pub = Publisher(sink, queue_size=queue_size, scene_rate_hz=50.0,
                    scene=SceneBuilder(default_config().robot))
    tracker = TrialTracker(0.002, pub.post_event)
    rows = None
    if not prefill:
        pub.start()
    for s in synthetic_samples(n):
        if trial and s.cycle == trial[0]:
            tracker.start()
        tracker.observe(s)
        if trial and s.cycle == trial[1]:
            rows = tracker.stop()
        pub.put(s)
        if not prefill and s.cycle % 100 == 99:
            assert pub.wait_published(pub.ring.accepted, WAIT)  # keep the queue short
    results = [tracker.finish(rows)] if rows is not None else []
    if prefill:
        pub.start()
    pub.close()
    return pub, results


def test_recording_holds_documented_entities_and_metrics_equal_the_logged_ones(
        tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    pub, (live,) = record(path)
    assert pub.ring.dropped == 0 and pub.published == N

    from rerun.chunk import RrdReader  # rerun's own API, independently of mmctl's reader

    store = RrdReader(path).stream().collect()
    table = store.reader(index=layout.TIMELINE_CYCLE).to_arrow_table()
    names = set(table.column_names)
    for s in layout.FULL_RATE + layout.PLOT_RATE:
        assert column_name(s.path) in names, s.path
        col = table.column(column_name(s.path))
        expected = N if s.rate == "full" else N // pub.stride
        assert len(col) - col.null_count == expected, s.path
    energy = np.array([v for v in table.column(column_name(layout.ENERGY.path)).to_pylist()
                       if v is not None])
    sent = list(synthetic_samples(N))
    assert np.array_equal(energy[:, 0], [s.e_total for s in sent])
    for entity in (layout.BASE, layout.ARM, layout.HANDLE, layout.FORCE_ARROW, layout.P_DES):
        assert 0 < entity_rows(path, entity, store=store) <= pub.batches, entity
    assert entity_rows(path, layout.EVENTS, store=store) >= 3  # state, trial start, metrics

    rec = load_recording(path)
    assert len(rec.cycle) == N and rec.period == 0.002
    (again,) = recording_metrics(rec)
    assert again.metrics == live.metrics  # bit-identical
    (trial,) = rec.trials
    assert trial.logged == {"E": live.metrics.E_mean, "F_h": live.metrics.F_mean,
                            "v": live.metrics.v_mean, "x_f": live.metrics.x_f,
                            "T_f": live.metrics.T_f, "samples": 700.0}
    assert (trial.start_cycle, trial.stop_cycle) == (200, 899)


def test_a_full_queue_drops_and_the_recording_holds_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "drops.rrd"
    pub, _ = record(path, n=500, queue_size=300, prefill=True, trial=None)
    assert pub.ring.dropped == 200 and pub.published == 300
    rec = load_recording(path)
    assert len(rec.cycle) + pub.ring.dropped == 500
    assert list(rec.cycle) == list(range(300))  # the newest were dropped, in order
    assert rec.dropped == 200
    assert entity_rows(path, layout.DROPPED.path) == 1
    (whole,) = recording_metrics(rec)
    assert whole.trial == 0 and whole.samples == 300


def test_metrics_command_prints_table_and_json(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "cli.rrd"
    _, (live,) = record(path, n=1000)
    capsys.readouterr()  # drop the log lines of the recording itself
    assert main(["metrics", str(path), "--json"]) == 0
    (line,) = capsys.readouterr().out.strip().splitlines()
    d = json.loads(line)
    assert {k: d[k] for k in ("E", "F_h", "v", "x_f", "T_f")} == {
        "E": live.metrics.E_mean, "F_h": live.metrics.F_mean, "v": live.metrics.v_mean,
        "x_f": live.metrics.x_f, "T_f": live.metrics.T_f}
    assert main(["metrics", str(path), "--compare"]) == 0
    out = capsys.readouterr().out
    assert "max |diff| 0" in out and "daemon logged" in out
    assert main(["metrics", str(tmp_path / "missing.rrd")]) == 2
    (tmp_path / "junk.rrd").write_bytes(b"not a recording")
    assert main(["metrics", str(tmp_path / "junk.rrd")]) == 2


def test_not_an_mmctl_recording(tmp_path: Path) -> None:
    import rerun as rr

    path = tmp_path / "other.rrd"
    rec = rr.RecordingStream("other")
    rec.save(str(path))
    rec.log("x", rr.Scalars([1.0]))
    rec.flush()
    rec.disconnect()
    with pytest.raises(RecordingError, match="no mmctl telemetry"):
        load_recording(path)


def test_connect_addresses() -> None:
    assert grpc_url("") == "rerun+http://127.0.0.1:9876/proxy"
    assert grpc_url("9877") == "rerun+http://127.0.0.1:9877/proxy"
    assert grpc_url("127.0.0.5:9000") == "rerun+http://127.0.0.5:9000/proxy"
    assert grpc_url("rerun+http://127.0.0.1:1/proxy") == "rerun+http://127.0.0.1:1/proxy"
    with pytest.raises(TelemetryError, match="HOST:PORT"):
        grpc_url("localhost")


def test_the_3d_view_draws_the_robot_from_its_urdf_turned_by_the_arms_joints(
        tmp_path: Path) -> None:
    """With the robot's URDF (`mmctl model urdf`), the recording holds every shape of
    it as rerun's URDF loader files them, and joint transforms in named frames that,
    chained from the base's frame to the handle at a recorded cycle, put the handle
    where the model's forward kinematics does for that cycle's joints."""
    import pinocchio as pin
    import rerun.urdf as ru
    from rerun.chunk import RrdReader

    from mmctl.model import RobotModel
    from mmctl.model.geometry import body_shapes
    from mmctl.model.ur10e import JOINT_NAMES
    from mmctl.model.urdf import link_name, urdf

    cfg = default_config()
    path = tmp_path / "robot.rrd"
    sink = RerunSink(Destinations(record=str(path)), recording_name="test",
                     static={"period_s": 0.002}, robot_urdf=urdf(cfg, collision=False))
    pub = Publisher(sink, scene_rate_hz=50.0, scene=SceneBuilder(cfg.robot))
    pub.start()
    sent = {s.cycle: s for s in synthetic_samples(400)}
    for s in sent.values():
        pub.put(s)
        if s.cycle % 40 == 39:  # a scene frame is the newest sample at a wake-up
            assert pub.wait_published(pub.ring.accepted, WAIT)
    pub.close()
    assert pub.error is None

    assert layout.ARM_JOINT_ENTITIES == tuple(f"{layout.ROBOT_JOINTS}/{n}_joint"
                                              for n in JOINT_NAMES)
    store = RrdReader(path).stream().collect()
    static = store.reader(index=None).to_arrow_table()
    drawn = {c.split(":")[0].rsplit("/", 1)[1] for c in static.column_names
             if c.startswith(f"/{layout.ROBOT}/") and "visual_geometries" in c}
    model = RobotModel(cfg.robot)
    for shape in body_shapes(cfg.robot, model.mount):
        assert shape.name in drawn, (shape.name, drawn)
        if shape.kind == "capsule":
            assert {f"{shape.name}_end_a", f"{shape.name}_end_b"} <= drawn
    assert not any("collision_geometries" in c for c in static.column_names)

    tree_file = tmp_path / "robot.urdf"  # the fixed joints, as rerun's parser reads them
    tree_file.write_text(urdf(cfg, collision=False))
    tree = ru.UrdfTree.from_file_path(tree_file)

    def fixed(joint: str) -> pin.SE3:
        found = tree.get_joint_by_name(joint)
        assert found is not None, joint
        tf = found.compute_transform(0.0)
        assert tf.translation is not None and tf.quaternion is not None
        (t,) = tf.translation.as_arrow_array().to_pylist()
        (x, y, z, w), = tf.quaternion.as_arrow_array().to_pylist()
        return pin.SE3(pin.Quaternion(w, x, y, z).matrix(), np.array(t))

    root = f"/{layout.ROBOT_JOINTS}/root:Transform3D:"
    assert static.column(root + "parent_frame").to_pylist()[0] == [f"tf#/{layout.BASE}"]
    assert static.column(root + "child_frame").to_pylist()[0] == ["base_link"]
    table = store.reader(index=layout.TIMELINE_CYCLE,
                         contents=[f"/{e}" for e in layout.ARM_JOINT_ENTITIES]).to_arrow_table()
    cycles = table.column(layout.TIMELINE_CYCLE).to_pylist()

    def col(entity: str, component: str) -> list[Any]:
        values: list[Any] = table.column(f"/{entity}:Transform3D:{component}").to_pylist()
        return values

    rows = [i for i in range(len(cycles))
            if all(col(e, "quaternion")[i] for e in layout.ARM_JOINT_ENTITIES)]
    assert len(rows) >= 3, len(rows)  # (one per scene frame)
    links = ["ur_base"] + [link_name(j) for j in range(1, 7)]
    for i in rows:
        pose = fixed("ur_base_joint")
        for j, entity in enumerate(layout.ARM_JOINT_ENTITIES):
            assert col(entity, "parent_frame")[i] == [links[j]]
            assert col(entity, "child_frame")[i] == [links[j + 1]]
            (t,) = col(entity, "translation")[i]
            (x, y, z, w), = col(entity, "quaternion")[i]
            pose = pose * pin.SE3(pin.Quaternion(w, x, y, z).normalized().matrix(),
                                  np.array(t))
        pose = pose * fixed("flange_joint") * fixed("handle_joint")
        q_a = np.asarray(sent[cycles[i]].q_a, dtype=float)[:6]
        expected = model.fk_base(np.concatenate((q_a, np.zeros(3))), "tool")
        # (float32 on the wire: 1e-7 per number over 1.5 m)
        np.testing.assert_allclose(pose.translation, expected.translation, atol=2e-6)
        np.testing.assert_allclose(pose.rotation, expected.rotation, atol=2e-6)
