"""Settings of one study run (not part of the daemon's configuration)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

from mmctl.config import Config, default_config, load_config
from mmctl.config.control import STRATEGIES
from mmctl.errors import ConfigError
from mmctl.sim.human import QUICK_HOLES, STUDY_HOLES
from mmctl.study.results import PAPER_APPROACHES

#: Users of ``--quick`` when ``--users`` is not given.
QUICK_USERS = 3


@dataclass(frozen=True)
class StudyConfig:
    """One study: who, which approaches, how long.

    users: number of simulated users; seed: population seed; strategies: control
    approaches, each an ``idk.strategy`` value; quick: the short two-hole task;
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

    def __post_init__(self) -> None:
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
            "t_max": 60.0 if quick else 120.0,
        }
        args.update(kw)
        return cls(**args)  # type: ignore[arg-type]

    def control_config(self, strategy: str) -> Config:
        """The control configuration of one execution: the file (or defaults) with
        ``idk.strategy`` set to ``strategy`` and ``loop.rate_hz`` to 1/dt.  The defaults
        are the paper's robot: without the hand-guiding caps, the joint-limit hand-over
        and the singularity braking it did not have (``limits.body_region: none``,
        ``idk.avoid_joint_limits: false``, ``safety.brake_condition: 1``: braked only at
        the fault's own level; a config file states its own)."""
        if self.config_path:
            cfg = load_config(Path(self.config_path))
        else:
            cfg = default_config()
            cfg = replace(cfg, limits=replace(cfg.limits, body_region="none"),  # type: ignore[type-var]
                          idk=replace(cfg.idk, avoid_joint_limits=False),  # type: ignore[type-var]
                          safety=replace(cfg.safety, brake_condition=1.0))  # type: ignore[type-var]
        return replace(cfg, idk=replace(cfg.idk, strategy=strategy),  # type: ignore[type-var]
                       loop=replace(cfg.loop, rate_hz=1.0 / self.dt))  # type: ignore[type-var]
