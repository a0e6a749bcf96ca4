"""The base over CANopen: four CiA 402 drives, `canopen` as the master.

Wire set-up (written by SDO at :meth:`CanopenBase.connect`, per drive, node ids from
``base.canopen.node_ids`` in the order FL, FR, BL, BR):

* 0x1017 producer heartbeat = ``heartbeat_period``; we consume it (silent for more
  than ``heartbeat_timeout`` -> ``DRIVE_HEARTBEAT``) and produce our own heartbeat
  (node ``master_node_id``, same period);
* 0x6060 = 3 (profile velocity); 0x6083/0x6084 = the wheel acceleration
  ``limits.base_linear_acceleration / wheel_radius`` in [counts/s^2];
* RPDO1 (COB-ID 0x200+id, synchronous): target velocity 0x60FF [counts/s];
* TPDO1 (0x180+id, every SYNC): position actual 0x6064 [counts], velocity actual
  0x606C [counts/s];
* TPDO2 (0x280+id, event-driven, type 255): statusword 0x6041 (sent on change).

Per cycle :meth:`CanopenBase.send_twist` sends the four RPDOs, then one SYNC; the
drives apply the targets and answer with TPDO1 on that SYNC.
:meth:`CanopenBase.read_odometry` integrates the newest TPDO1 positions (non-blocking;
usually the answers to the previous SYNC).  Units: counts = ``counts_per_rev`` per
wheel revolution, so ``rad = counts * 2 pi / counts_per_rev``.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

import can
import canopen
import numpy as np
import structlog
from canopen.nmt import NMT_STATES
from canopen.pdo import PdoMap
from canopen.sdo import SdoAbortedError, SdoCommunicationError
from canopen.sdo.exceptions import SdoError

from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import FaultCause, MmctlError, SafetyFault, TransportError
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.kinematics import OdometryIntegrator, WheelCommand, wrap_delta
from mmctl.transports.base.protocol import WHEEL_NAMES, DriveStatus
from mmctl.types import Odometry, Twist

if TYPE_CHECKING:
    from typing_extensions import Self

log = structlog.get_logger(__name__)

T = TypeVar("T")

_OPERATIONAL = 5
#: How long connect() waits for every drive's first OPERATIONAL heartbeat [s].
_STARTUP_TIMEOUT = 2.0
#: Receive-thread poll period; bounds how long close() waits for the thread [s].
_NOTIFIER_CYCLE = 0.05
_ZERO = np.zeros(4)
_TARGET = struct.Struct("<i")  # RPDO1: target velocity 0x60FF, INTEGER32 [counts/s]


def _rpdo1_cob_id(pdo: PdoMap) -> int:
    """RPDO1's COB-ID, after checking it maps exactly the INTEGER32 target velocity
    (what :meth:`CanopenBase._send_wheels` packs)."""
    mapped = [(var.index, var.subindex, var.length) for var in pdo.map]
    if mapped != [(ds.TARGET_VELOCITY, 0, 32)] or pdo.cob_id is None:
        raise TransportError(f"RPDO1 must map only 0x{ds.TARGET_VELOCITY:04X} (32 bits), "
                             f"got {mapped}")
    return int(pdo.cob_id)


def _parallel(fn: Callable[[int], T], n: int) -> list[T | BaseException]:
    """``fn(i)`` for i in range(n) concurrently (one SDO conversation per drive);
    each result or the exception it raised, in order."""
    out: list[T | BaseException] = []
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="canopen-sdo") as pool:
        futures = [pool.submit(fn, i) for i in range(n)]
        for f in futures:
            exc = f.exception()
            out.append(exc if exc is not None else f.result())
    return out


class CanopenBase:
    """:class:`~mmctl.transports.base.protocol.Base` over CANopen (CiA 402 drives).

    cfg: the ``base:`` section; limits: the ``limits:`` section (wheel speed and base
    acceleration).  No I/O before :meth:`connect`.
    """

    def __init__(self, cfg: BaseConfig, limits: LimitsConfig) -> None:
        self._cfg = cfg
        self._co = cfg.canopen
        self._ids: tuple[int, ...] = tuple(self._co.node_ids)
        self._n = len(self._ids)
        self._counts_per_rad = self._co.counts_per_rev / (2.0 * math.pi)
        self._rad_per_count = 1.0 / self._counts_per_rad
        self._accel_counts = max(1, round(
            limits.base_linear_acceleration / cfg.mecanum.wheel_radius * self._counts_per_rad))
        self._command = WheelCommand(cfg.mecanum, limits.wheel_velocity)
        self._odo = OdometryIntegrator(cfg.mecanum)
        self._network: canopen.Network | None = None
        self._nodes: list[canopen.RemoteNode] = []
        self._rpdo: list[PdoMap] = []
        self._rpdo_cob: list[int] = []
        self._hb_task: Any = None
        self._cond = threading.Condition()
        self._hb_time = [-math.inf] * self._n
        self._hb_state: list[int | None] = [None] * self._n
        self._statusword = [0] * self._n
        self._pos = [0] * self._n
        self._vel = [0] * self._n
        self._sample_time = 0.0
        self._rx_pos = [0] * self._n  # partial set being received (receive thread only)
        self._rx_vel = [0] * self._n
        self._rx_mask = 0
        self._all_mask = (1 << self._n) - 1
        self._prev_pos = [0] * self._n
        self._prev_time = -1.0
        self._enabled = False
        self._fault: SafetyFault | None = None

    # -- lifecycle -------------------------------------------------------------------

    def connect(self) -> None:
        """Open the CAN channel, check every drive answers, configure heartbeat, mode
        and PDOs by SDO, start them (NMT OPERATIONAL) and our heartbeat producer.

        Raises TransportError ("no drive answers on channel X (node ids ...)") when
        SDO requests time out, or naming the drive and object when one misbehaves.
        """
        if self._network is not None:
            return
        co = self._co
        net = canopen.Network()
        net.NOTIFIER_CYCLE = _NOTIFIER_CYCLE
        try:
            net.connect(interface=co.interface, channel=co.channel, bitrate=co.bitrate)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise TransportError(
                f"cannot open CAN interface {co.interface!r} channel {co.channel!r}: {exc}"
            ) from exc
        self._network = net
        self._reset_state()
        try:
            self._nodes = []
            for i, nid in enumerate(self._ids):
                node = canopen.RemoteNode(nid, ds.build_object_dictionary(nid))
                node.sdo.RESPONSE_TIMEOUT = co.sdo_timeout
                net.add_node(node)
                net.subscribe(0x700 + nid, partial(self._on_heartbeat, i))
                self._nodes.append(node)
            self._raise_errors(_parallel(self._probe_one, self._n), "does not answer")
            self._raise_errors(_parallel(self._configure_one, self._n), "cannot be configured")
            self._rpdo = [node.rpdo[1] for node in self._nodes]
            self._rpdo_cob = [_rpdo1_cob_id(pdo) for pdo in self._rpdo]
            for node in self._nodes:
                node.nmt.state = "OPERATIONAL"
            self._wait_operational()
            self._hb_task = net.send_periodic(
                0x700 + co.master_node_id, bytes([_OPERATIONAL]), co.heartbeat_period)
        except BaseException:
            self._teardown()
            raise
        self._odo.reset(time.monotonic())
        log.info("base_connected", transport="canopen", channel=co.channel, node_ids=self._ids)

    def enable(self) -> None:
        """Fault reset (controlword bit 7 edge) where a drive shows FAULT, then
        shutdown -> switch on -> enable operation, each step checked on 0x6041.

        Raises SafetyFault(DRIVE_FAULT) when a drive stays in FAULT, TransportError when
        a drive does not reach OPERATION ENABLED."""
        self._require_connected()
        self._fault = None
        self._send_wheels(_ZERO)
        results = _parallel(self._enable_one, self._n)
        for r in results:
            if isinstance(r, SafetyFault):
                self._fault = r
                raise r
        self._raise_errors(results, "cannot be enabled")
        self._enabled = True
        self.check()
        log.info("base_enabled", transport="canopen")

    def stop(self) -> None:
        """Zero target velocity on every drive (RPDOs + SYNC)."""
        if self._network is not None:
            self._send_wheels(_ZERO)

    def disable(self) -> None:
        """Zero target, then controlword SHUTDOWN (-> READY TO SWITCH ON) on every
        drive whose heartbeat is alive; silent drives are skipped (logged)."""
        if self._network is None:
            return
        self._send_wheels(_ZERO)
        self._enabled = False
        now = time.monotonic()
        alive = [now - t <= self._co.heartbeat_timeout for t in self._hb_time]
        for i, ok in enumerate(alive):
            if not ok:
                log.warning("base_disable_skipped_silent_drive", node_id=self._ids[i])

        def shutdown(i: int) -> None:
            if alive[i]:
                self._nodes[i].sdo[ds.CONTROLWORD].raw = ds.Controlword.SHUTDOWN

        self._raise_errors(_parallel(shutdown, self._n), "did not accept SHUTDOWN")

    def close(self) -> None:
        """Stop and disable (best effort, failures logged), NMT PRE-OPERATIONAL, close
        the channel.  Safe to call more than once."""
        if self._network is None:
            return
        try:
            if self._enabled:
                self.stop()
                self.disable()
        except MmctlError as exc:
            log.warning("base_close_disable_failed", error=str(exc))
        finally:
            self._teardown()
        log.info("base_closed", transport="canopen")

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- per cycle ---------------------------------------------------------------------

    def send_twist(self, vx: float, vy: float, wz: float) -> Twist:
        """Wheel speeds for the twist (scaled to the wheel limit, direction kept) as
        four RPDOs, then SYNC.  Returns the twist commanded.  Raises SafetyFault (after
        commanding zero) when a drive is faulty or silent, see the protocol doc."""
        if not self._enabled:
            raise TransportError("send_twist() before enable()")
        try:
            wheels, twist = self._command(vx, vy, wz)
        except ValueError:
            self._send_wheels(_ZERO)
            raise SafetyFault(FaultCause.NON_FINITE, twist=(vx, vy, wz)) from None
        fault = self._health()
        if fault is not None:
            self._send_wheels(_ZERO)
            raise fault
        self._send_wheels(wheels)
        return twist

    def read_odometry(self) -> Odometry:
        """Odometry from the newest TPDO1 samples (non-blocking).  Raises SafetyFault
        when unhealthy."""
        self._require_connected()
        fault = self._health()
        if fault is not None:
            raise fault
        with self._cond:
            t = self._sample_time
            if t != self._prev_time:
                pos = list(self._pos)
                vel = list(self._vel)
        if t != self._prev_time:
            k = self._rad_per_count
            d = np.array([wrap_delta(p, q) for p, q in zip(pos, self._prev_pos)]) * k
            self._odo.update(d, np.array(vel, dtype=float) * k, t)
            self._prev_pos = pos
            self._prev_time = t
        return self._odo.odometry()

    def check(self) -> None:
        """Raise SafetyFault when a drive is silent, not OPERATIONAL, or (once enabled)
        not in OPERATION ENABLED."""
        self._require_connected()
        fault = self._health()
        if fault is not None:
            raise fault

    def drive_status(self) -> list[DriveStatus]:
        """NMT state (from heartbeats; 'SILENT' when none within the timeout), CiA 402
        state and statusword (from TPDO2/SDO) and the last EMCY code per drive."""
        now = time.monotonic()
        out = []
        for i, nid in enumerate(self._ids):
            st = self._hb_state[i]
            if now - self._hb_time[i] > self._co.heartbeat_timeout or st is None:
                link = "SILENT"
            else:
                link = NMT_STATES.get(st, f"UNKNOWN {st}")
            code = 0
            if self._nodes and self._nodes[i].emcy.active:
                code = self._nodes[i].emcy.active[-1].code
            sw = self._statusword[i]
            out.append(DriveStatus(WHEEL_NAMES[i], nid, link, ds.decode_statusword(sw).value,
                                   sw, code))
        return out

    @property
    def network(self) -> canopen.Network | None:
        """The canopen network while connected (for diagnostics)."""
        return self._network

    # -- internals ---------------------------------------------------------------------

    def _reset_state(self) -> None:
        with self._cond:
            self._hb_time = [-math.inf] * self._n
            self._hb_state = [None] * self._n
            self._statusword = [0] * self._n
            self._rx_mask = 0
            self._sample_time = 0.0
            self._prev_time = -1.0
            self._fault = None
            self._enabled = False

    def _require_connected(self) -> None:
        if self._network is None:
            raise TransportError("base is not connected (call connect() first)")

    def _send_wheels(self, wheels: Sequence[float] | np.ndarray) -> None:
        net = self._network
        if net is None:
            raise TransportError("base is not connected (call connect() first)")
        k = self._counts_per_rad
        send = net.send_message
        try:
            # RPDO1's bytes packed here: the mapping is ours (one INTEGER32, checked at
            # connect), and canopen's per-variable encode costs ~4x the pack
            for cob, w in zip(self._rpdo_cob, wheels):
                send(cob, _TARGET.pack(round(w * k)))
            net.sync.transmit()
        except (can.CanError, RuntimeError) as exc:
            raise TransportError(f"CAN send failed on {self._co.channel!r}: {exc}") from exc
        except struct.error:
            raise SafetyFault(FaultCause.NON_FINITE, wheels=[float(w) for w in wheels],
                              why="wheel speed beyond INTEGER32 counts/s") from None

    def _health(self) -> SafetyFault | None:
        if self._fault is not None:
            return self._fault
        net = self._network
        if net is not None and net.notifier is not None and net.notifier.exception is not None:
            raise TransportError(f"CAN receive thread died: {net.notifier.exception!r}")
        now = time.monotonic()
        timeout = self._co.heartbeat_timeout
        fault = None
        for i, nid in enumerate(self._ids):
            age = now - self._hb_time[i]
            if age > timeout:
                fault = SafetyFault(FaultCause.DRIVE_HEARTBEAT, node_id=nid,
                                    wheel=WHEEL_NAMES[i], silent_for=round(age, 4))
            elif self._hb_state[i] != _OPERATIONAL:
                fault = SafetyFault(FaultCause.DRIVE_FAULT, node_id=nid, wheel=WHEEL_NAMES[i],
                                    nmt=NMT_STATES.get(self._hb_state[i] or 0, "?"))
            elif self._enabled and self._statusword[i] & 0x6F != 0x27:
                sw = self._statusword[i]
                code = self._nodes[i].emcy.active[-1].code if self._nodes[i].emcy.active else 0
                fault = SafetyFault(FaultCause.DRIVE_FAULT, node_id=nid, wheel=WHEEL_NAMES[i],
                                    state=ds.decode_statusword(sw).value,
                                    statusword=f"0x{sw:04X}", error_code=f"0x{code:04X}")
            if fault is not None:
                self._fault = fault
                log.error("base_fault", transport="canopen", cause=fault.cause.value,
                          **fault.details)
                return fault
        return None

    def _on_heartbeat(self, i: int, can_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        with self._cond:
            self._hb_time[i] = time.monotonic()
            self._hb_state[i] = data[0] & 0x7F
            self._cond.notify_all()

    def _on_tpdo1(self, i: int, pdo: PdoMap) -> None:
        """Collect one SYNC's four samples; publish them together once all arrived (so
        odometry never integrates a half-updated set)."""
        self._rx_pos[i] = int(pdo.map[0].raw)
        self._rx_vel[i] = int(pdo.map[1].raw)
        self._rx_mask |= 1 << i
        if self._rx_mask == self._all_mask:
            self._rx_mask = 0
            with self._cond:
                self._pos = list(self._rx_pos)
                self._vel = list(self._rx_vel)
                self._sample_time = time.monotonic()

    def _on_tpdo2(self, i: int, pdo: PdoMap) -> None:
        self._statusword[i] = int(pdo.map[0].raw)

    def _probe_one(self, i: int) -> None:
        dtype = self._nodes[i].sdo[ds.DEVICE_TYPE].raw
        if dtype & 0xFFFF != 402:
            raise TransportError(
                f"node {self._ids[i]} is not a CiA 402 drive (device type 0x{dtype:08X})")

    def _configure_one(self, i: int) -> None:
        node, nid, co = self._nodes[i], self._ids[i], self._co
        node.nmt.state = "PRE-OPERATIONAL"
        sdo = node.sdo
        sdo[ds.PRODUCER_HEARTBEAT_TIME].raw = max(1, round(co.heartbeat_period * 1000))
        sdo[ds.MODES_OF_OPERATION].raw = ds.MODE_PROFILE_VELOCITY
        sdo[ds.PROFILE_ACCELERATION].raw = self._accel_counts
        sdo[ds.PROFILE_DECELERATION].raw = self._accel_counts
        sdo[ds.TARGET_VELOCITY].raw = 0
        layout: tuple[tuple[PdoMap, int, int, tuple[int, ...]], ...] = (
            (node.rpdo[1], 0x200, 1, (ds.TARGET_VELOCITY,)),
            (node.rpdo[2], 0x300, 0, ()),
            (node.tpdo[1], 0x180, 1, (ds.POSITION_ACTUAL, ds.VELOCITY_ACTUAL)),
            (node.tpdo[2], 0x280, 255, (ds.STATUSWORD,)),
        )
        for pdo, cob, trans, objects in layout:
            pdo.clear()
            for index in objects:
                pdo.add_variable(index)
            pdo.cob_id = cob + nid
            pdo.trans_type = trans if objects else 255
            pdo.enabled = bool(objects)
            pdo.save()
        node.tpdo[1].add_callback(partial(self._on_tpdo1, i))
        node.tpdo[2].add_callback(partial(self._on_tpdo2, i))
        pos = sdo[ds.POSITION_ACTUAL].raw
        self._statusword[i] = sdo[ds.STATUSWORD].raw
        with self._cond:
            self._pos[i] = self._prev_pos[i] = self._rx_pos[i] = pos

    def _wait_operational(self) -> None:
        wait = max(_STARTUP_TIMEOUT, 5 * self._co.heartbeat_timeout)
        deadline = time.monotonic() + wait
        with self._cond:
            while any(s != _OPERATIONAL for s in self._hb_state):
                left = deadline - time.monotonic()
                if left <= 0:
                    bad = [nid for nid, s in zip(self._ids, self._hb_state) if s != _OPERATIONAL]
                    raise TransportError(
                        f"drive(s) {bad} sent no OPERATIONAL heartbeat within {wait:.1f} s "
                        f"on channel {self._co.channel!r}")
                self._cond.wait(left)

    def _enable_one(self, i: int) -> None:
        node, nid = self._nodes[i], self._ids[i]
        sdo = node.sdo
        sw = sdo[ds.STATUSWORD].raw
        state = ds.decode_statusword(sw)
        if state in (ds.Cia402State.FAULT, ds.Cia402State.FAULT_REACTION_ACTIVE):
            sdo[ds.CONTROLWORD].raw = ds.Controlword.DISABLE_VOLTAGE
            sdo[ds.CONTROLWORD].raw = ds.Controlword.FAULT_RESET
            sw, state = self._wait_state(i, ds.Cia402State.SWITCH_ON_DISABLED)
            if state is ds.Cia402State.FAULT:
                raise SafetyFault(FaultCause.DRIVE_FAULT, node_id=nid, wheel=WHEEL_NAMES[i],
                                  state=state.value, statusword=f"0x{sw:04X}",
                                  error_code=f"0x{sdo[ds.ERROR_CODE].raw:04X}")
        if state is ds.Cia402State.QUICK_STOP_ACTIVE:
            sdo[ds.CONTROLWORD].raw = ds.Controlword.DISABLE_VOLTAGE
            sw, state = self._wait_state(i, ds.Cia402State.SWITCH_ON_DISABLED)
        if state is not ds.Cia402State.OPERATION_ENABLED:
            sdo[ds.MODES_OF_OPERATION].raw = ds.MODE_PROFILE_VELOCITY
            for cw, want in (
                (ds.Controlword.SHUTDOWN, ds.Cia402State.READY_TO_SWITCH_ON),
                (ds.Controlword.SWITCH_ON, ds.Cia402State.SWITCHED_ON),
                (ds.Controlword.ENABLE_OPERATION, ds.Cia402State.OPERATION_ENABLED),
            ):
                sdo[ds.CONTROLWORD].raw = cw
                sw, state = self._wait_state(i, want)
                if state is not want:
                    raise TransportError(
                        f"drive {nid} stays in {state.value} (statusword 0x{sw:04X}) after "
                        f"controlword 0x{int(cw):04X}, expected {want.value}")
        self._statusword[i] = sw

    def _wait_state(self, i: int, want: ds.Cia402State) -> tuple[int, ds.Cia402State]:
        """Poll 0x6041 until it shows ``want`` or sdo_timeout passes."""
        deadline = time.monotonic() + self._co.sdo_timeout
        while True:
            sw = self._nodes[i].sdo[ds.STATUSWORD].raw
            state = ds.decode_statusword(sw)
            if state is want or time.monotonic() > deadline:
                return sw, state
            time.sleep(0.001)

    def _raise_errors(self, results: Sequence[object], what: str) -> None:
        timeouts = [nid for nid, r in zip(self._ids, results)
                    if isinstance(r, SdoCommunicationError)]
        ids = ", ".join(str(n) for n in self._ids)
        if timeouts and len(timeouts) == self._n:
            raise TransportError(
                f"no drive answers on channel {self._co.channel!r} (node ids {ids})")
        if timeouts:
            raise TransportError(
                f"drive(s) {', '.join(map(str, timeouts))} {what} on channel "
                f"{self._co.channel!r} (SDO timeout {self._co.sdo_timeout} s)")
        for nid, r in zip(self._ids, results):
            if isinstance(r, MmctlError):
                raise r
            if isinstance(r, SdoAbortedError | SdoError):
                raise TransportError(f"drive {nid} {what}: {r}") from r
            if isinstance(r, (can.CanError, RuntimeError)):
                raise TransportError(f"drive {nid} {what}: CAN error {r}") from r
            if isinstance(r, BaseException):
                raise r

    def _teardown(self) -> None:
        net, self._network = self._network, None
        self._enabled = False
        if net is None:
            return
        if self._hb_task is not None:
            self._hb_task.stop()
            self._hb_task = None
        try:
            for node in self._nodes:
                node.nmt.state = "PRE-OPERATIONAL"
        except (can.CanError, RuntimeError) as exc:
            log.warning("base_nmt_preop_failed", error=str(exc))
        net.disconnect()
        self._nodes = []
        self._rpdo = []
        self._rpdo_cob = []
