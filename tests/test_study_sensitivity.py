"""The Morris screening of the study's conclusions (`mmctl study sensitivity`): the
factor table, the variant it runs, the claims' judgement, the analysis on synthetic
outputs and the command end to end on a tiny setting."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.errors import ConfigError
from mmctl.study.config import StudyConfig
from mmctl.study.replication import Claim
from mmctl.study.results import Execution, Series
from mmctl.study.sensitivity import (
    FACTORS,
    R_CRIT,
    Factor,
    Point,
    analyse,
    check_factors,
    factor_by_name,
    judge,
    override,
    point_setting,
    population,
    r_crit,
    sample,
)
from mmctl.study.users import POPULATION, draw_user

pytest.importorskip("SALib")


def test_r_crit_is_the_papers_threshold() -> None:
    # z = Phi^-1(1 - 0.05/6) = 2.3940; n = 27: S = 378, sd = sqrt(27*28*55/24) = 41.623
    assert r_crit(27) == pytest.approx(2 * 2.39398 * math.sqrt(27 * 28 * 55 / 24) / 378,
                                       rel=1e-4)
    assert R_CRIT == pytest.approx(0.5272, abs=1e-3)
    assert r_crit(10) > r_crit(27)  # fewer users need a larger effect


def test_judge_differences_and_non_differences() -> None:
    higher = Claim("E", "locomotion", "min-energy", True, 1)
    a, b = np.array([2.0, 2.1, 2.5, 1.9]), np.array([0.5, 0.6, 0.4, 0.7])
    y, r, holds = judge(higher, a, b)
    assert y == pytest.approx(float(np.median(a - b))) and r == 1.0 and holds
    y, r, holds = judge(higher, b, a)  # the other way round: fails
    assert y < 0 and r == -1.0 and not holds
    lower = Claim("T_f", "switch", "min-energy", True, -1)
    assert judge(lower, b, a)[2] and judge(lower, b, a)[0] > 0
    none = Claim("v", "locomotion", "min-energy", False, 0)
    mixed = np.array([0.1, -0.2, 0.3, -0.4]), np.zeros(4)
    assert judge(none, *mixed)[2]  # r = -0.2
    assert not judge(none, a, b)[2]  # a clear difference: the claim of none fails


def test_the_factor_table() -> None:
    names = [f.name for f in FACTORS]
    assert len(set(names)) == len(names)
    for k, d in POPULATION.items():  # every population median, over its clipping range
        f = factor_by_name(f"human.{k}")
        assert (f.low, f.high, f.group, f.key) == (d.lo, d.hi, "human", k)
    assert factor_by_name("arm.speedj_acceleration").group == "plant"
    assert factor_by_name("layout.spread").group == "layout"
    for f in FACTORS:
        assert f.low < f.high and f.source
    check_factors(StudyConfig.make(quick=True), FACTORS)
    with pytest.raises(ConfigError, match="--factors"):
        factor_by_name("human.shoe_size")
    with pytest.raises(ConfigError, match="is not a configuration key"):
        check_factors(StudyConfig.make(quick=True), [Factor("sim.no_such_key", 0, 1, "", "x")])
    with pytest.raises(ConfigError, match="arm.speedj_acceleration"):
        check_factors(StudyConfig.make(quick=True),
                      [Factor("arm.speedj_acceleration", 1.0, 100.0, "rad/s^2", "x")])


def test_population_medians_move_and_nothing_else() -> None:
    pop = population([("stiffness", 600.0), ("speed", 10.0)])
    assert list(pop) == list(POPULATION)
    assert pop["stiffness"].centre == 600.0 and pop["stiffness"].lo == POPULATION["stiffness"].lo
    assert pop["speed"].centre == POPULATION["speed"].hi  # kept within the clipping range
    assert pop["damping"] == POPULATION["damping"]
    base = [draw_user(0, i) for i in range(20)]
    moved = [Point(medians=(("stiffness", 600.0),)).user(0, i) for i in range(20)]
    assert Point().user(0, 3) == base[3]
    assert np.median([u.stiffness for u in moved]) > np.median([u.stiffness for u in base])
    assert [u.damping for u in moved] == [u.damping for u in base]  # same draws otherwise


def test_points_set_configuration_keys_and_layouts() -> None:
    study = StudyConfig.make(quick=True, users=2)
    f = [factor_by_name("arm.speedj_acceleration"), factor_by_name("layout.spread"),
         factor_by_name("human.speed")]
    st, pt = point_setting(study, f, [6.0, 0.5, 0.3])
    assert st.holes == tuple((0.5 * u, 0.5 * w) for u, w in study.holes)
    assert st.wall.far_edge == (0.5 * study.wall.far_edge[0], 0.5 * study.wall.far_edge[1])
    assert st.wall.near_edge == (0.5 * study.wall.near_edge[0], 0.5 * study.wall.near_edge[1])
    assert pt.config_values == (("arm.speedj_acceleration", 6.0),)
    assert pt.medians == (("speed", 0.3),)
    cfg = pt.config(study.control_config("min-energy"))
    assert cfg.arm.speedj_acceleration == 6.0
    assert cfg.idk.strategy == "min-energy" and cfg.loop.rate_hz == 500.0  # the rest kept
    with pytest.raises(ConfigError, match="arm.speedj_acceleration"):
        override(cfg, [("arm.speedj_acceleration", -1.0)])


def _series(n: int = 10) -> Series:
    z = np.zeros(n, dtype=np.float32)
    return Series(z, z, z, z, z, z, np.zeros(n, dtype=np.int8))


def test_analysis_ranks_the_factor_that_moves_the_output() -> None:
    """Synthetic points: locomotion's E - min-energy's E = 4 x_0 (x_0 in 0..1) and
    nothing else moves: factor 0 ranks first, the others have mu* = 0, and the claim
    "E: locomotion > min-energy" holds only where x_0 > 0 (r = +1 there, 0 at x_0 = 0)."""
    factors = [Factor(f"human.f{i}", 0.0, 1.0, "", "test") for i in range(3)]
    x = sample(factors, 4, seed=2)
    assert np.array_equal(x, sample(factors, 4, seed=2))  # seeded
    points = []
    for row in x:
        execs = []
        for u in range(4):
            for s in ("locomotion", "switch", "min-energy"):
                e = 1.0 + (4.0 * row[0] if s == "locomotion" else 0.0)
                unfinished = u == 3 and s == "switch" and row[1] > 0.5
                execs.append(Execution(user=u, strategy=s, E=e, F_h=10.0, v=0.1, x_f=0.1,
                                       T_f=60.0 if unfinished else 30.0, E_base=0.5,
                                       F_max=20.0, switches=0, completed=not unfinished,
                                       faults=0, series=_series()))
        points.append(execs)
    doc = analyse(factors, x, points, seed=0)
    # completion is recorded per execution and counted per point and in all
    want = [int(row[1] > 0.5) for row in x]
    assert [p["unfinished"] for p in doc["points"]] == want
    assert doc["unfinished"] == sum(want) and doc["executions"] == 12 * len(x)
    for p, row in zip(doc["points"], x, strict=True):
        (ex,) = [e for e in p["executions"] if e["user"] == 3 and e["strategy"] == "switch"]
        assert ex["completed"] is not (row[1] > 0.5) and len(p["executions"]) == 12
    claim = next(c for c in doc["claims"] if c["claim"].startswith("Ē [J]: Locomotion >")
                 and "Minimum" in c["claim"])
    assert claim["factors"][0]["name"] == "human.f0" and claim["factors"][0]["rank"] == 1
    assert claim["factors"][0]["mu_star"] == pytest.approx(4.0)
    assert [f["mu_star"] for f in claim["factors"][1:]] == [0.0, 0.0]
    f0 = claim["factors"][0]
    assert sum(n for _, _, n in f0["holds_by_level"]) == len(x)
    for level, held, n in f0["holds_by_level"]:
        assert held == (n if level > 0 else 0)
    assert f0["holds_where"] != "everywhere"
    assert len(doc["points"]) == len(x) and len(doc["claims"]) == 15


# 18 executions of the whole update and plant: about 125 s on a quiet machine, over 420 s
# with both cores busy (CI)
@pytest.mark.timeout(1200)
def test_sensitivity_command_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["study", "sensitivity", "--trajectories", "2", "--users", "1", "--factors",
               "human.speed", "layout.spread", "--jobs", "1", "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads((tmp_path / "sensitivity.json").read_text())
    assert doc["trajectories"] == 2 and doc["users"] == 1 and len(doc["points"]) == 6
    assert [f["name"] for f in doc["factors"]] == ["human.speed", "layout.spread"]
    rows = list(csv.DictReader((tmp_path / "sensitivity.csv").open()))
    assert len(rows) == 15 * 2
    assert {r["factor"] for r in rows} == {"human.speed", "layout.spread"}
    for r in rows:
        assert float(r["mu_star"]) >= 0.0 and r["rank"] in ("1", "2")
    png = (tmp_path / "sensitivity.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "Morris screening" in capsys.readouterr().out


def test_bad_trajectories_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["study", "sensitivity", "--trajectories", "1", "--out", "/nonexistent"]) == 2
    assert "--trajectories" in capsys.readouterr().err


def test_the_points_tool_lists_the_screens_seeded_steps_and_refuses_a_point_outside_it(
) -> None:
    """tools/sensitivity_points.py runs a screen's points again by index: the sample is
    the screen's (seeded), so the step 24 -> 25 of the default screen is the stiffness
    step of trajectory 1 that docs/study.md's μ* re-check names."""
    import subprocess
    import sys
    from pathlib import Path

    tool = Path(__file__).resolve().parents[1] / "tools" / "sensitivity_points.py"
    out = subprocess.run([sys.executable, str(tool), "--steps"], capture_output=True,
                         text=True, check=True).stdout.splitlines()
    assert len(out) == 4 * 17  # 17 steps in each of the 4 trajectories
    steps = {int(line.split()[0]): line for line in out}
    assert "human.stiffness: 150 -> 650" in steps[24]
    assert "human.speed: 0.38 -> 0.2267" in steps[25]
    assert 17 not in steps  # point 17 ends trajectory 0
    bad = subprocess.run([sys.executable, str(tool), "72"], capture_output=True, text=True,
                         check=False)
    assert bad.returncode == 2 and "give point indices in 0..71 (got [72])" in bad.stderr
