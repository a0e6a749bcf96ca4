"""Settings of one study run (not part of the daemon's configuration)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from mmctl.config import Config, default_config, load_config
from mmctl.config.control import STRATEGIES
from mmctl.errors import ConfigError
from mmctl.sim.human import (
    QUICK_HOLES,
    QUICK_WALL_FAMILY,
    STUDY_HOLES,
    WALL_FAMILY,
    WallFamily,
    draw_wall_layout,
)
from mmctl.study.results import PAPER_APPROACHES

#: Users of ``--quick`` when ``--users`` is not given.
QUICK_USERS = 3
#: The study's tasks: the paper's wall (horizontal insertion) or the horizontal board.
TASKS: tuple[str, ...] = ("wall", "board")
#: The arm's preferred pose for the wall task (robot.q_des) [rad]: wrist 1 = -pi -
#: shoulder - elbow turns the peg (tool z) horizontal, pointing forward (base +x; the
#: board pose's wrist 1 of -pi/2 points it down); shoulder and elbow put the handle at
#: (0.62, 0.17, 1.05) m in the base frame: 1.05 m above the floor, a standing adult's
#: elbow height (Pheasant & Haslegrave, Bodyspace: median men 1.09 m, women 1.005 m),
#: 0.13 m ahead of the base's front edge (half its 0.98 m length) and 0.65 m from the
#: arm's mount, within every simulated user's comfortable reach (0.80-1.00 m), as the
#: board pose's handle is (0.52 m); condition number of J J^T 63.  docs/study.md.
WALL_Q_DES: tuple[float, ...] = (0.0, -1.6697, 2.5, -3.9719, -1.5708, 0.0)


@dataclass(frozen=True)
class StudyConfig:
    """One study: who, which approaches, how long.

    users: number of simulated users; seed: population seed; strategies: control
    approaches, each an ``idk.strategy`` value; quick: the short two-hole task;
    task: "wall" (the paper's: holes in a vertical wall, a layout drawn per seed from
    ``wall``, a :class:`~mmctl.sim.human.WallFamily`) or "board" (holes in the
    horizontal plane through the start handle, offsets ``holes``);
    dt: control period [s] (the daemon's T: the control config's ``loop.rate_hz`` is
    set to 1/dt); t_max: give up an execution after this
    long [s]; record_every: keep every n-th sample of the time series;
    config_path: control configuration YAML (None: the defaults).
    """

    users: int = 27
    seed: int = 0
    strategies: tuple[str, ...] = PAPER_APPROACHES
    quick: bool = False
    dt: float = 0.002
    t_max: float = 120.0
    record_every: int = 5
    config_path: str | None = None
    holes: tuple[tuple[float, float], ...] = field(default=STUDY_HOLES)
    task: str = "wall"
    wall: WallFamily = field(default=WALL_FAMILY)

    def __post_init__(self) -> None:
        if self.task not in TASKS:
            raise ConfigError("study.task", self.task, f"must be one of {', '.join(TASKS)}")
        if self.users < 1:
            raise ConfigError("study.users", self.users, "must be >= 1")
        if not 0.0 < self.dt <= 0.02:
            raise ConfigError("study.dt", self.dt, "must be in (0, 0.02] s")
        if self.t_max <= 0.0:
            raise ConfigError("study.t_max", self.t_max, "must be > 0 s")
        if self.record_every < 1:
            raise ConfigError("study.record_every", self.record_every, "must be >= 1")
        if not self.strategies:
            raise ConfigError("study.strategies", self.strategies, "name at least one strategy")
        for s in self.strategies:
            if s not in STRATEGIES:
                raise ConfigError("study.strategies", s, f"must be one of {', '.join(STRATEGIES)}")
        if len(set(self.strategies)) != len(self.strategies):
            raise ConfigError("study.strategies", self.strategies, "must not repeat a strategy")

    @classmethod
    def make(cls, quick: bool = False, users: int | None = None, **kw: object) -> StudyConfig:
        """Defaults for a full or ``quick`` study; ``users`` None = 27 or QUICK_USERS."""
        args: dict[str, object] = {
            "users": users if users is not None else (QUICK_USERS if quick else 27),
            "quick": quick,
            "holes": QUICK_HOLES if quick else STUDY_HOLES,
            "wall": QUICK_WALL_FAMILY if quick else WALL_FAMILY,
            "t_max": 60.0 if quick else 120.0,
        }
        args.update(kw)
        return cls(**args)  # type: ignore[arg-type]

    def layout(self, handle_height: float | None = None) -> tuple[tuple[float, float], ...]:
        """The wall task's holes ``(w, z)`` [m] of this seed, in the order of visit
        (:func:`~mmctl.sim.human.draw_wall_layout`); ``handle_height`` [m]: the start
        handle's height, given to the hole at handle height."""
        return draw_wall_layout(self.seed, self.wall, handle_height)

    def control_config(self, strategy: str) -> Config:
        """The control configuration of one execution: the file (or defaults) with
        ``idk.strategy`` set to ``strategy`` and ``loop.rate_hz`` to 1/dt.  The defaults
        are the paper's robot: without the hand-guiding caps, the joint-limit hand-over,
        the singularity braking and the self-collision check it did not have
        (``limits.body_region: none``, ``idk.avoid_joint_limits: false``,
        ``safety.brake_condition: 1``: braked only at the fault's own level,
        ``safety.collision_check: false``; a config file states its own).  The wall task sets
        ``robot.q_des`` to :data:`WALL_Q_DES` (the peg horizontal), with a file too: the
        preferred pose belongs to the task (``robot.q_init``, if the file sets it, must
        then hold the peg horizontal as well)."""
        if self.config_path:
            cfg = load_config(Path(self.config_path))
        else:
            cfg = default_config()
            cfg = replace(cfg, limits=replace(cfg.limits, body_region="none"),  # type: ignore[type-var]
                          idk=replace(cfg.idk, avoid_joint_limits=False),  # type: ignore[type-var]
                          safety=replace(cfg.safety, brake_condition=1.0,  # type: ignore[type-var]
                                         collision_check=False))
        if self.task == "wall":
            cfg = replace(cfg, robot=replace(cfg.robot, q_des=WALL_Q_DES))  # type: ignore[type-var]
        return replace(cfg, idk=replace(cfg.idk, strategy=strategy),  # type: ignore[type-var]
                       loop=replace(cfg.loop, rate_hz=1.0 / self.dt))  # type: ignore[type-var]
