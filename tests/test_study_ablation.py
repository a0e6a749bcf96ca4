"""The study's ablations (issue 32): each removes one modelling choice and nothing
else; the table names the choices a claim's effect rests on."""

from __future__ import annotations

import numpy as np
import pytest

from mmctl.study import ablation as ab
from mmctl.study.config import StudyConfig
from mmctl.study.results import Execution, Series
from mmctl.study.users import draw_user


def test_each_ablation_changes_its_own_setting_and_nothing_else() -> None:
    study = StudyConfig.make(quick=True, users=2)
    cfg = study.control_config("switch")
    by = {a.name: a for a in ab.ABLATIONS}
    assert by["dead_band_0"].config(cfg).sensor.wrench.deadband_force == 0.0
    assert by["dead_band_0"].config(cfg).sensor.wrench.deadband_torque == 0.0
    assert by["no_slip"].config(cfg).sim.base_slip_lateral == 0.0
    assert by["no_slip"].config(cfg).sim.base_slip_longitudinal == 0.0
    assert by["press_cost_0"].config(cfg) == cfg
    person = draw_user(0, 1)
    assert by["press_cost_0"].user(0, 1) == type(person)(
        **{**person.__dict__, "press_time": 0.0})
    assert by["no_decision_delay"].user(0, 1).decision_delay == 0.0
    assert by["baseline"].user(0, 1) == person and by["baseline"].config(cfg) == cfg


def _ex(user: int, strategy: str, t_f: float) -> Execution:
    z = np.zeros(1, dtype=np.float32)
    return Execution(user, strategy, 1.0, 10.0, 0.1, 0.1, t_f, 0.5, 20.0, 0, True, 0,
                     Series(z, z, z, z, z, z, np.zeros(1, dtype=np.int8)))


def test_the_table_names_the_ablation_a_claims_effect_rests_on() -> None:
    """T_f: switch > min-energy in the baseline (every user), gone without the press
    cost: the claim rests on press_cost_0; others on the control law or nothing."""
    def run(switch_extra: float) -> list[Execution]:
        out = []
        for u in range(6):
            out += [_ex(u, "locomotion", 30.0 + 0.1 * u), _ex(u, "min-energy", 30.0 + 0.1 * u),
                    # (without the extra: a few ms either way, no effect)
                    _ex(u, "switch", 30.0 + 0.1 * u + switch_extra + 0.01 * (u + 1) * (-1) ** u)]
        return out

    md, rows = ab.table({"baseline": run(1.0), "press_cost_0": run(0.0)})
    row = next(r for r in rows if r["claim"].startswith("T_f [s]: Switch >"))
    assert row["r"]["baseline"] == pytest.approx(1.0) and row["rests_on"] == ["press_cost_0"]
    assert "press_cost_0 |" in md
