"""From the raw sensor wrench to the human wrench ``f_h`` in the control frame (pure).

One cycle, :meth:`WrenchProcessor.step`, in this order:

1. **checks** on the raw sample (sensor frame): any non-finite number ->
   ``NON_FINITE``; no new sample (same ``sequence``) for longer than ``stale_timeout``
   -> ``SENSOR_STALE``; a component beyond the sensing range (``range_force``,
   ``range_torque``, ATI Axia80 M20: 500/500/900 N, 20 N m) -> ``SENSOR_SATURATION``.
2. **gravity compensation and tare**: ``c = raw - bias - g(R)`` where ``g(R)`` is the
   handle's weight seen in the sensor frame, ``R = R_base_sensor`` (sensor axes in the
   base frame, from FK), gravity along -z of the base frame::

       f_g = R^T (0, 0, -m g0),   t_g = p_com x f_g      (sensor frame)

   A software tare (:meth:`WrenchProcessor.start_tare`) averages ``raw - g(R)`` over the
   next ``tare_samples`` fresh samples into ``bias``, so the handle's weight is *not*
   absorbed into the bias and compensation stays right at every later orientation.
   While taring, ``f_h`` is zero.
3. **control frame**: torque moved to the control point (``control_point``, sensor frame,
   default the sensor origin): ``t_P = t - p x f``; then both rotated into base axes,
   ``f_b = R f``, ``t_b = R t_P``.
4. **limit**: ``|f_b| > force_limit`` or ``|t_b| > torque_limit`` -> ``WRENCH_LIMIT``.
5. **dead band**, isotropic and continuous, on force and torque separately:
   ``v -> v * max(|v| - d, 0) / |v|`` (a push just above ``d`` gives a small ``f_h``,
   not a jump; the result does not depend on the frame).
6. **low-pass**, first order with cut-off ``fc``, exact discretisation for a held input:
   ``y[k+1] = a y[k] + (1 - a) u[k]``, ``a = exp(-2 pi fc dt)``; a unit step gives
   ``y[k] = 1 - exp(-k dt / tau)``, ``tau = 1 / (2 pi fc)``.  It runs once per step (per
   control period ``dt``), in the control frame, so a turning sensor does not rotate the
   filter's memory.
7. **mask**: axes with ``axis_mask`` False are zeroed.

Faults are returned **as a value** (``WrenchOutput.fault`` + ``details``), never raised,
so the loop can feed them to the safety monitor as conditions; ``raise_if_fault()``
turns one into a :class:`~mmctl.errors.SafetyFault` for callers that prefer that.  On a
fault ``f_h`` is zero and the filter state is kept.  Nothing latches here: the daemon's
safety monitor latches.  (The transports themselves raise ``SafetyFault`` for device
status, saturation and staleness; this module re-checks staleness and range for any
``ForceSensor``.)  No I/O, no clocks: the caller passes ``now`` (time.monotonic) [s].
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from mmctl.config.sensor import WrenchConfig
from mmctl.errors import FaultCause, SafetyFault
from mmctl.types import Vec, Wrench

#: standard gravity [m/s^2]
G0 = 9.80665


class WrenchState(NamedTuple):
    """What the processor remembers between cycles (replace, never mutate).

    bias: (6,) sensor frame [N, N m]; filtered: (6,) low-pass output, control frame;
    last_sequence: sequence of the newest sample seen (-1 none); last_fresh: its
    timestamp [s] (nan none); tare_left: fresh samples still to average (0 = not
    taring); tare_total: samples the running tare averages; tare_sum: (6,) running sum
    of ``raw - g(R)`` while taring.
    """

    bias: Vec
    filtered: Vec
    last_sequence: int
    last_fresh: float
    tare_left: int
    tare_total: int
    tare_sum: Vec


class WrenchOutput(NamedTuple):
    """One cycle's result.

    f_h: (6,) processed human wrench in the control frame [N, N m] (zero on fault or
    while taring); compensated: (6,) ``raw - bias - g(R)`` in the sensor frame; fault:
    the cause or None; details: key-values for the fault event; taring: a tare is in
    progress; fresh: this sample is new (its sequence differs from the previous one).
    """

    f_h: Vec
    compensated: Vec
    fault: FaultCause | None
    details: dict[str, Any]
    taring: bool
    fresh: bool

    def raise_if_fault(self) -> None:
        """Raise the fault as a :class:`SafetyFault`, if there is one."""
        if self.fault is not None:
            raise SafetyFault(self.fault, **self.details)


class WrenchProcessor:
    """The pure wrench pipeline of SPEC §1 step 1 (see module doc).

    cfg: the ``sensor.wrench`` section; dt: control period [s]; control_point: (3,)
    position of the control point in the sensor frame [m] (torques are expressed about
    it; default the sensor origin).
    """

    def __init__(self, cfg: WrenchConfig, dt: float, control_point: ArrayLike = (0.0, 0.0, 0.0)):
        if not dt > 0.0:
            raise ValueError(f"dt = {dt!r}: must be > 0 [s]")
        self.cfg = cfg
        self.dt = float(dt)
        self.tau = 1.0 / (2.0 * np.pi * cfg.lowpass_cutoff)
        self.alpha = float(np.exp(-self.dt / self.tau))
        self._mass = cfg.handle_mass
        self._com = np.asarray(cfg.handle_com, dtype=np.float64)
        self._weight_base = np.array((0.0, 0.0, -cfg.handle_mass * G0))
        self._point = np.asarray(control_point, dtype=np.float64).reshape(3)
        self._range = np.array(cfg.range_force + cfg.range_torque, dtype=np.float64)
        self._mask = np.array(cfg.axis_mask, dtype=np.float64)
        self._zero6 = np.zeros(6)

    def initial_state(self) -> WrenchState:
        """No bias, filter at rest, no sample seen."""
        return WrenchState(np.zeros(6), np.zeros(6), -1, float("nan"), 0, 0, np.zeros(6))

    def start_tare(self, state: WrenchState, samples: int | None = None) -> WrenchState:
        """Begin a tare over the next ``samples`` (default ``tare_samples``) fresh samples."""
        n = self.cfg.tare_samples if samples is None else int(samples)
        if n <= 0:
            raise ValueError(f"tare samples = {n}: must be > 0")
        return state._replace(tare_left=n, tare_total=n, tare_sum=np.zeros(6))

    def gravity_wrench(self, r_base_sensor: ArrayLike) -> Vec:
        """(6,) the handle's weight as the sensor measures it, sensor frame [N, N m]."""
        r = np.asarray(r_base_sensor, dtype=np.float64)
        f = r.T @ self._weight_base
        return np.concatenate((f, np.cross(self._com, f)))

    def step(self, state: WrenchState, wrench: Wrench, r_base_sensor: ArrayLike,
             now: float) -> tuple[WrenchState, WrenchOutput]:
        """One cycle: (state, raw sample, sensor orientation (3, 3), now [s]) -> (state, out)."""
        raw = wrench.as_array()
        r = np.asarray(r_base_sensor, dtype=np.float64)
        fresh = wrench.sequence != state.last_sequence
        if not (np.all(np.isfinite(raw)) and np.all(np.isfinite(r)) and np.isfinite(now)):
            return state, self._fault(raw, FaultCause.NON_FINITE, fresh, state,
                                      raw=raw.tolist(), sequence=wrench.sequence)
        last_fresh = wrench.timestamp if fresh else state.last_fresh
        age = now - last_fresh
        if age > self.cfg.stale_timeout:
            return state, self._fault(raw, FaultCause.SENSOR_STALE, fresh, state,
                                      age_ms=round(age * 1e3, 2), sequence=wrench.sequence)
        state = state._replace(last_sequence=wrench.sequence, last_fresh=last_fresh)
        over = np.abs(raw) > self._range
        if over.any():
            axis = int(np.argmax(over))
            return state, self._fault(raw, FaultCause.SENSOR_SATURATION, fresh, state,
                                      axis=axis, value=float(raw[axis]))

        g = self.gravity_wrench(r)
        if state.tare_left > 0:
            if fresh:
                tare_sum = state.tare_sum + (raw - g)
                left = state.tare_left - 1
                if left == 0:
                    state = state._replace(bias=tare_sum / state.tare_total,
                                           filtered=np.zeros(6), tare_left=0,
                                           tare_sum=np.zeros(6))
                else:
                    state = state._replace(tare_left=left, tare_sum=tare_sum)
            comp = raw - state.bias - g
            return state, WrenchOutput(self._zero6.copy(), comp, None, {}, True, fresh)

        comp = raw - state.bias - g
        f_s = comp[:3]
        t_s = comp[3:] - np.cross(self._point, f_s)
        f_b = r @ f_s
        t_b = r @ t_s
        f_norm = float(np.linalg.norm(f_b))
        t_norm = float(np.linalg.norm(t_b))
        if f_norm > self.cfg.force_limit or t_norm > self.cfg.torque_limit:
            return state, self._fault(comp, FaultCause.WRENCH_LIMIT, fresh, state,
                                      force=round(f_norm, 3), torque=round(t_norm, 4))
        u = np.concatenate((_deadband(f_b, f_norm, self.cfg.deadband_force),
                            _deadband(t_b, t_norm, self.cfg.deadband_torque)))
        filtered = self.alpha * state.filtered + (1.0 - self.alpha) * u
        state = state._replace(filtered=filtered)
        return state, WrenchOutput(filtered * self._mask, comp, None, {}, False, fresh)

    # -- helpers -------------------------------------------------------------------------

    def _fault(self, comp: Vec, cause: FaultCause, fresh: bool, state: WrenchState,
               **details: Any) -> WrenchOutput:
        return WrenchOutput(self._zero6.copy(), comp, cause, details, state.tare_left > 0, fresh)


def _deadband(v: Vec, norm: float, d: float) -> Vec:
    """Shrink ``v`` by ``d`` along its direction; zero inside the band."""
    if norm <= d:
        return np.zeros(3)
    return v * ((norm - d) / norm)
