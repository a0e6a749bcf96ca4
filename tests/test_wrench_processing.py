"""WrenchProcessor: tare, gravity compensation, dead band, low-pass, rotation, mask, faults."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from mmctl.config import default_config
from mmctl.control.wrench import G0, WrenchProcessor
from mmctl.errors import FaultCause, SafetyFault
from mmctl.types import Wrench

DT = 0.002
I3 = np.eye(3)


def wcfg(**over: object):
    base = default_config().sensor.wrench
    plain: dict[str, object] = {
        "deadband_force": 0.0, "deadband_torque": 0.0, "axis_mask": (True,) * 6,
        "handle_mass": 0.0, "stale_timeout": 1.0, "tare_samples": 4,
    }
    plain.update(over)
    return dataclasses.replace(base, **plain)


def sample(w, seq: int, t: float = 0.0) -> Wrench:
    a = np.asarray(w, dtype=float)
    return Wrench(a[:3].copy(), a[3:].copy(), t, seq, 0)


def weight_in_sensor(r: np.ndarray, mass: float, com) -> np.ndarray:
    """What a real sensor reads from a handle at rest (written independently here)."""
    f = r.T @ np.array([0.0, 0.0, -mass * G0])
    return np.concatenate((f, np.cross(np.asarray(com, dtype=float), f)))


def run(proc: WrenchProcessor, samples, rotations, t0: float = 0.0):
    state = proc.initial_state()
    outs = []
    for k, (w, r) in enumerate(zip(samples, rotations)):
        state, out = proc.step(state, sample(w, k, t0 + k * DT), r, t0 + k * DT)
        outs.append(out)
    return state, outs


def test_gravity_wrench_formula() -> None:
    proc = WrenchProcessor(wcfg(handle_mass=2.0, handle_com=(0.01, 0.0, 0.08)), DT)
    g = proc.gravity_wrench(I3)
    mg = 2.0 * G0
    np.testing.assert_allclose(g, [0, 0, -mg, 0, 0.01 * mg, 0], atol=1e-12)
    # sensor upside down (z down): the weight pulls along +z of the sensor
    flip = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    np.testing.assert_allclose(proc.gravity_wrench(flip)[:3], [0, 0, mg], atol=1e-12)


def test_handle_at_rest_reads_zero_at_every_orientation_after_a_tare() -> None:
    cfg = wcfg(handle_mass=0.8, handle_com=(0.02, -0.01, 0.09), tare_samples=10)
    proc = WrenchProcessor(cfg, DT)
    offset = np.array([1.5, -0.7, 3.0, 0.05, -0.02, 0.01])  # the sensor's own zero drift
    r0 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix()
    state = proc.start_tare(proc.initial_state())
    raw0 = offset + weight_in_sensor(r0, cfg.handle_mass, cfg.handle_com)
    for k in range(10):
        state, out = proc.step(state, sample(raw0, k, k * DT), r0, k * DT)
        assert out.taring and not out.f_h.any()
    assert state.tare_left == 0
    np.testing.assert_allclose(state.bias, offset, atol=1e-12)
    for i, r in enumerate(Rotation.random(25, random_state=7).as_matrix()):
        raw = offset + weight_in_sensor(r, cfg.handle_mass, cfg.handle_com)
        k = 10 + i
        state, out = proc.step(state, sample(raw, k, k * DT), r, k * DT)
        assert out.fault is None
        np.testing.assert_allclose(out.compensated, 0.0, atol=1e-12)
        np.testing.assert_allclose(out.f_h, 0.0, atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1),
       mass=st.floats(0.0, 5.0), com=st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3))
def test_compensation_cancels_any_handle_weight(quat, mass, com) -> None:
    cfg = wcfg(handle_mass=mass, handle_com=tuple(com))
    proc = WrenchProcessor(cfg, DT)
    r = Rotation.from_quat(quat).as_matrix()
    raw = weight_in_sensor(r, mass, com)
    _, out = proc.step(proc.initial_state(), sample(raw, 0), r, 0.0)
    np.testing.assert_allclose(out.compensated, 0.0, atol=1e-9)


def test_tare_counts_fresh_samples_only() -> None:
    proc = WrenchProcessor(wcfg(handle_mass=0.0, tare_samples=3), DT)
    state = proc.start_tare(proc.initial_state())
    seqs = [1, 1, 1, 2, 2, 3]  # repeated sequence = the same sample again
    values = [1.0, 1.0, 1.0, 2.0, 2.0, 6.0]
    for k, (s, v) in enumerate(zip(seqs, values)):
        state, out = proc.step(state, sample([v, 0, 0, 0, 0, 0], s, k * DT), I3, k * DT)
    assert state.tare_left == 0 and out.taring  # the completing cycle still outputs zero
    assert state.bias[0] == pytest.approx(3.0)  # (1 + 2 + 6) / 3
    state, out = proc.step(state, sample([3.0, 0, 0, 0, 0, 0], 4, 6 * DT), I3, 6 * DT)
    assert not out.taring and out.compensated[0] == pytest.approx(0.0)


@pytest.mark.parametrize("direction", [(1, 0, 0), (0.6, -0.8, 0), (1, 2, -2)])
def test_dead_band_is_isotropic_and_continuous(direction) -> None:
    d = 2.0
    proc = WrenchProcessor(wcfg(deadband_force=d, deadband_torque=0.5, lowpass_cutoff=200.0),
                           DT)
    u = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    for magnitude, expected in ((1.9, 0.0), (2.0, 0.0), (3.0, 1.0), (12.0, 10.0)):
        raw = np.concatenate((magnitude * u, [0.0, 0.0, 0.0]))
        _, outs = run(proc, [raw] * 300, [I3] * 300)
        np.testing.assert_allclose(outs[-1].f_h[:3], expected * u, atol=1e-12)
    raw = np.array([0, 0, 0, 0.0, 0.3, 0.4])  # |t| = 0.5 = band
    _, outs = run(proc, [raw] * 50, [I3] * 50)
    assert not outs[-1].f_h.any()


def test_low_pass_step_response_matches_the_analytic_solution() -> None:
    fc = 20.0
    proc = WrenchProcessor(wcfg(lowpass_cutoff=fc), DT)
    tau = 1.0 / (2 * np.pi * fc)
    raw = np.array([10.0, 0, 0, 0, 0, 0])
    _, outs = run(proc, [raw] * 60, [I3] * 60)
    k = np.arange(1, 61)
    analytic = 10.0 * (1.0 - np.exp(-k * DT / tau))
    np.testing.assert_allclose([o.f_h[0] for o in outs], analytic, rtol=1e-12)
    assert proc.alpha == pytest.approx(np.exp(-DT / tau), rel=1e-15)


def test_rotation_into_base_axes_and_control_point() -> None:
    rz = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    proc = WrenchProcessor(wcfg(handle_mass=0.0, lowpass_cutoff=500.0), DT)
    raw = np.array([10.0, 0, 0, 1.0, 0, 0])  # sensor x: becomes base y
    _, outs = run(proc, [raw] * 200, [rz] * 200)
    np.testing.assert_allclose(outs[-1].f_h, [0, 10.0, 0, 0, 1.0, 0], atol=1e-9)
    # torque about a control point 0.1 m along sensor x of a push along sensor z
    proc = WrenchProcessor(wcfg(handle_mass=0.0, lowpass_cutoff=500.0), DT,
                           control_point=(0.1, 0.0, 0.0))
    raw = np.array([0, 0, 10.0, 0, 0, 0])
    _, outs = run(proc, [raw] * 200, [I3] * 200)
    # t_P = t - p x f = -(0.1, 0, 0) x (0, 0, 10) = (0, 1, 0)
    np.testing.assert_allclose(outs[-1].f_h, [0, 0, 10.0, 0, 1.0, 0], atol=1e-9)


def test_mask_zeroes_the_masked_axes() -> None:
    proc = WrenchProcessor(wcfg(handle_mass=0.0, axis_mask=(True, False, True, False, True, False),
                                lowpass_cutoff=500.0), DT)
    raw = np.array([5.0, 6.0, 7.0, 0.5, 0.6, 0.7])
    _, outs = run(proc, [raw] * 200, [I3] * 200)
    np.testing.assert_allclose(outs[-1].f_h, [5.0, 0, 7.0, 0, 0.6, 0], atol=1e-9)
    assert default_config().sensor.wrench.axis_mask == (True, True, True, False, False, False)


def test_stale_when_the_sequence_stops_advancing() -> None:
    proc = WrenchProcessor(wcfg(handle_mass=0.0, stale_timeout=0.010), DT)
    state = proc.initial_state()
    w = sample([1, 0, 0, 0, 0, 0], seq=7, t=1.000)
    state, out = proc.step(state, w, I3, 1.000)
    assert out.fault is None and out.fresh
    state, out = proc.step(state, w, I3, 1.0095)  # within the timeout: still fine
    assert out.fault is None and not out.fresh
    state, out = proc.step(state, w, I3, 1.0102)
    assert out.fault is FaultCause.SENSOR_STALE
    assert out.details["age_ms"] == pytest.approx(10.2)
    assert not out.f_h.any()
    state, out = proc.step(state, sample([1, 0, 0, 0, 0, 0], seq=8, t=1.012), I3, 1.0121)
    assert out.fault is None  # a new sample clears the condition (the daemon latches)


@pytest.mark.parametrize(
    ("raw", "cause"),
    [
        ([np.nan, 0, 0, 0, 0, 0], FaultCause.NON_FINITE),
        ([0, 0, np.inf, 0, 0, 0], FaultCause.NON_FINITE),
        ([0, 0, 901.0, 0, 0, 0], FaultCause.SENSOR_SATURATION),
        ([0, -501.0, 0, 0, 0, 0], FaultCause.SENSOR_SATURATION),
        ([0, 0, 0, 0, 20.5, 0], FaultCause.SENSOR_SATURATION),
        ([120.0, 100.0, 0, 0, 0, 0], FaultCause.WRENCH_LIMIT),
        ([0, 0, 0, 10.0, 10.0, 10.0], FaultCause.WRENCH_LIMIT),
    ],
)
def test_faults_are_values(raw, cause: FaultCause) -> None:
    proc = WrenchProcessor(wcfg(handle_mass=0.0), DT)
    state0 = proc.initial_state()
    state, out = proc.step(state0, sample(raw, 1), I3, 0.0)
    assert out.fault is cause
    assert not out.f_h.any()
    np.testing.assert_array_equal(state.filtered, state0.filtered)
    with pytest.raises(SafetyFault) as info:
        out.raise_if_fault()
    assert info.value.cause is cause


def test_non_finite_rotation_is_a_fault() -> None:
    proc = WrenchProcessor(wcfg(), DT)
    r = I3.copy()
    r[0, 0] = np.nan
    _, out = proc.step(proc.initial_state(), sample([0] * 6, 1), r, 0.0)
    assert out.fault is FaultCause.NON_FINITE


def test_within_range_and_limits_passes() -> None:
    proc = WrenchProcessor(wcfg(handle_mass=0.0), DT)
    _, out = proc.step(proc.initial_state(), sample([0, 0, 149.0, 0, 0, 14.9], 1), I3, 0.0)
    assert out.fault is None
    out.raise_if_fault()


def test_bad_dt_and_tare_count_are_refused() -> None:
    with pytest.raises(ValueError, match="dt"):
        WrenchProcessor(wcfg(), 0.0)
    proc = WrenchProcessor(wcfg(), DT)
    with pytest.raises(ValueError, match="tare"):
        proc.start_tare(proc.initial_state(), 0)


@settings(max_examples=200, deadline=None)
@given(raw=st.lists(st.floats(-1e6, 1e6), min_size=6, max_size=6),
       quat=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(
           lambda q: np.linalg.norm(q) > 0.1))
def test_output_is_always_finite(raw, quat) -> None:
    proc = WrenchProcessor(default_config().sensor.wrench, DT)
    r = Rotation.from_quat(quat).as_matrix()
    state = proc.initial_state()
    for k in range(3):
        state, out = proc.step(state, sample(raw, k, k * DT), r, k * DT)
        assert np.all(np.isfinite(out.f_h))
        assert np.all(np.isfinite(state.filtered))
