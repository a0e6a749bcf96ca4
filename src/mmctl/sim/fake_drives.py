"""Four simulated CiA 402 drives on a python-can ``virtual`` channel, and the wheel plant.

:class:`FakeDrives` is the parent-side handle: ``FakeDrives(cfg).start()`` puts four
``canopen.LocalNode`` drives (node ids ``base.canopen.node_ids``) on the configured
virtual channel; the real :class:`~mmctl.transports.base.canopen_base.CanopenBase`
master then talks to them over CANopen.  The four nodes share one ``canopen.Network``
(one bus object and one receive thread: a quarter of the message copies four separate
buses would cost on a 2-core machine); the master has its own.  A python-can virtual
bus exists only inside one process, so master and fakes must share the process.

Each drive: NMT slave with heartbeat producer (0x1017), boot-up message, SDO server;
the CiA 402 state machine on controlword writes (:func:`cia402.next_state`), modes of
operation (only 3 = profile velocity is accepted), RPDOs applied on the next SYNC,
TPDOs sent on SYNC (types 1-240) or on change (254/255), using whatever PDO mapping the
master wrote (reloaded on NMT start); EMCY on faults.  The wheels are simulated by
:class:`WheelPlant`: velocity ramps toward the target at the profile acceleration
0x6083/0x6084, positions integrate the velocity, and a drive that received no command
for ``base.command_watchdog`` ramps to zero.  Fault injection: :meth:`FakeDrives.
inject_fault` (FAULT state + EMCY), :meth:`FakeDrives.inject_silence` (heartbeat stops,
nothing answered), :meth:`FakeDrives.resume`.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from types import TracebackType
from typing import TYPE_CHECKING, Any

import canopen
import numpy as np
import structlog
from canopen.pdo import PdoMap
from canopen.sdo import SdoAbortedError
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.config.base import BaseConfig, MecanumConfig
from mmctl.config.control import LimitsConfig
from mmctl.control.mecanum import odometry_matrix
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.protocol import WHEEL_NAMES, DriveStatus

if TYPE_CHECKING:
    from typing_extensions import Self

log = structlog.get_logger(__name__)

Vec = NDArray[np.float64]
_SUBSTEP = 0.001  # plant integration step [s]
_ABORT_VALUE_RANGE = 0x0609_0030


class WheelPlant:
    """Four wheels (FL, FR, BL, BR) and the base pose they drive. Thread-safe.

    Each wheel's speed [rad/s] moves toward its effective target at ``accel`` (speeding
    up) or ``decel`` (slowing down) [rad/s^2]; the effective target is 0 while the
    wheel is disabled or ``watchdog`` [s] after its last command.  The pose (x, y [m],
    yaw [rad], world frame) integrates the least-squares base twist of the wheel
    increments.  Time is ``time.monotonic()``; the state advances lazily to the time
    of each call.
    """

    def __init__(self, geom: MecanumConfig, accel: float, watchdog: float) -> None:
        self._p = odometry_matrix(geom)
        self.lock = threading.RLock()
        self.theta = np.zeros(4)
        self.omega = np.zeros(4)
        self.target = np.zeros(4)
        self.enabled = np.zeros(4, dtype=bool)
        self.accel = np.full(4, float(accel))
        self.decel = np.full(4, float(accel))
        self.last_command = np.full(4, -math.inf)
        self.watchdog = float(watchdog)
        self.pose = np.zeros(3)
        self.t = time.monotonic()

    def advance(self, now: float) -> None:
        """Integrate up to monotonic time ``now`` [s] in steps of at most 1 ms."""
        with self.lock:
            while self.t < now:
                h = min(_SUBSTEP, now - self.t)
                expiry = self.last_command + self.watchdog
                pending = expiry[(expiry > self.t) & (expiry < self.t + h)]
                if pending.size:
                    h = max(float(pending.min()) - self.t, 1e-9)
                live = self.enabled & (self.t < expiry)
                tgt = np.where(live, self.target, 0.0)
                dv = tgt - self.omega
                slowing = dv * self.omega < 0.0
                rate = np.where(slowing, self.decel, self.accel) * h
                new = self.omega + np.clip(dv, -rate, rate)
                dtheta = 0.5 * (self.omega + new) * h
                self.omega = new
                self.theta += dtheta
                dx, dy, dyaw = self._p @ dtheta
                mid = self.pose[2] + 0.5 * dyaw
                c, s = math.cos(mid), math.sin(mid)
                self.pose += (c * dx - s * dy, s * dx + c * dy, dyaw)
                self.t += h

    def command(self, wheel: int, omega: float, now: float) -> None:
        """New target [rad/s] for ``wheel`` at ``now`` (also feeds its watchdog)."""
        with self.lock:
            self.advance(now)
            self.target[wheel] = omega
            self.last_command[wheel] = now

    def set_enabled(self, wheel: int, on: bool, now: float) -> None:
        """Power stage on/off (off ramps to zero at the deceleration)."""
        with self.lock:
            self.advance(now)
            self.enabled[wheel] = on

    def get_pose(self, now: float) -> tuple[float, float, float]:
        """(x, y [m], yaw [rad]) at ``now``."""
        with self.lock:
            self.advance(now)
            return float(self.pose[0]), float(self.pose[1]), float(self.pose[2])


def _maps(pdos: Any) -> list[PdoMap]:
    """The PDO maps of a node's RPDO or TPDO object."""
    return list(pdos.map.values())


def _read(node: canopen.LocalNode, index: int) -> int:
    """An integer object of ``node``'s dictionary (through its read callbacks)."""
    var = node.object_dictionary.get_variable(index)
    assert var is not None, f"0x{index:04X} is not a variable"
    return int(var.decode_raw(node.get_data(index, 0)))


@dataclass
class _Drive:
    """One simulated drive's CiA 402 side."""

    wheel: int
    node: canopen.LocalNode
    state: ds.Cia402State = ds.Cia402State.SWITCH_ON_DISABLED
    controlword: int = 0
    mode: int = 0
    error_code: int = 0
    silent: bool = False
    pdo_dirty: bool = True
    rpdo_pending: list[PdoMap] = field(default_factory=list)
    last_event: dict[int, bytes] = field(default_factory=dict)
    log: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=20_000))


class FakeDrives:
    """The four simulated drives (parent-side handle; see the module doc).

    cfg: a :class:`~mmctl.config.Config` (or its ``base:`` section, then ``limits``
    gives the acceleration; defaults otherwise).  Only the ``virtual`` interface is
    allowed.  No I/O before :meth:`start`.
    """

    def __init__(self, cfg: Config | BaseConfig, limits: LimitsConfig | None = None) -> None:
        if isinstance(cfg, Config):
            base, limits = cfg.base, cfg.limits
        else:
            base, limits = cfg, limits or LimitsConfig()
        if base.canopen.interface != "virtual":
            raise ValueError(f"FakeDrives runs on the 'virtual' interface only, "
                             f"not {base.canopen.interface!r}")
        self.cfg = base
        self.node_ids: tuple[int, ...] = tuple(base.canopen.node_ids)
        self._counts_per_rad = base.canopen.counts_per_rev / (2.0 * math.pi)
        self.plant = WheelPlant(base.mecanum, limits.base_linear_acceleration
                                / base.mecanum.wheel_radius, base.command_watchdog)
        self._lock = self.plant.lock
        self._network: canopen.Network | None = None
        self._drives: dict[int, _Drive] = {}
        self._sync_count = 0
        self._sync_time: float | None = None  # while handling a SYNC: its time
        self._error: BaseException | None = None

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> FakeDrives:
        """Connect to the virtual channel and boot the drives (boot-up message, then
        PRE-OPERATIONAL; heartbeat off until the master writes 0x1017)."""
        if self._network is not None:
            return self
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05
        net.connect(interface="virtual", channel=self.cfg.canopen.channel)
        self._network = net
        for wheel, nid in enumerate(self.node_ids):
            node = canopen.LocalNode(nid, ds.build_object_dictionary(nid))
            net.add_node(node)
            drive = _Drive(wheel, node)
            node.add_read_callback(self._guard(partial(self._on_read, drive)))
            node.add_write_callback(self._guard(partial(self._on_write, drive)))
            for pdo in _maps(node.rpdo):
                pdo.add_callback(self._guard(partial(self._on_rpdo, drive)))
            net.subscribe(0, self._guard(partial(self._on_nmt, drive)))
            self._drives[nid] = drive
        net.subscribe(0x80, self._guard(self._on_sync))
        for drive in self._drives.values():
            drive.node.nmt.send_command(0x81)  # reset: boot-up message
            drive.node.nmt.send_command(0x80)  # -> PRE-OPERATIONAL
        log.info("fake_drives_started", channel=self.cfg.canopen.channel, node_ids=self.node_ids)
        return self

    def stop(self) -> None:
        """Stop heartbeats and leave the channel; re-raise an error a handler stored."""
        net, self._network = self._network, None
        if net is not None:
            for drive in self._drives.values():
                drive.node.nmt.stop_heartbeat()
            net.disconnect()
            log.info("fake_drives_stopped", channel=self.cfg.canopen.channel)
        self.check()

    def check(self) -> None:
        """Re-raise the first exception a CAN handler of the fakes raised, if any."""
        if self._error is not None:
            raise self._error

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    # -- what tests and the simulator read ---------------------------------------------

    def node(self, node_id: int) -> canopen.LocalNode:
        """The LocalNode of drive ``node_id`` (its object dictionary is the truth)."""
        return self._drives[node_id].node

    def target_counts(self) -> list[int]:
        """0x60FF of each drive (FL, FR, BL, BR) from its object dictionary [counts/s]."""
        return [_read(d.node, ds.TARGET_VELOCITY) for d in self._drives.values()]

    def target_velocities(self) -> Vec:
        """0x60FF of each drive converted to wheel speed (4,) [rad/s]."""
        return np.array(self.target_counts(), dtype=float) / self._counts_per_rad

    def command_log(self, node_id: int) -> list[tuple[float, int]]:
        """Every RPDO target the drive received: (monotonic time [s], counts/s)."""
        with self._lock:
            return list(self._drives[node_id].log)

    def wheel_velocities(self) -> Vec:
        """Actual simulated wheel speeds (4,) [rad/s] now."""
        with self._lock:
            self.plant.advance(time.monotonic())
            return self.plant.omega.copy()

    def pose(self) -> tuple[float, float, float]:
        """The simulated base pose (x, y [m], yaw [rad]) in the world frame, now."""
        return self.plant.get_pose(time.monotonic())

    @property
    def sync_count(self) -> int:
        """SYNC messages the drives have received."""
        return self._sync_count

    def states(self) -> list[DriveStatus]:
        """Drive-side view: NMT state ('SILENT' when injected), CiA 402 state, statusword."""
        with self._lock:
            out = []
            for d in self._drives.values():
                sw = self._statusword(d)
                link = "SILENT" if d.silent else d.node.nmt.state
                out.append(DriveStatus(WHEEL_NAMES[d.wheel], int(d.node.id or 0), link,
                                       d.state.value, sw, d.error_code))
            return out

    # -- fault injection ----------------------------------------------------------------

    def inject_fault(self, node_id: int, code: int = 0x2310) -> None:
        """Drive ``node_id`` enters FAULT (EMCY ``code``, default 0x2310 over-current;
        statusword TPDO sent at once); it ramps to zero."""
        with self._lock:
            d = self._drives[node_id]
            self._set_state(d, ds.Cia402State.FAULT)
            d.error_code = code
            if not d.silent and self._network is not None:
                d.node.emcy.send(code, register=0x01)
                self._emit_events(d)
        log.info("fake_drive_fault_injected", node_id=node_id, code=f"0x{code:04X}",
                 sync_count=self._sync_count)

    def inject_silence(self, node_id: int) -> None:
        """Drive ``node_id`` goes silent: no heartbeat, no TPDO, no SDO answer, and it
        ignores everything it receives (its watchdog then ramps it to zero)."""
        with self._lock:
            d = self._drives[node_id]
            d.silent = True
            d.node.nmt.stop_heartbeat()
            if self._network is not None:
                self._network.unsubscribe(0x600 + node_id, d.node.sdo.on_request)
        log.info("fake_drive_silenced", node_id=node_id, sync_count=self._sync_count)

    def resume(self, node_id: int) -> None:
        """Undo :meth:`inject_silence`: heartbeat and answers come back."""
        with self._lock:
            d = self._drives[node_id]
            if not d.silent or self._network is None:
                return
            d.silent = False
            self._network.subscribe(0x600 + node_id, d.node.sdo.on_request)
            d.node.nmt.start_heartbeat(_read(d.node, ds.PRODUCER_HEARTBEAT_TIME))

    # -- CAN handlers (run in the network's receive thread) -----------------------------

    def _guard(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """Store (and log) the first exception of a handler; SDO aborts pass through."""

        def wrapped(*args: Any, **kwargs: Any) -> Any:
            try:
                return fn(*args, **kwargs)
            except SdoAbortedError:
                raise
            except Exception as exc:
                if self._error is None:
                    self._error = exc
                log.exception("fake_drives_handler_failed", handler=getattr(fn, "func", fn))
                raise

        return wrapped

    def _statusword(self, d: _Drive) -> int:
        reached = bool(abs(self.plant.omega[d.wheel] - self.plant.target[d.wheel]) < 1e-3)
        return ds.encode_statusword(d.state, target_reached=reached)

    def _set_state(self, d: _Drive, state: ds.Cia402State) -> None:
        if state is not d.state:
            d.state = state
            self.plant.set_enabled(d.wheel, state is ds.Cia402State.OPERATION_ENABLED,
                                   time.monotonic())

    def _on_read(self, d: _Drive, index: int, subindex: int, od: Any) -> int | None:
        if index == ds.STATUSWORD:
            return self._statusword(d)
        if index in (ds.POSITION_ACTUAL, ds.VELOCITY_ACTUAL):
            if self._sync_time is None:  # an SDO read: now (on SYNC: already advanced)
                self.plant.advance(time.monotonic())
            if index == ds.POSITION_ACTUAL:
                counts = round(float(self.plant.theta[d.wheel]) * self._counts_per_rad)
                return (counts + 2**31) % 2**32 - 2**31
            return round(float(self.plant.omega[d.wheel]) * self._counts_per_rad)
        if index == ds.ERROR_CODE:
            return d.error_code
        if index == ds.ERROR_REGISTER:
            return 0x01 if d.error_code else 0
        if index == ds.MODES_OF_OPERATION_DISPLAY:
            return d.mode
        return None

    def _on_write(self, d: _Drive, index: int, subindex: int, od: Any, data: bytes) -> None:
        if not od.fixed_size:
            return
        value = int(od.decode_raw(bytes(data)))
        now = time.monotonic() if self._sync_time is None else self._sync_time
        with self._lock:
            if index == ds.CONTROLWORD:
                new = ds.next_state(d.state, value, d.controlword)
                d.controlword = value
                if new is not d.state:
                    was_fault = d.state is ds.Cia402State.FAULT
                    self._set_state(d, new)
                    if was_fault:
                        d.error_code = 0
                        d.node.emcy.reset()
                    self._emit_events(d)
            elif index == ds.MODES_OF_OPERATION:
                if value != ds.MODE_PROFILE_VELOCITY:
                    raise SdoAbortedError(_ABORT_VALUE_RANGE)
                d.mode = value
            elif index == ds.TARGET_VELOCITY:
                self.plant.command(d.wheel, value / self._counts_per_rad, now)
            elif index == ds.PROFILE_ACCELERATION:
                self.plant.advance(now)
                self.plant.accel[d.wheel] = max(value, 1) / self._counts_per_rad
            elif index == ds.PROFILE_DECELERATION:
                self.plant.advance(now)
                self.plant.decel[d.wheel] = max(value, 1) / self._counts_per_rad
            elif 0x1400 <= index <= 0x1BFF:
                d.pdo_dirty = True

    def _on_nmt(self, d: _Drive, can_id: int, data: bytearray, timestamp: float) -> None:
        if d.silent or d.node.nmt.state != "OPERATIONAL":
            return
        with self._lock:
            if d.pdo_dirty:
                d.node.rpdo.read()
                d.node.tpdo.read()
                d.pdo_dirty = False
                d.last_event.clear()
            self._emit_events(d)

    def _on_rpdo(self, d: _Drive, pdo: PdoMap) -> None:
        if d.silent or d.node.nmt.state != "OPERATIONAL":
            return
        with self._lock:
            if pdo not in d.rpdo_pending:
                d.rpdo_pending.append(pdo)
            for var in pdo.map:
                if var.index == ds.TARGET_VELOCITY:
                    d.log.append((time.monotonic(), int(var.raw)))
            if pdo.trans_type is not None and pdo.trans_type >= 254:
                self._apply_rpdos(d)

    def _apply_rpdos(self, d: _Drive) -> None:
        for pdo in d.rpdo_pending:
            for var in pdo.map:
                d.node.set_data(var.index, var.subindex, var.get_data())
        d.rpdo_pending.clear()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self._sync_count += 1
            now = time.monotonic()
            self.plant.advance(now)
            # every drive applies its target and samples its encoder at the SYNC instant
            self._sync_time = now
            try:
                for d in self._drives.values():
                    if not d.silent and d.node.nmt.state == "OPERATIONAL":
                        self._apply_rpdos(d)
                for d in self._drives.values():
                    if d.silent or d.node.nmt.state != "OPERATIONAL":
                        continue
                    for pdo in _maps(d.node.tpdo):
                        tt = pdo.trans_type
                        if pdo.enabled and tt is not None and 1 <= tt <= 240 \
                                and self._sync_count % tt == 0:
                            self._fill(d, pdo)
                            pdo.transmit()
                    self._emit_events(d)
            finally:
                self._sync_time = None

    def _fill(self, d: _Drive, pdo: PdoMap) -> None:
        for var in pdo.map:
            var.set_data(d.node.get_data(var.index, var.subindex))

    def _emit_events(self, d: _Drive) -> None:
        """Send event-driven TPDOs (type 254/255) whose content changed."""
        if d.silent or self._network is None or d.node.nmt.state != "OPERATIONAL":
            return
        for no, pdo in enumerate(_maps(d.node.tpdo)):
            if pdo.enabled and pdo.trans_type is not None and pdo.trans_type >= 254:
                self._fill(d, pdo)
                data = bytes(pdo.data)
                if d.last_event.get(no) != data:
                    d.last_event[no] = data
                    pdo.transmit()
