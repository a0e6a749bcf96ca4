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

import math
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
        # decided once here, so that step() is a handful of small matrix products:
        # g(R) = -m g0 [I; [c]x] R^T e_z = gravity_map @ R[2, :]
        com = np.asarray(cfg.handle_com, dtype=np.float64)
        self._gravity_map = -cfg.handle_mass * G0 * np.vstack((np.eye(3), _skew(com)))
        # sensor-frame wrench -> torque about the control point: t_P = t - [p]x f
        shift = np.eye(6)
        shift[3:, :3] = -_skew(np.asarray(control_point, dtype=np.float64).reshape(3))
        self._shift = shift
        self._range = np.array(cfg.range_force + cfg.range_torque, dtype=np.float64)
        self._mask = np.array(cfg.axis_mask, dtype=np.float64)
        self._f_limit = cfg.force_limit
        self._t_limit = cfg.torque_limit
        self._db_f = cfg.deadband_force
        self._db_t = cfg.deadband_torque
        self._stale = cfg.stale_timeout

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
        w: Vec = self._gravity_map @ np.asarray(r_base_sensor, dtype=np.float64)[2]
        return w

    def step(self, state: WrenchState, wrench: Wrench, r_base_sensor: ArrayLike,
             now: float) -> tuple[WrenchState, WrenchOutput]:
        """One cycle: (state, raw sample, sensor orientation (3, 3), now [s]) -> (state, out)."""
        raw = wrench.as_array()
        r = np.asarray(r_base_sensor, dtype=np.float64)
        fresh = wrench.sequence != state.last_sequence
        in_range = bool((np.abs(raw) <= self._range).all())  # False for NaN too
        if not (in_range or np.isfinite(raw).all()) or not (
                np.isfinite(r).all() and math.isfinite(now)):
            return state, self._fault(raw, FaultCause.NON_FINITE, fresh, state,
                                      raw=raw.tolist(), sequence=wrench.sequence)
        last_fresh = wrench.timestamp if fresh else state.last_fresh
        age = now - last_fresh
        if age > self._stale:
            return state, self._fault(raw, FaultCause.SENSOR_STALE, fresh, state,
                                      age_ms=round(age * 1e3, 2), sequence=wrench.sequence)
        if not in_range:
            axis = int(np.argmax(np.abs(raw) > self._range))
            state = state._replace(last_sequence=wrench.sequence, last_fresh=last_fresh)
            return state, self._fault(raw, FaultCause.SENSOR_SATURATION, fresh, state,
                                      axis=axis, value=float(raw[axis]))

        comp = raw - self._gravity_map @ r[2]  # raw - g(R), bias not yet removed
        if state.tare_left > 0:
            tare_left, tare_sum, bias = state.tare_left, state.tare_sum, state.bias
            filtered = state.filtered
            if fresh:
                tare_sum = tare_sum + comp
                tare_left -= 1
                if tare_left == 0:
                    bias = tare_sum / state.tare_total
                    tare_sum = np.zeros(6)
                    filtered = np.zeros(6)
            state = WrenchState(bias, filtered, wrench.sequence, last_fresh, tare_left,
                                state.tare_total, tare_sum)
            return state, WrenchOutput(np.zeros(6), comp - bias, None, {}, True, fresh)

        comp -= state.bias
        ft = r @ (self._shift @ comp).reshape(2, 3).T  # (3, 2): columns f_b, t_b
        f_b = ft[:, 0]
        t_b = ft[:, 1]
        f_norm = math.sqrt(f_b @ f_b)
        t_norm = math.sqrt(t_b @ t_b)
        if f_norm > self._f_limit or t_norm > self._t_limit:
            state = state._replace(last_sequence=wrench.sequence, last_fresh=last_fresh)
            return state, self._fault(comp, FaultCause.WRENCH_LIMIT, fresh, state,
                                      force=round(f_norm, 3), torque=round(t_norm, 4))
        u = np.empty(6)
        u[:3] = _deadband(f_b, f_norm, self._db_f)
        u[3:] = _deadband(t_b, t_norm, self._db_t)
        filtered = self.alpha * state.filtered + (1.0 - self.alpha) * u
        state = WrenchState(state.bias, filtered, wrench.sequence, last_fresh, 0,
                            state.tare_total, state.tare_sum)
        return state, WrenchOutput(filtered * self._mask, comp, None, {}, False, fresh)

    # -- helpers -------------------------------------------------------------------------

    def _fault(self, comp: Vec, cause: FaultCause, fresh: bool, state: WrenchState,
               **details: Any) -> WrenchOutput:
        return WrenchOutput(np.zeros(6), comp, cause, details, state.tare_left > 0, fresh)


def _skew(v: Vec) -> Vec:
    """(3, 3) cross-product matrix: ``_skew(a) @ b == a x b``."""
    return np.array(((0.0, -v[2], v[1]), (v[2], 0.0, -v[0]), (-v[1], v[0], 0.0)))


def _deadband(v: Vec, norm: float, d: float) -> Vec:
    """Shrink ``v`` by ``d`` along its direction; zero inside the band."""
    if norm <= d:
        return 0.0 * v
    return v * ((norm - d) / norm)
