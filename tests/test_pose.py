"""`mmctl pose record`: the arm's current pose as robot.q_des, checked and written into a
config file without disturbing the rest of it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mmctl.commands.pose import check_pose, with_q_des
from mmctl.config import config_from_dict, default_config, load_config
from mmctl.errors import MmctlError

ROOT = Path(__file__).resolve().parents[1]
Q = [0.1, -1.2, 1.5, -1.8, -1.57, 0.3]


@pytest.mark.parametrize("text", [
    ("name: x\nrobot:\n  base_mass: 115  # kg\n  q_des:\n    - 0.0\n    - 1.0\n    - 0\n"
     "    - 0\n    - 0\n    - 0\n  tool_offset: [0, 0, 0.18]\narm:\n  host: a\n"),
    "name: x\nrobot:\n  q_des: [1, 2, 3, 4, 5, 6]\narm: {}\n",
    "name: x\n",
    "",
    "robot:  # the robot\n    base_mass: 100\n",
])
def test_q_des_is_set_and_nothing_else_changes(tmp_path: Path, text: str) -> None:
    out = with_q_des(text, Q)
    path = tmp_path / "c.yaml"
    path.write_text(out)
    cfg = load_config(path)
    assert list(cfg.robot.q_des) == pytest.approx(Q)
    kept = [ln for ln in text.splitlines() if "q_des" not in ln and not ln.startswith("    - ")]
    assert all(ln in out.splitlines() for ln in kept), out  # every other line stays


def test_the_robots_own_config_keeps_its_comments(tmp_path: Path) -> None:
    text = (ROOT / "config" / "robot.yaml").read_text()
    out = with_q_des(text, Q)
    assert out.count("#") == text.count("#") + 1  # the recorded-by note
    path = tmp_path / "robot.yaml"
    path.write_text(out)
    assert list(load_config(path).robot.q_des) == pytest.approx(Q)


def test_a_pose_at_a_joint_limit_or_singular_is_refused() -> None:
    cfg = default_config()
    check_pose(list(cfg.robot.q_des), cfg)  # the default preferred pose is fine
    q = list(cfg.robot.q_des)
    q[3] = cfg.limits.joint_position_min[3] + 0.05  # inside the margin
    with pytest.raises(MmctlError, match=r"joint 3 is at .* must be within"):
        check_pose(q, cfg)
    with pytest.raises(MmctlError, match="close to a singular configuration"):
        check_pose([0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0], cfg)
    tight = config_from_dict({"limits": {"joint_position_max": [2.2] * 6}})
    q = list(Q)
    q[2] = 2.1  # inside the limit, not by the margin
    with pytest.raises(MmctlError, match=r"joint 2 is at 2.1000 rad: .* \[-2.9916, 2.0500\]"):
        check_pose(q, tight)
