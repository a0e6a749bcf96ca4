"""`mmctl study --quick` end to end through the real control step(), and determinism."""

from __future__ import annotations

import contextlib
import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.errors import ConfigError
from mmctl.model import RobotModel
from mmctl.sim.human import HandleObservation, HumanAction, Phase, SimulatedHuman, noise_seed
from mmctl.study.config import StudyConfig
from mmctl.study.report import results_csv
from mmctl.study.runner import run_execution, run_study, start_configuration, study_task
from mmctl.study.users import draw_user

USERS = 2


@pytest.fixture(scope="module")
def quick_cli(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("study")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        rc = main(["study", "--quick", "--users", str(USERS), "--seed", "7", "--jobs", "2",
                   "--out", str(out)])
    assert rc == 0
    (out / "stdout.txt").write_text(printed.getvalue())
    return out


def test_quick_study_writes_every_output(quick_cli: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("results.csv", "summary.json", "boxplots.png", "velocity.png", "energy.png"):
        f = quick_cli / name
        assert f.is_file() and f.stat().st_size > 0, name
    for name in ("boxplots.png", "velocity.png", "energy.png"):
        assert (quick_cli / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader((quick_cli / "results.csv").open()))
    assert len(rows) == USERS * 3
    assert [r["strategy"] for r in rows[:3]] == ["locomotion", "switch", "min-energy"]
    for r in rows:
        assert r["completed"] == "1" and r["faults"] == "0"
        assert 0.0 < float(r["E"]) < 20.0
        assert 2.0 < float(r["F_h"]) < 40.0
        assert 0.03 < float(r["v"]) < 0.5
        assert 0.0 <= float(r["x_f"]) < 1.5
        assert 3.0 < float(r["T_f"]) < 60.0
        assert 0.0 <= float(r["x_f_hold"]) < 1.5
        # one far hole: the switch user presses the button; the others have none
        assert (int(r["switches"]) >= 1) if r["strategy"] == "switch" else r["switches"] == "0"
    doc = json.loads((quick_cli / "summary.json").read_text())
    assert set(doc["medians"]) == {"locomotion", "switch", "min-energy"}
    for med in doc["medians"].values():
        assert set(med) == {"E", "F_h", "v", "x_f", "T_f", "x_f_hold"}
    assert set(doc["friedman"]) == {"E", "F_h", "v", "x_f", "T_f", "x_f_hold"}
    assert doc["task"] == "wall" and len(doc["holes_approach"]) == 2
    printed = (quick_cli / "stdout.txt").read_text()
    assert "x_f hold [m] sim | paper" in printed and "| x_f hold [m] |" in printed
    pairs = {"locomotion vs switch", "locomotion vs min-energy", "switch vs min-energy"}
    for metric in ("E", "F_h", "v", "x_f", "T_f"):
        assert set(doc["pairwise"][metric]) == pairs
        for r in doc["pairwise"][metric].values():
            assert 0.0 <= r["p"] <= r["p_corr"] <= 1.0
    assert doc["median_user"] in range(USERS)


def test_base_moves_least_with_min_energy(quick_cli: Path) -> None:
    rows = list(csv.DictReader((quick_cli / "results.csv").open()))
    by = {(int(r["user"]), r["strategy"]): r for r in rows}
    for u in range(USERS):
        assert float(by[u, "min-energy"]["E_base"]) < float(by[u, "locomotion"]["E_base"])
        assert float(by[u, "min-energy"]["E"]) < float(by[u, "locomotion"]["E"])


def test_same_seed_same_results_whatever_the_jobs(quick_cli: Path) -> None:
    study = StudyConfig.make(quick=True, users=USERS, seed=7)
    res = run_study(study, jobs=1)
    assert results_csv(res.executions) == (quick_cli / "results.csv").read_text()


def test_human_sees_no_mode_in_a_closed_loop_run() -> None:
    """Closed-loop runs under two approaches: replaying each run's observations into a
    fresh human reproduces every action exactly, so nothing but the observations
    reaches the human; the same human faces both approaches."""
    study = StudyConfig.make(quick=True, users=1, seed=3, t_max=3.0)
    logs = {}
    for strategy in ("locomotion", "min-energy"):
        log: list[tuple[HandleObservation, HumanAction]] = []
        ex, _, _ = run_execution(study, 0, strategy, observe=lambda o, a, log=log: log.append((o, a)))
        assert not ex.completed and ex.T_f == pytest.approx(3.0, abs=0.01)  # t_max reached
        logs[strategy] = log
    cfg = study.control_config("min-energy")
    task = study_task(RobotModel(cfg.robot), start_configuration(cfg), study)
    for log in logs.values():
        fresh = SimulatedHuman(draw_user(3, 0), task, noise_seed=noise_seed(3, 0), button=False)
        for obs, act in log:
            again = fresh.update(obs)
            np.testing.assert_array_equal(again.force, act.force)
            assert (again.switch_request, again.phase) == (act.switch_request, act.phase)
    # the approaches did differ (so the check is not vacuous)
    a, b = (np.array([o.base for o, _ in logs[s]]) for s in ("locomotion", "min-energy"))
    assert np.abs(a - b).max() > 1e-3


def test_bad_arguments() -> None:
    with pytest.raises(ConfigError, match="strategies"):
        StudyConfig(strategies=("nonsense",))
    with pytest.raises(ConfigError):
        StudyConfig(users=0)
    assert main(["study", "--jobs", "0"]) == 2


# --- issue 19: the wall task, the hold, the button, the noise in closed loop ---


def test_the_wall_task_at_the_study_start_pose() -> None:
    """At the wall pose the peg (tool z) is horizontal and points forward; the holes lie
    on a vertical wall ahead, at heights within the family's range, one at the handle's
    height, the farthest beyond the UR10e's 1.3 m reach from its mount."""
    study = StudyConfig()
    cfg = study.control_config("min-energy")
    model = RobotModel(cfg.robot)
    q0 = start_configuration(cfg)
    kin = model.update(q0, inertia=False)
    assert kin.R_base[:, 2] @ np.array([1.0, 0.0, 0.0]) > 0.999
    task = study_task(model, q0, study)
    assert task.surface is not None
    normal = np.array(task.surface.normal)
    np.testing.assert_allclose(normal, [-1.0, 0.0, 0.0], atol=1e-5)  # q_des to 0.1 mrad
    heights = []
    mount = np.array(cfg.robot.arm_mount[:2])
    far = 0.0
    for h in task.holes:
        ap, bt = np.array(h.approach), np.array(h.bottom)
        assert (ap - np.array(task.surface.point)) @ normal == pytest.approx(0.0, abs=1e-12)
        np.testing.assert_allclose(bt - ap, -study.wall.depth * normal, atol=1e-12)
        heights.append(ap[2])
        far = max(far, float(np.linalg.norm(ap[:2] - mount)))
    lo, hi = study.wall.heights
    assert all(lo <= z <= hi for z in heights)
    assert min(abs(z - kin.p[2]) for z in heights) < 1e-12
    assert far > 1.3
    assert study.wall.holes[0] <= len(task.holes) <= study.wall.holes[1]
    # the board task keeps the configuration's pose (tool down): a horizontal board
    board = StudyConfig(task="board")
    bcfg = board.control_config("min-energy")
    btask = study_task(RobotModel(bcfg.robot), start_configuration(bcfg), board)
    assert btask.surface is not None
    np.testing.assert_allclose(btask.surface.normal, [0.0, 0.0, 1.0], atol=1e-5)
    assert len(btask.holes) == len(board.holes)


def test_the_wall_task_needs_a_horizontal_peg() -> None:
    study = StudyConfig()
    cfg = StudyConfig(task="board").control_config("locomotion")  # q_des: tool down
    with pytest.raises(ConfigError, match="robot.q_des.*horizontal"):
        study_task(RobotModel(cfg.robot), start_configuration(cfg), study)
    with pytest.raises(ConfigError, match="study.task"):
        StudyConfig(task="floor")


class _Hold:
    """A study variant whose users hold for ``hold`` seconds."""

    def __init__(self, hold: float) -> None:
        self.hold = hold

    def config(self, cfg):  # type: ignore[no-untyped-def]
        return cfg

    def chain(self, cfg):  # type: ignore[no-untyped-def]
        from mmctl.control.cycle import CycleChain

        return CycleChain(cfg)

    def user(self, seed: int, index: int):  # type: ignore[no-untyped-def]
        from dataclasses import replace

        return replace(draw_user(seed, index), hold_time=self.hold)


def test_the_hold_moves_x_f_hold_and_not_t_f() -> None:
    study = StudyConfig.make(quick=True, users=1, seed=5)
    held, _, n_held = run_execution(study, 0, "min-energy")
    none, _, n_none = run_execution(study, 0, "min-energy", variant=_Hold(0.0))
    assert held.completed and none.completed
    for m in ("E", "F_h", "v", "x_f", "T_f"):  # every metric stops at T_f
        assert held.metric(m) == none.metric(m), m
    assert none.x_f_hold == none.x_f
    assert abs(held.x_f_hold - held.x_f) > 1e-4  # the null-space task went on
    assert n_held - n_none == pytest.approx(draw_user(5, 0).hold_time / study.dt, abs=3)


def test_only_the_switch_user_presses_and_the_noise_is_the_users() -> None:
    """The switch approach's user presses (and pauses) for the far hole; the others
    never do; the motor noise is the same stream in every approach."""
    study = StudyConfig.make(quick=True, users=1, seed=7)
    logs: dict[str, list[HumanAction]] = {}
    execs = {}
    for strategy in ("locomotion", "switch", "min-energy"):
        log: list[HumanAction] = []
        execs[strategy], _, _ = run_execution(study, 0, strategy,
                                              observe=lambda o, a, log=log: log.append(a))
        logs[strategy] = log
    press = draw_user(7, 0).press_time
    for strategy, log in logs.items():
        pressing = sum(1 for a in log if a.phase is Phase.PRESS) * study.dt
        if strategy == "switch":
            assert execs[strategy].switches >= 2
            assert pressing == pytest.approx(execs[strategy].switches * press, abs=0.02)
        else:
            assert pressing == 0.0 and execs[strategy].switches == 0
            assert not any(a.switch_request for a in log)
    n = min(len(v) for v in logs.values())
    ref = np.array([a.noise for a in logs["locomotion"][:n]])
    for strategy in ("switch", "min-energy"):
        np.testing.assert_array_equal(np.array([a.noise for a in logs[strategy][:n]]), ref)


class _LowForceLimit(_Hold):
    """A study variant whose wrench limit is below the users' push: the first push is a
    ``wrench_limit`` fault."""

    def __init__(self, limit: float) -> None:
        super().__init__(0.0)
        self.limit = limit

    def config(self, cfg):  # type: ignore[no-untyped-def]
        from dataclasses import replace

        w = replace(cfg.sensor.wrench, force_limit=self.limit)
        return replace(cfg, sensor=replace(cfg.sensor, wrench=w))

    def user(self, seed: int, index: int):  # type: ignore[no-untyped-def]
        return draw_user(seed, index)


def test_the_study_runs_the_daemons_update_a_fault_stops_the_robot_for_good() -> None:
    """The study runs the daemon's whole update, not only the control chain: a fault
    (a push beyond the wrench limit) goes through the safety state machine, which
    latches it and stops the robot; it stays at rest (nobody re-enables) while the
    person goes on pushing, and the task is not finished."""
    study = StudyConfig.make(quick=True, users=1, seed=5, t_max=4.0)
    log: list[tuple[HandleObservation, HumanAction]] = []
    ex, _, _ = run_execution(study, 0, "min-energy", variant=_LowForceLimit(6.0),
                             observe=lambda o, a: log.append((o, a)))
    assert ex.faults > 0 and not ex.completed and ex.stopped == "wrench_limit"
    forces = np.array([np.linalg.norm(a.force) for _, a in log])
    first = int(np.argmax(forces > 6.0))  # the person's push crosses the limit here
    assert forces.max() > 6.0 and first > 0
    # from shortly after the fault to the end the handle does not move, while pushed
    later = np.array([o.position for o, _ in log[first + 100:]])
    assert len(later) > 500 and forces[first + 100:].min() > 6.0
    assert np.abs(later - later[0]).max() < 1e-6
    # the same run with the limit above the push moves the handle on, never stopped
    free, _, _ = run_execution(study, 0, "min-energy", variant=_LowForceLimit(150.0))
    assert free.faults == 0 and free.v > 0.01 and free.stopped == ""
