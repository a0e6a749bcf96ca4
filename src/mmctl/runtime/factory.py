"""Build a :class:`~mmctl.runtime.daemon.Daemon` from a configuration, and open the
simulated robot's process for it.

The devices are the *real* transports either way.  The daemon never starts or stops
the simulation: whoever runs it does (`mmctl run`, `mmctl bench loop`), with
:func:`open_sim`, before the daemon connects, and closes it after the daemon stopped;
the daemon only gets the link (for its status and the person's hands during a tare).
Configurations whose CAN links are python-can's in-process ``virtual`` bus get no link:
whoever built them runs the fakes in the same process (tests that step the daemon
cycle by cycle).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from mmctl.config import Config
from mmctl.runtime.core import ControlCore
from mmctl.runtime.daemon import Daemon
from mmctl.runtime.devices import open_devices
from mmctl.runtime.inputlog import InputLog
from mmctl.runtime.loop import Wait
from mmctl.runtime.notify import Notifier

if TYPE_CHECKING:
    from mmctl.runtime.sim_link import SimLink
    from mmctl.telemetry.service import TelemetryService


def in_process_sim(cfg: Config) -> bool:
    """True when a CAN link of the simulated robot is the in-process ``virtual`` bus."""
    return any(link.interface == "virtual" for _key, link in cfg.can_links())


def wants_sim_process(cfg: Config) -> bool:
    """True when ``cfg`` drives the simulated robot in a process of its own."""
    return cfg.sim.enabled and not in_process_sim(cfg)


def sim_link(cfg: Config, log_dir: Path | None = None) -> SimLink | None:
    """The link to the simulated robot's process for ``cfg`` (not started yet), or None
    when ``cfg`` has none (:func:`wants_sim_process`).  log_dir: where a simulation the
    link starts writes its fakes' command logs when it stops."""
    if not wants_sim_process(cfg):
        return None
    from mmctl.runtime.sim_link import SimLink

    return SimLink(cfg, log_dir=log_dir)


def open_sim(cfg: Config) -> SimLink | None:
    """:func:`sim_link`, attached to or started (its fakes listening: the daemon can
    connect).  Close it (``close()``) after the daemon stopped."""
    sim = sim_link(cfg)
    if sim is None:
        return None
    try:
        sim.start()
    except BaseException:
        sim.close()
        raise
    return sim


def create_daemon(cfg: Config, socket_path: Path | None, *, sim: SimLink | None = None,
                  notifier: Notifier | None = None, telemetry: TelemetryService | None = None,
                  loop_wait: Wait | None = None, input_log: InputLog | None = None) -> Daemon:
    """The daemon for ``cfg`` (nothing started or connected yet).

    sim: the simulated robot's process, opened (:func:`open_sim`), or None.  telemetry:
    a :class:`~mmctl.telemetry.service.TelemetryService`; default: one built from
    ``cfg.telemetry`` (publishing nothing unless a destination is configured).
    loop_wait: the loop's wait strategy (default: sleep, then spin; `mmctl bench loop`
    gives its own).  input_log: an opened :class:`~mmctl.runtime.inputlog.InputLog` the
    loop writes every cycle into (closed at the daemon's shutdown).
    """
    devices = open_devices(cfg)
    core = ControlCore(cfg)
    if telemetry is None:
        from mmctl.telemetry.service import TelemetryService, destinations_from

        telemetry = TelemetryService(cfg, destinations_from(cfg))
    return Daemon(cfg, devices, core, socket_path=socket_path, notifier=notifier, sim=sim,
                  telemetry=telemetry, loop_wait=loop_wait, input_log=input_log)
