"""Force/torque sensor transports behind one seam, :class:`ForceSensor`.

``open_sensor(cfg.sensor)`` builds the transport named by ``sensor.transport`` (``can``:
:class:`~mmctl.transports.sensor.can_ft.CanForceSensor`, ``rdt``:
:class:`~mmctl.transports.sensor.rdt.RdtForceSensor`) without doing any I/O; connect it
with ``connect()`` or a ``with`` block.  The transport modules are imported lazily so
that importing this package does not pull in python-can.
"""

from __future__ import annotations

from mmctl.config.sensor import SensorConfig
from mmctl.transports.sensor.protocol import ForceSensor, SensorStats

__all__ = ["ForceSensor", "SensorStats", "open_sensor"]


def open_sensor(cfg: SensorConfig) -> ForceSensor:
    """The (not yet connected) transport ``cfg.transport`` configured from ``cfg``."""
    if cfg.transport == "can":
        from mmctl.transports.sensor.can_ft import CanForceSensor

        return CanForceSensor(cfg.can, stale_timeout=cfg.wrench.stale_timeout)
    if cfg.transport == "rdt":
        from mmctl.transports.sensor.rdt import RdtForceSensor

        return RdtForceSensor(cfg.rdt, stale_timeout=cfg.wrench.stale_timeout)
    raise ValueError(f"sensor.transport = {cfg.transport!r}: must be 'can' or 'rdt'")
