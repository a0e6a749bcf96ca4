"""Build a :class:`~mmctl.runtime.daemon.Daemon` from a configuration.

With ``sim.enabled`` the simulated world (fake UR controller process, fake CAN sensor,
fake CANopen drives, simulated person) is created too; the devices are the *real*
transports either way.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mmctl.config import Config
from mmctl.runtime.core import ControlCore
from mmctl.runtime.daemon import Daemon
from mmctl.runtime.devices import open_devices
from mmctl.runtime.notify import Notifier


def create_daemon(cfg: Config, socket_path: Path | None, *, sim_log: Path | None = None,
                  notifier: Notifier | None = None, telemetry: Any = None) -> Daemon:
    """The daemon for ``cfg`` (nothing started or connected yet).

    telemetry: a :class:`~mmctl.telemetry.service.TelemetryService`; default: one built
    from ``cfg.telemetry`` (publishing nothing unless a destination is configured).
    """
    sim = None
    button = None
    if cfg.sim.enabled:
        from mmctl.runtime.sim_world import SimWorld

        sim = SimWorld(cfg, log_dir=sim_log)
        button = sim.button
    devices = open_devices(cfg, button=button)
    core = ControlCore(cfg)
    if telemetry is None:
        from mmctl.telemetry.service import TelemetryService, destinations_from

        telemetry = TelemetryService(cfg, destinations_from(cfg))
    return Daemon(cfg, devices, core, socket_path=socket_path, notifier=notifier, sim=sim,
                  telemetry=telemetry)
