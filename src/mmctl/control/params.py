"""Run-time parameter changes (`mmctl set KEY VALUE`, `mmctl get KEY`): which keys may
change while the robot runs, and the configuration with one key changed, validated as
a configuration file is (:func:`with_value`).

Settable: the admittance's virtual mass and damping, the whole-body caps and the
reduced profile's speed (``limits.energy``, ``base_speed``, ``ee_speed``,
``reduced_ee_speed``, ``body_region``), the null-space gain and the IDK's weights.
Everything else (ports, periods, the robot's geometry, the safety thresholds) needs a
restart: it is built into devices and watchdogs at start-up.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from mmctl.config import Config, config_from_dict, to_dict
from mmctl.errors import ConfigError, MmctlError

#: the keys `mmctl set` may change while the daemon runs
SETTABLE: tuple[str, ...] = (
    "admittance.mass", "admittance.damping",
    "limits.energy", "limits.base_speed", "limits.ee_speed", "limits.reduced_ee_speed",
    "limits.body_region",
    "idk.null_gain",
    "idk.locomotion.w_alpha", "idk.locomotion.w_beta",
    "idk.constrained.task_weight",
)


def get_value(cfg: Config, key: str) -> Any:
    """The plain value (lists for tuples) of ``key`` (dotted path) in ``cfg``;
    MmctlError naming the key and what exists at that level when there is none."""
    node: Any = cfg
    path: list[str] = []
    for part in key.split("."):
        if not dataclasses.is_dataclass(node):
            raise MmctlError(f"{key}: {'.'.join(path)} is a value, not a section")
        names = [f.name for f in dataclasses.fields(node)]
        if part not in names:
            where = ".".join(path) or "the top level"
            raise MmctlError(f"{key}: unknown key; keys at {where}: {', '.join(names)}")
        node = getattr(node, part)
        path.append(part)
    return to_dict(node)


def with_value(cfg: Config, key: str, value: Any) -> Config:
    """``cfg`` with ``key`` set to ``value``, validated as a whole (ConfigError naming
    the key, the value and what is allowed).  A single number for a list of numbers
    sets every entry (``mmctl set admittance.damping 60``)."""
    if key not in SETTABLE:
        get_value(cfg, key)  # an unknown key: say so
        raise ConfigError(key, value, "cannot change while the daemon runs (a restart "
                          f"takes it from the file); settable: {', '.join(SETTABLE)}")
    old = get_value(cfg, key)
    if (isinstance(old, list) and old and all(isinstance(x, (int, float)) for x in old)
            and isinstance(value, (int, float)) and not isinstance(value, bool)):
        value = [value] * len(old)
    data = to_dict(cfg)
    node = data
    *parents, last = key.split(".")
    for part in parents:
        node = node[part]
    node[last] = value
    return config_from_dict(data, source="mmctl set")
