"""Config: every error names the key path, the value and what is allowed."""

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from mmctl.cli import main
from mmctl.config import Config, ConfigError, config_from_dict, default_config, load_config, to_dict
from simconfig import LOAD_PROOF, sim_config

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("path", sorted((ROOT / "config").glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_configs_are_valid(path: Path) -> None:
    cfg = load_config(path)
    assert cfg.robot.base_mass == 115.0


def test_shipped_configs_are_the_expected_ones() -> None:
    assert {p.name for p in (ROOT / "config").glob("*.yaml")} >= {"sim.yaml", "robot.yaml"}


def test_defaults_are_the_paper_values() -> None:
    cfg = default_config()
    assert cfg.admittance.mass == (4.0,) * 6
    assert cfg.admittance.damping == (75.0,) * 6
    assert cfg.idk.null_gain == (1.0,) * 6 + (0.0,) * 3


@pytest.mark.parametrize(
    ("data", "key", "fragment"),
    [
        ({"robot": {"q_dess": [0] * 6}}, "robot.q_dess", "unknown key; did you mean 'q_des'? allowed keys here: arm_mount"),
        ({"robot": {"q_des": [0, 0, 0, 0, 0]}}, "robot.q_des", "expected a list of 6 numbers, got 5"),
        ({"robot": {"q_des": "up"}}, "robot.q_des", "expected a list of 6 numbers"),
        ({"admittance": {"damping": [75, 75, -75, 75, 75, 75]}}, "admittance.damping[2]",
         "must be >= 1.0 and <= 10000.0 [N s/m | N m s/rad]; the paper's 75"),
        ({"admittance": {"mass": [4, 4, 4, 0, 4, 4]}}, "admittance.mass[3]", "must be >= 0.1"),
        ({"robot": {"base_mass": -115}}, "robot.base_mass", "must be >= 10.0 and <= 1000.0 [kg]"),
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
    assert "admittance.damping[2] = -75.0: must be >= 1.0 and <= 10000.0" in err
    assert err.count("\n") == 1
    broken = tmp_path / "broken.yaml"
    broken.write_text("robot: [unclosed\n")
    assert main(["check-config", str(broken)]) == 2
    assert "not valid YAML" in capsys.readouterr().err
    assert main(["check-config", str(tmp_path / "missing.yaml")]) == 2
    assert "cannot be read" in capsys.readouterr().err


# -- every number has a physically sensible range ------------------------------------------

def _numbers(cls: type, path: str = "") -> Iterator[tuple[str, Any, dataclasses.Field[Any]]]:
    """(key path, element type, field) of every number (or list of numbers) in a section."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        typ = hints[f.name]
        key = f"{path}.{f.name}" if path else f.name
        args = [a for a in typing.get_args(typ) if a is not type(None)]
        if typing.get_origin(typ) in (typing.Union, types.UnionType):
            typ = args[0]
        if dataclasses.is_dataclass(typ):
            yield from _numbers(typ, key)  # type: ignore[arg-type]
        elif typing.get_origin(typ) is tuple and typing.get_args(typ)[0] in (int, float):
            yield key, typing.get_args(typ)[0], f
        elif typ in (int, float):
            yield key, typ, f


ALL_NUMBERS = list(_numbers(Config))


def test_the_schema_walk_finds_the_numbers() -> None:
    keys = {k for k, _t, _f in ALL_NUMBERS}
    assert {"loop.rate_hz", "daemon.ready_timeout", "sensor.can.timeout",
            "sensor.wrench.stale_timeout", "limits.joint_velocity", "robot.q_init"} <= keys
    assert len(keys) > 90


@pytest.mark.parametrize(("key", "typ", "field"), ALL_NUMBERS, ids=[k for k, _t, _f in ALL_NUMBERS])
def test_every_number_has_a_lower_and_an_upper_bound_and_a_reason(
        key: str, typ: type, field: dataclasses.Field[Any]) -> None:
    meta = field.metadata
    assert meta.get("ge") is not None or meta.get("gt") is not None, f"{key}: no lower bound"
    assert meta.get("le") is not None or meta.get("lt") is not None, f"{key}: no upper bound"
    assert meta.get("why"), f"{key}: no reason for its range"


def test_every_default_is_inside_its_own_range() -> None:
    """The defaults are not validated when a key is absent: give all of them explicitly."""
    data = to_dict(default_config())
    assert to_dict(config_from_dict(data)) == data


@pytest.mark.parametrize(("text", "key"), [
    ("loop:\n  rate_hz: 1e-300\n", "loop.rate_hz"),  # was an OverflowError at start
    ("daemon:\n  ready_timeout: 1e300\n", "daemon.ready_timeout"),  # OverflowError
    ("sensor:\n  can:\n    timeout: 1e300\n", "sensor.can.timeout"),  # every cycle an error
    ("loop:\n  rate_hz: 1.0e-300\n", "loop.rate_hz"),
    ("sim:\n  ready_timeout: 1.0e+300\n", "sim.ready_timeout"),
])
def test_values_that_failed_at_run_time_are_rejected_by_check_config(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, key: str) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    line = text.count("\n")  # the key's line: the last of the snippet
    assert f"{bad}:{line}: {key} = " in err and "must be >= " in err and " and <= " in err, err
    assert err.count("\n") == 1
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    assert info.value.key == key


@pytest.mark.parametrize(("data", "key"), [
    ({"sensor": {"wrench": {"stale_timeout": 10}}}, "sensor.wrench.stale_timeout"),  # 10 ms
    ({"base": {"command_watchdog": 200}}, "base.command_watchdog"),  # 200 ms
    ({"base": {"canopen": {"heartbeat_timeout": 100}}}, "base.canopen.heartbeat_timeout"),
    ({"base": {"serial": {"link_timeout": 100}}}, "base.serial.link_timeout"),
    ({"sensor": {"can": {"timeout": 5}}}, "sensor.can.timeout"),  # 5 ms
    ({"robot": {"base_mass": 115_000}}, "robot.base_mass"),  # grams
    ({"robot": {"tool_offset": [0, 0, 180]}}, "robot.tool_offset[2]"),  # millimetres
    ({"base": {"mecanum": {"wheel_radius": 127}}}, "base.mecanum.wheel_radius"),  # mm
    ({"sensor": {"wrench": {"handle_mass": 600}}}, "sensor.wrench.handle_mass"),  # grams
    ({"robot": {"arm_mount_yaw": 180}}, "robot.arm_mount_yaw"),  # degrees
    ({"limits": {"position_margin": 10}}, "limits.position_margin"),  # degrees
    ({"arm": {"watchdog_min_frequency": 0.1}}, "arm.watchdog_min_frequency"),  # 10 s
])
def test_unit_slips_are_caught(data: dict[str, Any], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "x.yaml")
    assert info.value.key == key
    assert "must be >= " in str(info.value) and "; " in str(info.value)  # range and reason


@pytest.mark.parametrize(("data", "key", "fragment"), [
    ({"limits": {"joint_velocity": [2.1, 2, 3, 3, 3, 3]}}, "limits.joint_velocity[0]",
     "<= 2.0944 [rad/s]; the UR10e's own limits"),
    ({"limits": {"joint_velocity": [2, 2, 3.2, 3, 3, 3]}}, "limits.joint_velocity[2]", "<= 3.1416"),
    ({"limits": {"joint_acceleration": [41] * 6}}, "limits.joint_acceleration[0]", "<= 40.0"),
    ({"limits": {"base_linear_velocity": 2.0}}, "limits.base_linear_velocity", "<= 1.5"),
    ({"limits": {"wheel_velocity": 30}}, "limits.wheel_velocity", "<= 27.27"),
    ({"limits": {"joint_position_max": [7] * 6}}, "limits.joint_position_max[0]", "<= 6.2832"),
    ({"arm": {"frequency": 1000}}, "arm.frequency", "<= 500.0"),
    ({"arm": {"stop_deceleration": 50}}, "arm.stop_deceleration", "<= 40.0"),
    ({"sensor": {"wrench": {"force_limit": 600}}}, "sensor.wrench.force_limit", "<= 500.0"),
    ({"sensor": {"wrench": {"handle_mass": 13}}}, "sensor.wrench.handle_mass", "payload"),
    ({"base": {"canopen": {"bitrate": 2_000_000}}}, "base.canopen.bitrate", "<= 1000000"),
])
def test_values_beyond_the_hardware_s_own_limits_are_rejected(
        data: dict[str, Any], key: str, fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "x.yaml")
    assert info.value.key == key
    assert fragment in str(info.value), str(info.value)


@pytest.mark.parametrize(("data", "key", "fragment"), [
    ({"loop": {"rate_hz": 1000, "spin_margin": 0.001}}, "loop.spin_margin", "loop period"),
    ({"base": {"canopen": {"heartbeat_timeout": 0.02, "heartbeat_period": 0.02}}},
     "base.canopen.heartbeat_timeout", "> base.canopen.heartbeat_period"),
    ({"sensor": {"wrench": {"deadband_force": 10, "force_limit": 10}}},
     "sensor.wrench.deadband_force", "< force_limit"),
    ({"sensor": {"wrench": {"deadband_torque": 1, "torque_limit": 0.5}}},
     "sensor.wrench.deadband_torque", "< torque_limit"),
    ({"base": {"mecanum": {"wheel_signs": [1, -1, 0.5, 1]}}}, "base.mecanum.wheel_signs[2]",
     "-1 or 1"),
])
def test_cross_checks(data: dict[str, Any], key: str, fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "x.yaml")
    assert info.value.key == key
    assert fragment in str(info.value), str(info.value)


def test_the_tests_generous_settings_are_still_valid(tmp_path: Path) -> None:
    """LOAD_PROOF (staleness and watchdogs a loaded machine cannot exhaust) and the
    hand-stepped daemon's settings sit inside the ranges."""
    cfg = config_from_dict(sim_config("127.0.0.2", tmp_path, LOAD_PROOF))
    assert cfg.sensor.wrench.stale_timeout == 5.0 and cfg.arm.stale_cycles == 10_000
    assert cfg.base.command_watchdog == 10.0 and cfg.loop.max_total_misses == 10**9
    assert cfg.daemon.command_timeout == 30.0
    config_from_dict({
        "arm": {"stale_cycles": 10_000, "watchdog_min_frequency": 1.0, "stop_deceleration": 7.5},
        "sensor": {"wrench": {"stale_timeout": 5.0}},
        "base": {"canopen": {"heartbeat_timeout": 5.0, "sdo_timeout": 5.0, "stop_timeout": 10.0},
                 "serial": {"link_timeout": 5.0, "timeout": 1.0}, "command_watchdog": 10.0},
        "loop": {"max_consecutive_misses": 5_000, "max_total_misses": 1_000_000_000}})


# -- YAML: duplicate keys, YAML 1.2 numbers ------------------------------------------------

def test_a_duplicate_top_level_key_names_the_key_and_both_lines(tmp_path: Path) -> None:
    f = tmp_path / "dup.yaml"
    f.write_text("loop:\n  rate_hz: 500\narm:\n  host: 127.0.0.2\nloop:\n  max_total_misses: 9\n")
    with pytest.raises(ConfigError) as info:
        load_config(f)
    msg = str(info.value)
    assert info.value.key == "loop"
    assert msg.startswith(f"{f}: loop = 'lines 1 and 5': duplicate key"), msg
    assert "first on line 1, again on line 5" in msg


def test_a_duplicate_nested_key_names_its_path_and_both_lines(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "dup.yaml"
    f.write_text("name: x\nsensor:\n  wrench:\n    stale_timeout: 0.01\n"
                 "    deadband_force: 1.0\n    stale_timeout: 0.05\n")
    assert main(["check-config", str(f)]) == 2
    err = capsys.readouterr().err
    assert "sensor.wrench.stale_timeout = 'lines 4 and 6': duplicate key" in err, err
    assert err.count("\n") == 1
    f.write_text("base:\n  canopen: {channel: a, port: 1, channel: b}\n")  # flow style
    with pytest.raises(ConfigError) as info:
        load_config(f)
    assert info.value.key == "base.canopen.channel" and "'lines 2 and 2'" in str(info.value)
    f.write_text("loop:\n  cpu_affinity: [1]\nloop: {}\n")
    with pytest.raises(ConfigError, match="'lines 1 and 3'"):
        load_config(f)


def test_merge_keys_and_equal_keys_in_different_mappings_are_not_duplicates(tmp_path: Path) -> None:
    f = tmp_path / "ok.yaml"
    f.write_text("sensor:\n  can: &bus {interface: socketcand, host: 127.0.0.2, port: 29536}\n"
                 "base:\n  canopen:\n    <<: *bus\n    port: 29536\n    channel: b\n")
    cfg = load_config(f)
    assert cfg.base.canopen.interface == "socketcand" and cfg.base.canopen.channel == "b"


def test_exponent_floats_are_numbers(tmp_path: Path) -> None:
    """YAML 1.1 (PyYAML) reads 1e-3 as a string; a config means the number."""
    f = tmp_path / "f.yaml"
    f.write_text("idk:\n  constrained:\n    eps: 1e-7\n    task_weight: 5E+5\n")
    cfg = load_config(f)
    assert cfg.idk.constrained.eps == 1e-7 and cfg.idk.constrained.task_weight == 5e5


def test_an_empty_file_is_the_defaults(tmp_path: Path) -> None:
    f = tmp_path / "empty.yaml"
    f.write_text("# nothing\n")
    assert load_config(f) == default_config()


def test_a_tare_longer_than_the_person_can_let_go_is_rejected() -> None:
    config_from_dict({"loop": {"rate_hz": 500}, "sensor": {"wrench": {"tare_samples": 10_000}}})
    with pytest.raises(ConfigError) as info:
        config_from_dict({"loop": {"rate_hz": 50}, "sensor": {"wrench": {
            "tare_samples": 2000, "stale_timeout": 0.05}}})
    assert info.value.key == "sensor.wrench.tare_samples"
    assert "at most 20 s at loop.rate_hz = 50 Hz (<= 1000 samples)" in str(info.value)


@pytest.mark.parametrize(("data", "key", "fragment"), [
    ({"loop": {"rate_hz": 10}}, "arm.watchdog_min_frequency", "<= loop.rate_hz / 2 = 5 Hz"),
    ({"loop": {"rate_hz": 20, "base_divider": 4}, "arm": {"watchdog_min_frequency": 1}},
     "loop.base_divider", "must be <= 2: a twist every 0.2 s"),
    ({"loop": {"rate_hz": 50}, "arm": {"watchdog_min_frequency": 1}},
     "sensor.wrench.stale_timeout", "must be > the loop period 1 / loop.rate_hz = 0.02 s"),
])
def test_what_the_loop_feeds_once_a_cycle_fits_its_period(
        data: dict[str, Any], key: str, fragment: str) -> None:
    with pytest.raises(ConfigError) as info:
        config_from_dict(data, "x.yaml")
    assert info.value.key == key
    assert fragment in str(info.value), str(info.value)
    # the slowest loop the defaults fit; a slow loop with what fits it
    config_from_dict({"loop": {"rate_hz": 200}})
    config_from_dict({"loop": {"rate_hz": 20, "base_divider": 4},
                      "arm": {"watchdog_min_frequency": 1}, "base": {"command_watchdog": 0.4},
                      "sensor": {"wrench": {"stale_timeout": 0.1}}})


@pytest.mark.parametrize(("content", "fragment"), [
    (b"loop:\n  rate_hz: " + b"9" * 400 + b"\n", "loop.rate_hz = 9999"),  # beyond a double
    (b"a: " + b"[" * 5000, "nested too deeply"),
    (b"\xff\xfe name: x\n", "is not UTF-8 text"),
])
def test_hostile_files_are_one_config_error(tmp_path: Path, content: bytes, fragment: str) -> None:
    f = tmp_path / "hostile.yaml"
    f.write_bytes(content)
    with pytest.raises(ConfigError) as info:
        load_config(f)
    assert fragment in str(info.value)


def test_the_configuration_reference_is_current() -> None:
    """docs/configuration.md is generated from the schema: regenerate it with
    ``python -c "from mmctl.config import reference; print(reference(), end='')" >
    docs/configuration.md``."""
    from mmctl.config import reference

    assert (ROOT / "docs" / "configuration.md").read_text() == reference()


def test_config_reference_lists_every_key_with_default_and_range(
        capsys: pytest.CaptureFixture[str]) -> None:
    """`mmctl config reference`: every key of the schema, with its default and what is
    allowed; --markdown is docs/configuration.md."""
    from mmctl.cli import main
    from mmctl.config import reference, to_dict

    assert main(["config", "reference"]) == 0
    out = capsys.readouterr().out

    def leaves(d: dict[str, object], path: str = "") -> list[str]:
        keys: list[str] = []
        for k, v in d.items():
            p = f"{path}.{k}" if path else k
            keys += leaves(v, p) if isinstance(v, dict) else [p]
        return keys

    every = leaves(to_dict(default_config()))
    listed = [ln.split(" = ")[0] for ln in out.splitlines() if not ln.startswith(" ")]
    assert listed == every
    assert "limits.body_region = 'chest'\n    allowed: 'none' | 'neck'" in out
    assert "enabling.active_low = False\n    allowed: true | false" in out
    assert "robot.q_init = null [rad / m]\n    allowed: 9 x" in out
    assert main(["config", "reference", "--markdown"]) == 0
    assert capsys.readouterr().out == reference()
    assert main(["config", "check", str(ROOT / "config" / "robot.yaml")]) == 0
    assert capsys.readouterr().out == "ok\n"


def test_q_des_inside_the_limits_and_a_private_socket() -> None:
    with pytest.raises(ConfigError, match=r"robot.q_des\[2\] = 3.1: must be within"):
        config_from_dict({"robot": {"q_des": [0, -1.9, 3.1, -1.57, -1.57, 0]}})
    with pytest.raises(ConfigError, match="daemon.socket_mode = '0o666': must not be world"):
        config_from_dict({"daemon": {"socket_mode": 0o666}})


def test_the_built_in_defaults_are_the_robots_not_a_simulation() -> None:
    """An empty configuration drives the real robot (it never starts a simulation);
    without a configuration named, commands mean the simulated robot's profile, which
    is installed with the package (the repository's config/sim.yaml links to it)."""
    from mmctl.config import config_from_dict, sim_profile

    empty = config_from_dict({})
    assert not empty.sim.enabled and not empty.sim.human and not empty.sim.auto_enable
    assert (empty.sensor.can.interface, empty.sensor.can.channel) == ("socketcan", "can0")
    assert (empty.base.canopen.interface, empty.base.canopen.channel) == ("socketcan", "can1")
    assert empty.arm.host == "192.168.0.100"
    assert (ROOT / "config" / "sim.yaml").resolve() == sim_profile().resolve()
    assert load_config(sim_profile()).sim.enabled


def test_without_a_config_commands_use_the_installed_simulation(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from mmctl.config import sim_profile
    from mmctl.runtime.client import default_config_path, load

    monkeypatch.chdir(tmp_path)  # no ./config/sim.yaml here
    monkeypatch.delenv("MMCTL_CONFIG", raising=False)
    assert default_config_path() == sim_profile()
    assert load(None).sim.enabled
    (tmp_path / "empty.yaml").write_text("{}\n")
    assert not load(str(tmp_path / "empty.yaml")).sim.enabled


def test_the_ros2_section_names_a_bad_namespace_and_domain() -> None:
    from mmctl.ros2.bridge import topic_name

    cfg = config_from_dict({"ros2": {"topic_prefix": "/robot1/", "domain_id": 7}})
    assert (cfg.ros2.topic_prefix, cfg.ros2.domain_id, cfg.ros2.enabled) == ("/robot1/", 7, False)
    assert topic_name(cfg.ros2.topic_prefix, "/joint_states") == "/robot1/joint_states"
    assert topic_name("", "mmctl/wrench/human") == "/mmctl/wrench/human"
    with pytest.raises(ConfigError, match=r"ros2.topic_prefix = 'robot-1': must be a ROS 2 "):
        config_from_dict({"ros2": {"topic_prefix": "robot-1"}})
    with pytest.raises(ConfigError, match=r"ros2.domain_id = 233: must be >= 0 and <= 232"):
        config_from_dict({"ros2": {"domain_id": 233}})
    with pytest.raises(ConfigError, match=r"ros2.discovery_range = 'lan'"):
        config_from_dict({"ros2": {"discovery_range": "lan"}})


def test_a_typo_d_key_gets_the_closest_allowed_key_and_its_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`mmctl check-config` on a file with a typo: the file's line of the key, the key,
    the value, the nearest allowed key, and all allowed keys."""
    bad = tmp_path / "typo.yaml"
    bad.write_text("loop:\n  rate_hz: 500\n\nsim:\n  # comment\n  auto_enabel: true\n")
    assert main(["check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:6: sim.auto_enabel = True: unknown key; did you mean 'auto_enable'? " \
           "allowed keys here: " in err, err
    assert "auto_enable" in err.split("allowed keys here:")[1]


def test_no_suggestion_for_a_key_like_no_allowed_one(tmp_path: Path) -> None:
    bad = tmp_path / "far.yaml"
    bad.write_text("sim:\n  zzzzqq: 1\n")
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    assert "did you mean" not in str(info.value)
    assert str(info.value).startswith(f"{bad}:2: sim.zzzzqq = 1: unknown key; allowed keys")


def test_an_error_in_a_list_item_names_the_items_line(
        tmp_path: Path) -> None:
    """A list entry: its own line, not its key's."""
    bad = tmp_path / "list.yaml"
    bad.write_text("admittance:\n  damping:\n    - 75\n    - 75\n    - -75\n"
                   "    - 75\n    - 75\n    - 75\n")
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    assert str(info.value).startswith(f"{bad}:5: admittance.damping[2] = -75"), info.value
