"""Four simulated CiA 402 drives on a python-can ``virtual`` channel, driving the wheels.

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
master wrote (reloaded on NMT start); EMCY on faults and watchdog events.  The wheels
are simulated by :class:`~mmctl.sim.wheels.WheelPlant`: the demand ramps toward the
target at the profile acceleration 0x6083/0x6084, with the base's command latency,
velocity loop and mecanum slip of the ``sim:`` section
(:class:`~mmctl.sim.wheels.BaseDynamics`); positions integrate the velocity.  :meth:`FakeDrives.pose` is what the wheels' encoders integrate
to (the master's odometry should agree), :meth:`FakeDrives.world_state` where the base
actually is (slip included).

Every way a drive stops is the one its objects select, as on a device:

* its command watchdog: consumer heartbeat 0x1016:01 (monitoring starts with the first
  heartbeat of the producer) and the RPDO deadline 0x1400+n:05 (starts with the first
  RPDO after NMT start); an event sends EMCY 0x8130 / 0x8250 and, in OPERATION ENABLED,
  does what the abort connection option code 0x6007 says (0 nothing, 1 fault, 2 disable
  voltage, 3 quick stop).  Nothing stops a drive whose objects are at their defaults
  (all off);
* quick stop per 0x605A (ramp on 0x6084 or 0x6085, then SWITCH ON DISABLED or stay);
  shutdown / disable operation per 0x605B / 0x605C (0, the default of 0x605B: power
  stage off at once; 1: slow-down ramp 0x6084, the state changes once at rest);
* a fault: FAULT REACTION ACTIVE while the 0x605E reaction brings the wheel to rest
  (default: quick-stop ramp), then FAULT; no controlword acts in FAULT REACTION ACTIVE;
* power stage off: the wheel coasts (a slow friction decay, see :class:`~mmctl.sim.wheels.WheelPlant`),
  each switch-off logged with the wheel speed (:meth:`FakeDrives.power_offs`).

A supervisor thread acts on deadlines and ramp ends as they fall due (each at its own
time in the plant's integration).  Like a real drive, which timestamps a frame as its
controller receives it and services its watchdogs in real time, the watchdogs judge each
heartbeat and RPDO by when it reached the bus (python-can's arrival stamp), never by when
the shared receive thread got round to it: on a loaded machine that thread falls seconds
behind, and frames the master sent on time would otherwise look late.  For the same
reason no deadline acts while frames that reached the bus before it still wait to be
handled (:class:`_Arrivals`); once they are, a deadline the master really missed acts,
at its own time.  Fault injection: :meth:`FakeDrives.inject_fault`,
:meth:`FakeDrives.inject_silence` (heartbeat stops, nothing answered or heard),
:meth:`FakeDrives.resume`, :meth:`FakeDrives.reboot` (power off, all objects to their
defaults, boot-up, PRE-OPERATIONAL; an NMT reset node / communication does the same).
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from types import TracebackType
from typing import TYPE_CHECKING, Any

import can
import canopen
import numpy as np
import structlog
from canopen.network import MessageListener
from canopen.pdo import PdoMap
from canopen.sdo.exceptions import SdoAbortedError
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.config.base import BaseConfig
from mmctl.config.control import LimitsConfig
from mmctl.config.runtime import SimConfig
from mmctl.errors import again
from mmctl.sim.wheels import SUBSTEP, BaseDynamics, WheelPlant
from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.protocol import WHEEL_NAMES, DriveStatus

if TYPE_CHECKING:
    from typing_extensions import Self

log = structlog.get_logger(__name__)

Vec = NDArray[np.float64]
_ABORT_VALUE_RANGE = 0x0609_0030


def _maps(pdos: Any) -> list[PdoMap]:
    """The PDO maps of a node's RPDO or TPDO object."""
    return list(pdos.map.values())


def _read(node: canopen.LocalNode, index: int, subindex: int = 0) -> int:
    """An integer object of ``node``'s dictionary (through its read callbacks)."""
    var = node.object_dictionary.get_variable(index, subindex)
    assert var is not None, f"0x{index:04X}:{subindex} is not a variable"
    return int(var.decode_raw(node.get_data(index, subindex)))


S = ds.Cia402State
#: Option codes the simulated drives accept (others: SDO abort "value range").
_ACCEPTED: dict[int, frozenset[int]] = {
    ds.ABORT_CONNECTION_OPTION: frozenset({0, 1, 2, 3}),
    ds.QUICK_STOP_OPTION: frozenset({0, 1, 2, 5, 6}),
    ds.SHUTDOWN_OPTION: frozenset({0, 1}),
    ds.DISABLE_OPERATION_OPTION: frozenset({0, 1}),
    ds.FAULT_REACTION_OPTION: frozenset({0, 1, 2}),
}
#: The supervisor thread sleeps at most this long between looks at the clock [s].
_SUPERVISOR_NAP = 0.05
#: While a due deadline waits for frames that reached the bus before it to be handled,
#: the supervisor looks again after this [s].
_BACKLOG_NAP = 0.005
#: A frame's arrival stamp older than this is not believed (a wall-clock step, a frame
#: never stamped): the time it is handled counts as its arrival [s].
_MAX_BACKLOG = 30.0


def _arrival(stamp: float | None) -> float:
    """When a frame being handled now reached the bus, on the monotonic clock: ``stamp``
    is python-can's ``Message.timestamp``, wall clock (``time.time()``), set as the frame
    reached the channel (the virtual bus stamps it on send; in the simulator's process
    that is :mod:`mmctl.sim.socketcand` putting the master's frame on the channel).
    Never after now; a missing or unbelievable stamp (see :data:`_MAX_BACKLOG`) gives
    now.  (Wall clock read first: a pause between the two reads makes the frame look
    younger, never older than it is.)"""
    wall = time.time()
    now = time.monotonic()
    if stamp is None:
        return now
    age = wall - stamp
    return now - age if 0.0 < age <= _MAX_BACKLOG else now


class _Arrivals(MessageListener):
    """canopen's listener (it hands each received frame to the nodes' handlers), which
    also knows how far the receive thread has got: the arrival stamp of the frame it
    took last (every frame that reached the bus before it has been handled) and, through
    the virtual bus's receive queue (a frame put there counts as an unfinished task until
    this listener has handled it: ``queue.Queue.task_done``), whether any frame waits."""

    def __init__(self, network: canopen.Network, bus: can.BusABC) -> None:
        super().__init__(network)
        rx = getattr(bus, "queue", None)  # python-can's VirtualBus: its receive queue
        self._rx: queue.Queue[can.Message] | None = rx if isinstance(rx, queue.Queue) else None
        self._stamp = time.time()  # nothing before this reached us

    def on_message_received(self, msg: can.Message) -> None:
        self._stamp = msg.timestamp
        try:
            super().on_message_received(msg)
        finally:
            if self._rx is not None:
                self._rx.task_done()

    def horizon(self, now: float) -> float:
        """The monotonic time [s] before which every frame that reached the bus has been
        handled: ``now`` when none waits (or, on a bus without a queue to look at,
        always), else the arrival of the frame in hand (or of the last one handled)."""
        if self._rx is None or self._rx.unfinished_tasks == 0:
            return now
        return now - max(0.0, time.time() - self._stamp)


@dataclass
class _Drive:
    """One simulated drive's CiA 402 side."""

    wheel: int
    node: canopen.LocalNode
    state: ds.Cia402State = S.SWITCH_ON_DISABLED
    controlword: int = 0
    mode: int = 0
    error_code: int = 0
    silent: bool = False
    pdo_dirty: bool = True
    rpdo_pending: list[PdoMap] = field(default_factory=list)
    last_event: dict[int, bytes] = field(default_factory=dict)
    log: deque[tuple[float, int]] = field(default_factory=lambda: deque(maxlen=20_000))
    #: while the wheel ramps to rest: the state entered once it is at rest
    ramp_to: ds.Cia402State | None = None
    #: consumer heartbeat (0x1016:01): producer node id, time [s]; arrival (monotonic)
    #: of the last heartbeat seen (None: monitoring not started, i.e. none received since
    #: configured or since the last timeout)
    hb_producer: int = 0
    hb_time: float = 0.0
    hb_last: float | None = None
    #: RPDO deadline (0x1400+n:05) [s] per RPDO number n (0-based), loaded on NMT
    #: start; arrival (monotonic) of the last reception per RPDO (monitoring starts with
    #: the first one)
    rpdo_no: dict[int, int] = field(default_factory=dict)
    rpdo_timer: dict[int, float] = field(default_factory=dict)
    rpdo_last: dict[int, float] = field(default_factory=dict)
    #: EMCY code of a pending communication error (heartbeat / RPDO deadline), or 0
    comm_error: int = 0
    #: (monotonic time [s], event) of every watchdog event and state change
    events: deque[tuple[float, str]] = field(default_factory=lambda: deque(maxlen=1000))


class FakeDrives:
    """The four simulated drives (parent-side handle; see the module doc).

    cfg: a :class:`~mmctl.config.Config` (or its ``base:`` section, then ``limits``
    gives the acceleration and ``sim`` the base's dynamics; defaults otherwise).  The
    drives sit on python-can's ``virtual`` bus, channel ``base.canopen.channel``,
    whatever the interface the master uses to get there (``socketcand``:
    :mod:`mmctl.sim.socketcand` serves the channel).  No I/O before :meth:`start`.
    """

    def __init__(self, cfg: Config | BaseConfig, limits: LimitsConfig | None = None,
                 sim: SimConfig | None = None) -> None:
        if isinstance(cfg, Config):
            base, limits, sim = cfg.base, cfg.limits, cfg.sim
        else:
            base, limits, sim = cfg, limits or LimitsConfig(), sim or SimConfig()
        self.cfg = base
        self.node_ids: tuple[int, ...] = tuple(base.canopen.node_ids)
        self._counts_per_rad = base.canopen.counts_per_rev / (2.0 * math.pi)
        od = ds.build_object_dictionary(1)
        accel, decel = (od.get_variable(i) for i in (ds.PROFILE_ACCELERATION,
                                                      ds.PROFILE_DECELERATION))
        assert accel is not None and decel is not None
        self._default_accel = int(accel.default or 1) / self._counts_per_rad  # [rad/s^2]
        self._default_decel = int(decel.default or 1) / self._counts_per_rad
        # no plant-side watchdog: the drives stop by their objects (0x1016, 0x1400:05)
        self.plant = WheelPlant(base.mecanum, self._default_accel, None,
                                dynamics=BaseDynamics.from_config(sim))
        self.plant.decel[:] = self._default_decel
        self.plant.coasting[:] = True  # power stages off (SWITCH ON DISABLED)
        self._lock = self.plant.lock
        self._cond = threading.Condition(self._lock)
        self._network: canopen.Network | None = None
        self._arrivals: _Arrivals | None = None
        self._drives: dict[int, _Drive] = {}
        self._sync_count = 0
        self._sync_time: float | None = None  # while handling a SYNC: its time
        self._servicing = False
        self._error: BaseException | None = None
        self._supervisor: threading.Thread | None = None
        self._stopping = False
        self._heartbeat_handler = self._guard(self._on_consumed_heartbeat)

    # -- lifecycle -------------------------------------------------------------------

    def start(self) -> FakeDrives:
        """Connect to the virtual channel and boot the drives (boot-up message, then
        PRE-OPERATIONAL; heartbeat off until the master writes 0x1017)."""
        if self._network is not None:
            return self
        bus = can.Bus(interface="virtual", channel=self.cfg.canopen.channel)
        net = canopen.Network(bus)
        net.NOTIFIER_CYCLE = 0.05
        self._arrivals = _Arrivals(net, bus)
        assert type(net.listeners[0]) is MessageListener
        net.listeners[0] = self._arrivals  # in place of canopen's own, doing what it did
        net.connect()
        self._network = net
        for wheel, nid in enumerate(self.node_ids):
            node = canopen.LocalNode(nid, ds.build_object_dictionary(nid))
            net.add_node(node)
            drive = _Drive(wheel, node)
            drive.rpdo_no = {id(pdo): no for no, pdo in enumerate(_maps(node.rpdo))}
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
        self._stopping = False
        self._supervisor = threading.Thread(target=self._supervise, name="fake-drives-timer",
                                            daemon=True)
        self._supervisor.start()
        log.info("fake_drives_started", channel=self.cfg.canopen.channel, node_ids=self.node_ids)
        return self

    def stop(self) -> None:
        """Stop heartbeats and leave the channel; re-raise an error a handler stored."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._supervisor is not None:
            self._supervisor.join(5.0)
            self._supervisor = None
        net, self._network = self._network, None
        if net is not None:
            for drive in self._drives.values():
                drive.node.nmt.stop_heartbeat()
            net.disconnect()
            self._arrivals = None  # nothing is received any more: none waits
            log.info("fake_drives_stopped", channel=self.cfg.canopen.channel)
        self.check()

    def check(self) -> None:
        """Re-raise the first exception a CAN handler of the fakes raised, if any."""
        if self._error is not None:
            raise again(self._error)

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

    def event_log(self, node_id: int) -> list[tuple[float, str]]:
        """The drive's watchdog events and state changes: (monotonic time [s], text),
        e.g. ``"heartbeat consumer timeout"``, ``"rpdo1 deadline missed"``,
        ``"state QUICK STOP ACTIVE"``, ``"reboot"``."""
        with self._lock:
            return list(self._drives[node_id].events)

    def power_offs(self) -> list[tuple[float, int, float]]:
        """Every time a drive's power stage switched off: (monotonic time [s], node id,
        wheel speed at that instant [rad/s])."""
        with self._lock:
            return [(t, self.node_ids[w], v) for t, w, v in self.plant.power_offs]

    def wheel_velocities(self) -> Vec:
        """Actual simulated wheel speeds (4,) [rad/s] now (watchdog events due by now
        act at their deadlines first, so looking never changes the physics)."""
        with self._lock:
            self._service(time.monotonic())
            return self.plant.omega.copy()

    def wheel_positions(self) -> Vec:
        """Actual simulated wheel angles (4,) [rad] now (unwrapped)."""
        with self._lock:
            self._service(time.monotonic())
            return self.plant.theta.copy()

    def pose(self) -> tuple[float, float, float]:
        """The base pose (x, y [m], yaw [rad]) the wheels' encoders integrate to, now:
        what the master's odometry should find (no slip; :meth:`world_state` has it)."""
        with self._lock:
            self._service(time.monotonic())
            return self.plant.get_odometry_pose(time.monotonic())

    def world_state(self) -> tuple[tuple[float, float, float], Vec]:
        """Where the base actually is and how it moves, now: pose (x, y [m], yaw [rad],
        world frame) and twist (3,) (v_x, v_y [m/s], ω_z [rad/s], base frame), mecanum
        slip included (what the person's hand moves with)."""
        with self._lock:
            self._service(time.monotonic())
            return self.plant.get_pose(time.monotonic()), self.plant.twist()

    @property
    def sync_count(self) -> int:
        """SYNC messages the drives have received."""
        return self._sync_count

    def states(self) -> list[DriveStatus]:
        """Drive-side view: NMT state ('SILENT' when injected), CiA 402 state, statusword."""
        with self._lock:
            self._service(time.monotonic())
            out = []
            for d in self._drives.values():
                sw = self._statusword(d)
                link = "SILENT" if d.silent else d.node.nmt.state
                out.append(DriveStatus(WHEEL_NAMES[d.wheel], int(d.node.id or 0), link,
                                       d.state.value, sw, d.error_code))
            return out

    # -- fault injection ----------------------------------------------------------------

    def inject_fault(self, node_id: int, code: int = 0x2310) -> None:
        """Drive ``node_id`` detects a fault (EMCY ``code``, default 0x2310 over-current):
        FAULT REACTION ACTIVE while its wheel comes to rest as the fault reaction option
        code 0x605E says (default: on the quick-stop ramp 0x6085), then FAULT; the
        statusword TPDO goes out on each change."""
        with self._lock:
            self._fault(self._drives[node_id], code, time.monotonic())
        log.info("fake_drive_fault_injected", node_id=node_id, code=f"0x{code:04X}",
                 sync_count=self._sync_count)

    def inject_silence(self, node_id: int) -> None:
        """Drive ``node_id`` goes silent: no heartbeat, no TPDO, no SDO answer, and it
        ignores everything it receives (so its own watchdog, if configured, stops it)."""
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

    def reboot(self, node_id: int) -> None:
        """Drive ``node_id`` restarts (a power glitch, a watchdog reset): its power stage
        switches off at once (the wheel coasts), every object returns to its default
        (PDO mappings, heartbeat producer 0 = off, watchdog and option codes, modes,
        ramps), it sends its boot-up message and waits in NMT PRE-OPERATIONAL, SWITCH ON
        DISABLED.  A silent drive comes back talking."""
        with self._lock:
            d = self._drives[node_id]
            if d.silent:
                self.resume(node_id)
            self._reboot(d, time.monotonic())
        log.info("fake_drive_rebooted", node_id=node_id, sync_count=self._sync_count)

    # -- the drive's behaviour ------------------------------------------------------------

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

    def _note(self, d: _Drive, now: float, what: str) -> None:
        d.events.append((now, what))

    def _set_state(self, d: _Drive, state: ds.Cia402State, now: float) -> None:
        """Enter ``state``: the power stage follows (OPERATION ENABLED: on, tracking the
        target; QUICK STOP ACTIVE / FAULT REACTION ACTIVE: as their ramp set it;
        any other state: off, the wheel coasts); statusword TPDO on change."""
        if state is S.OPERATION_ENABLED:
            self.plant.track(d.wheel, now)
        elif state not in (S.QUICK_STOP_ACTIVE, S.FAULT_REACTION_ACTIVE):
            d.ramp_to = None
            self.plant.power_off(d.wheel, now)
        if state is not d.state:
            d.state = state
            self._note(d, now, f"state {state.value}")
            self._emit_events(d)

    def _ramp(self, d: _Drive, decel_index: int, then: ds.Cia402State, now: float) -> None:
        """Bring the wheel to rest on the deceleration ``decel_index`` (0x6084 or 0x6085)
        with the power stage on; once at rest the drive enters ``then``."""
        decel = max(_read(d.node, decel_index), 1) / self._counts_per_rad
        self.plant.ramp_to_rest(d.wheel, decel, now)
        d.ramp_to = then
        self._cond.notify_all()

    def _quick_stop(self, d: _Drive, now: float) -> None:
        """OPERATION ENABLED -> QUICK STOP ACTIVE, stopping as 0x605A says."""
        option = _read(d.node, ds.QUICK_STOP_OPTION)
        if option == ds.QUICK_STOP_COAST:
            self._set_state(d, S.SWITCH_ON_DISABLED, now)
            return
        decel = (ds.PROFILE_DECELERATION if option in (ds.QUICK_STOP_SLOW_DOWN_RAMP,
                                                       ds.QUICK_STOP_SLOW_DOWN_RAMP_STAY)
                 else ds.QUICK_STOP_DECELERATION)
        stay = option in (ds.QUICK_STOP_SLOW_DOWN_RAMP_STAY, ds.QUICK_STOP_QUICK_STOP_RAMP_STAY)
        self._ramp(d, decel, S.QUICK_STOP_ACTIVE if stay else S.SWITCH_ON_DISABLED, now)
        self._set_state(d, S.QUICK_STOP_ACTIVE, now)

    def _fault(self, d: _Drive, code: int, now: float) -> None:
        """A fault: EMCY, FAULT REACTION ACTIVE (the 0x605E reaction while the power
        stage is on), then FAULT."""
        if d.state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            return
        d.error_code = code
        if not d.silent and self._network is not None:
            d.node.emcy.send(code, register=0x01)
        powered = d.state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
        option = _read(d.node, ds.FAULT_REACTION_OPTION)
        if not powered or option == ds.FAULT_REACTION_COAST:
            self._set_state(d, S.FAULT_REACTION_ACTIVE, now)
            self._set_state(d, S.FAULT, now)
            return
        decel = (ds.PROFILE_DECELERATION if option == ds.FAULT_REACTION_SLOW_DOWN_RAMP
                 else ds.QUICK_STOP_DECELERATION)
        self._ramp(d, decel, S.FAULT, now)
        self._set_state(d, S.FAULT_REACTION_ACTIVE, now)

    def _controlword(self, d: _Drive, value: int, now: float) -> None:
        """The master wrote 0x6040: the CiA 402 transition, completed as the option
        codes say (0x605B shutdown / 0x605C disable operation: at once, the motor
        coasting, or after the slow-down ramp; quick stop per 0x605A)."""
        new = ds.next_state(d.state, value, d.controlword)
        d.controlword = value
        if new is d.state:
            return
        old = d.state
        if d.ramp_to is not None and old is S.OPERATION_ENABLED:
            # a shutdown / disable-operation ramp runs: only a quick stop or a
            # disable voltage (power off at once) changes it
            if new is S.QUICK_STOP_ACTIVE:
                self._quick_stop(d, now)
            elif new is S.SWITCH_ON_DISABLED:
                self._set_state(d, new, now)
            return
        if old is S.OPERATION_ENABLED and new in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON):
            option = _read(d.node, ds.SHUTDOWN_OPTION if new is S.READY_TO_SWITCH_ON
                           else ds.DISABLE_OPERATION_OPTION)
            if option == ds.STOP_OPTION_SLOW_DOWN_RAMP:
                self._ramp(d, ds.PROFILE_DECELERATION, new, now)  # state shown: OE
            else:
                self._set_state(d, new, now)
            return
        if new is S.QUICK_STOP_ACTIVE:
            self._quick_stop(d, now)
            return
        if old is S.FAULT:
            d.error_code = 0
            if not d.silent and self._network is not None:
                d.node.emcy.reset()
        if new is S.OPERATION_ENABLED:
            d.ramp_to = None
            if d.comm_error and not d.silent and self._network is not None:
                d.comm_error = 0
                d.node.emcy.reset()
        self._set_state(d, new, now)

    def _comm_event(self, d: _Drive, code: int, what: str, now: float) -> None:
        """A consumer heartbeat timeout or an RPDO deadline miss: EMCY, then in
        OPERATION ENABLED the abort connection option code 0x6007's action."""
        self._note(d, now, what)
        d.comm_error = code
        if not d.silent and self._network is not None:
            d.node.emcy.send(code, register=0x11)  # generic + communication error
        if d.state is not S.OPERATION_ENABLED or d.ramp_to is not None:
            return
        action = _read(d.node, ds.ABORT_CONNECTION_OPTION)
        if action == ds.ABORT_FAULT:
            self._fault(d, code, now)
        elif action == ds.ABORT_DISABLE_VOLTAGE:
            self._set_state(d, S.SWITCH_ON_DISABLED, now)
        elif action == ds.ABORT_QUICK_STOP:
            self._quick_stop(d, now)

    def _service(self, now: float) -> float:
        """Everything due by ``now``: watchdog events (at their deadlines, in order),
        ends of ramps.  Returns when the next thing is due (monotonic [s], inf: none).

        A deadline acts only once every frame that reached the bus before it has been
        handled (:meth:`_Arrivals.horizon`): one still waiting in the receive queue may
        be the heartbeat or RPDO that meets it.  Until then it is held, looked at again
        every :data:`_BACKLOG_NAP`."""
        if self._servicing:
            return math.inf
        self._servicing = True
        try:
            seen = now if self._arrivals is None else min(now, self._arrivals.horizon(now))
            due: list[tuple[float, int, _Drive, int, str]] = []
            for d in self._drives.values():
                if d.hb_last is not None and d.hb_time > 0.0 \
                        and seen >= d.hb_last + d.hb_time:
                    due.append((d.hb_last + d.hb_time, d.wheel, d, ds.EMCY_HEARTBEAT,
                                "heartbeat consumer timeout"))
                    d.hb_last = None
                for no, last in list(d.rpdo_last.items()):
                    limit = d.rpdo_timer.get(no, 0.0)
                    if limit > 0.0 and seen >= last + limit:
                        due.append((last + limit, d.wheel, d, ds.EMCY_RPDO_TIMEOUT,
                                    f"rpdo{no + 1} deadline missed"))
                        del d.rpdo_last[no]
            for t, _, d, code, what in sorted(due, key=lambda e: e[:2]):
                self.plant.advance(t)
                self._comm_event(d, code, what, max(t, self.plant.t))
            self.plant.advance(now)
            wake = math.inf
            for d in self._drives.values():
                if d.ramp_to is not None:
                    if self.plant.omega[d.wheel] == 0.0:
                        then, d.ramp_to = d.ramp_to, None
                        self._note(d, now, "at rest")
                        self._set_state(d, then, now)
                    else:
                        wake = min(wake, now + self.plant.rest_time(d.wheel) + SUBSTEP)
                deadlines = [last + d.rpdo_timer[no] for no, last in d.rpdo_last.items()
                             if d.rpdo_timer.get(no, 0.0) > 0.0]
                if d.hb_last is not None and d.hb_time > 0.0:
                    deadlines.append(d.hb_last + d.hb_time)
                for t in deadlines:  # one past now is held: frames before it still wait
                    wake = min(wake, t if t > now else now + _BACKLOG_NAP)
            return wake
        finally:
            self._servicing = False

    def _supervise(self) -> None:
        """The drives' clock: watchdog deadlines and ramp ends, as they fall due."""
        with self._cond:
            while not self._stopping:
                now = time.monotonic()
                try:
                    wake = self._service(now)
                except Exception as exc:  # stored, re-raised by check()/stop()
                    if self._error is None:
                        self._error = exc
                    log.exception("fake_drives_timer_failed")
                    return
                self._cond.wait(min(max(wake - now, 0.0002), _SUPERVISOR_NAP))

    def _reboot(self, d: _Drive, now: float) -> None:
        self._note(d, now, "reboot")
        self.plant.power_off(d.wheel, now)
        node = d.node
        node.nmt.stop_heartbeat()
        node.data_store.clear()  # every object back to its default
        d.state = S.SWITCH_ON_DISABLED  # (NOT READY TO SWITCH ON, then at once this)
        d.controlword = d.mode = d.error_code = d.comm_error = 0
        d.ramp_to = None
        d.hb_producer, d.hb_time, d.hb_last = 0, 0.0, None
        d.rpdo_timer.clear()
        d.rpdo_last.clear()
        d.rpdo_pending.clear()
        d.last_event.clear()
        w = d.wheel
        self.plant.accel[w] = self._default_accel
        self.plant.decel[w] = self._default_decel
        self.plant.drop_commands(w)  # target 0, nothing in flight
        if self._network is not None:
            node.rpdo.read()  # the default mappings: every PDO invalid
            node.tpdo.read()
            d.pdo_dirty = True
            node.nmt.send_command(0x81)  # INITIALISING: boot-up message
            node.nmt.send_command(0x80)  # -> PRE-OPERATIONAL (heartbeat: 0x1017 = 0, off)

    # -- CAN handlers (run in the network's receive thread) -----------------------------

    def _on_read(self, d: _Drive, index: int, subindex: int, od: Any) -> int | None:
        if index == ds.STATUSWORD:
            with self._lock:
                if self._sync_time is None:  # an SDO read: bring the drive up to now
                    self._service(time.monotonic())
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
            return (0x01 if d.error_code else 0) | (0x10 if d.comm_error else 0)
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
                self._controlword(d, value, now)
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
            elif index in _ACCEPTED:
                if value not in _ACCEPTED[index]:
                    raise SdoAbortedError(_ABORT_VALUE_RANGE)
            elif index == ds.CONSUMER_HEARTBEAT_TIME and subindex == 1:
                producer, ms = (value >> 16) & 0x7F, value & 0xFFFF
                d.hb_producer, d.hb_time, d.hb_last = producer, ms / 1000.0, None
                if producer and ms and self._network is not None:
                    self._network.subscribe(0x700 + producer, self._heartbeat_handler)
            elif 0x1400 <= index <= 0x1BFF:
                d.pdo_dirty = True

    def _on_consumed_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        producer = can_id - 0x700
        with self._lock:
            now = time.monotonic()
            at = _arrival(timestamp)  # judged by when it reached the bus
            for d in self._drives.values():
                if d.silent or d.hb_producer != producer or d.hb_time <= 0.0:
                    continue
                first = d.hb_last is None
                d.hb_last = at if d.hb_last is None else max(d.hb_last, at)
                if first:
                    self._note(d, now, f"heartbeat consumer: node {producer} heard")
                    self._cond.notify_all()

    def _on_nmt(self, d: _Drive, can_id: int, data: bytearray, timestamp: float) -> None:
        if d.silent:
            return
        if len(data) >= 2 and data[0] in (0x81, 0x82) and data[1] in (0, d.node.id):
            with self._lock:
                self._reboot(d, time.monotonic())  # reset node / communication: a reboot
            return
        if d.node.nmt.state != "OPERATIONAL":
            d.rpdo_last.clear()  # no PDOs outside OPERATIONAL: no deadline either
            return
        with self._lock:
            if d.pdo_dirty:
                d.node.rpdo.read()
                d.node.tpdo.read()
                d.pdo_dirty = False
                d.last_event.clear()
                d.rpdo_last.clear()
                d.rpdo_timer = {
                    no: _read(d.node, 0x1400 + no, ds.EVENT_TIMER_SUBINDEX) / 1000.0
                    for no, pdo in enumerate(_maps(d.node.rpdo)) if pdo.enabled}
            self._emit_events(d)

    def _on_rpdo(self, d: _Drive, pdo: PdoMap) -> None:
        if d.silent or d.node.nmt.state != "OPERATIONAL" or not pdo.enabled:
            return
        with self._lock:
            now = time.monotonic()
            no = d.rpdo_no.get(id(pdo), 0)
            if d.rpdo_timer.get(no, 0.0) > 0.0:
                at = _arrival(pdo.timestamp)  # judged by when it reached the bus
                first = no not in d.rpdo_last
                d.rpdo_last[no] = at if first else max(d.rpdo_last[no], at)
                if first:
                    self._cond.notify_all()
            if pdo not in d.rpdo_pending:
                d.rpdo_pending.append(pdo)
            for var in pdo.map:
                if var.index == ds.TARGET_VELOCITY:
                    d.log.append((now, int(var.raw)))
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
            self._service(now)
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
