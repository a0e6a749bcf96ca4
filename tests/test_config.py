"""Config: every error names the key path, the value and what is allowed."""

from __future__ import annotations

from pathlib import Path

import pytest

from mmctl.cli import main
from mmctl.config import ConfigError, config_from_dict, default_config, load_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["sim.yaml", "robot.yaml"])
def test_shipped_configs_are_valid(name: str) -> None:
    cfg = load_config(ROOT / "config" / name)
    assert cfg.robot.base_mass == 115.0


def test_defaults_are_the_paper_values() -> None:
    cfg = default_config()
    assert cfg.admittance.mass == (4.0,) * 6
    assert cfg.admittance.damping == (75.0,) * 6
    assert cfg.idk.null_gain == (1.0,) * 6 + (0.0,) * 3


@pytest.mark.parametrize(
    ("data", "key", "fragment"),
    [
        ({"robot": {"q_dess": [0] * 6}}, "robot.q_dess", "unknown key; allowed keys here: arm_mount"),
        ({"robot": {"q_des": [0, 0, 0, 0, 0]}}, "robot.q_des", "expected a list of 6 numbers, got 5"),
        ({"robot": {"q_des": "up"}}, "robot.q_des", "expected a list of 6 numbers"),
        ({"admittance": {"damping": [75, 75, -75, 75, 75, 75]}}, "admittance.damping[2]", "must be > 0.0"),
        ({"admittance": {"mass": [4, 4, 4, 0, 4, 4]}}, "admittance.mass[3]", "must be > 0.0"),
        ({"robot": {"base_mass": -115}}, "robot.base_mass", "must be > 0.0 [kg]"),
        ({"robot": {"base_mass": True}}, "robot.base_mass", "must be a number"),
        ({"robot": {"base_mass": float("nan")}}, "robot.base_mass", "finite"),
        ({"idk": {"strategy": "fastest"}}, "idk.strategy", "must be one of 'min-energy'"),
        ({"idk": {"locomotion": {"w_beta": [1] * 6}}}, "idk.locomotion.w_beta", "9 numbers"),
        ({"limits": {"joint_position_min": [4] * 6, "joint_position_max": [3] * 6}},
         "limits.joint_position_min[0]", "must be < joint_position_max[0]"),
        ({"sensor": {"transport": "usb"}}, "sensor.transport", "'can', 'rdt'"),
        ({"sensor": {"can": {"base_id": 300}}}, "sensor.can.base_id", "<= 127"),
        ({"loop": {"rate_hz": "fast"}}, "loop.rate_hz", "must be a number"),
        ({"arm": []}, "arm", "expected a mapping"),
    ],
)
def test_errors_name_key_value_and_allowed(data: dict, key: str, fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "x.yaml")
    msg = str(info.value)
    assert msg.startswith(f"x.yaml: {key} = "), msg
    assert fragment in msg
    assert info.value.key == key


def test_config_is_frozen() -> None:
    cfg = default_config()
    with pytest.raises(AttributeError):
        cfg.robot.base_mass = 1.0  # type: ignore[misc]


def test_check_config_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check-config", str(ROOT / "config" / "sim.yaml")]) == 0
    assert capsys.readouterr().out.strip() == "ok"
    bad = tmp_path / "bad.yaml"
    bad.write_text("admittance:\n  damping: [75, 75, -75, 75, 75, 75]\n")
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "admittance.damping[2] = -75.0: must be > 0.0" in err
    assert err.count("\n") == 1
    broken = tmp_path / "broken.yaml"
    broken.write_text("robot: [unclosed\n")
    assert main(["check-config", str(broken)]) == 2
    assert "not valid YAML" in capsys.readouterr().err
    assert main(["check-config", str(tmp_path / "missing.yaml")]) == 2
    assert "cannot be read" in capsys.readouterr().err
