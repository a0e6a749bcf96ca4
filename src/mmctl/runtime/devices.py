"""The robot's devices as the daemon sees them: open, stop, close — in that order.

:func:`open_devices` builds the real transports from the configuration (the same
client code talks to the hardware and to the simulated robot's fakes); transport
modules are imported here, lazily, so that the control commands of the CLI never load
ur_rtde, python-can or canopen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import structlog

from mmctl.config import Config
from mmctl.errors import FaultCause, MmctlError, SafetyFault

if TYPE_CHECKING:
    from mmctl.transports.arm import Arm
    from mmctl.transports.base import Base
    from mmctl.transports.sensor import ForceSensor

log = structlog.get_logger("mmctl.devices")


class Button(Protocol):
    """A digital input: the handle button that toggles switch mode."""

    def pressed(self) -> bool: ...


class ArmDigitalInput:
    """A UR digital input read through the arm transport's ``digital_input(index)``."""

    def __init__(self, arm: Any, index: int):
        self._arm = arm
        self.index = index

    def pressed(self) -> bool:
        return bool(self._arm.digital_input(self.index))


class EnablingSwitch:
    """The enabling (hold-to-run) switch's contacts, read from the arm's newest sample
    (``Arm.digital_input``; see :class:`~mmctl.config.runtime.EnablingConfig`).

    :meth:`held` in every cycle, after the arm's read: True while every contact reads
    held; contacts that disagree for longer than ``discrepancy_time`` raise
    SafetyFault(ENABLING_DEVICE) (released meanwhile), and keep raising until they
    agree again."""

    def __init__(self, arm: Any, inputs: tuple[int, ...], active_low: bool,
                 discrepancy_time: float):
        self._arm = arm
        self.inputs = tuple(inputs)
        self._held_level = not active_low
        self.discrepancy_time = discrepancy_time
        self._disagree_since: float | None = None
        self.last: bool | None = None
        """The last reading (None: not read yet, or the contacts disagree)."""

    def held(self, now: float) -> bool:
        """Whether the switch is held at ``now`` [s] (monotonic clock)."""
        levels = [bool(self._arm.digital_input(i)) for i in self.inputs]
        held = [lvl == self._held_level for lvl in levels]
        if all(held) or not any(held):
            self._disagree_since = None
            self.last = held[0]
            return self.last
        self.last = None
        if self._disagree_since is None:
            self._disagree_since = now
        apart = now - self._disagree_since
        if apart > self.discrepancy_time:
            raise SafetyFault(FaultCause.ENABLING_DEVICE, inputs=list(self.inputs),
                              levels=[int(v) for v in levels],
                              disagree_for=round(apart, 4),
                              why="the switch's contacts disagree (a broken wire or a "
                                  "welded contact)")
        return False


@dataclass
class Devices:
    """Arm, sensor, base (and an optional handle button), connected and closed together."""

    arm: Arm
    sensor: ForceSensor
    base: Base
    button: Button | None = None
    enabling: EnablingSwitch | None = None
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


def open_devices(cfg: Config, button: Button | None = None) -> Devices:
    """The real transports for ``cfg`` (not yet connected)."""
    from mmctl.runtime import logging as mmctl_logging
    from mmctl.transports.base import open_base
    from mmctl.transports.sensor import open_sensor
    from mmctl.transports.ur_rtde_process import UrRtdeProcessArm

    # ur_rtde in a process of its own: its crashes, hangs and GIL-holding calls stay there
    arm = UrRtdeProcessArm(cfg.arm, cfg.limits, mmctl_logging.CURRENT)
    if button is None and cfg.daemon.switch_input >= 0:
        button = ArmDigitalInput(arm, cfg.daemon.switch_input)
    return Devices(arm=arm, sensor=open_sensor(cfg.sensor), base=open_base(cfg),
                   button=button, enabling=enabling_switch(cfg, arm))


def enabling_switch(cfg: Config, arm: Any) -> EnablingSwitch | None:
    """The enabling switch ``cfg.enabling`` describes, on ``arm``'s inputs (None: none)."""
    e = cfg.enabling
    if not e.inputs:
        return None
    return EnablingSwitch(arm, e.inputs, e.active_low, e.discrepancy_time)
