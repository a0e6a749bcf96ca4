"""The robot's devices as the daemon sees them: open, stop, close — in that order.

:func:`open_devices` builds the real transports from the configuration (the same
client code talks to the hardware and to the simulated robot's fakes); transport
modules are imported here, lazily, so that the control commands of the CLI never load
ur_rtde, python-can or canopen.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import structlog

from mmctl.config import Config
from mmctl.errors import MmctlError

if TYPE_CHECKING:
    from mmctl.transports.arm import Arm
    from mmctl.transports.base import Base
    from mmctl.transports.sensor import ForceSensor

log = structlog.get_logger("mmctl.devices")


@dataclass
class Devices:
    """Arm, sensor, base, connected and closed together (the handle's button and the
    enabling switch are digital inputs of the arm's samples, read by the update)."""

    arm: Arm
    sensor: ForceSensor
    base: Base
    connected: list[str] = field(default_factory=list)

    def connect(self) -> None:
        """Connect arm, sensor, base; on failure close what was opened and re-raise."""
        try:
            for name in ("arm", "sensor", "base"):
                getattr(self, name).connect()
                self.connected.append(name)
                log.info("device_connected", device=name)
        except BaseException:
            self.close()
            raise

    def stop(self, arm_deceleration: float, disable_base: bool = True,
             arm: bool = True, wait: bool = True) -> list[str]:
        """Zero the base, speedStop the arm, then disable the base; every step is tried.

        The base's zero target (RPDOs + SYNC) goes first: it never waits, while the
        arm's speedStop waits for the controller's handshake.  ``arm=False`` leaves the
        arm out (a reconnect owns it; nothing it runs moves).  ``wait``: the base's
        disable waits for the wheels to rest (False on the loop thread: the drives ramp
        down by themselves).  Returns the names of the steps that failed (each logged);
        never raises.
        """
        failed: list[str] = []
        steps: list[tuple[str, Callable[[], None]]] = [("base.stop", self.base.stop)]
        if arm:
            steps.append(("arm.stop", lambda: self.arm.stop(arm_deceleration)))
        if disable_base:
            steps.append(("base.disable", lambda: self.base.disable(wait)))
        for name, fn in steps:
            try:
                fn()
            except (MmctlError, OSError, RuntimeError) as exc:
                failed.append(name)
                log.error("stop_command_failed", step=name, error=str(exc),
                          cause=getattr(exc, "cause", None))
        return failed

    def close(self, arm: bool = True) -> None:
        """Close every device (idempotent, errors logged); ``arm=False`` leaves the arm
        open (a reconnect still owns it)."""
        for name in ("base", "sensor", "arm")[:None if arm else 2]:
            try:
                getattr(self, name).close()
            except (MmctlError, OSError, RuntimeError) as exc:
                log.error("device_close_failed", device=name, error=str(exc))
        self.connected.clear()


def sensor_in_process_of_its_own(cfg: Config) -> bool:
    """``sensor.process``, unless the sensor is on python-can's in-process ``virtual``
    bus (no other process reaches it)."""
    s = cfg.sensor
    return s.process and not (s.transport == "can" and s.can.interface == "virtual")


def link_scheduling(cfg: Config) -> tuple[int, tuple[int, ...]]:
    """The device links' processes' SCHED_FIFO priority and CPUs: below the loop's
    priority (10 lower, at least 1; 0 when the loop has none) and off the loop's CPUs
    when it is pinned and others remain (a link at the loop's priority on the loop's CPU
    takes turns with it instead of yielding)."""
    prio = max(cfg.loop.rt_priority - 10, 1) if cfg.loop.rt_priority > 0 else 0
    cpus: tuple[int, ...] = ()
    loop_cpus = set(cfg.loop.cpu_affinity)
    if loop_cpus and hasattr(os, "sched_getaffinity"):
        cpus = tuple(sorted(os.sched_getaffinity(0) - loop_cpus))
    return prio, cpus


def open_devices(cfg: Config) -> Devices:
    """The real transports for ``cfg`` (not yet connected)."""
    from mmctl.runtime import logging as mmctl_logging
    from mmctl.transports.base import open_base
    from mmctl.transports.sensor import open_sensor
    from mmctl.transports.ur_rtde_process import UrRtdeProcessArm

    # ur_rtde in a process of its own: its crashes, hangs and GIL-holding calls stay there
    arm = UrRtdeProcessArm(cfg.arm, cfg.limits, mmctl_logging.CURRENT)
    prio, cpus = link_scheduling(cfg)
    sensor: ForceSensor
    if sensor_in_process_of_its_own(cfg):  # the loop only reads the newest sample
        from mmctl.transports.sensor.link_process import SensorLinkProcess

        period = 1.0 / cfg.loop.rate_hz
        sensor = SensorLinkProcess(cfg.sensor, period=period,
                                   lead=min(cfg.sensor.process_lead, 0.5 * period),
                                   rt_priority=prio, cpu_affinity=cpus,
                                   log_setup=mmctl_logging.CURRENT)
    else:
        sensor = open_sensor(cfg.sensor)
    base: Base
    co = cfg.base.canopen  # python-can's `virtual` bus: no other process reaches it
    if cfg.base.process and not (cfg.base.transport == "canopen" and co.interface == "virtual"):
        from mmctl.transports.base.link_process import BaseLinkProcess

        # its own process: the loop reads the newest odometry and leaves its commands
        base = BaseLinkProcess(cfg, period=1.0 / cfg.loop.rate_hz,
                               rt_priority=prio, cpu_affinity=cpus,
                               log_setup=mmctl_logging.CURRENT)
    else:
        base = open_base(cfg)
    return Devices(arm=arm, sensor=sensor, base=base)
