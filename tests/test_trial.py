"""Trial bracketing and the paper's metrics (eq. 14-16) on synthetic data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.telemetry import layout
from mmctl.telemetry.batch import full_rate
from mmctl.telemetry.events import Event
from mmctl.telemetry.recording import RecordedTrial, Recording, recording_metrics
from mmctl.telemetry.ring import encode, rows_of
from mmctl.telemetry.sample import zero_sample
from mmctl.telemetry.synthetic import synthetic_samples
from mmctl.telemetry.trial import TrialError, TrialTracker, compute


def hand_sample(k: int, e: float, f: tuple[float, float, float], v: tuple[float, float, float],
                p: tuple[float, float, float]):  # type: ignore[no-untyped-def]
    s = zero_sample(k, k * 0.002)
    return s._replace(e_total=e, f_h=np.array([*f, 7.0, 7.0, 7.0]),
                      v=np.array([*v, 9.0, 9.0, 9.0]), p=np.array(p),
                      p_des=np.array([1.0, 0.0, 1.0]))


HAND = [
    hand_sample(10, 1.0, (3.0, 4.0, 0.0), (0.0, 0.3, 0.4), (1.0, 0.0, 1.0)),
    hand_sample(11, 2.0, (0.0, 0.0, 12.0), (0.1, 0.0, 0.0), (1.0, 0.1, 1.0)),
    hand_sample(12, 6.0, (6.0, 8.0, 0.0), (0.0, 0.0, 0.2), (1.3, 0.4, 1.0)),
]


def test_metrics_match_hand_computed_values() -> None:
    m = compute(0.002, [1.0, 2.0, 6.0], [5.0, 12.0, 10.0], [0.5, 0.1, 0.2],
                [1.3, 0.4, 1.0], [1.0, 0.0, 1.0])
    assert m.E_mean == pytest.approx(3.0)
    assert m.F_mean == pytest.approx(9.0)
    assert m.v_mean == pytest.approx(0.8 / 3)
    assert m.x_f == pytest.approx(0.5)  # |(0.3, 0.4, 0)|
    assert m.T_f == pytest.approx(0.006)


def test_tracker_brackets_whole_cycles_and_uses_force_and_linear_parts() -> None:
    events: list[Event] = []
    tr = TrialTracker(0.002, events.append)
    tr.observe(HAND[0])  # before start: ignored
    assert tr.start() == 1 and tr.active
    for s in HAND:
        tr.observe(s)
    rows = tr.stop()
    assert not tr.active
    tr.observe(HAND[0])  # after stop: ignored
    r = tr.finish(rows)
    assert (r.trial, r.start_cycle, r.stop_cycle, r.samples) == (1, 10, 12, 3)
    # torques (7) and angular rates (9) are not part of F_h and v:
    assert r.metrics.F_mean == pytest.approx(9.0)
    assert r.metrics.v_mean == pytest.approx(0.8 / 3)
    assert r.metrics.E_mean == pytest.approx(3.0)
    assert r.metrics.x_f == pytest.approx(0.5)
    assert r.metrics.T_f == pytest.approx(0.006)
    d = r.as_dict()
    assert {k: d[k] for k in layout.METRIC_KEYS} == pytest.approx(
        {"E": 3.0, "F_h": 9.0, "v": 0.8 / 3, "x_f": 0.5, "T_f": 0.006})
    start, stop = events
    assert (start.cycle, start.entity, start.values) == (
        10, "trial/bracket", {"trial": 1, "start_cycle": 10})
    assert stop.cycle == 12 and stop.entity == layout.TRIAL_METRICS
    assert stop.values is not None and stop.values["E"] == r.metrics.E_mean
    assert stop.values["samples"] == 3 and "trial 1:" in stop.text


def test_tracker_refuses_out_of_order_commands() -> None:
    tr = TrialTracker(0.002)
    with pytest.raises(TrialError, match="no trial is running"):
        tr.stop()
    tr.start()
    with pytest.raises(TrialError, match="already running"):
        tr.start()
    rows = tr.stop()
    with pytest.raises(TrialError, match="saw no control cycle"):
        tr.finish(rows)
    assert tr.start() == 2


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 300), start=st.integers(0, 50), length=st.integers(1, 200),
       seed=st.integers(0, 10_000))
def test_tracker_and_recorded_columns_give_identical_metrics(n: int, start: int, length: int,
                                                             seed: int) -> None:
    """What the daemon computes live equals what `mmctl metrics` recomputes from the
    full-rate columns (bit for bit), for any bracket inside the recording."""
    rng = np.random.default_rng(seed)
    samples = [s._replace(e_total=float(rng.exponential()), f_h=rng.normal(size=6) * 20,
                          v=rng.normal(size=6) * 0.2)
               for s in synthetic_samples(n)]
    start = min(start, n - 1)
    stop = min(start + length, n) - 1
    tr = TrialTracker(0.002)
    for s in samples:
        if s.cycle == start:
            tr.start()
        tr.observe(s)
        if s.cycle == stop:
            rows = tr.stop()
    live = tr.finish(rows)
    cols = full_rate(rows_of(samples))
    rec = Recording("mem", cols.cycle, cols.time_ns, cols.values,
                    [RecordedTrial(1, start, stop, None)], {"period_s": 0.002})
    (again,) = recording_metrics(rec)
    assert again.metrics == live.metrics
    assert (again.start_cycle, again.stop_cycle, again.samples) == (start, stop, stop - start + 1)


def test_recording_without_trials_is_one_whole_trial_and_unstopped_runs_to_the_end() -> None:
    samples = list(synthetic_samples(40))
    cols = full_rate(rows_of(samples))
    rec = Recording("mem", cols.cycle, cols.time_ns, cols.values, [], {})
    (whole,) = recording_metrics(rec)
    assert (whole.trial, whole.samples, whole.finished) == (0, 40, True)
    assert rec.period == pytest.approx(0.002)
    assert whole.metrics.T_f == pytest.approx(0.08)
    e = np.array([s.e_total for s in samples])
    assert whole.metrics.E_mean == pytest.approx(e.mean(), rel=1e-15)
    rec2 = rec._replace(trials=[RecordedTrial(1, 30, None, None)])
    (open_trial,) = recording_metrics(rec2)
    assert (open_trial.samples, open_trial.stop_cycle, open_trial.finished) == (10, 39, False)
    assert math.isclose(open_trial.metrics.x_f, float(np.linalg.norm(
        samples[-1].p - samples[-1].p_des)), rel_tol=1e-14)  # a rotation apart


def test_service_brackets_trials_with_telemetry_off() -> None:
    """With no destination the loop builds no samples, except while a trial runs."""
    from types import SimpleNamespace

    from mmctl.config import default_config
    from mmctl.telemetry.service import TelemetryService

    svc = TelemetryService(default_config())
    # a core whose "cycle result" is already a sample (ControlCore.fill_row has its own test)
    core = SimpleNamespace(fill_row=lambda s, cycle, t, safety, prev, row: encode(s, row, prev))
    daemon = SimpleNamespace(sample_hook=svc.hook(core), core=core)
    assert daemon.sample_hook is None and not svc.enabled

    def on_loop(fn):  # type: ignore[no-untyped-def]
        return fn()  # the daemon runs it on the loop thread

    def install(hook):  # type: ignore[no-untyped-def]
        daemon.sample_hook = hook  # the daemon's own hook slot

    assert svc.command({"cmd": "trial", "action": "start"}, on_loop, install, core) == {
        "trial": 1, "started": True}
    assert daemon.sample_hook is not None
    for s in HAND:
        daemon.sample_hook(s, s.cycle, s.t, s.safety)
    out = svc.command({"cmd": "trial", "action": "stop"}, on_loop, install, core)
    assert daemon.sample_hook is None
    assert out["E"] == pytest.approx(3.0) and out["samples"] == 3 and out["trial"] == 1
    status = svc.command({"cmd": "trial", "action": "status"}, on_loop, install, core)
    assert status["active"] is False and status["trials"][0]["x_f"] == pytest.approx(0.5)
    with pytest.raises(TrialError):
        svc.command({"cmd": "trial", "action": "stop"}, on_loop, install, core)
    with pytest.raises(Exception, match="expected start, stop or status"):
        svc.command({"cmd": "trial", "action": "pause"}, on_loop, install, core)
    svc.close()
