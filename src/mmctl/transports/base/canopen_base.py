"""The base over CANopen: four CiA 402 drives, `canopen` as the master.

Wire set-up (written by SDO at :meth:`CanopenBase.connect`, per drive, node ids from
``base.canopen.node_ids`` in the order FL, FR, BL, BR; the objects that make a drive
stop read back and checked):

* 0x1017 producer heartbeat = ``heartbeat_period``; we consume it (silent for more
  than ``heartbeat_timeout`` -> ``DRIVE_HEARTBEAT``; a boot-up message -> the drive
  rebooted, ``DRIVE_FAULT``) and produce our own heartbeat (node ``master_node_id``,
  same period);
* the drive's own command watchdog, ``base.command_watchdog`` [ms]: consumer heartbeat
  0x1016:01 = ``master_node_id << 16 | ms`` (our heartbeat), RPDO1 deadline (event
  timer 0x1400:05) = ms, abort connection option 0x6007 = 3 (quick stop).  A drive that
  misses either in OPERATION ENABLED quick-stops by itself (0x605A = 2: to rest on the
  quick-stop deceleration 0x6085, then SWITCH ON DISABLED);
* how a drive stops: shutdown option 0x605B = 1 and disable operation option 0x605C = 1
  (slow down on 0x6084, then open the power stage: never while the wheel turns),
  fault reaction 0x605E = 2 (quick-stop ramp, then FAULT);
* 0x6060 = 3 (profile velocity); 0x6083/0x6084/0x6085 = the wheel acceleration
  ``limits.base_linear_acceleration / wheel_radius`` in [counts/s^2];
* RPDO1 (COB-ID 0x200+id, synchronous): target velocity 0x60FF [counts/s];
* RPDO2 (COB-ID 0x300+id, event-driven, type 255, no deadline): controlword 0x6040,
  sent only by ``disable(wait=False)`` (below); every other controlword goes by SDO;
* TPDO1 (0x180+id, every SYNC): position actual 0x6064 [counts], velocity actual
  0x606C [counts/s];
* TPDO2 (0x280+id, event-driven, type 255): statusword 0x6041 (sent on change).

Per cycle :meth:`CanopenBase.send_twist` sends the four RPDOs, then one SYNC; the
drives apply the targets and answer with TPDO1 on that SYNC.
:meth:`CanopenBase.read_odometry` integrates the newest TPDO1 positions (non-blocking;
usually the answers to the previous SYNC).  Units: counts = ``counts_per_rev`` per
wheel revolution, so ``rad = counts * 2 pi / counts_per_rev``.

A drive that rebooted (boot-up message) comes back with its default objects (no PDOs,
no heartbeat, no watchdog, shutdown option 0 = coast): :meth:`CanopenBase.enable`
configures it again, fully, before enabling it.  See docs/base-drives.md.

**The loop thread's calls never wait for a drive.**  :meth:`CanopenBase.stop` sends
the zero targets (four RPDO1s + SYNC); :meth:`CanopenBase.disable` with ``wait=False``
sends the zero targets, then SHUTDOWN as the controlword in RPDO2, to every drive whose
last statusword (TPDO2, sent on change) does not show it stopping by itself already
(QUICK STOP ACTIVE, FAULT REACTION ACTIVE, FAULT): frames only, no SDO, so a silent bus
costs nothing (it used to cost an SDO timeout per silent drive, 0.5 s on the loop).
Chosen over a fire-and-forget SDO (its unsolicited answer would land in the queue of
the next SDO transfer, possibly another thread's) and over deferring the SDOs to a
thread (the drive would learn of the stop later).  A drive that misses the frame is
caught by its own watchdog: it stops hearing our heartbeat or its RPDO1 deadline expires
(``base.command_watchdog``) and quick-stops (0x6007 = 3).  ``disable()`` (waiting, off
the loop) still goes by SDO and checks every drive's state.

**A lost link** (the CAN channel fails under the master: socketcand connection closed,
adapter gone; see :mod:`mmctl.transports.canbus`): every call raises
:class:`~mmctl.errors.LinkLost` (cause ``base_link_lost``) at once, without waiting,
until :meth:`CanopenBase.reconnect` opens a new network and configures the drives
again (left disabled).  Neither the receive thread nor the heartbeat producer dies.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor, wait
from functools import partial
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

import can
import canopen
import numpy as np
import structlog
from canopen.nmt import NMT_STATES
from canopen.objectdictionary import ODVariable
from canopen.pdo import PdoMap
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError, SdoError

from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.errors import (
    ConfigError,
    FaultCause,
    LinkLost,
    MmctlError,
    SafetyFault,
    TransportError,
)
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.kinematics import OdometryIntegrator, WheelCommand, wrap_delta
from mmctl.transports.base.protocol import WHEEL_NAMES, DriveStatus
from mmctl.transports.canbus import GuardedBus, describe, open_bus
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
#: Poll period of 0x6041 while a drive ramps to rest (disable, fault reaction) [s].
_REST_POLL = 0.005
#: Fault-reset edges enable() sends before it gives up on a drive in FAULT.
_RESET_ATTEMPTS = 3
_ZERO = np.zeros(4)
#: CiA 402 states in which the power stage is on (or a stopping ramp still runs).
_MOVING = frozenset({ds.Cia402State.OPERATION_ENABLED, ds.Cia402State.QUICK_STOP_ACTIVE,
                     ds.Cia402State.FAULT_REACTION_ACTIVE})
#: States in which the power stage is off or the drive holds at rest by itself.
_SETTLED = frozenset(set(ds.Cia402State) - _MOVING - {ds.Cia402State.UNKNOWN})
_TARGET = struct.Struct("<i")  # RPDO1: target velocity 0x60FF, INTEGER32 [counts/s]
_CONTROL = struct.Struct("<H")  # RPDO2: controlword 0x6040, UNSIGNED16
#: CiA 402 states in which a drive already stops by itself (no SHUTDOWN sent to it).
_STOPPING = frozenset({ds.Cia402State.QUICK_STOP_ACTIVE, ds.Cia402State.FAULT_REACTION_ACTIVE,
                       ds.Cia402State.FAULT})


def _rpdo_cob_id(pdo: PdoMap, index: int, bits: int) -> int:
    """An RPDO's COB-ID, after checking it maps exactly object ``index`` of ``bits``
    (what :meth:`CanopenBase._send_wheels` / :meth:`CanopenBase._send_shutdowns` pack)."""
    mapped = [(var.index, var.subindex, var.length) for var in pdo.map]
    if mapped != [(index, 0, bits)] or pdo.cob_id is None:
        raise TransportError(f"{pdo.name} must map only 0x{index:04X} ({bits} bits), "
                             f"got {mapped}")
    return int(pdo.cob_id)


def _parallel(fn: Callable[[int], T], n: int, keepalive: Callable[[], None] | None = None,
              every: float = 0.05) -> list[T | BaseException]:
    """``fn(i)`` for i in range(n) concurrently (one SDO conversation per drive);
    each result or the exception it raised, in order.  While they run, ``keepalive()``
    is called every ``every`` [s] from the calling thread."""
    out: list[T | BaseException] = []
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="canopen-sdo") as pool:
        futures = [pool.submit(fn, i) for i in range(n)]
        if keepalive is not None:
            while wait(futures, timeout=every).not_done:
                keepalive()
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
        wheel_accel = limits.base_linear_acceleration / cfg.mecanum.wheel_radius  # [rad/s^2]
        self._accel_counts = max(1, round(wheel_accel * self._counts_per_rad))
        rest = limits.wheel_velocity / wheel_accel  # [s] from the wheel limit to rest
        if self._co.stop_timeout < rest:
            raise ConfigError(
                "base.canopen.stop_timeout", self._co.stop_timeout,
                f"must be at least {rest:.3f} s: the wheels take that long from "
                f"limits.wheel_velocity = {limits.wheel_velocity} rad/s to rest at "
                f"limits.base_linear_acceleration = {limits.base_linear_acceleration} m/s^2")
        watchdog_ms = round(cfg.command_watchdog * 1000)
        self._watchdog_ms = watchdog_ms
        #: period of the zero targets sent while enable()/disable() wait [s]
        self._keepalive = cfg.command_watchdog / 4.0
        #: (index, subindex, value): what connect() writes besides the PDOs, and reads
        #: back; the stop-related objects first
        self._settings: tuple[tuple[int, int, int], ...] = (
            (ds.PRODUCER_HEARTBEAT_TIME, 0, max(1, round(self._co.heartbeat_period * 1000))),
            (ds.QUICK_STOP_DECELERATION, 0, self._accel_counts),
            (ds.PROFILE_ACCELERATION, 0, self._accel_counts),
            (ds.PROFILE_DECELERATION, 0, self._accel_counts),
            (ds.QUICK_STOP_OPTION, 0, ds.QUICK_STOP_QUICK_STOP_RAMP),
            (ds.SHUTDOWN_OPTION, 0, ds.STOP_OPTION_SLOW_DOWN_RAMP),
            (ds.DISABLE_OPERATION_OPTION, 0, ds.STOP_OPTION_SLOW_DOWN_RAMP),
            (ds.FAULT_REACTION_OPTION, 0, ds.FAULT_REACTION_QUICK_STOP_RAMP),
            (ds.ABORT_CONNECTION_OPTION, 0, ds.ABORT_QUICK_STOP),
            (ds.CONSUMER_HEARTBEAT_TIME, 1, self._co.master_node_id << 16 | watchdog_ms),
            (ds.MODES_OF_OPERATION, 0, ds.MODE_PROFILE_VELOCITY),
        )
        self._command = WheelCommand(cfg.mecanum, limits.wheel_velocity)
        self._odo = OdometryIntegrator(cfg.mecanum)
        self._network: canopen.Network | None = None
        self._bus: GuardedBus | None = None
        self._nodes: list[canopen.RemoteNode] = []
        self._rpdo: list[PdoMap] = []
        self._rpdo_cob: list[int] = []
        self._rpdo2_cob: list[int] = []
        self._hb_task: Any = None
        self._cond = threading.Condition()
        self._hb_time = [-math.inf] * self._n
        self._hb_state: list[int | None] = [None] * self._n
        self._booted = [False] * self._n  # boot-up message seen since configured
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
        bus = open_bus(co, FaultCause.BASE_LINK, connect_timeout=co.sdo_timeout * 4)
        net = canopen.Network(bus)
        net.NOTIFIER_CYCLE = _NOTIFIER_CYCLE
        net.connect()
        self._network = net
        self._bus = bus
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
            self._rpdo_cob = [_rpdo_cob_id(pdo, ds.TARGET_VELOCITY, 32) for pdo in self._rpdo]
            self._rpdo2_cob = [_rpdo_cob_id(node.rpdo[2], ds.CONTROLWORD, 16)
                               for node in self._nodes]
            for node in self._nodes:
                node.nmt.state = "OPERATIONAL"
            self._wait_operational(range(self._n))
            self._hb_task = net.send_periodic(
                0x700 + co.master_node_id, bytes([_OPERATIONAL]), co.heartbeat_period)
        except BaseException:
            self._teardown()
            raise
        self._odo.reset(time.monotonic())
        log.info("base_connected", transport="canopen", channel=co.channel, node_ids=self._ids)

    def reconnect(self) -> None:
        """Bring a lost link back: release what is left of the old network (no I/O on a
        dead link), then :meth:`connect` again (every drive probed and configured by
        SDO, NMT OPERATIONAL, our heartbeat) and :meth:`disable` (waiting: a drive found
        still in OPERATION ENABLED ramps to rest before its power stage opens), so the
        drives are left disabled; :meth:`enable` arms them.  Does nothing while the
        link works (idempotent).  Blocks up to the SDO and stop timeouts: not for the
        loop thread.

        Raises :class:`~mmctl.errors.LinkLost` (cause ``base_link_lost``) naming the
        channel while the channel or the drives do not answer."""
        bus = self._bus
        if self._network is not None and bus is not None and bus.lost is None:
            return
        self._teardown()
        try:
            self.connect()
            self.disable()
        except TransportError as exc:
            self._teardown()
            raise LinkLost.wrap(describe(self._co), FaultCause.BASE_LINK,
                                "reconnect failed", exc) from exc
        log.info("base_reconnected", transport="canopen", channel=self._co.channel)

    def enable(self) -> None:
        """Bring every drive to OPERATION ENABLED, each step checked on 0x6041.

        A drive that rebooted since it was configured (boot-up message seen, or its
        consumer heartbeat 0x1016:01 reads back wrong) is first configured again, fully
        (objects, PDOs, NMT OPERATIONAL).  A drive in FAULT REACTION ACTIVE is waited
        for (it is bringing its wheel to rest; no reset is possible there) until FAULT,
        at most ``base.canopen.stop_timeout``; in FAULT the reset edge (controlword bit
        7) is sent, and repeated if the drive stays in FAULT; a drive in QUICK STOP
        ACTIVE is waited for until it has come to rest.  A drive found in OPERATION
        ENABLED may still be ramping down on the stop's SHUTDOWN (its statusword changes
        only at rest): it gets SHUTDOWN and is waited for until its power stage is off.  Then shutdown -> switch on ->
        enable operation.  Blocks up to about ``stop_timeout`` + a few ``sdo_timeout``.

        Raises SafetyFault(DRIVE_FAULT) when a drive stays in FAULT, TransportError when
        a drive does not reach OPERATION ENABLED; then every drive is disabled again (a
        failed enable never takes effect later)."""
        self._require_connected()
        self._fault = None
        try:
            self._reconfigure_rebooted()
            self._send_wheels(_ZERO)
            # zero targets keep flowing while a drive is waited for: the RPDO deadline
            # of a drive already in OPERATION ENABLED must not expire meanwhile
            results = _parallel(self._enable_one, self._n, self._keep_zero, self._keepalive)
            for r in results:
                if isinstance(r, SafetyFault):
                    self._fault = r
                    raise r
            self._raise_errors(results, "cannot be enabled")
            # the RPDO deadline (0x1400:05) runs from here: the caller sends targets now
            self._send_wheels(_ZERO)
            self._enabled = True
            self.check()
        except BaseException:
            self._enabled = False
            try:
                self.disable()
            except MmctlError as exc:
                log.warning("base_enable_undo_failed", error=str(exc))
            raise
        log.info("base_enabled", transport="canopen")

    def stop(self) -> None:
        """Zero target velocity on every drive (RPDOs + SYNC); the drives slow down on
        their profile deceleration 0x6084.  Never waits (the loop thread calls it in the
        cycle that detects a fault): frames only; LinkLost at once on a lost link."""
        if self._network is not None:
            self._send_wheels(_ZERO)

    def disable(self, wait: bool = True) -> None:
        """Bring every wheel to rest, then open the power stages.

        Zero target, then controlword SHUTDOWN by SDO to every drive, including those
        whose heartbeat looks lost (any drive that still answers SDOs is reached; one
        that does not costs its SDO timeout and is reported).  Each drive executes the
        shutdown as 0x605B = 1 (written at connect) says: it ramps to rest on its
        profile deceleration 0x6084, and only then switches its power stage off (READY
        TO SWITCH ON).  A drive already stopping by itself (QUICK STOP ACTIVE, FAULT
        REACTION ACTIVE) is left to finish.

        ``wait``: **block** until every drive that answered has its power stage off (or
        is in FAULT), at most ``base.canopen.stop_timeout`` (2 s by default; from the
        wheel speed limit the ramp takes <= 1.15 s), plus the SDO time of a silent drive
        (``sdo_timeout``, retried once).  Raises TransportError naming the drives that
        did not answer or are still turning then; a drive is never forced off while its
        wheel turns.  ``wait=False`` (the loop thread stopping the robot): frames only,
        never an SDO (see the module doc): zero targets, then SHUTDOWN in RPDO2 to each
        drive not already stopping by itself (by its last TPDO2 statusword); each drive
        ramps down by itself.  Raises LinkLost at once on a lost link."""
        if self._network is None:
            return
        self._enabled = False
        t0 = time.monotonic()
        if not wait:
            self._send_wheels(_ZERO)
            self._send_shutdowns()
            return
        try:
            self._send_wheels(_ZERO)
        except TransportError as exc:  # the SDOs below may still get through
            log.warning("base_disable_zero_target_failed", error=str(exc))
        results = _parallel(self._disable_one, self._n, self._keep_zero, self._keepalive)
        self._raise_errors(results, "cannot be disabled")
        log.info("base_disabled", transport="canopen",
                 waited_ms=round((time.monotonic() - t0) * 1e3, 1))

    def close(self) -> None:
        """Stop and disable (best effort, failures logged), NMT PRE-OPERATIONAL, close
        the channel.  Safe to call more than once."""
        if self._network is None:
            return
        try:
            if self._enabled and (self._bus is None or self._bus.lost is None):
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
            self._booted = [False] * self._n
            self._statusword = [0] * self._n
            self._rx_mask = 0
            self._sample_time = 0.0
            self._prev_time = -1.0
            self._fault = None
            self._enabled = False

    def _keep_zero(self) -> None:
        """Zero targets (RPDOs + SYNC) while enable()/disable() wait for drives: they
        feed the RPDO deadline of the drives in OPERATION ENABLED; errors logged."""
        try:
            self._send_wheels(_ZERO)
        except MmctlError as exc:
            log.warning("base_keepalive_failed", error=str(exc))

    def _require_connected(self) -> None:
        if self._network is None:
            raise TransportError("base is not connected (call connect() first)")
        bus = self._bus
        if bus is not None and bus.lost is not None:
            bus.check()

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

    def _send_shutdowns(self) -> None:
        """SHUTDOWN as RPDO2 (controlword) to every drive whose last statusword does not
        show it stopping by itself; frames only, answered by nothing."""
        net = self._network
        if net is None:
            raise TransportError("base is not connected (call connect() first)")
        frame = _CONTROL.pack(ds.Controlword.SHUTDOWN)
        try:
            for cob, sw in zip(self._rpdo2_cob, self._statusword):
                if ds.decode_statusword(sw) not in _STOPPING:
                    net.send_message(cob, frame)
        except (can.CanError, RuntimeError) as exc:
            raise TransportError(f"CAN send failed on {self._co.channel!r}: {exc}") from exc
        log.info("base_shutdown_sent", transport="canopen", via="rpdo2")

    def _health(self) -> SafetyFault | None:
        bus = self._bus
        if bus is not None and bus.lost is not None:
            bus.check()
        if self._fault is not None:
            return self._fault
        net = self._network
        if net is not None and net.notifier is not None and net.notifier.exception is not None:
            assert bus is not None
            bus.fail(net.notifier.exception, "the receive thread")
            bus.check()
        now = time.monotonic()
        timeout = self._co.heartbeat_timeout
        fault = None
        for i, nid in enumerate(self._ids):
            age = now - self._hb_time[i]
            if self._booted[i]:
                fault = SafetyFault(FaultCause.DRIVE_FAULT, node_id=nid, wheel=WHEEL_NAMES[i],
                                    state="rebooted (boot-up message)")
            elif age > timeout:
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
        state = data[0] & 0x7F
        with self._cond:
            self._hb_time[i] = time.monotonic()
            self._hb_state[i] = state
            if state == 0:  # boot-up: the drive restarted with its default objects
                self._booted[i] = True
            self._cond.notify_all()
        if state == 0:
            log.warning("base_drive_rebooted", transport="canopen", node_id=self._ids[i],
                        wheel=WHEEL_NAMES[i])

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
        """NMT PRE-OPERATIONAL, write every setting and the PDO layout, read the settings
        back (TransportError naming the object when one differs)."""
        node, nid = self._nodes[i], self._ids[i]
        with self._cond:
            self._booted[i] = False
        node.nmt.state = "PRE-OPERATIONAL"
        sdo = node.sdo
        for index, sub, value in self._settings:
            self._entry(i, index, sub).raw = value
        sdo[ds.TARGET_VELOCITY].raw = 0
        layout: tuple[tuple[PdoMap, int, int, tuple[int, ...], int | None], ...] = (
            (node.rpdo[1], 0x200, 1, (ds.TARGET_VELOCITY,), self._watchdog_ms),
            (node.rpdo[2], 0x300, 255, (ds.CONTROLWORD,), 0),
            (node.tpdo[1], 0x180, 1, (ds.POSITION_ACTUAL, ds.VELOCITY_ACTUAL), None),
            (node.tpdo[2], 0x280, 255, (ds.STATUSWORD,), None),
        )
        for pdo, cob, trans, objects, event_timer in layout:
            pdo.clear()
            for index in objects:
                pdo.add_variable(index)
            pdo.cob_id = cob + nid
            pdo.trans_type = trans if objects else 255
            pdo.event_timer = event_timer  # RPDO1: the deadline [ms]
            pdo.enabled = bool(objects)
            pdo.save()
        for pdo, cb in ((node.tpdo[1], partial(self._on_tpdo1, i)),
                        (node.tpdo[2], partial(self._on_tpdo2, i))):
            pdo.callbacks.clear()  # a reconfigured drive: not twice
            pdo.add_callback(cb)
        wrong = self._wrong_settings(i)
        if wrong:
            raise TransportError(f"drive {nid} does not keep its settings: {'; '.join(wrong)}")
        pos = sdo[ds.POSITION_ACTUAL].raw
        self._statusword[i] = sdo[ds.STATUSWORD].raw
        with self._cond:
            self._pos[i] = self._prev_pos[i] = self._rx_pos[i] = pos
        log.info("base_drive_configured", transport="canopen", node_id=nid,
                 command_watchdog_ms=self._watchdog_ms)

    def _entry(self, i: int, index: int, sub: int) -> Any:
        """The SDO variable index:sub of drive ``i`` (sub ignored for a plain variable)."""
        node = self._nodes[i]
        if isinstance(node.object_dictionary[index], ODVariable):
            return node.sdo[index]
        return node.sdo[index][sub]

    def _wrong_settings(self, i: int) -> list[str]:
        """The settings (and RPDO1's deadline, mapping, COB-ID) drive ``i`` reads back
        differently from what connect() wrote, as text."""
        want = [*self._settings,
                (ds.RPDO1_COMMUNICATION, ds.EVENT_TIMER_SUBINDEX, self._watchdog_ms),
                (ds.RPDO1_COMMUNICATION, 1, 0x200 + self._ids[i]),
                (0x1600, 0, 1), (0x1600, 1, ds.TARGET_VELOCITY << 16 | 32),
                (0x1401, 1, 0x300 + self._ids[i]),
                (0x1601, 0, 1), (0x1601, 1, ds.CONTROLWORD << 16 | 16)]
        wrong = []
        for index, sub, value in want:
            got = int(self._entry(i, index, sub).raw)
            if index in (ds.RPDO1_COMMUNICATION, 0x1401) and sub == 1:
                got &= 0xBFFF_FFFF  # the RTR bit is not ours to set
            if got != value:
                wrong.append(f"0x{index:04X}:{sub:02X} = {got}, wrote {value}")
        return wrong

    def _reconfigure_rebooted(self) -> None:
        """Configure again, fully, every drive that rebooted since connect (boot-up
        seen, or its consumer heartbeat 0x1016:01 no longer what we wrote), then NMT
        OPERATIONAL and wait for its heartbeat."""
        consumer = self._co.master_node_id << 16 | self._watchdog_ms

        def refresh(i: int) -> bool:
            entry = self._nodes[i].sdo[ds.CONSUMER_HEARTBEAT_TIME][1]
            if not self._booted[i] and int(entry.raw) == consumer:
                return False
            log.warning("base_drive_reconfigure", transport="canopen", node_id=self._ids[i],
                        booted=self._booted[i])
            self._configure_one(i)
            return True

        results = _parallel(refresh, self._n)
        self._raise_errors(results, "cannot be configured")
        redo = [i for i, r in enumerate(results) if r is True]
        for i in redo:
            self._nodes[i].nmt.state = "OPERATIONAL"
        self._wait_operational(redo)

    def _wait_operational(self, which: Sequence[int] | range) -> None:
        wait = max(_STARTUP_TIMEOUT, 5 * self._co.heartbeat_timeout)
        deadline = time.monotonic() + wait
        with self._cond:
            while any(self._hb_state[i] != _OPERATIONAL for i in which):
                left = deadline - time.monotonic()
                if left <= 0:
                    bad = [self._ids[i] for i in which if self._hb_state[i] != _OPERATIONAL]
                    raise TransportError(
                        f"drive(s) {bad} sent no OPERATIONAL heartbeat within {wait:.1f} s "
                        f"on channel {self._co.channel!r}")
                self._cond.wait(left)

    def _enable_one(self, i: int) -> None:
        node, nid = self._nodes[i], self._ids[i]
        sdo = node.sdo
        sw = sdo[ds.STATUSWORD].raw
        state = ds.decode_statusword(sw)
        if state is ds.Cia402State.OPERATION_ENABLED:
            # maybe ramping to rest on a SHUTDOWN the loop's stop sent (0x605B = 1: the
            # statusword shows OPERATION ENABLED until the wheel is at rest, then READY
            # TO SWITCH ON): taken as enabled, it would switch off under the armed robot.
            # SHUTDOWN again (a drive at rest switches off at once) and wait for the end
            # of the ramp; then the whole sequence from a known state.
            sdo[ds.CONTROLWORD].raw = ds.Controlword.SHUTDOWN
            sw, state = self._wait_state(i, _SETTLED, self._co.stop_timeout, _REST_POLL)
            if state in _MOVING:
                raise TransportError(
                    f"drive {nid} still in {state.value} {self._co.stop_timeout} s after "
                    f"SHUTDOWN (statusword 0x{sw:04X})")
        if state is ds.Cia402State.FAULT_REACTION_ACTIVE:
            # still bringing its wheel to rest: CiA 402 has no reset from here, a reset
            # edge now is lost; wait for FAULT
            sw, state = self._wait_state(i, {ds.Cia402State.FAULT}, self._co.stop_timeout,
                                         _REST_POLL)
        if state is ds.Cia402State.FAULT:
            for _ in range(_RESET_ATTEMPTS):
                sdo[ds.CONTROLWORD].raw = ds.Controlword.DISABLE_VOLTAGE  # bit 7 low
                sdo[ds.CONTROLWORD].raw = ds.Controlword.FAULT_RESET  # its rising edge
                sw, state = self._wait_state(i, {ds.Cia402State.SWITCH_ON_DISABLED},
                                             self._co.sdo_timeout)
                if state is not ds.Cia402State.FAULT:
                    break
        if state in (ds.Cia402State.FAULT, ds.Cia402State.FAULT_REACTION_ACTIVE):
            raise SafetyFault(FaultCause.DRIVE_FAULT, node_id=nid, wheel=WHEEL_NAMES[i],
                              state=state.value, statusword=f"0x{sw:04X}",
                              error_code=f"0x{sdo[ds.ERROR_CODE].raw:04X}")
        if state is ds.Cia402State.QUICK_STOP_ACTIVE:
            # 0x605A = 2: it goes to SWITCH ON DISABLED by itself once at rest
            sw, state = self._wait_state(i, {ds.Cia402State.SWITCH_ON_DISABLED},
                                         self._co.stop_timeout, _REST_POLL)
            if state is ds.Cia402State.QUICK_STOP_ACTIVE:
                raise TransportError(
                    f"drive {nid} stays in QUICK STOP ACTIVE {self._co.stop_timeout} s "
                    f"(statusword 0x{sw:04X})")
        if state is not ds.Cia402State.OPERATION_ENABLED:
            for cw, want in (
                (ds.Controlword.SHUTDOWN, ds.Cia402State.READY_TO_SWITCH_ON),
                (ds.Controlword.SWITCH_ON, ds.Cia402State.SWITCHED_ON),
                (ds.Controlword.ENABLE_OPERATION, ds.Cia402State.OPERATION_ENABLED),
            ):
                sdo[ds.CONTROLWORD].raw = cw
                sw, state = self._wait_state(i, {want}, self._co.sdo_timeout)
                if state is not want:
                    raise TransportError(
                        f"drive {nid} stays in {state.value} (statusword 0x{sw:04X}) after "
                        f"controlword 0x{int(cw):04X}, expected {want.value}")
        self._statusword[i] = sw

    def _disable_one(self, i: int) -> None:
        """SHUTDOWN by SDO (unless the drive stops by itself already), then wait until
        its power stage is off (at most stop_timeout)."""
        nid, sdo = self._ids[i], self._nodes[i].sdo
        state = ds.decode_statusword(sdo[ds.STATUSWORD].raw)
        if state not in _STOPPING:
            sdo[ds.CONTROLWORD].raw = ds.Controlword.SHUTDOWN
        sw, state = self._wait_state(i, _SETTLED, self._co.stop_timeout, _REST_POLL)
        self._statusword[i] = sw
        if state in _MOVING:
            speed = sdo[ds.VELOCITY_ACTUAL].raw * self._rad_per_count
            raise TransportError(
                f"drive {nid} still in {state.value} {self._co.stop_timeout} s after "
                f"SHUTDOWN (wheel at {speed:.2f} rad/s); base.canopen.stop_timeout too short "
                "or the drive ignores its shutdown option 0x605B")

    def _wait_state(self, i: int, want: set[ds.Cia402State] | frozenset[ds.Cia402State],
                    timeout: float, poll: float = 0.001) -> tuple[int, ds.Cia402State]:
        """Poll 0x6041 (every ``poll`` [s]) until it shows a state in ``want`` or
        ``timeout`` [s] passes."""
        deadline = time.monotonic() + timeout
        while True:
            sw = self._nodes[i].sdo[ds.STATUSWORD].raw
            state = ds.decode_statusword(sw)
            if state in want or time.monotonic() > deadline:
                return sw, state
            time.sleep(poll)

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
        bus, self._bus = self._bus, None
        self._enabled = False
        if net is None:
            return
        if self._hb_task is not None:
            self._hb_task.stop()
            self._hb_task = None
        if bus is None or bus.lost is None:
            try:
                for node in self._nodes:
                    node.nmt.state = "PRE-OPERATIONAL"
            except (can.CanError, RuntimeError, MmctlError) as exc:
                log.warning("base_nmt_preop_failed", error=str(exc))
        try:
            net.disconnect()
        except Exception as exc:  # noqa: BLE001 - canopen re-raises a dead receive thread's
            log.warning("base_disconnect_failed", error=f"{type(exc).__name__}: {exc}")
        self._nodes = []
        self._rpdo = []
        self._rpdo_cob = []
        self._rpdo2_cob = []
