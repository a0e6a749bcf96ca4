"""The simulated participants: a seeded population of :class:`HumanParams`.

User ``i`` of seed ``s`` is drawn from its own generator
``numpy.random.default_rng(SeedSequence([s, i]))``, so a user is the same whatever
the number of users or worker processes.  The distributions (medians, spreads and
clipping ranges) are in :data:`POPULATION`; ``docs/study.md`` tabulates them.  A
user's motor noise comes from a generator of its own,
:func:`mmctl.sim.human.noise_seed` ``(seed, index)``: the same in every approach.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from mmctl.sim.human import HumanParams


@dataclass(frozen=True)
class Draw:
    """One parameter's distribution: ``kind`` "lognormal" (``centre`` = median, ``spread``
    = sigma of the log), "normal" (mean, standard deviation) or "uniform" (``centre`` ±
    ``spread``), then clipped to [``lo``, ``hi``]."""

    kind: str
    centre: float
    spread: float
    lo: float
    hi: float

    def sample(self, rng: np.random.Generator) -> float:
        """One value."""
        if self.kind == "lognormal":
            v = self.centre * float(np.exp(self.spread * rng.standard_normal()))
        elif self.kind == "normal":
            v = self.centre + self.spread * float(rng.standard_normal())
        elif self.kind == "uniform":
            v = self.centre + self.spread * float(rng.uniform(-1.0, 1.0))
        else:
            raise ValueError(f"unknown distribution {self.kind!r}; use lognormal, normal, uniform")
        return min(max(v, self.lo), self.hi)


#: Parameter -> distribution.  Drawn in this order (changing the order changes users).
POPULATION: dict[str, Draw] = {
    "stiffness": Draw("lognormal", 350.0, 0.35, 150.0, 900.0),  # N/m
    "damping": Draw("lognormal", 30.0, 0.30, 10.0, 80.0),  # N s/m
    "speed": Draw("normal", 0.25, 0.04, 0.15, 0.38),  # m/s
    "reaction_time": Draw("lognormal", 0.30, 0.25, 0.15, 0.70),  # s
    "dwell_time": Draw("uniform", 0.6, 0.2, 0.4, 0.8),  # s
    "f_comfort": Draw("normal", 40.0, 6.0, 25.0, 60.0),  # N
    # comfort_reach: 0.62-0.77 of the UR10e's 1.3 m reach (UR data sheet): a person
    # who steers the arm by the handle treats its reach as their own, whose normal
    # (forearm-sweep) reach is 0.75 of the maximum (15 in / 20 in, Sanders & McCormick
    # 1987, as ergonomics guides quote it); UR's "recommended reach" is inside its
    # maximum, beyond it the tool's orientation (held horizontal in the wall task) is
    # restricted (UR, "What is a singularity?").  docs/study.md, "Population".
    "comfort_reach": Draw("uniform", 0.90, 0.10, 0.80, 1.00),  # m
    "near_distance": Draw("uniform", 0.25, 0.07, 0.18, 0.32),  # m
    "decision_delay": Draw("lognormal", 0.60, 0.30, 0.30, 1.50),  # s
    # (issue 19; drawn after the others, so earlier users keep their values)
    # force CV: median 4 %, sigma_log 0.6 = sqrt(ln(1 + (3.1 / 4.3)^2)) from the
    # 4.1-4.5 % +- 3.1 % of Baweja et al. 2009 (Exp Brain Res 197:35)
    "force_cv": Draw("lognormal", 0.04, 0.60, 0.01, 0.15),  # 1
    # button press: the keystroke-level model's K, 0.20 s (average skilled typist) to
    # 0.28 s (average non-secretary typist) (Card, Moran & Newell 1980)
    "press_time": Draw("uniform", 0.24, 0.04, 0.20, 0.28),  # s
}

#: Insertion speed as a fraction of the reach speed; f_max - f_comfort [N].
INSERTION_RATIO = 0.32
FORCE_HEADROOM = 30.0
#: The end-of-trial hold [s], the same for everyone (the protocol's instruction): three
#: time constants of the paper's null-space gain G = 1 s^-1.
HOLD_TIME = 3.0


def draw_user(seed: int, index: int,
              population: Mapping[str, Draw] | None = None) -> HumanParams:
    """User ``index`` (0-based) of the population of ``seed``; ``population``: other
    distributions with :data:`POPULATION`'s keys in its order (the sensitivity
    analysis moves their medians), default :data:`POPULATION`."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))
    pop = POPULATION if population is None else population
    v = {name: d.sample(rng) for name, d in pop.items()}
    return HumanParams(
        stiffness=v["stiffness"],
        damping=v["damping"],
        speed=v["speed"],
        insertion_speed=INSERTION_RATIO * v["speed"],
        reaction_time=v["reaction_time"],
        dwell_time=v["dwell_time"],
        f_comfort=v["f_comfort"],
        f_max=v["f_comfort"] + FORCE_HEADROOM,
        comfort_reach=v["comfort_reach"],
        near_distance=v["near_distance"],
        decision_delay=v["decision_delay"],
        hold_time=HOLD_TIME,
        press_time=v["press_time"],
        force_cv=v["force_cv"],
    )


def draw_users(n: int, seed: int) -> list[HumanParams]:
    """Users 0 .. n-1 of the population of ``seed``."""
    if n < 1:
        raise ValueError(f"need at least one user, got {n}")
    return [draw_user(seed, i) for i in range(n)]
