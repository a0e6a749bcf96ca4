"""What the daemon's parts (:mod:`mmctl.runtime.operator`, :mod:`mmctl.runtime.driver`)
may use of one another: the :class:`~mmctl.runtime.daemon.Daemon`'s attributes and the
few methods one part calls on another.  For the type checker only: imported under
``TYPE_CHECKING``, never at run time (so no stub here can hide a real method)."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.control.calibration import ToolCalibration
from mmctl.control.safety import Safety
from mmctl.control.update import Readings, Update, UpdateState
from mmctl.runtime.core import ControlCore, CycleResult
from mmctl.runtime.daemon import SampleHook
from mmctl.runtime.devices import Devices
from mmctl.runtime.inputlog import InputLog
from mmctl.runtime.logging import RateLimiter
from mmctl.runtime.loop import CycleLoop
from mmctl.runtime.notify import Notifier
from mmctl.runtime.sim_link import SimLink
from mmctl.runtime.timing import TimingRing
from mmctl.telemetry.service import TelemetryService
from mmctl.types import Wrench


class DaemonParts:
    """The daemon's state and cross-part methods, as the parts see them."""

    cfg: Config
    devices: Devices
    core: ControlCore
    update: Update
    ustate: UpdateState
    inbox_size: int
    readings: Readings | None
    input_log: InputLog | None
    _updated: UpdateState
    _inputs: tuple[int, ...]
    notifier: Notifier
    sim: SimLink | None
    telemetry: TelemetryService | None
    ring: TimingRing
    loop: CycleLoop
    period: float
    cycles: int
    commands_sent: dict[str, int]
    step_ns: NDArray[np.int64]
    hook_ns: NDArray[np.int64]
    phase_ns: NDArray[np.int64]
    sample_hook: SampleHook | None
    last: CycleResult | None
    last_cycle: int
    _t0_ns: int
    _limiter: RateLimiter
    _arm_busy: bool
    _arm_reconnect: threading.Lock
    _base_busy: bool
    _sensor_busy: bool
    _phase_sensor: Callable[[int, float], None] | None
    _base_enable: threading.Lock
    _commands: queue.SimpleQueue[tuple[Any, Future[Any]]]
    _stop_requested: threading.Event
    _param_lock: threading.Lock
    _healthy_cycle: threading.Event
    _handlers: dict[str, Callable[[Mapping[str, Any]], Any]]
    _sensor_request: Callable[[], None] | None
    _request_at_start: bool
    calibration: ToolCalibration | None

    @property
    def safety(self) -> Safety:
        raise NotImplementedError

    @property
    def speed_scaling(self) -> float:
        raise NotImplementedError

    def _on_loop(self, cmd: Any, timeout: float | None = None) -> Any: ...

    def step_once(self, overrun: bool = False) -> None: ...

    def apply_now(self, cmd: Any) -> Any: ...

    def _cmd_calibrate(self, req: Mapping[str, Any]) -> Any: ...

    def _calibration_cycle(self, c: ToolCalibration, result: CycleResult | None,
                           wrench: Wrench | None, repeats: int) -> CycleResult | None:
        raise NotImplementedError

    def status(self) -> dict[str, Any]:
        raise NotImplementedError

    def status_snapshot(self) -> dict[str, Any]:
        raise NotImplementedError

    def _update_status(self) -> None: ...

    def request_stop(self, reason: str = "requested") -> None: ...

    def _send_stop(self) -> None: ...
