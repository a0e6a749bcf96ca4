"""Build a :class:`~mmctl.runtime.daemon.Daemon` from a configuration.

The devices are the *real* transports either way.  With ``sim.enabled`` the daemon
also gets a :class:`~mmctl.runtime.sim_link.SimLink`: it attaches to the simulated
robot's own process (`mmctl sim`) or starts one.  Configurations whose CAN links are
python-can's in-process ``virtual`` bus get none: whoever built them runs the fakes
in the same process (tests that step the daemon cycle by cycle).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mmctl.config import Config
from mmctl.runtime.core import ControlCore
from mmctl.runtime.daemon import Daemon
from mmctl.runtime.devices import open_devices
from mmctl.runtime.inputlog import InputLog
from mmctl.runtime.loop import Wait
from mmctl.runtime.notify import Notifier


def in_process_sim(cfg: Config) -> bool:
    """True when a CAN link of the simulated robot is the in-process ``virtual`` bus."""
    return any(link.interface == "virtual" for _key, link in cfg.can_links())


def create_daemon(cfg: Config, socket_path: Path | None, *, sim_log: Path | None = None,
                  notifier: Notifier | None = None, telemetry: Any = None,
                  attach_sim: bool | None = None, loop_wait: Wait | None = None,
                  input_log: InputLog | None = None) -> Daemon:
    """The daemon for ``cfg`` (nothing started or connected yet).

    telemetry: a :class:`~mmctl.telemetry.service.TelemetryService`; default: one built
    from ``cfg.telemetry`` (publishing nothing unless a destination is configured).
    attach_sim: link to (or start) `mmctl sim`; default: ``sim.enabled`` unless the
    CAN links are in-process (:func:`in_process_sim`).  loop_wait: the loop's wait
    strategy (default: sleep, then spin; `mmctl bench loop` gives its own).  input_log:
    an opened :class:`~mmctl.runtime.inputlog.InputLog` the loop writes every cycle into
    (closed at the daemon's shutdown).
    """
    if attach_sim is None:
        attach_sim = cfg.sim.enabled and not in_process_sim(cfg)
    sim = None
    if attach_sim:
        from mmctl.runtime.sim_link import SimLink

        sim = SimLink(cfg, log_dir=sim_log)
    devices = open_devices(cfg)
    core = ControlCore(cfg)
    if telemetry is None:
        from mmctl.telemetry.service import TelemetryService, destinations_from

        telemetry = TelemetryService(cfg, destinations_from(cfg))
    return Daemon(cfg, devices, core, socket_path=socket_path, notifier=notifier, sim=sim,
                  telemetry=telemetry, loop_wait=loop_wait, input_log=input_log)
