"""Whole-body caps for hand guiding derived from ISO/TS 15066's transient-contact values.

ISO/TS 15066:2016 (collaborative robots), Annex A, gives per body region the largest
permissible *transient* contact force ``F_T`` (Table A.2: twice the quasi-static value),
the region's effective spring constant ``k`` and its effective mass ``m_H`` (Table A.3).
A robot that hits the region transfers at most its kinetic energy, stored in the
region's spring as ``F^2 / (2 k)``; so

* energy cap:      ``E_max = F_T^2 / (2 k)``                         (ISO/TS 15066, A.3)
* speed cap:       ``v_max = F_T / sqrt(mu k)``,  ``mu = (1/m_H + 1/m_R)^-1``   (A.4)

with ``m_R`` the robot's effective mass at the contact.  For the **base** (it moves as
one rigid body) ``m_R`` is the whole robot: base, arm and the load under the sensor.
For the **end-effector** it is ISO/TS 15066's ``m_R = M / 2 + m_L`` (A.6), ``M`` the
arm's moving mass and ``m_L`` the load (handle); while the base moves too, the energy
cap bounds the whole body anyway.  The reduced profile for first runs caps the
end-effector at 0.25 m/s, ISO 10218-1's reduced speed for hand guiding.

The caps are the *defaults* (``limits.body_region``); each can be set explicitly.  These
are design values from a body model, not a risk assessment: the lab's own assessment of
the application decides.
"""

from __future__ import annotations

import math
from typing import NamedTuple

#: ISO 10218-1:2011, 5.10.3 / 5.6: reduced speed (hand guiding, first runs) [m/s].
REDUCED_SPEED = 0.25


class BodyRegion(NamedTuple):
    """ISO/TS 15066:2016 Annex A values of one body region."""

    transient_force: float  # F_T [N], Table A.2 (2 x the quasi-static force)
    spring: float  # k [N/m], Table A.3 (given there in N/mm)
    mass: float  # m_H [kg], Table A.3


#: Regions where transient contact is permitted (skull, forehead and face are not).
BODY_REGIONS: dict[str, BodyRegion] = {
    "neck": BodyRegion(300.0, 50e3, 1.2),
    "back": BodyRegion(420.0, 35e3, 40.0),  # back and shoulders
    "chest": BodyRegion(280.0, 25e3, 40.0),
    "abdomen": BodyRegion(220.0, 10e3, 40.0),
    "pelvis": BodyRegion(360.0, 25e3, 40.0),
    "upper_arm": BodyRegion(300.0, 30e3, 3.0),  # upper arm and elbow joint
    "lower_arm": BodyRegion(320.0, 40e3, 2.0),  # lower arm and wrist joint
    "hand": BodyRegion(280.0, 75e3, 0.6),  # hands and fingers
    "thigh": BodyRegion(440.0, 50e3, 75.0),  # thighs and knees
    "lower_leg": BodyRegion(260.0, 60e3, 75.0),
}


class Caps(NamedTuple):
    """Whole-body caps: kinetic energy [J], base linear speed and end-effector linear
    speed [m/s] (inf: none)."""

    energy: float
    base_speed: float
    ee_speed: float


NO_CAPS = Caps(math.inf, math.inf, math.inf)


def reduced_mass(m_h: float, m_r: float) -> float:
    """``mu = (1/m_H + 1/m_R)^-1`` [kg] (ISO/TS 15066 eq. A.3)."""
    return 1.0 / (1.0 / m_h + 1.0 / m_r)


def derive(region: str, robot_mass: float, arm_mass: float, load: float) -> Caps:
    """The caps for ``region`` (:data:`BODY_REGIONS`, or "none": no caps).

    robot_mass: base + arm + load [kg]; arm_mass: the arm's moving mass [kg]; load:
    the mass under the sensor (handle) [kg]."""
    if region == "none":
        return NO_CAPS
    b = BODY_REGIONS[region]
    energy = b.transient_force ** 2 / (2.0 * b.spring)
    base = b.transient_force / math.sqrt(reduced_mass(b.mass, robot_mass) * b.spring)
    ee = b.transient_force / math.sqrt(reduced_mass(b.mass, arm_mass / 2.0 + load) * b.spring)
    return Caps(energy, base, ee)
