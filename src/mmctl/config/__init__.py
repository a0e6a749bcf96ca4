"""YAML configuration -> one frozen, validated :class:`Config`.

Every key has a default (the simulated robot); a file only states what differs.
Errors name the key path, the value and what is allowed::

    config/bad.yaml: admittance.damping[2] = -75.0: must be > 0.0 [N s/m | N m s/rad]
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from mmctl.config.arm import ArmConfig
from mmctl.config.base import BaseConfig, CanopenConfig
from mmctl.config.control import AdmittanceConfig, IdkConfig, LimitsConfig, WallsConfig
from mmctl.config.robot import RobotConfig
from mmctl.config.runtime import (
    DaemonConfig,
    EnablingConfig,
    LoopConfig,
    Ros2Config,
    SafetyConfig,
    SimConfig,
    TelemetryConfig,
)
from mmctl.config.schema import build, keys, param, section, sub, to_dict
from mmctl.config.sensor import SensorCanConfig, SensorConfig
from mmctl.errors import ConfigError

#: The longest a tare may take [s] (sensor.wrench.tare_samples / loop.rate_hz).
MAX_TARE_SECONDS = 20.0

__all__ = ["Config", "ConfigError", "config_from_dict", "default_config", "load_config", "to_dict"]


@section
class Config:
    """The whole daemon configuration."""

    robot: RobotConfig = sub(RobotConfig)
    admittance: AdmittanceConfig = sub(AdmittanceConfig)
    idk: IdkConfig = sub(IdkConfig)
    limits: LimitsConfig = sub(LimitsConfig)
    walls: WallsConfig = sub(WallsConfig)
    arm: ArmConfig = sub(ArmConfig)
    sensor: SensorConfig = sub(SensorConfig)
    base: BaseConfig = sub(BaseConfig)
    loop: LoopConfig = sub(LoopConfig)
    safety: SafetyConfig = sub(SafetyConfig)
    daemon: DaemonConfig = sub(DaemonConfig)
    enabling: EnablingConfig = sub(EnablingConfig)
    telemetry: TelemetryConfig = sub(TelemetryConfig)
    ros2: Ros2Config = sub(Ros2Config)
    sim: SimConfig = sub(SimConfig)
    name: str = param("mmctl", doc="a label for logs and recordings")

    def _check_against_the_period(self, source: str | None) -> None:
        """What the loop feeds once per cycle must not starve at ``loop.rate_hz``."""
        rate = self.loop.rate_hz
        period = 1.0 / rate
        if self.arm.watchdog_min_frequency > rate / 2.0:
            raise ConfigError(
                "arm.watchdog_min_frequency", self.arm.watchdog_min_frequency,
                f"must be <= loop.rate_hz / 2 = {rate / 2.0:g} Hz: the loop kicks the "
                "controller's watchdog once per cycle, and one late cycle must not stop "
                "the arm", source)
        sends = self.loop.base_divider * period
        if sends > self.base.command_watchdog / 2.0:
            raise ConfigError(
                "loop.base_divider", self.loop.base_divider,
                f"must be <= {int(self.base.command_watchdog / 2.0 * rate)}: a twist every "
                f"{sends:g} s (base_divider / loop.rate_hz) must reach the drives twice "
                f"within base.command_watchdog = {self.base.command_watchdog:g} s (the "
                "drives' or the bridge's own stop)", source)
        if self.sensor.wrench.stale_timeout <= period:
            raise ConfigError(
                "sensor.wrench.stale_timeout", self.sensor.wrench.stale_timeout,
                f"must be > the loop period 1 / loop.rate_hz = {period:g} s: a sample is "
                "up to a period old when the next cycle judges it", source)

    def can_links(self) -> list[tuple[str, CanopenConfig | SensorCanConfig]]:
        """The CAN sections in use, as (key, section): the base's CANopen bus (when
        ``base.transport`` is canopen) and the sensor's (when ``sensor.transport`` is can)."""
        links: list[tuple[str, CanopenConfig | SensorCanConfig]] = (
            [("base.canopen", self.base.canopen)] if self.base.transport == "canopen" else [])
        if self.sensor.transport == "can":
            links.append(("sensor.can", self.sensor.can))
        return links

    def validate(self, path: str, source: str | None) -> None:
        """The timeouts and watchdogs fit the loop's period; a tare fits in the person's
        patience; the simulated robot serves CAN where the CAN sections look for it."""
        self._check_against_the_period(source)
        lim, m = self.limits, self.limits.position_margin
        for i, (x, lo, hi) in enumerate(zip(self.robot.q_des, lim.joint_position_min,
                                            lim.joint_position_max)):
            if not lo + m <= x <= hi - m:
                raise ConfigError(
                    f"robot.q_des[{i}]", x,
                    f"must be within limits.joint_position_min/max[{i}] by "
                    f"limits.position_margin: [{lo + m:g}, {hi - m:g}] rad (the null-space "
                    "term pulls the arm there)", source)
        if self.daemon.socket_mode & 0o002:
            raise ConfigError("daemon.socket_mode", oct(self.daemon.socket_mode),
                              "must not be world-writable (o+w): whoever may write to the "
                              "control socket may arm the robot; e.g. 0o660 (owner and group)",
                              source)
        if self.daemon.switch_input in self.enabling.inputs:
            raise ConfigError("enabling.inputs", list(self.enabling.inputs),
                              f"must not include daemon.switch_input = "
                              f"{self.daemon.switch_input} (the switch-mode button)", source)
        tare = self.sensor.wrench.tare_samples / self.loop.rate_hz
        if tare > MAX_TARE_SECONDS:
            raise ConfigError(
                "sensor.wrench.tare_samples", self.sensor.wrench.tare_samples,
                f"must take at most {MAX_TARE_SECONDS:g} s at loop.rate_hz = "
                f"{self.loop.rate_hz:g} Hz (<= {int(MAX_TARE_SECONDS * self.loop.rate_hz)} "
                "samples): the person lets go of the handle for the whole tare", source)
        if not self.sim.enabled:
            return
        for key, link in self.can_links():
            if link.interface == "socketcand":
                if link.host != self.sim.host:
                    raise ConfigError(f"{key}.host", link.host, "must be sim.host "
                                      f"({self.sim.host}): the simulated robot serves CAN "
                                      "there (sim.enabled is true)", source)
                if link.port != self.sim.can_port:
                    raise ConfigError(f"{key}.port", link.port, "must be sim.can_port "
                                      f"({self.sim.can_port}) (sim.enabled is true)", source)
            elif link.interface != "virtual":
                raise ConfigError(f"{key}.interface", link.interface,
                                  "must be 'socketcand' (the simulated robot's own process) "
                                  "or 'virtual' (fakes in the same process: tests) while "
                                  "sim.enabled is true", source)


_REFERENCE_HEAD = """# Configuration: every key, its default and its range

Generated from the schema (`src/mmctl/config/*.py`, `param(..., why=...)`) by
`mmctl config reference --markdown` (`mmctl.config.reference()`); `tests/test_config.py`
keeps this file equal to it.  A value
outside its range is rejected at start (`mmctl check-config FILE`) with one line naming
the key, the value, the range and its reason.  Upper bounds are the hardware's own
limits where there are some (SPEC section 2); elsewhere they catch a unit slip (a time
in ms written as s, a length in mm written as m).  A key with `[i]` is a list: the range
holds for each entry (a tuple: one bound per entry).

Checks between keys: `loop.spin_margin` < the loop period 1 / `loop.rate_hz`;
`arm.watchdog_min_frequency` <= `loop.rate_hz` / 2; `loop.base_divider` / `loop.rate_hz`
<= `base.command_watchdog` / 2; `sensor.wrench.stale_timeout` > the loop period;
`base.canopen.heartbeat_timeout` > `base.canopen.heartbeat_period`;
`base.command_watchdog` >= 2 x `base.canopen.heartbeat_period`; the dead bands below
their limits; a tare (`sensor.wrench.tare_samples` / `loop.rate_hz`) of at most 20 s;
wheel signs -1 or 1; joint position minima below their maxima; `robot.q_des` inside the
joint limits by `limits.position_margin`; `daemon.socket_mode` not world-writable;
`enabling.inputs` at most two different inputs, not `daemon.switch_input`;
`base.canopen.stop_timeout` at least the wheels' ramp to rest (at connect).

A key given twice in one YAML mapping is an error naming it and both lines.

| key | default | allowed | unit | meaning (range: why that range) |
|---|---|---|---|---|
"""


def reference() -> str:
    """docs/configuration.md: every key's default, range, unit and meaning."""
    def cell(text: str) -> str:
        return text.replace("|", "\\|")
    rows = [f"| `{key}` | `{cell(default)}` | {cell(allowed)} | {cell(unit)} | {cell(meaning)} |"
            for key, default, allowed, unit, meaning in keys(Config)]
    return _REFERENCE_HEAD + "\n".join(rows) + "\n"


def config_from_dict(data: Any, source: str | None = None) -> Config:
    """Validate a mapping (e.g. parsed YAML) into a :class:`Config`."""
    cfg: Config = build(Config, data, "", source)
    return cfg


def default_config() -> Config:
    """All defaults: the real robot's (``sim.enabled`` false, SocketCAN ``can0`` /
    ``can1``, the UR at 192.168.0.100); the simulated robot is :func:`sim_profile`."""
    return config_from_dict({})


def sim_profile() -> Path:
    """The simulated robot's configuration installed with the package (the repository's
    config/sim.yaml is a link to it): what every command uses when no configuration is
    named and ./config/sim.yaml does not exist."""
    return Path(__file__).with_name("sim.yaml")


def sim_config() -> Config:
    """:func:`sim_profile` loaded."""
    return load_config(sim_profile())


class _Loader(yaml.SafeLoader):  # type: ignore[misc]  # (PyYAML: no type stubs here)
    """PyYAML's safe loader, with YAML 1.2's floats (``1e-3``: a number, not the string
    YAML 1.1 makes of it); :func:`_parse` checks the node tree for duplicate keys before
    constructing it (YAML 1.2 forbids them; PyYAML keeps the last one silently)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"))

_MERGE_TAG = "tag:yaml.org,2002:merge"


def _key_text(node: yaml.Node) -> str:
    return str(node.value) if isinstance(node, yaml.ScalarNode) else f"<{node.id}>"


def _check_duplicates(root: yaml.Node, source: str) -> dict[str, int]:
    """Every mapping in the document, at any depth: each key once (a ``<<`` merge key is
    YAML's own way to override, not a duplicate).  Iterative: any depth the parser took.

    Returns the line (1-based) of every key path and list item (``a.b``, ``a.b[2]``), for
    the errors found later (:func:`load_config`)."""
    lines: dict[str, int] = {}
    seen_nodes: set[int] = set()
    stack: list[tuple[yaml.Node, str]] = [(root, "")]
    while stack:
        node, path = stack.pop()
        if id(node) in seen_nodes:  # an alias of a node already checked
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict[tuple[str, str], int] = {}
            for key_node, value_node in node.value:
                if key_node.tag == _MERGE_TAG:
                    stack.append((value_node, path))
                    continue
                key = _key_text(key_node)
                key_path = f"{path}.{key}" if path else key
                line = key_node.start_mark.line + 1
                ident = (key_node.tag, key) if isinstance(key_node, yaml.ScalarNode) else (
                    "", str(id(key_node)))
                if ident in first:
                    raise ConfigError(
                        key_path, f"lines {first[ident]} and {line}",
                        f"duplicate key (first on line {first[ident]}, again on line {line}): "
                        "YAML would silently keep only the last one; give it once", source)
                first[ident] = line
                lines.setdefault(key_path, line)
                stack.append((value_node, key_path))
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                lines.setdefault(f"{path}[{i}]", item.start_mark.line + 1)
                stack.append((item, f"{path}[{i}]"))
    return lines


def _parse(text: str, source: str) -> tuple[Any, dict[str, int]]:
    """The YAML document in ``text`` (None when empty), with no duplicate keys, and the
    line of each key path (:func:`_check_duplicates`)."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None, {}
        lines = _check_duplicates(node, source)
        return loader.construct_document(node), lines
    finally:
        loader.dispose()


def load_config(path: str | Path) -> Config:
    """Read and validate a YAML file; every problem raises :class:`ConfigError`
    (including a key given twice in one mapping: the error names both lines)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError("<file>", str(p), f"cannot be read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError("<file>", str(p), f"is not UTF-8 text ({exc.reason} at byte "
                          f"{exc.start})") from None
    try:
        data, lines = _parse(text, str(p))
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "?"
        raise ConfigError("<yaml>", where, f"is not valid YAML ({getattr(exc, 'problem', exc)})", str(p)) from None
    except RecursionError:
        raise ConfigError("<yaml>", "?", "is nested too deeply to be a configuration",
                          str(p)) from None
    try:
        return config_from_dict(data, str(p))
    except ConfigError as exc:
        line = _line_of(exc.key, lines)
        if line is None or exc.source != str(p):
            raise
        raise ConfigError(exc.key, exc.value, exc.allowed, f"{p}:{line}") from None


def _line_of(key: str, lines: Mapping[str, int]) -> int | None:
    """The line of ``key`` (a path as the errors name it), or of the nearest enclosing
    key the file has (a missing key: the section that lacks it); None if none."""
    while key:
        if key in lines:
            return lines[key]
        cut = max(key.rfind("."), key.rfind("["))
        if cut <= 0:
            return None
        key = key[:cut]
    return None
