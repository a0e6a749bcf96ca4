"""YAML configuration -> one frozen, validated :class:`Config`.

Every key has a default (the simulated robot); a file only states what differs.
Errors name the key path, the value and what is allowed::

    config/bad.yaml: admittance.damping[2] = -75.0: must be > 0.0 [N s/m | N m s/rad]
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from mmctl.config.arm import ArmConfig
from mmctl.config.base import BaseConfig, CanopenConfig
from mmctl.config.control import AdmittanceConfig, IdkConfig, LimitsConfig
from mmctl.config.robot import RobotConfig
from mmctl.config.runtime import (
    DaemonConfig,
    LoopConfig,
    SafetyConfig,
    SimConfig,
    TelemetryConfig,
)
from mmctl.config.schema import build, param, section, sub, to_dict
from mmctl.config.sensor import SensorCanConfig, SensorConfig
from mmctl.errors import ConfigError

__all__ = ["Config", "ConfigError", "config_from_dict", "default_config", "load_config", "to_dict"]


@section
class Config:
    """The whole daemon configuration."""

    robot: RobotConfig = sub(RobotConfig)
    admittance: AdmittanceConfig = sub(AdmittanceConfig)
    idk: IdkConfig = sub(IdkConfig)
    limits: LimitsConfig = sub(LimitsConfig)
    arm: ArmConfig = sub(ArmConfig)
    sensor: SensorConfig = sub(SensorConfig)
    base: BaseConfig = sub(BaseConfig)
    loop: LoopConfig = sub(LoopConfig)
    safety: SafetyConfig = sub(SafetyConfig)
    daemon: DaemonConfig = sub(DaemonConfig)
    telemetry: TelemetryConfig = sub(TelemetryConfig)
    sim: SimConfig = sub(SimConfig)
    name: str = param("mmctl", doc="a label for logs and recordings")

    def can_links(self) -> list[tuple[str, CanopenConfig | SensorCanConfig]]:
        """The CAN sections in use, as (key, section): the base's CANopen bus (when
        ``base.transport`` is canopen) and the sensor's (when ``sensor.transport`` is can)."""
        links: list[tuple[str, CanopenConfig | SensorCanConfig]] = (
            [("base.canopen", self.base.canopen)] if self.base.transport == "canopen" else [])
        if self.sensor.transport == "can":
            links.append(("sensor.can", self.sensor.can))
        return links

    def validate(self, path: str, source: str | None) -> None:
        """The simulated robot serves CAN where the CAN sections look for it."""
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


def config_from_dict(data: Any, source: str | None = None) -> Config:
    """Validate a mapping (e.g. parsed YAML) into a :class:`Config`."""
    cfg: Config = build(Config, data, "", source)
    return cfg


def default_config() -> Config:
    """All defaults: the simulated robot."""
    return config_from_dict({})


def load_config(path: str | Path) -> Config:
    """Read and validate a YAML file; every problem raises :class:`ConfigError`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError("<file>", str(p), f"cannot be read ({exc.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "?"
        raise ConfigError("<yaml>", where, f"is not valid YAML ({getattr(exc, 'problem', exc)})", str(p)) from None
    return config_from_dict(data, str(p))
