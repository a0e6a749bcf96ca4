"""The paper's trial metrics (eqs. 14-16) from arrays sampled every ``T`` seconds."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike


class TrialMetrics(NamedTuple):
    """E_mean [J], F_mean [N], v_mean [m/s], x_f [m], T_f [s] of one execution."""

    E_mean: float
    F_mean: float
    v_mean: float
    x_f: float
    T_f: float


def _norms(x: ArrayLike, name: str) -> np.ndarray:
    """Row norms of the translational part: (N,) norms as given, or the first 3 columns."""
    a = np.asarray(x, dtype=float)
    norms: np.ndarray
    if a.ndim == 1:
        norms = np.abs(a)
        return norms
    if a.ndim == 2 and a.shape[1] in (3, 6):
        norms = np.linalg.norm(a[:, :3], axis=1)
        return norms
    raise ValueError(f"{name} must be (N,), (N, 3) or (N, 6), got {a.shape}")


def trial_metrics(
    dt: float,
    E_K: ArrayLike,
    f_h: ArrayLike,
    v: ArrayLike,
    p_final: ArrayLike,
    p_des: ArrayLike,
) -> TrialMetrics:
    """Metrics of one execution sampled at ``t = kT``, k = 1..N, ``T = dt`` [s].

    E_K: (N,) kinetic energy [J]; f_h: (N, 6) human wrench or (N, 3) force or (N,)
    norms -- the force part is used (the paper keeps rotations fixed); v: (N, 6)
    end-effector twist / (N, 3) linear velocity / (N,) speeds [m/s] -- the linear part is
    used; p_final, p_des: (3,) end-effector position at ``T_f`` and ``FK(q_des)`` [m]
    (both in the same frame).  ``T_f = N T``.
    """
    e = np.asarray(E_K, dtype=float).reshape(-1)
    f = _norms(f_h, "f_h")
    s = _norms(v, "v")
    n = len(e)
    if n == 0 or len(f) != n or len(s) != n:
        raise ValueError(f"E_K, f_h and v need the same non-zero length, got {n}, {len(f)}, {len(s)}")
    x_f = float(np.linalg.norm(np.asarray(p_final, dtype=float) - np.asarray(p_des, dtype=float)))
    return TrialMetrics(float(e.mean()), float(f.mean()), float(s.mean()), x_f, n * dt)
