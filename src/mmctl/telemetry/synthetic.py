"""Synthetic samples with known values, for tests and for exercising the viewer layout.

A smooth push: the handle force rises and falls, the base drifts forward, the arm
joints sway around ``q0``; every quantity is a closed-form function of the cycle index,
so tests can compare what a recording holds against what was sent.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np

from mmctl.model.planar import point_to_world
from mmctl.telemetry.sample import TelemetrySample

#: a comfortable arm pose [rad] (the default preferred configuration)
Q0 = np.array([0.0, -1.9, 1.9, -1.5708, -1.5708, 0.0])


def synthetic_sample(k: int, period: float = 0.002, p_des: tuple[float, float, float] = (
        0.9, 0.0, 1.0)) -> TelemetrySample:
    """The sample of cycle ``k`` (see the module docstring); ``period`` T [s]; p_des: the
    preferred position in the mobile base frame [m] (the sample holds it in the world)."""
    t = k * period
    push = math.sin(0.5 * t) ** 2
    f = np.array([30.0 * push, 5.0 * math.sin(1.3 * t), -2.0, 0.0, 0.0, 0.0])
    v_d = np.array([0.2 * push, 0.03 * math.sin(1.3 * t), 0.0, 0.0, 0.0, 0.0])
    v = 0.95 * v_d
    q_a = Q0 + 0.15 * np.sin(0.7 * t + np.arange(6))
    qd_arm = 0.1 * np.cos(0.7 * t + np.arange(6))
    twist = np.array([0.15 * push, 0.0, 0.05 * math.sin(0.2 * t)])
    e_arm = 0.5 * float(qd_arm @ qd_arm)
    e_base = 0.5 * 115.0 * float(twist[:2] @ twist[:2]) + 0.5 * 15.0 * twist[2] ** 2
    x, y, yaw = 0.1 * t, 0.02 * t, 0.05 * t
    p_des_w = point_to_world(x, y, yaw, p_des)
    p = p_des_w + np.array([0.05 * math.sin(0.3 * t), 0.02, -0.01])
    return TelemetrySample(
        cycle=k, t=t, q_a=q_a, base_pose=np.array([x, y, yaw]), f_h=f,
        v_d=v_d, v=v, qd_cmd=np.concatenate((qd_arm, twist)),
        e_total=e_arm + e_base, e_arm=e_arm, e_base=e_base, p=p, p_des=p_des_w,
        mode="min-energy", safety="armed", nearest=0.1 + 0.02 * math.sin(0.4 * t),
        qd_a=0.105 * np.cos(0.7 * t + np.arange(6)),  # d/dt of q_a
        f_raw=np.array([f[0], f[1], f[2] - 19.6, 0.0, 0.0, 0.1]),  # + a 2 kg handle
    )


def synthetic_samples(n: int, start: int = 0, period: float = 0.002) -> Iterator[TelemetrySample]:
    """Samples of cycles ``start`` .. ``start + n - 1``."""
    for k in range(start, start + n):
        yield synthetic_sample(k, period)
