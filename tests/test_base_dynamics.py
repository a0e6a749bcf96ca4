"""The simulated base's departure from its commands (issue 19, item 2): command latency,
the drives' velocity loop and mecanum slip (`mmctl.sim.wheels.BaseDynamics`, the
``sim.base_*`` keys), in the wheels the fakes and the study share, and what the study's
cycle sees (the odometry) against what the world sees (the actual motion)."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from mmctl.config import config_from_dict, default_config
from mmctl.config.base import MecanumConfig
from mmctl.control.mecanum import odometry_matrix, twist_to_wheels
from mmctl.errors import ConfigError
from mmctl.sim.plant import Plant
from mmctl.sim.wheels import STANDSTILL, SUBSTEP, BaseDynamics, WheelPlant

GEOM = MecanumConfig()
ACC = 23.6  # [rad/s^2] about the drives' profile acceleration
IDEAL = {"base_latency": 0.0, "base_velocity_tau": 0.0, "base_slip_longitudinal": 0.0,
         "base_slip_lateral": 0.0}


def wheels(dyn: BaseDynamics, accel: float = ACC, watchdog: float | None = None) -> WheelPlant:
    w = WheelPlant(GEOM, accel, watchdog, t0=0.0, dynamics=dyn)
    for i in range(4):
        w.track(i, 0.0)
    return w


# -- the old plant, frozen: what zero settings must reproduce bit for bit ---------------

class _OldWheelPlant:
    """sim/wheels.py's WheelPlant before issue 19 (commit acdf5d7), unchanged."""

    def __init__(self, geom: MecanumConfig, accel: float, watchdog: float | None,
                 t0: float) -> None:
        self._p = odometry_matrix(geom)
        self.theta = np.zeros(4)
        self.omega = np.zeros(4)
        self.target = np.zeros(4)
        self.enabled = np.zeros(4, dtype=bool)
        self.accel = np.full(4, float(accel))
        self.decel = np.full(4, float(accel))
        self.stop_decel = np.full(4, math.nan)
        self.coasting = np.zeros(4, dtype=bool)
        self.last_command = np.full(4, -math.inf)
        self.watchdog = watchdog
        self.pose = np.zeros(3)
        self.t = t0
        self.power_offs: list[tuple[float, int, float]] = []

    def advance(self, now: float) -> None:
        while self.t < now:
            h = min(SUBSTEP, now - self.t)
            if self.watchdog is not None:
                expiry = self.last_command + self.watchdog
                pending = expiry[(expiry > self.t) & (expiry < self.t + h)]
                if pending.size:
                    h = max(float(pending.min()) - self.t, 1e-9)
                live = self.enabled & (self.t < expiry)
            else:
                live = self.enabled
            tgt = np.where(live, self.target, 0.0)
            dv = tgt - self.omega
            slowing = dv * self.omega < 0.0
            rate = np.where(slowing, self.decel, self.accel)
            ramping = ~np.isnan(self.stop_decel)
            if ramping.any():
                rate = np.where(ramping, self.stop_decel, rate)
                dv = np.where(ramping, -self.omega, dv)
            rate = rate * h
            new = self.omega + np.clip(dv, -rate, rate)
            if self.coasting.any():
                mu_tau = 1.0 * 1.0
                free = np.maximum((np.abs(self.omega) + mu_tau) * math.exp(-h / 1.0) - mu_tau,
                                  0.0)
                new = np.where(self.coasting, np.sign(self.omega) * free, new)
            dtheta = 0.5 * (self.omega + new) * h
            self.omega = new
            self.theta += dtheta
            dx, dy, dyaw = self._p @ dtheta
            mid = self.pose[2] + 0.5 * dyaw
            c, s = math.cos(mid), math.sin(mid)
            self.pose += (c * dx - s * dy, s * dx + c * dy, dyaw)
            self.t += h

    def command(self, wheel: int, omega: float, now: float) -> None:
        self.advance(now)
        self.target[wheel] = omega
        self.last_command[wheel] = now

    def set_enabled(self, wheel: int, on: bool, now: float) -> None:
        self.advance(now)
        self.enabled[wheel] = on
        self.stop_decel[wheel] = math.nan
        self.coasting[wheel] = False

    def track(self, wheel: int, now: float) -> None:
        self.set_enabled(wheel, True, now)

    def ramp_to_rest(self, wheel: int, decel: float, now: float) -> None:
        self.advance(now)
        self.enabled[wheel] = False
        self.stop_decel[wheel] = max(float(decel), 1e-9)
        self.coasting[wheel] = False

    def power_off(self, wheel: int, now: float) -> None:
        self.advance(now)
        if not self.coasting[wheel]:
            self.power_offs.append((now, wheel, float(self.omega[wheel])))
        self.enabled[wheel] = False
        self.stop_decel[wheel] = math.nan
        self.coasting[wheel] = True


@pytest.mark.parametrize("watchdog", [None, 0.2])
def test_zero_settings_reproduce_the_old_wheels_bit_for_bit(watchdog: float | None) -> None:
    """Every mode (tracking, watchdog, ramp to rest, coasting, the bridge's switch) at
    random times: theta, omega, pose and the power-off log are identical."""
    rng = random.Random(7)
    new = WheelPlant(GEOM, ACC, watchdog, t0=0.0, dynamics=BaseDynamics())
    old = _OldWheelPlant(GEOM, ACC, watchdog, t0=0.0)
    now = 0.0
    for _ in range(600):
        now += rng.choice([0.0003, 0.001, 0.002, 0.0071, 0.05, 0.3])
        wheel, what, value = rng.randrange(4), rng.random(), rng.uniform(-20.0, 20.0)
        for p in (new, old):
            if what < 0.55:
                p.command(wheel, value, now)
            elif what < 0.7:
                p.track(wheel, now)
            elif what < 0.8:
                p.ramp_to_rest(wheel, 10.0, now)
            elif what < 0.9:
                p.power_off(wheel, now)
            else:
                p.set_enabled(wheel, False, now)
        old.advance(now)
        new.advance(now)
        assert np.array_equal(new.theta, old.theta)
        assert np.array_equal(new.omega, old.omega)
        assert np.array_equal(new.pose, old.pose)
        assert np.array_equal(new.odometry_pose, old.pose)
    assert [tuple(x) for x in new.power_offs] == old.power_offs
    assert len(old.power_offs) > 10


def test_zero_settings_reproduce_the_old_study_plant_bit_for_bit() -> None:
    """The study's Plant with ``sim.base_*`` all 0 against the old Plant's base: the
    twist through the transport's WheelCommand, targets set, wheels advanced."""
    from mmctl.transports.base.kinematics import WheelCommand

    cfg = config_from_dict({"sim": IDEAL})
    q0 = np.array([0.0, -1.2, 1.5, -0.3, 1.57, 0.0, 0.4, -0.2, 0.3])
    plant = Plant(cfg, q0)
    acc = cfg.limits.base_linear_acceleration / GEOM.wheel_radius
    old = _OldWheelPlant(GEOM, acc, None, t0=0.0)
    old.pose[:] = q0[6:]
    for i in range(4):
        old.track(i, 0.0)
    cmd = WheelCommand(GEOM, cfg.limits.wheel_velocity)
    p = odometry_matrix(GEOM)
    rng = np.random.default_rng(3)
    t = 0.0
    for k in range(1500):
        twist = rng.uniform(-0.6, 0.6, 3) if k % 150 < 120 else np.zeros(3)
        s = plant.step(np.zeros(6), twist, 0.002)
        w, _ = cmd(*(float(x) for x in twist))
        old.target[:] = w
        t += 0.002
        old.advance(t)
        assert np.array_equal(s.q[6:], old.pose)
        assert np.array_equal(s.qd[6:], p @ old.omega)
        odo = plant.odometry()
        assert np.array_equal(odo.pose, s.q[6:]) and np.array_equal(odo.twist, s.qd[6:])


# -- 1. command latency ---------------------------------------------------------------------

@pytest.mark.parametrize("latency", [0.0005, 0.002, 0.0137])
def test_latency_delays_the_wheels_by_the_dead_time(latency: float) -> None:
    """A target sent at t0 leaves the wheel at rest until t0 + latency, then ramps at
    the drive's acceleration from there."""
    w = wheels(BaseDynamics(latency=latency))
    t0 = 0.1
    w.command(0, 10.0, t0)
    for dt in np.linspace(0.0, 0.05, 101):
        w.advance(t0 + dt)
        want = min(max(dt - latency, 0.0) * ACC, 10.0)
        assert w.omega[0] == pytest.approx(want, abs=1e-9), dt
    assert w.last_command[0] == t0  # the watchdog counts from the sending


def test_latency_keeps_the_order_of_commands_and_the_plant_applies_it() -> None:
    """Commands in flight act in order, each after the dead time; the study's Plant
    sends its wheel targets through the same queue."""
    w = wheels(BaseDynamics(latency=0.004), accel=1e9)  # the demand jumps: see the targets
    for k, target in enumerate([1.0, 2.0, 3.0]):
        w.command(1, target, 0.001 * k)
    seen = []
    for k in range(12):
        w.advance(0.001 * k + 0.0005)
        seen.append(float(w.omega[1]))
    assert seen[:4] == [0.0] * 4 and seen[4:7] == [1.0, 2.0, 3.0] and seen[7:] == [3.0] * 5
    cfg = config_from_dict({"sim": {**IDEAL, "base_latency": 0.006}})
    plant = Plant(cfg, np.zeros(9))
    speeds = [float(plant.step(np.zeros(6), [0.3, 0.0, 0.0], 0.002).qd[6]) for _ in range(6)]
    assert speeds[:3] == [0.0] * 3 and speeds[3] > 0.0  # 3 steps of 2 ms: 6 ms


# -- 2. the drives' velocity loop -------------------------------------------------------------

@pytest.mark.parametrize("tau", [0.005, 0.01, 0.04])
def test_the_velocity_loops_step_response_has_the_configured_time_constant(tau: float) -> None:
    """With a demand that jumps (a huge profile acceleration), the wheel speed is a first
    order step response: 63.2 % of the step after tau (the demand's jump takes the
    first integration step, 0.1 ms here: half of it is delay), and the exact solution
    after it."""
    w = wheels(BaseDynamics(velocity_tau=tau), accel=1e9)
    w.command(2, 10.0, 0.0)
    h = 0.0001
    crossed = None
    for k in range(1, round(5 * tau / h)):
        t = k * h
        w.advance(t)
        if crossed is None and w.omega[2] >= 10.0 * (1 - math.exp(-1)):
            crossed = t
        # after the demand's ramp-in over [0, h]: the first-order solution
        want = 10.0 * (1 - tau / h * math.expm1(h / tau) * math.exp(-t / tau))
        assert w.omega[2] == pytest.approx(want, rel=1e-9, abs=1e-12)
    assert crossed is not None and tau <= crossed <= tau + 1.5 * h  # at tau + h/2
    assert w.demand[2] == 10.0


def test_the_velocity_loop_trails_a_ramp_by_acceleration_times_tau() -> None:
    tau = 0.02
    w = wheels(BaseDynamics(velocity_tau=tau))
    w.command(0, 20.0, 0.0)
    w.advance(0.5)  # ramping for 0.85 s at 23.6 rad/s^2: 25 tau in, the lag has settled
    assert float(w.demand[0] - w.omega[0]) == pytest.approx(ACC * tau, rel=1e-6)


def test_with_a_velocity_loop_a_stopped_wheel_is_exactly_at_rest() -> None:
    """The demand at 0 and the wheel below the standstill window: held at 0 (a fake
    drive's 'at rest' and the tests' `== 0.0` need it); ramp to rest ends within the
    time rest_time() announces."""
    w = wheels(BaseDynamics(velocity_tau=0.01))
    w.command(0, 5.0, 0.0)
    w.command(1, 5.0, 0.0)
    w.advance(1.0)
    w.command(0, 0.0, 1.0)
    w.advance(1.6)
    assert w.omega[0] == 0.0 and w.demand[0] == 0.0
    w.ramp_to_rest(1, 10.0, 1.6)
    rest = w.rest_time(1)
    assert 0.5 < rest < 0.5 + 0.01 * math.log(0.1 / STANDSTILL) + SUBSTEP
    w.advance(1.6 + rest - 0.004)
    assert w.omega[1] != 0.0
    w.advance(1.6 + rest + 2 * SUBSTEP)
    assert w.omega[1] == 0.0


class _CountingPlant(WheelPlant):
    """A WheelPlant that counts its integration steps (two pose updates per step)."""

    steps = 0

    def _integrate(self, pose: list[float], dx: float, dy: float,  # type: ignore[override]
                   dyaw: float) -> None:
        type(self).steps += 1
        WheelPlant._integrate(pose, dx, dy, dyaw)


class _SteppingPlant(WheelPlant):
    """A WheelPlant that never skips: every 1-ms step taken."""

    def _at_rest(self) -> bool:
        return False


def test_a_plant_at_rest_skips_its_steps_and_one_about_to_move_does_not() -> None:
    """Standing wheels with nothing to track cost no 1-ms steps however long the gap (a
    starved simulation's drives held their lock through such steps for > 10 s); a
    command in flight, a target to track or a wheel still turning are stepped as ever,
    and the skip changes nothing: the same state as stepping through."""
    dyn = BaseDynamics(latency=0.004, velocity_tau=0.01)
    w = _CountingPlant(GEOM, ACC, None, t0=0.0, dynamics=dyn)
    for i in range(4):
        w.track(i, 0.0)
    _CountingPlant.steps = 0
    w.advance(10.0)
    assert _CountingPlant.steps == 0 and w.t == 10.0
    assert not w.omega.any() and not w.pose.any() and not w.theta.any()
    w.command(2, 4.0, 10.0)  # in flight for 4 ms, then tracked
    w.advance(10.5)
    assert 500 <= _CountingPlant.steps // 2 <= 502 and w.omega[2] > 0.0  # (+ the dead time's split)
    w.command(2, 0.0, 10.5)
    w.advance(12.0)  # slowing down, then at rest: stepped until it stands
    assert w.omega[2] == 0.0 and w.demand[2] == 0.0
    ref = _SteppingPlant(GEOM, ACC, None, t0=0.0, dynamics=dyn)  # the same, stepped through
    for i in range(4):
        ref.track(i, 0.0)
    ref.advance(10.0)
    ref.command(2, 4.0, 10.0)
    ref.advance(10.5)
    ref.command(2, 0.0, 10.5)
    ref.advance(12.0)
    n = _CountingPlant.steps
    w.advance(20.0)
    ref.advance(20.0)
    assert _CountingPlant.steps == n  # at rest again: skipped
    for name in ("theta", "omega", "demand", "pose", "odometry_pose"):
        np.testing.assert_array_equal(getattr(w, name), getattr(ref, name), err_msg=name)


# -- 3. mecanum slip -------------------------------------------------------------------------

@pytest.mark.parametrize(("twist", "ratio"), [
    ((0.4, 0.0, 0.0), (0.98, None, None)),
    ((0.0, 0.4, 0.0), (None, 0.93, None)),
])
def test_slip_makes_the_actual_displacement_a_fraction_of_the_odometrys(
    twist: tuple[float, float, float], ratio: tuple[float | None, ...]
) -> None:
    """Straight along x (y): the base covers 1 - slip_longitudinal (1 - slip_lateral) of
    what the wheels' odometry says; the encoders (theta) are those of the ideal base."""
    dyn = BaseDynamics(slip_longitudinal=0.02, slip_lateral=0.07)
    w, ideal = wheels(dyn), wheels(BaseDynamics())
    for p in (w, ideal):
        for i, speed in enumerate(twist_to_wheels(GEOM, np.array(twist))):
            p.command(i, float(speed), 0.0)
        p.advance(2.0)
    assert np.array_equal(w.theta, ideal.theta)
    assert np.array_equal(w.odometry_pose, ideal.pose)
    for axis, r in enumerate(ratio):
        if r is not None:
            assert w.pose[axis] == pytest.approx(r * w.odometry_pose[axis], rel=1e-12)
            assert w.twist()[axis] == pytest.approx(r * w.odometry_twist()[axis], rel=1e-12)
            assert abs(w.pose[axis]) > 0.5


def test_slip_turning_on_the_spot_follows_the_contact_points() -> None:
    """Rotation moves the contact points by ω b along x and ω a along y: the yaw rate
    keeps (k_x b² + k_y a²) / (a² + b²) of the odometry's."""
    dyn = BaseDynamics(slip_longitudinal=0.02, slip_lateral=0.07)
    a, b = GEOM.half_length, GEOM.half_width
    k = (0.98 * b * b + 0.93 * a * a) / (a * a + b * b)
    assert np.allclose(dyn.slip_factors(GEOM), [0.98, 0.93, k])
    w = wheels(dyn)
    for i, speed in enumerate(twist_to_wheels(GEOM, np.array([0.0, 0.0, 0.5]))):
        w.command(i, float(speed), 0.0)
    w.advance(1.0)
    assert w.pose[2] == pytest.approx(k * w.odometry_pose[2], rel=1e-12)
    assert np.abs(w.pose[:2]).max() < 1e-12


def test_the_study_plant_separates_the_world_from_the_odometry() -> None:
    """Plant.state(): where the base is (slip); Plant.odometry(): what the encoders say;
    the study's clock hands the cycle the odometry and the sensor the actual yaw."""
    from mmctl.model import RobotModel
    from mmctl.sim.handle import HandleSensor
    from mmctl.study.runner import _Clock

    cfg = config_from_dict({"sim": {**IDEAL, "base_slip_longitudinal": 0.1,
                                    "base_slip_lateral": 0.2}})
    q0 = np.array([0.0, -1.2, 1.5, -0.3, 1.57, 0.0, 0.0, 0.0, 0.0])
    plant = Plant(cfg, q0)
    for _ in range(500):
        s = plant.step(np.zeros(6), [0.3, 0.2, 0.0], 0.002)
    odo = plant.odometry()
    assert s.q[6] == pytest.approx(0.9 * odo.pose[0], rel=1e-9)
    assert s.q[7] == pytest.approx(0.8 * odo.pose[1], rel=1e-9)
    assert s.qd[6:8] == pytest.approx([0.9 * 0.3, 0.8 * 0.2], rel=1e-9)
    assert odo.twist[:2] == pytest.approx([0.3, 0.2], rel=1e-9)
    clock = _Clock(plant, HandleSensor(cfg), RobotModel(cfg.robot), 0.002)
    r = clock.readings(np.zeros(3), q=s.q, qd=s.qd)
    assert (r.odom.x, r.odom.y) == (odo.pose[0], odo.pose[1])
    assert (r.odom.vx, r.odom.vy) == (odo.twist[0], odo.twist[1])
    assert np.array_equal(r.arm.q, s.q[:6])


# -- 4. configuration -------------------------------------------------------------------------

def test_the_defaults_are_the_documented_values_and_reach_the_plant() -> None:
    cfg = default_config()
    dyn = BaseDynamics.from_config(cfg.sim)
    assert dyn == BaseDynamics(0.002, 0.01, 0.01, 0.03)
    assert Plant(cfg, np.zeros(9)).wheels.dynamics == dyn


@pytest.mark.parametrize(("key", "value"), [
    ("base_latency", -0.001), ("base_latency", 0.2), ("base_velocity_tau", 1.0),
    ("base_slip_longitudinal", 0.6), ("base_slip_lateral", -0.1),
])
def test_out_of_range_settings_name_the_key(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"sim.{key}"):
        config_from_dict({"sim": {key: value}})


def test_bad_dynamics_are_refused() -> None:
    with pytest.raises(ValueError, match="slip"):
        WheelPlant(GEOM, ACC, None, t0=0.0, dynamics=BaseDynamics(slip_lateral=1.0))
    with pytest.raises(ValueError, match="velocity_tau"):
        WheelPlant(GEOM, ACC, None, t0=0.0, dynamics=BaseDynamics(velocity_tau=-1.0))
