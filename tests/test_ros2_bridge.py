"""The ROS 2 bridge checked by a real ROS 2 client nobody here wrote: the daemon runs on
its simulated robot with ``ros2.enabled``, and an rclpy node (the ros-rclpy Jazzy
wheels, Fast DDS underneath) subscribes to the bridge's topics (tests/ros2_probe.py).
Both run in a private network namespace with only loopback up, so discovery never
leaves the machine; where no namespace can be made the test is skipped, saying so.

/tf and /tf_static are read with a plain DDS reader: tf2_msgs has no wheel on PyPI, so
rclpy cannot import its type here (the graph still shows the type rclpy sees, and
tests/test_ros2_messages.py decodes the TFMessage bytes with rosbags)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from mmctl.config import load_config
from mmctl.model import RobotModel
from mmctl.model.robot import planar_pose
from simconfig import LOAD_PROOF, write_sim_config

pytest.importorskip("cyclonedds", reason="the ROS 2 bridge's extra (mmctl[ros2])")
pytest.importorskip("rclpy", reason="the ros-rclpy wheels (the test extra)")

from mmctl.ros2.bridge import ROS_JOINT_NAMES

pytestmark = pytest.mark.timeout(600)
PROBE = Path(__file__).with_name("ros2_probe.py")
TOPICS = {"/joint_states": "sensor_msgs/msg/JointState", "/tf": "tf2_msgs/msg/TFMessage",
          "/tf_static": "tf2_msgs/msg/TFMessage", "/robot_description": "std_msgs/msg/String",
          "/mmctl/wrench/human": "geometry_msgs/msg/WrenchStamped",
          "/mmctl/wrench/raw": "geometry_msgs/msg/WrenchStamped",
          "/mmctl/twist/desired": "geometry_msgs/msg/TwistStamped",
          "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}


def _namespace() -> list[str]:
    """The command prefix that runs a shell in a new network namespace, loopback up."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        pytest.skip("no `unshare`/`ip` here: the ROS 2 test needs a private network "
                    "namespace so that DDS discovery never leaves the machine")
    probe = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up"],
                           capture_output=True, text=True, check=False)
    if probe.returncode != 0:
        pytest.skip("cannot make a private network namespace (`unshare -n`: "
                    f"{probe.stderr.strip() or probe.returncode}); the ROS 2 test needs one "
                    "so that DDS discovery never leaves the machine")
    return ["unshare", "-n", "sh", "-c"]


def _pose(frame: dict) -> pin.SE3:  # type: ignore[type-arg]
    x, y, z, w = frame["xyzw"]
    return pin.SE3(pin.Quaternion(w, x, y, z).normalized().matrix(), np.array(frame["xyz"]))


def test_a_real_rclpy_node_sees_the_robot(tmp_path: Path) -> None:
    prefix = _namespace()
    path = write_sim_config("127.0.0.9", tmp_path, {
        **LOAD_PROOF, "sim": {"human": False, "auto_enable": True},
        "ros2": {"enabled": True}})
    out = tmp_path / "probe.json"
    cmd = (f"ip link set lo up && exec {sys.executable} {PROBE} {path} "
           f"{tmp_path / 'mmctl.sock'} {out} 4")
    run = subprocess.run([*prefix, cmd], capture_output=True, text=True, timeout=540,
                         check=False)
    log = out.with_suffix(".daemon.log")
    assert run.returncode == 0 and out.exists(), (
        run.stdout[-2000:], run.stderr[-3000:], log.read_text()[-3000:] if log.exists() else "")
    r = json.loads(out.read_text())
    assert r["armed"], log.read_text()[-3000:]

    # the graph lists each topic with the type a stock ROS 2 node expects
    for topic, typ in TOPICS.items():
        assert r["graph"].get(topic) == [typ], (topic, r["graph"].get(topic))

    # joint states: ur_description's names; at rest, the positions are the status's
    st = r["status"]
    last = r["joints_last"]
    assert r["joint_count"] > 10 and last["name"] == list(ROS_JOINT_NAMES)
    q = np.asarray(st["robot"]["q"], dtype=float)
    np.testing.assert_allclose(last["position"], q[:6], atol=2e-4)  # (status rounds)
    assert np.all(np.abs(last["velocity"]) < 0.01)

    # the description parses (pinocchio's URDF reader) and is the configured robot
    cfg = load_config(path)
    described = pin.buildModelFromXML(r["description"])
    assert [described.names[i] for i in range(1, described.njoints)] == list(ROS_JOINT_NAMES)
    model = RobotModel(cfg.robot)
    data = described.createData()
    pin.forwardKinematics(described, data, q[:6])
    pin.updateFramePlacements(described, data)
    handle = data.oMf[described.getFrameId("handle")]
    np.testing.assert_allclose(handle.translation, model.fk_base(q, "tool").translation,
                               atol=1e-9)

    # the TF chain from odom to the handle resolves and equals the model's FK
    tf = r["tf"]
    chain, frame = [], "handle"
    while frame != "odom":
        assert frame in tf, (frame, sorted(tf))
        chain.append(tf[frame])
        frame = tf[frame]["parent"]
        assert len(chain) < 20
    pose = pin.SE3.Identity()
    for link in reversed(chain):
        pose = pose * _pose(link)
    expected = planar_pose(q[6], q[7], q[8]) * model.fk_base(q, "tool")
    np.testing.assert_allclose(pose.translation, expected.translation, atol=1e-6)
    np.testing.assert_allclose(pose.rotation, expected.rotation, atol=1e-6)

    # the human wrench in the handle's frame: the status's f_h (base axes) turned
    rot = model.fk_base(q, "tool").rotation
    f_h = np.asarray(st["robot"]["f_h"], dtype=float)
    assert r["wrench"]["frame"] == "handle" and r["twist"]["frame"] == "handle"
    np.testing.assert_allclose(r["wrench"]["force"], rot.T @ f_h[:3], atol=0.5)
    # the raw wrench in the sensor's frame: the handle's weight, before the tare (> 5 N)
    assert r["raw"]["frame"] == "sensor" and np.linalg.norm(r["raw"]["force"]) > 5.0

    # diagnostics: the state and the mode, and the loop's timing
    (diag,) = r["diagnostics"]
    assert diag["name"] == "mmctl: controller" and diag["level"] == 0
    assert diag["values"]["state"] == "armed" == st["state"]
    assert diag["values"]["mode"] == st["mode"]
    assert int(diag["values"]["cycles"]) > 0
    assert r["daemon_rc"] == 0
