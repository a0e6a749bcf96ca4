"""Issue 17 point 5 at the daemon level: the real RDT transport next to the fake Net F/T
(loopback UDP), the arm and the base scripted as in ``test_fault_matrix.py``, the daemon
stepped by hand with ``Daemon.step_once`` on the real clock (the RDT samples carry real
time stamps).

The sensor reboots while the robot is armed: the daemon stops it with ``sensor_stale``
(one fault event); enabling is refused while the sensor is silent; the transport sends
its start request again until the rebooted sensor streams, and the samples flow again
(no condition in the cycles after it); the fault stays latched until the operator
enables, which is then accepted.

The staleness timeout is 1 s and the sensor is down for 1.5 s: the silence always
exceeds the timeout, and a loaded machine cannot starve the fake's thread for 1 s, so
no other fault can come in.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from structlog.testing import capture_logs

from mmctl.config import Config, config_from_dict
from mmctl.errors import FaultCause
from mmctl.model.robot import RobotModel
from mmctl.runtime.safety import EnableRefused, SafetyState
from mmctl.sim.fake_rdt import FakeRdtServer
from mmctl.sim.wrench_source import ConstantWrench
from mmctl.transports.sensor.rdt import RdtForceSensor
from test_fault_matrix import Clock, Recorder, Rig, ScriptedArm, ScriptedBase, base_config

WAIT = 30.0  # [s] bound of every wait for an event on a loaded machine
STALE = 1.0  # [s] sensor.wrench.stale_timeout
DOWN = 1.5  # [s] the sensor boots this long: longer than STALE


class RealClock(Clock):
    """The monotonic clock: the control core compares the RDT samples' time stamps
    with it (the scripted arm and base stamp theirs with it too)."""

    def __call__(self) -> float:
        return time.monotonic()


class RdtRig(Rig):
    """:class:`Rig` with the real RDT transport as the sensor, on the real clock."""

    def __init__(self, cfg: Config, model: RobotModel, sensor: RdtForceSensor):
        self.cfg = cfg
        self.model = model
        self.clock = RealClock()
        self.rec = Recorder()
        q = np.array(cfg.robot.q_des[:6], dtype=float)
        self.arm = ScriptedArm(self.rec, self.clock, q, cfg.arm.stale_cycles)
        self.sensor = sensor  # type: ignore[assignment]
        self.base = ScriptedBase(self.rec, self.clock, cfg)
        self.healthy = 0  # cycles in a row without a condition (see healthy_for)
        self.daemon = self.start_daemon()

    def rest_wrench(self) -> Any:
        """(6,) what the sensor reads with nobody at the handle, at the held pose."""
        q = np.array(self.cfg.robot.q_des[:6], dtype=float)
        r = self.model.fk_base(np.concatenate((q, np.zeros(3))), "sensor").rotation
        return self._core().wrench.gravity_wrench(r)

    def step_until(self, what: str, done: Any) -> None:
        """Step (a millisecond apart, so records arrive) until ``done()``."""
        deadline = time.monotonic() + WAIT
        while not done():
            assert time.monotonic() < deadline, (
                f"not {what} within {WAIT} s: {self.daemon.safety.as_dict()}, "
                f"conditions {self.daemon.last_conditions}, {self.sensor.stats()}")
            self.step()
            time.sleep(0.001)

    def healthy_for(self, cycles: int) -> bool:
        """The last ``cycles`` cycles in a row without any condition (counted by the
        calls: call once per step)."""
        self.healthy = 0 if self.daemon.last_conditions else self.healthy + 1
        return self.healthy >= cycles


@pytest.fixture
def fake() -> Iterator[FakeRdtServer]:
    with FakeRdtServer(ConstantWrench(np.zeros(6)), rate_hz=500.0) as f:
        yield f


def test_a_rebooted_rdt_sensor_faults_recovers_and_stays_latched_until_enable(
        fake: FakeRdtServer) -> None:
    cfg = config_from_dict(base_config({
        "sensor": {"transport": "rdt", "wrench": {"stale_timeout": STALE},
                   "rdt": {"restart_after": 0.05, "connect_timeout": WAIT}},
    }))
    host, port = fake.address
    sensor = RdtForceSensor(dataclasses.replace(cfg.sensor.rdt, host=host, port=port),
                            stale_timeout=cfg.sensor.wrench.stale_timeout)
    rig = RdtRig(cfg, RobotModel(cfg.robot), sensor)
    d = rig.daemon
    try:
        fake.source = ConstantWrench(rig.rest_wrench())  # nobody at the handle
        rig.step_until("healthy", lambda: rig.healthy_for(3))
        rig.enable()
        assert d.safety.armed
        # a stream as long as a sensor's (hundreds of records): the rebooted one's first
        # records are then behind it, whichever of them the client sees first (a START
        # re-sent while the first new record is in flight may cost that record)
        rig.step_until("a long stream", lambda: sensor.stats().received > 300)
        starts = fake.starts

        with capture_logs() as logs:
            fake.reboot(down_for=DOWN)
            rig.step_until("stopped", lambda: rig.state is SafetyState.FAULT)
            assert d.safety.latched is FaultCause.SENSOR_STALE, d.safety.as_dict()
            assert FaultCause.SENSOR_STALE in d.last_conditions
            with pytest.raises(EnableRefused, match="sensor_stale"):
                rig.enable()  # the last cycle found it: refused while the sensor is silent

            # the transport re-starts the stream; the daemon keeps the fault latched
            rig.step_until("streaming again", lambda: rig.healthy_for(10))
            assert rig.state is SafetyState.FAULT
            assert d.safety.latched is FaultCause.SENSOR_STALE
        faults = [e for e in logs if e["event"] == "fault"]
        assert [e["cause"] for e in faults] == ["sensor_stale"], faults
        stats = sensor.stats()
        assert fake.starts > starts and stats.restarts >= fake.starts - starts
        assert stats.resets == 1
        assert [e["event"] for e in logs if e["event"].startswith("rdt_stream")] == [
            "rdt_stream_recovered"]

        rig.enable()  # the operator's enable clears it
        assert d.safety.armed and d.safety.latched is None
        rig.step_until("healthy when armed", lambda: rig.healthy_for(3))
        assert d.safety.armed
    finally:
        d.shutdown()
