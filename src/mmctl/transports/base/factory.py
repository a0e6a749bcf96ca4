"""``open_base``: the configured base transport, built lazily (canopen / pyserial are
imported only for the transport used)."""

from __future__ import annotations

from mmctl.config import Config
from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import ConfigError
from mmctl.transports.base.protocol import Base

TRANSPORTS: tuple[str, ...] = ("canopen", "serial")


def open_base(
    cfg: Config | BaseConfig, *, limits: LimitsConfig | None = None,
    transport: str | None = None, port: str | None = None,
) -> Base:
    """An unconnected :class:`Base` (no I/O yet: call ``connect()`` or use ``with``).

    cfg: the whole config (its ``limits`` are used) or the ``base:`` section (then
    ``limits``, default: the default limits); transport: overrides ``base.transport``;
    port: overrides ``base.serial.port`` (serial only).
    """
    if isinstance(cfg, Config):
        base, limits = cfg.base, cfg.limits
    else:
        base, limits = cfg, limits or LimitsConfig()
    kind = transport or base.transport
    if kind == "canopen":
        from mmctl.transports.base.canopen_base import CanopenBase

        return CanopenBase(base, limits)
    if kind == "serial":
        from mmctl.transports.base.serial_base import SerialBase

        return SerialBase(base, limits, port=port)
    raise ConfigError("base.transport", kind, f"must be one of {', '.join(TRANSPORTS)}")
