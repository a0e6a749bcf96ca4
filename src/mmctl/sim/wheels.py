"""The base's wheels: four wheels that follow their drives' velocity targets, and the pose
they drive.  Part of the simulated robot's one plant (:mod:`mmctl.sim.plant`): the fake
CiA 402 drives and the fake serial bridge run it in real time, the study in simulated
time; both see the same wheel dynamics.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque

import numpy as np
from numpy.typing import NDArray

from mmctl.config.base import MecanumConfig
from mmctl.control.mecanum import odometry_matrix

Vec = NDArray[np.float64]
SUBSTEP = 0.001
"""[s] the wheels' integration step."""
#: Coasting wheel (power stage off): viscous time constant [s] and dry friction [rad/s^2].
COAST_TIME_CONSTANT = 1.0
COAST_FRICTION = 1.0


class WheelPlant:
    """Four wheels (FL, FR, BL, BR) and the base pose they drive. Thread-safe.

    Each wheel is in one of three modes:

    * tracking (``enabled``): its speed [rad/s] moves toward its target at ``accel``
      (speeding up) or ``decel`` (slowing down) [rad/s^2]; with a ``watchdog`` [s]
      (None: none), the target is 0 once the wheel had no command for that long;
    * ramping to rest (:meth:`ramp_to_rest`): power stage on, speed toward 0 at the
      given deceleration, then held at 0;
    * coasting (:meth:`power_off`): power stage off, the wheel runs free and slows only
      by friction: ``d|w|/dt = -|w| / COAST_TIME_CONSTANT - COAST_FRICTION`` (a model:
      a free mecanum wheel under the base's weight; at rest after
      ``tau ln(1 + |w0| / (mu tau))``, 1.9 s from 5.4 rad/s).

    ``enabled`` False without a mode (:meth:`set_enabled`, the serial bridge's
    switch) ramps to zero at ``decel``.  Every switch to coasting is logged in
    :attr:`power_offs` with the wheel's speed at that instant.  The pose (x, y [m],
    yaw [rad], world frame) integrates the least-squares base twist of the wheel
    increments.  Time is the caller's clock (``time.monotonic()`` for the fakes,
    simulated time for the study), starting at ``t0`` (default: ``time.monotonic()``);
    the state advances lazily to the time of each call.
    """

    def __init__(self, geom: MecanumConfig, accel: float, watchdog: float | None,
                 t0: float | None = None) -> None:
        self._p = odometry_matrix(geom)
        self.lock = threading.RLock()
        self.theta = np.zeros(4)
        self.omega = np.zeros(4)
        self.target = np.zeros(4)
        self.enabled = np.zeros(4, dtype=bool)
        self.accel = np.full(4, float(accel))
        self.decel = np.full(4, float(accel))
        self.stop_decel = np.full(4, math.nan)  # ramping to rest at this [rad/s^2]
        self.coasting = np.zeros(4, dtype=bool)
        self.last_command = np.full(4, -math.inf)
        self.watchdog = watchdog
        self.pose = np.zeros(3)
        self.t = time.monotonic() if t0 is None else t0
        #: (monotonic time [s], wheel, speed [rad/s]) at each switch to coasting
        self.power_offs: deque[tuple[float, int, float]] = deque(maxlen=1000)

    def advance(self, now: float) -> None:
        """Integrate up to monotonic time ``now`` [s] in steps of at most 1 ms."""
        with self.lock:
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
                    mu_tau = COAST_FRICTION * COAST_TIME_CONSTANT
                    free = np.maximum((np.abs(self.omega) + mu_tau)
                                      * math.exp(-h / COAST_TIME_CONSTANT) - mu_tau, 0.0)
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
        """New target [rad/s] for ``wheel`` at ``now`` (also feeds its watchdog)."""
        with self.lock:
            self.advance(now)
            self.target[wheel] = omega
            self.last_command[wheel] = now

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
        """While ramping to rest: how long until the wheel is at rest [s] (else inf)."""
        with self.lock:
            rate = float(self.stop_decel[wheel])
            w = abs(float(self.omega[wheel]))
            if math.isnan(rate):
                return math.inf
            return w / rate

    def get_pose(self, now: float) -> tuple[float, float, float]:
        """(x, y [m], yaw [rad]) at ``now``."""
        with self.lock:
            self.advance(now)
            return float(self.pose[0]), float(self.pose[1]), float(self.pose[2])
