"""The simulated robot: the fakes that speak the real wire protocols, and a person.

:class:`SimWorld` starts the fake UR controller (its own process, on ``arm.host``),
the fake ATI sensor on the virtual CAN channel ``sensor.can.channel`` (or the RDT
server), the four fake CiA 402 drives on ``base.canopen.channel``, and a thread playing
a person at the handle.  When the configuration's CAN sections use ``socketcand``, a
:class:`~mmctl.sim.socketcand.SocketcandServer` on ``sim.host:sim.can_port`` serves
those virtual channels to other processes (the daemon).  `mmctl sim`
(:mod:`mmctl.sim.service`) runs one in its own process; tests of the daemon's chain
may also run one next to an in-process daemon on the ``virtual`` interface.

The person (:class:`~mmctl.sim.human.SimulatedHuman`, a peg-in-hole task repeated
forever) observes the handle's true pose: the fake UR's joints, the fake drives' base
pose and the model's FK.  The hand force it applies is turned into what the sensor
measures (:class:`~mmctl.sim.handle.HandleSensor`: the study's too): rotated into the
sensor frame, its torque about the sensor origin, plus the handle's weight and a
constant sensor bias (``sim.handle_mass``, ``handle_com``, ``sensor_bias``: the true
values `mmctl calibrate tool` finds).  The person's switch requests press the handle
button: UR digital input ``daemon.switch_input`` of the fake controller (as wired on
the robot), or :attr:`SimWorld.button` when no input is configured.  While the daemon
tares, the person lets go (:meth:`SimWorld.hold`), as a real operator would.

:mod:`mmctl.sim.service` (the simulation's control socket, `mmctl sim ...`) overrides
the person with a constant push and injects faults into the fakes; see :data:`FAULTS`.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog

from mmctl.config import Config
from mmctl.errors import MmctlError
from mmctl.model.planar import base_to_world, rot_z
from mmctl.sim.handle import HandleSensor
from mmctl.types import Vec

if TYPE_CHECKING:
    from mmctl.sim.fake_drives import FakeDrives
    from mmctl.sim.fake_ft_can import FakeFtCanSensor
    from mmctl.sim.fake_rdt import FakeRdtServer
    from mmctl.sim.fake_ur import FakeURController
    from mmctl.sim.human import SimulatedHuman
    from mmctl.sim.socketcand import SocketcandServer

log = structlog.get_logger("mmctl.sim")

#: Injectable faults: name -> what it does to the fakes.
FAULTS = {
    "sensor_silent": "the CAN sensor stops answering",
    "sensor_status": "the sensor's status word reports a bus error",
    "sensor_saturation": "the sensor reports gauge saturation",
    "wrench_over_limit": "the person pushes 200 N along the handle's axis (no torque)",
    "arm_protective_stop": "the UR goes into protective stop",
    "arm_emergency_stop": "the UR's emergency stop is pressed",
    "arm_not_playing": "the UR program is stopped (pendant stop)",
    "arm_frozen": "the UR stops streaming RTDE data (timestamp frozen)",
    "arm_disconnected": "the UR controller process dies",
    "drive_fault": "drive 1 (FL) enters FAULT",
    "drive_silent": "drive 1 (FL) stops its heartbeat",
    "drive_reboot": "drive 1 (FL) reboots (power glitch): default objects, boot-up message",
    "sensor_garbage": "the CAN sensor answers with malformed (3-byte) frames",
    "enabling_contact": "the enabling switch's second contact stays open (a broken wire)",
    "sensor_unplugged": "the sensor's CAN adapter is pulled (socketcand: its connections "
                        "dropped, opening its channel refused until plugged back)",
    "base_unplugged": "the drives' CAN adapter is pulled (as sensor_unplugged, for the base)",
}
#: Faults that are events, not states: "off" means nothing.
_EVENTS = {"arm_not_playing", "drive_fault", "drive_reboot"}
#: [s] how long an event fault stays listed in the status when its effect cannot be
#: read back from the fake (a reboot's): long enough for a 1 s live view to show it
EVENT_LISTED_S = 10.0
_HUMAN_PERIOD = 0.01  # [s] the person's update period (100 Hz: slow next to a hand)


class SimWorld:
    """The fakes and the simulated person (see the module docstring).

    cfg: the daemon's configuration (addresses, channels, geometry); log_dir: where
    :meth:`close` writes the fakes' command logs (``ur_commands.jsonl``,
    ``drive_commands.jsonl``), or None.
    """

    def __init__(self, cfg: Config, log_dir: Path | None = None):
        if cfg.base.transport != "canopen":
            raise MmctlError("the simulated robot's base is CANopen drives: base.transport "
                             f"must be 'canopen', not {cfg.base.transport!r}")
        self.cfg = cfg
        self.log_dir = log_dir
        #: the handle button when no UR digital input is configured (daemon.switch_input -1)
        self.button = False
        self._button_input = cfg.daemon.switch_input
        self._button_sent = False
        #: the enabling switch on the handle (``enabling.inputs``): the person's hand
        #: holds it unless released (``mmctl sim enabling --release``)
        self.enabling_held = True
        self.speed_slider = 1.0
        self.can_server: SocketcandServer | None = None
        q0 = cfg.robot.q_init[:6] if cfg.robot.q_init is not None else cfg.robot.q_des
        self.q_init = np.asarray(q0, dtype=float)
        self._ur: FakeURController | None = None
        self._drives: FakeDrives | None = None
        self._sensor: FakeFtCanSensor | FakeRdtServer | None = None
        self.error: BaseException | None = None
        self.human_on = False
        self.push: Vec | None = None
        self._push_until = math.inf
        self._faults: set[str] = set()
        self._events: dict[str, float] = {}  # event fault -> time.monotonic() injected
        self._wrench = np.zeros(6)
        self._last_force = np.zeros(3)
        self._handle = np.zeros(3)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._human: SimulatedHuman | None = None
        self._request_was: str | None = None
        self._press_until = 0.0
        self._hold_until = 0.0
        self._update_lock = threading.Lock()
        self.updates = 0
        #: push steps: each set_push/end of push is a new step number; the sensor's first
        #: sample that carries it is stamped (CLOCK_MONOTONIC) in ``step_samples``
        self._step = 0
        self._wrench_step = 0
        self._sampled_step = 0
        self.step_samples: list[tuple[int, float]] = []

    @property
    def ur(self) -> FakeURController:
        """The fake UR controller (after :meth:`start`)."""
        if self._ur is None:
            raise MmctlError("the simulated robot is not started")
        return self._ur

    @property
    def drives(self) -> FakeDrives:
        """The fake CiA 402 drives (after :meth:`start`)."""
        if self._drives is None:
            raise MmctlError("the simulated robot is not started")
        return self._drives

    @property
    def sensor(self) -> FakeFtCanSensor | FakeRdtServer:
        """The fake force/torque sensor (after :meth:`start`)."""
        if self._sensor is None:
            raise MmctlError("the simulated robot is not started")
        return self._sensor

    # -- lifecycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Start the fakes and the person's thread (the person is idle until
        :meth:`start_human`; the sensor already measures the handle's weight)."""
        from mmctl.model.robot import RobotModel, sensor_rotation
        from mmctl.sim.fake_drives import FakeDrives
        from mmctl.sim.fake_ur import FakeURController

        cfg = self.cfg
        self.model = RobotModel(cfg.robot)
        self._r_flange_sensor = sensor_rotation(cfg.robot)
        self._handle_sensor = HandleSensor(cfg)
        self._ur = FakeURController(cfg.arm.host, q_init=self.q_init).start()
        self._apply_enabling()
        self._drives = FakeDrives(cfg).start()
        self._update()  # the first wrench before the sensor answers anything
        if cfg.sensor.transport == "can":
            from mmctl.sim.fake_ft_can import FakeFtCanSensor

            self._sensor = FakeFtCanSensor(self, channel=cfg.sensor.can.channel,
                                          base_id=cfg.sensor.can.base_id).start()
        else:
            from mmctl.sim.fake_rdt import FakeRdtServer

            r = cfg.sensor.rdt
            self._sensor = FakeRdtServer(self, host=r.host, port=r.port,
                                        counts_per_force=r.counts_per_force,
                                        counts_per_torque=r.counts_per_torque).start()
        served = self._served_channels()
        if served:
            from mmctl.sim.socketcand import SocketcandServer

            self.can_server = SocketcandServer(cfg.sim.host, cfg.sim.can_port,
                                               channels=served).start()
        self._thread = threading.Thread(target=self._run, name="mmctl-sim-human", daemon=True)
        self._thread.start()
        log.info("sim_started", arm_host=cfg.arm.host, sensor=cfg.sensor.transport,
                 base_channel=cfg.base.canopen.channel, human=cfg.sim.human,
                 socketcand=None if not served else f"{cfg.sim.host}:{cfg.sim.can_port}",
                 channels=served)

    def _served_channels(self) -> list[str]:
        """The virtual channels the daemon reaches through socketcand."""
        return [link.channel for _key, link in self.cfg.can_links()
                if link.interface == "socketcand"]

    def start_human(self) -> None:
        """Let the simulated person start the task (if ``sim.human``)."""
        if self.cfg.sim.human:
            self.human_on = True

    def hold(self, seconds: float) -> None:
        """The person (or push) lets go of the handle for ``seconds`` (a tare)."""
        if not (math.isfinite(seconds) and 0.0 <= seconds <= 60.0):
            raise MmctlError(f"hold needs 0..60 s, got {seconds!r}")
        with self._lock:
            self._hold_until = time.monotonic() + seconds
        self._update()  # the hand is off before the reply: the daemon tares next

    def close(self) -> None:
        """Stop the person and the fakes; write the command logs (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        if self.log_dir is not None and self._ur is not None:
            self._write_logs(self.log_dir)
        for name in ("can_server", "_sensor", "_drives", "_ur"):
            fake = getattr(self, name)
            if fake is None:
                continue
            try:
                fake.stop()
            except Exception as exc:  # noqa: BLE001 -- report, keep closing the others
                log.error("sim_fake_stop_failed", fake=name.lstrip("_"), error=repr(exc))
            setattr(self, name, None)

    # -- what the fake sensor measures (WrenchSource) -------------------------------------
    def wrench(self, t: float) -> Vec:
        """The sensor-frame wrench (6,) [N, N m] right now (``t`` unused: the person's
        thread keeps it current).  Stamps the first sample of each push step."""
        wrench, step = self._wrench, self._wrench_step
        if step != self._sampled_step:
            self._sampled_step = step
            self.step_samples.append((step, time.monotonic()))
            del self.step_samples[:-1000]
        return wrench.copy()

    # -- the person's thread ------------------------------------------------------------
    def _run(self) -> None:
        try:
            next_t = time.monotonic()
            while not self._stop.is_set():
                self._update()
                next_t += _HUMAN_PERIOD
                delay = next_t - time.monotonic()
                if delay > 0:
                    self._stop.wait(delay)
                else:
                    next_t = time.monotonic()
        except Exception as exc:
            self.error = exc
            log.exception("sim_human_failed", error=repr(exc))

    def _observe(self) -> tuple[Vec, Vec, Vec, Vec, Vec, Vec]:
        """True q (9,), qd (9,), handle position and velocity in the world [m, m/s], the
        tool's and the sensor's orientation in the base frame (3, 3) (the tool frame has
        the flange's axes, the sensor's are turned by ``robot.sensor_rotation``)."""
        arm = self.ur.state()
        (x, y, yaw), twist = self.drives.world_state()  # slip included: where it is
        q = np.concatenate((arm.q, [x, y, yaw]))
        qd = np.concatenate((arm.qd, twist))
        kin = self.model.update(q, inertia=False)
        v_w = base_to_world(kin.J[:3] @ qd, yaw)
        return q, qd, kin.p, v_w, kin.R_base, kin.R_base @ self._r_flange_sensor

    def _human_force(self, t: float, q: Vec, p: Vec, v: Vec) -> Vec:
        from mmctl.sim.human import HandleObservation

        if self._human is None:
            self._human = self._make_human(q)
        act = self._human.update(HandleObservation(t, p, v, q[6:9]))
        if act.switch_request is not None and act.switch_request != self._request_was:
            self._request_was = act.switch_request
            self._press_until = t + 0.1  # a 100 ms press of the handle button
        return np.asarray(act.force, dtype=float)

    def _make_human(self, q: Vec) -> SimulatedHuman:
        from mmctl.sim.human import STUDY_HOLES, SimulatedHuman, peg_in_hole_task
        from mmctl.study.users import draw_user

        kin = self.model.update(q, inertia=False)
        mount = self.cfg.robot.arm_mount
        task = peg_in_hole_task(kin.p, rot_z(q[8]) @ kin.R_base[:, 2], float(q[8]), STUDY_HOLES,
                                arm_mount_xy=(float(mount[0]), float(mount[1])))
        return SimulatedHuman(draw_user(self.cfg.sim.human_seed, 0), task, loop=True)

    def _update(self) -> None:
        with self._update_lock:  # the person's thread, and set_push/hold at once
            self._update_locked()

    def _update_locked(self) -> None:
        t = time.monotonic()
        q, _qd, p, v, r_bt, r_bs = self._observe()
        force = np.zeros(3)
        with self._lock:
            push = self.push if t < self._push_until else None
            holding = t < self._hold_until
            faults = set(self._faults)
            step = self._step
        if holding:
            pass  # hands off the handle: the daemon tares
        elif push is not None:
            force = push.copy()
        elif self.human_on:
            force = self._human_force(t, q, p, v)
        if "wrench_over_limit" in faults:  # along the tool axis: above the force limit,
            force = 200.0 * base_to_world(r_bt[:, 2], q[8])  # (no torque: no saturation)
        self._press(t < self._press_until)
        self._wrench = self._handle_sensor.measure(force, float(q[8]), r_bs)
        self._wrench_step = step
        self._last_force = force
        self._handle = p
        self.updates += 1

    def _press(self, on: bool) -> None:
        """The handle button: the fake UR's digital input (changes only), or ``button``."""
        self.button = on
        if self._button_input >= 0 and on != self._button_sent and self._ur is not None:
            self._button_sent = on
            try:
                self.ur.set_digital_input(self._button_input, on)
            except MmctlError as exc:  # the controller is down (a fault test): no button
                log.warning("sim_button_failed", error=str(exc))

    def _apply_enabling(self) -> None:
        """The enabling switch's contacts on the fake UR's inputs: each reads its held
        level while held (``enabling.active_low``), the other level released; the
        ``enabling_contact`` fault keeps the second contact at its released level."""
        e = self.cfg.enabling
        if not e.inputs:
            return
        with self._lock:
            held, broken = self.enabling_held, "enabling_contact" in self._faults
        levels = {index: (held and not (broken and k == len(e.inputs) - 1)) != e.active_low
                  for k, index in enumerate(e.inputs)}
        try:  # in one request: a dual-channel switch's contacts change together (two
            # requests to a starved controller were 58 ms apart: a discrepancy fault)
            self.ur.set_digital_inputs(levels)
        except MmctlError as exc:  # the controller is down (a fault test)
            log.warning("sim_enabling_failed", error=str(exc))

    # -- what the simulation's control socket asks (mmctl.sim.service) ------------------
    def set_enabling(self, held: bool) -> None:
        """The person holds (True) or releases (False) the enabling switch."""
        if not self.cfg.enabling.inputs:
            raise MmctlError("no enabling switch is configured (enabling.inputs is empty)")
        with self._lock:
            self.enabling_held = bool(held)
        self._apply_enabling()
        log.info("sim_enabling", held=bool(held))

    def set_speed_slider(self, fraction: float) -> None:
        """The pendant's speed slider (0..1): the fake UR runs speedJ that much slower."""
        self.ur.set_speed_slider(fraction)
        with self._lock:
            self.speed_slider = float(fraction)
        log.info("sim_speed_slider", fraction=fraction)

    def press(self) -> None:
        """Press the handle button for 100 ms."""
        self._press_until = time.monotonic() + 0.1

    def set_push(self, force: Any, duration: float | None = None) -> None:
        """A constant world-frame push [N] instead of the person (None ends it); in the
        sensor's next sample (a new step: :attr:`step_samples`)."""
        if force is not None:
            try:
                f = np.asarray(force, dtype=float).reshape(-1)
            except (TypeError, ValueError):
                f = np.zeros(0)
            if f.shape != (3,) or not np.all(np.isfinite(f)):
                raise MmctlError(f"push must be 3 finite numbers [N], got {force!r}")
            if duration is not None and not (isinstance(duration, (int, float))
                                             and math.isfinite(duration) and duration > 0):
                raise MmctlError(f"push duration must be a number of seconds > 0, got {duration!r}")
        with self._lock:
            self._step += 1
            if force is None:
                self.push = None
            else:
                self.push = f
                self._push_until = (math.inf if duration is None
                                    else time.monotonic() + float(duration))
        self._update()

    def inject(self, fault: str, on: bool = True) -> None:
        """Switch one of :data:`FAULTS` on or off in the fakes."""
        if fault not in FAULTS:
            raise MmctlError(f"unknown sim fault {fault!r}; known: {', '.join(FAULTS)}")
        if fault == "enabling_contact" and len(self.cfg.enabling.inputs) < 2:
            raise MmctlError("the enabling_contact fault needs a two-contact enabling switch "
                             "(enabling.inputs with 2 inputs)")
        from mmctl.sim.fake_ft_can import STATUS_BUS_ERROR, STATUS_SATURATION

        nid = self.cfg.base.canopen.node_ids[0]
        if fault == "sensor_silent":
            self.sensor.silent = on
        elif fault == "sensor_status":
            self.sensor.status = STATUS_BUS_ERROR if on else 0
        elif fault == "sensor_saturation":
            self.sensor.status = STATUS_SATURATION if on else 0
        elif fault == "arm_protective_stop":
            self.ur.set_protective_stop(on)
        elif fault == "arm_emergency_stop":
            self.ur.set_emergency_stop(on)
        elif fault == "arm_not_playing":
            if on:
                self.ur.stop_program()
        elif fault == "arm_frozen":
            self.ur.freeze_stream(on)
        elif fault == "arm_disconnected":
            if on:
                self.ur.kill()
            else:
                self.ur.restart()
                self._apply_enabling()  # a new controller process: its inputs start at 0
        elif fault == "drive_fault":
            if on:
                self.drives.inject_fault(nid)
        elif fault == "drive_silent":
            if on:
                self.drives.inject_silence(nid)
            else:
                self.drives.resume(nid)
        elif fault == "drive_reboot":
            if on:
                self.drives.reboot(nid)
        elif fault == "sensor_garbage":
            self.sensor.garbage = on
        elif fault in ("sensor_unplugged", "base_unplugged"):
            if self.can_server is None:
                raise MmctlError(f"the {fault} fault needs the CAN links served by socketcand "
                                 "(sensor.can / base.canopen interface: socketcand)")
            link = self.cfg.sensor.can if fault == "sensor_unplugged" else self.cfg.base.canopen
            self.can_server.unplug(link.channel, on)
        with self._lock:
            if fault in _EVENTS:
                if on:  # an event: nothing stays on, but its effect may (active_faults)
                    self._events[fault] = time.monotonic()
            elif on:
                self._faults.add(fault)
            else:
                self._faults.discard(fault)
        if fault == "enabling_contact":
            self._apply_enabling()
        log.info("sim_fault", fault=fault, on=on)

    def active_faults(self) -> list[str]:
        """The injected faults in effect now: the states switched on, and the events
        whose effect holds (drive_fault: the drive still in FAULT, or its fault
        reaction; arm_not_playing: the UR's program not running again yet;
        drive_reboot: for EVENT_LISTED_S after it)."""
        with self._lock:
            active = set(self._faults)
            events = dict(self._events)
        now = time.monotonic()
        for name, when in events.items():
            if name == "drive_fault":
                nid = self.cfg.base.canopen.node_ids[0]
                still = any(d.address == nid and "FAULT" in d.state
                            for d in self.drives.states())
            elif name == "arm_not_playing":
                still = self.ur.alive and self.ur.state().runtime_state != 2  # PLAYING
            else:
                still = now - when < EVENT_LISTED_S
            if still:
                active.add(name)
            elif now - when >= EVENT_LISTED_S:
                with self._lock:
                    if self._events.get(name) == when:
                        del self._events[name]
        return sorted(active)

    def status(self) -> dict[str, Any]:
        """For ``mmctl status``: the person, the push, the injected faults in effect
        (:meth:`active_faults`), truth."""
        return {
            "human": self.human_on,
            "push": None if self.push is None else self.push.tolist(),
            "faults": self.active_faults(),
            # the handle where the arm and the base are right now (the person's last
            # update may be a while ago on a busy machine)
            "handle_world": [round(float(x), 5) for x in self._handle_truth()],
            "hand_force": [round(float(x), 3) for x in self._last_force],
            "button": self.button,
            "speed_slider": self.speed_slider,
            "enabling": None if not self.cfg.enabling.inputs else (
                "held" if self.enabling_held else "released"),
            "holding": time.monotonic() < self._hold_until,
            "socketcand": None if self.can_server is None else {
                "address": "{}:{}".format(*self.can_server.address),
                "clients": self.can_server.clients()},
            "ur_pid": None if self._ur is None else self._ur.pid,
            # the fake controller's joints as its process publishes them right now
            # (shared memory: true also while the daemon's own threads were stopped)
            **self._arm_truth(),
            **self._base_truth(),
            "updates": self.updates,
            "error": None if self.error is None else repr(self.error),
        }

    def _handle_truth(self) -> Vec:
        if self._ur is None or self._drives is None:
            return self._handle
        with self._update_lock:  # the model's buffers are the person's thread's too
            return self._observe()[2]

    def _arm_truth(self) -> dict[str, Any]:
        if self._ur is None:
            return {}
        arm = self.ur.state()
        return {"arm_q": [round(float(x), 6) for x in arm.q],
                "arm_qd": [round(float(x), 6) for x in arm.qd],
                "arm_time": arm.controller_time}

    def _base_truth(self) -> dict[str, Any]:
        if self._drives is None:
            return {}
        return {"base_pose": [round(float(x), 6) for x in self.drives.world_state()[0]],
                "wheel_velocities": [round(float(x), 4) for x in self.drives.wheel_velocities()]}

    def _write_logs(self, d: Path) -> None:
        d.mkdir(parents=True, exist_ok=True)
        try:
            entries = self.ur.commands()
        except MmctlError as exc:
            log.warning("sim_ur_log_unavailable", error=str(exc))
            entries = []
        with (d / "ur_commands.jsonl").open("w") as f:
            for e in entries:
                row = {k: (v.value if hasattr(v, "value") else v) for k, v in e._asdict().items()}
                f.write(json.dumps(row) + "\n")
        with (d / "drive_commands.jsonl").open("w") as f:
            for nid in self.cfg.base.canopen.node_ids:
                for t, counts in self.drives.command_log(nid):
                    f.write(json.dumps({"node_id": nid, "t": t, "counts": counts}) + "\n")
