"""The base's wheels: four wheels that follow their drives' velocity targets, and the pose
they drive.  Part of the simulated robot's one plant (:mod:`mmctl.sim.plant`): the fake
CiA 402 drives and the fake serial bridge run it in real time, the study in simulated
time; both see the same wheel dynamics.

Between a velocity command and the floor (:class:`BaseDynamics`, the ``sim.base_*``
keys; all zero: the wheels follow their targets exactly, as before issue 19):

1. **command latency**: a target takes effect ``latency`` [s] after it was sent (the
   bus and the drive's cycle);
2. **the drive's velocity loop**: the wheel speed follows the drive's profile (its
   demand, which ramps toward the target at the profile acceleration) through a first
   order lag of time constant ``velocity_tau`` [s];
3. **mecanum slip**: the base moves a fraction ``1 - slip`` of what its wheels' rolling
   says, ``slip_longitudinal`` along the base's x axis, ``slip_lateral`` along y.  The
   wheels' encoders (:attr:`WheelPlant.theta`, :attr:`WheelPlant.omega`) and the
   odometry they give (:attr:`WheelPlant.odometry_pose`) do not see it; the world does
   (:attr:`WheelPlant.pose`, :meth:`WheelPlant.twist`).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.config.base import MecanumConfig
from mmctl.config.runtime import SimConfig
from mmctl.control.mecanum import odometry_matrix

Vec = NDArray[np.float64]
SUBSTEP = 0.001
"""[s] the wheels' integration step."""
#: Coasting wheel (power stage off): viscous time constant [s] and dry friction [rad/s^2].
COAST_TIME_CONSTANT = 1.0
COAST_FRICTION = 1.0
STANDSTILL = 0.01
"""[rad/s] with a velocity loop (``velocity_tau`` > 0): a powered wheel whose demand is
0 and whose speed is below this is at rest (held at exactly 0), as a drive's standstill
window (CiA 402 velocity threshold 0x606F) declares it; 1.3 mm/s at the rim."""


class BaseDynamics(NamedTuple):
    """How the base departs from its wheel commands (module doc).  The zero default is
    the ideal base: targets act at once, wheels follow their demand exactly, no slip.

    latency [s]: command dead time; velocity_tau [s]: the velocity loop's time
    constant; slip_longitudinal, slip_lateral: the fractions (0..1) of the odometry's
    base-frame x and y motion the base does not achieve.
    """

    latency: float = 0.0
    velocity_tau: float = 0.0
    slip_longitudinal: float = 0.0
    slip_lateral: float = 0.0

    @classmethod
    def from_config(cls, sim: SimConfig) -> BaseDynamics:
        """From the ``sim:`` section's ``base_*`` keys."""
        return cls(float(sim.base_latency), float(sim.base_velocity_tau),
                   float(sim.base_slip_longitudinal), float(sim.base_slip_lateral))

    def slip_factors(self, geom: MecanumConfig) -> Vec:
        """(k_x, k_y, k_yaw): the actual base twist is ``k * odometry twist`` (base frame).

        Slip scales each wheel's contact-point velocity by ``k_x = 1 - slip_longitudinal``
        along x and ``k_y = 1 - slip_lateral`` along y; the rigid motion that best fits
        the four scaled contact velocities (least squares, wheels at (±a, ±b)) is
        ``(k_x v_x, k_y v_y, k_yaw ω)`` with ``k_yaw = (k_x b² + k_y a²) / (a² + b²)``:
        turning on the spot, the contact points move along y by ``ω a`` and along x by
        ``ω b``.
        """
        kx = 1.0 - self.slip_longitudinal
        ky = 1.0 - self.slip_lateral
        a, b = geom.half_length, geom.half_width
        kyaw = (kx * b * b + ky * a * a) / (a * a + b * b)
        return np.array([kx, ky, kyaw])


class WheelPlant:
    """Four wheels (FL, FR, BL, BR) and the base pose they drive. Thread-safe.

    Each wheel is in one of three modes:

    * tracking (``enabled``): its drive's demand [rad/s] moves toward its target at
      ``accel`` (speeding up) or ``decel`` (slowing down) [rad/s^2]; with a
      ``watchdog`` [s] (None: none), the target is 0 once the wheel had no command for
      that long;
    * ramping to rest (:meth:`ramp_to_rest`): power stage on, demand toward 0 at the
      given deceleration, then held at 0;
    * coasting (:meth:`power_off`): power stage off, the wheel runs free and slows only
      by friction: ``d|w|/dt = -|w| / COAST_TIME_CONSTANT - COAST_FRICTION`` (a model:
      a free mecanum wheel under the base's weight; at rest after
      ``tau ln(1 + |w0| / (mu tau))``, 1.9 s from 5.4 rad/s); the demand follows the
      wheel (a drive's profile starts from the actual speed when re-enabled).

    The wheel speed :attr:`omega` is the demand :attr:`demand` through the velocity
    loop (``dynamics.velocity_tau``; 0: equal); a target from :meth:`command` reaches
    :attr:`target` ``dynamics.latency`` later.  ``enabled`` False without a mode
    (:meth:`set_enabled`, the serial bridge's switch) ramps to zero at ``decel``.  Every
    switch to coasting is logged in :attr:`power_offs` with the wheel's speed at that
    instant.  Two poses (x, y [m], yaw [rad], world frame): :attr:`odometry_pose`
    integrates the least-squares base twist of the wheel increments (what the encoders
    say), :attr:`pose` the same with the slip factors (where the base is).  Time is the
    caller's clock (``time.monotonic()`` for the fakes, simulated time for the study),
    starting at ``t0`` (default: ``time.monotonic()``); the state advances lazily to
    the time of each call.
    """

    def __init__(self, geom: MecanumConfig, accel: float, watchdog: float | None,
                 t0: float | None = None, dynamics: BaseDynamics | None = None) -> None:
        dyn = BaseDynamics() if dynamics is None else dynamics
        for name, value in dyn._asdict().items():
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"dynamics.{name} must be finite and >= 0, got {value}")
        if dyn.slip_longitudinal >= 1.0 or dyn.slip_lateral >= 1.0:
            raise ValueError(f"slip must be < 1 (the base would not move), got {dyn}")
        self._p = odometry_matrix(geom)
        self.dynamics = dyn
        self._k = dyn.slip_factors(geom)
        self.lock = threading.RLock()
        self.theta = np.zeros(4)
        self.omega = np.zeros(4)
        self.demand = np.zeros(4)
        self.target = np.zeros(4)
        self.enabled = np.zeros(4, dtype=bool)
        self.accel = np.full(4, float(accel))
        self.decel = np.full(4, float(accel))
        self.stop_decel = np.full(4, math.nan)  # ramping to rest at this [rad/s^2]
        self.coasting = np.zeros(4, dtype=bool)
        self.last_command = np.full(4, -math.inf)
        self.watchdog = watchdog
        self.pose = np.zeros(3)
        self.odometry_pose = np.zeros(3)
        self.t = time.monotonic() if t0 is None else t0
        #: commands in flight: (time they act [s], wheel, target [rad/s]), in time order
        self.pending: deque[tuple[float, int, float]] = deque()
        #: (monotonic time [s], wheel, speed [rad/s]) at each switch to coasting
        self.power_offs: deque[tuple[float, int, float]] = deque(maxlen=1000)

    def set_pose(self, x: float, y: float, yaw: float) -> None:
        """Place the base (both poses) at (x, y [m], yaw [rad])."""
        with self.lock:
            self.pose[:] = (x, y, yaw)
            self.odometry_pose[:] = (x, y, yaw)

    def twist(self) -> Vec:
        """The base's actual twist (3,) (v_x, v_y [m/s], ω_z [rad/s], base frame): the
        odometry's (:meth:`odometry_twist`) times the slip factors."""
        with self.lock:
            out: Vec = self._k * (self._p @ self.omega)
            return out

    def odometry_twist(self) -> Vec:
        """The twist (3,) of the wheel speeds (what the encoders say), base frame."""
        with self.lock:
            out: Vec = self._p @ self.omega
            return out

    def advance(self, now: float) -> None:
        """Integrate up to monotonic time ``now`` [s] in steps of at most 1 ms.

        The four wheels are stepped in plain floats (numpy's per-call cost on 4-element
        arrays made a step ~1 ms of CPU on a busy machine: a moving base cost the
        simulation a whole core, and a status request waiting for this lock went
        unanswered for a minute); the arrays are the state between calls."""
        tau = self.dynamics.velocity_tau
        with self.lock:
            if not self.t < now:
                return
            if self._at_rest():
                self.t = now  # nothing moves nor will: no steps to take
                return
            t = self.t
            pending = self.pending
            omega, demand = self.omega.tolist(), self.demand.tolist()
            target, theta = self.target.tolist(), self.theta.tolist()
            enabled, coasting = self.enabled.tolist(), self.coasting.tolist()
            accel, decel = self.accel.tolist(), self.decel.tolist()
            stop_decel = self.stop_decel.tolist()
            wd = self.watchdog
            expiry = None if wd is None else [c + wd for c in self.last_command.tolist()]
            p_odo = self._p
            kx, ky, kw = self._k.tolist()
            pose, odo_pose = self.pose.tolist(), self.odometry_pose.tolist()
            mu_tau = COAST_FRICTION * COAST_TIME_CONSTANT
            lag_h = math.nan  # the step the lag's factors were computed for
            e = g = 0.0
            dth = [0.0] * 4
            while t < now:
                h = min(SUBSTEP, now - t)
                while pending and pending[0][0] <= t:
                    _, wheel, value = pending.popleft()
                    target[wheel] = value
                if pending and pending[0][0] < t + h:
                    h = max(pending[0][0] - t, 1e-9)
                if expiry is not None:
                    due = [x for x in expiry if t < x < t + h]
                    if due:
                        h = max(min(due) - t, 1e-9)
                    live = [on and t < x for on, x in zip(enabled, expiry, strict=True)]
                else:
                    live = enabled
                if tau > 0.0 and h != lag_h:
                    # first-order lag, exact for a demand linear over the step
                    lag_h, e = h, math.exp(-h / tau)
                    g = -tau / h * math.expm1(-h / tau)  # (tau / h)(1 - e), accurately
                free_e = math.exp(-h / COAST_TIME_CONSTANT) if True in coasting else 0.0
                for i in range(4):
                    d0, w0 = demand[i], omega[i]
                    dv = (target[i] if live[i] else 0.0) - d0
                    ramp = stop_decel[i]
                    if not math.isnan(ramp):  # ramping to rest
                        rate, dv = ramp * h, -d0
                    else:
                        rate = (decel[i] if dv * d0 < 0.0 else accel[i]) * h
                    d1 = d0 + min(max(dv, -rate), rate)
                    if tau > 0.0:
                        w1 = d1 + (w0 - d0) * e - (d1 - d0) * g
                        if d1 == 0.0 and abs(w1) < STANDSTILL:
                            w1 = 0.0
                    else:
                        w1 = d1
                    if coasting[i]:
                        free = max((abs(w0) + mu_tau) * free_e - mu_tau, 0.0)
                        w1 = free if w0 > 0.0 else -free if w0 < 0.0 else 0.0
                        d1 = w1
                    dth[i] = 0.5 * (w0 + w1) * h
                    omega[i] = w1
                    demand[i] = w1 if tau == 0.0 else d1
                    theta[i] += dth[i]
                # (numpy's product: its rounding is the odometry's, bit for bit)
                dx, dy, dyaw = (p_odo @ np.array(dth)).tolist()
                self._integrate(odo_pose, dx, dy, dyaw)
                self._integrate(pose, kx * dx, ky * dy, kw * dyaw)
                t += h
            self.t = t
            self.omega[:], self.demand[:], self.target[:] = omega, demand, target
            self.theta[:] = theta
            self.pose[:], self.odometry_pose[:] = pose, odo_pose

    def _at_rest(self) -> bool:
        """Every wheel stands, its demand is 0 and stays 0: no target it tracks (the
        watchdog only ever zeroes one) and no command in flight.  Integrating then
        changes nothing but the time: the drives' clock skips it (an idle simulation,
        e.g. before the master configures them, costs no 1-ms steps; on a busy machine
        those steps, under the drives' lock, had starved their SDO server for > 10 s)."""
        return not (self.pending or self.omega.any() or self.demand.any()
                    or (self.enabled & (self.target != 0.0)).any())

    @staticmethod
    def _integrate(pose: list[float], dx: float, dy: float, dyaw: float) -> None:
        """Add a base-frame displacement (dx, dy [m], dyaw [rad]) to ``pose`` (x, y,
        yaw, world frame), rotated with the mid-step yaw."""
        mid = pose[2] + 0.5 * dyaw
        c, s = math.cos(mid), math.sin(mid)
        pose[0] += c * dx - s * dy
        pose[1] += s * dx + c * dy
        pose[2] += dyaw

    def command(self, wheel: int, omega: float, now: float) -> None:
        """New target [rad/s] for ``wheel`` sent at ``now`` (also feeds its watchdog);
        it acts ``dynamics.latency`` later."""
        with self.lock:
            self.advance(now)
            self.last_command[wheel] = now
            if self.dynamics.latency > 0.0:
                self.pending.append((now + self.dynamics.latency, wheel, float(omega)))
            else:
                self.target[wheel] = omega

    def command_all(self, omega: Vec, now: float) -> None:
        """New targets (4,) [rad/s] for every wheel sent at ``now`` (the state must be
        advanced to ``now``: the study sets them at the start of a step)."""
        with self.lock:
            if self.dynamics.latency > 0.0:
                due = now + self.dynamics.latency
                self.pending.extend((due, i, float(w)) for i, w in enumerate(omega))
            else:
                self.target[:] = omega
            self.last_command[:] = now

    def drop_commands(self, wheel: int) -> None:
        """Forget ``wheel``'s commands in flight, target 0 (a drive that reboots)."""
        with self.lock:
            self.pending = deque(c for c in self.pending if c[1] != wheel)
            self.target[wheel] = 0.0

    def set_enabled(self, wheel: int, on: bool, now: float) -> None:
        """Power stage on/off, the serial bridge's way (off ramps to zero at the
        deceleration; it never coasts)."""
        with self.lock:
            self.advance(now)
            self.enabled[wheel] = on
            self.stop_decel[wheel] = math.nan
            self.coasting[wheel] = False

    def track(self, wheel: int, now: float) -> None:
        """Power stage on, the wheel follows its target."""
        with self.lock:
            self.advance(now)
            self.enabled[wheel] = True
            self.stop_decel[wheel] = math.nan
            self.coasting[wheel] = False

    def ramp_to_rest(self, wheel: int, decel: float, now: float) -> None:
        """Power stage on, speed to 0 at ``decel`` [rad/s^2], then held at 0."""
        with self.lock:
            self.advance(now)
            self.enabled[wheel] = False
            self.stop_decel[wheel] = max(float(decel), 1e-9)
            self.coasting[wheel] = False

    def power_off(self, wheel: int, now: float) -> None:
        """Power stage off: the wheel coasts (logged in :attr:`power_offs`)."""
        with self.lock:
            self.advance(now)
            if not self.coasting[wheel]:
                self.power_offs.append((now, wheel, float(self.omega[wheel])))
            self.enabled[wheel] = False
            self.stop_decel[wheel] = math.nan
            self.coasting[wheel] = True

    def rest_time(self, wheel: int) -> float:
        """While ramping to rest: how long until the wheel is at rest [s] (else inf):
        the demand's ramp, then (with a velocity loop) the lag's decay to
        :data:`STANDSTILL`."""
        with self.lock:
            rate = float(self.stop_decel[wheel])
            if math.isnan(rate):
                return math.inf
            demand = abs(float(self.demand[wheel]))
            tau = self.dynamics.velocity_tau
            if tau == 0.0:
                return demand / rate
            # the lag trails a ramp by rate * tau; after it, it decays from there
            lag = abs(float(self.omega[wheel])) if demand == 0.0 else rate * tau
            return demand / rate + tau * math.log(max(lag, STANDSTILL) / STANDSTILL)

    def get_pose(self, now: float) -> tuple[float, float, float]:
        """(x, y [m], yaw [rad]) where the base is at ``now`` (slip included)."""
        with self.lock:
            self.advance(now)
            return float(self.pose[0]), float(self.pose[1]), float(self.pose[2])

    def get_odometry_pose(self, now: float) -> tuple[float, float, float]:
        """(x, y [m], yaw [rad]) the wheels' encoders integrate to at ``now``."""
        with self.lock:
            self.advance(now)
            p = self.odometry_pose
            return float(p[0]), float(p[1]), float(p[2])
