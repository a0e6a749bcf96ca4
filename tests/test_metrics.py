"""The paper's trial metrics (eqs. 14-16)."""

from __future__ import annotations

import numpy as np
import pytest

from mmctl.control.metrics import TrialMetrics, trial_metrics


def test_metrics_of_a_known_trial() -> None:
    n, T = 500, 0.002
    e = np.linspace(0.0, 2.0, n)
    f = np.zeros((n, 6))
    f[:, 0], f[:, 1] = 3.0, 4.0  # |f| = 5 N
    f[:, 3:] = 100.0  # torques are ignored (the paper holds rotations fixed)
    v = np.zeros((n, 6))
    v[:, 2] = -0.1
    m = trial_metrics(T, e, f, v, [1.0, 2.0, 3.0], [1.0, 2.0, 2.5])
    assert m == TrialMetrics(pytest.approx(1.0), pytest.approx(5.0), pytest.approx(0.1),
                             pytest.approx(0.5), pytest.approx(1.0))
    # norms may be given directly
    m2 = trial_metrics(T, e, np.full(n, 5.0), np.full(n, 0.1), [0, 0, 0], [0, 0, 0])
    assert m2.F_mean == pytest.approx(5.0) and m2.x_f == 0.0


def test_metrics_reject_mismatched_lengths() -> None:
    with pytest.raises(ValueError, match="same non-zero length"):
        trial_metrics(0.002, np.ones(3), np.ones(4), np.ones(3), [0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="f_h must be"):
        trial_metrics(0.002, np.ones(3), np.ones((3, 2)), np.ones(3), [0, 0, 0], [0, 0, 0])
