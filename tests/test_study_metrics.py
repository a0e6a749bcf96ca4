"""The study's per-execution metrics (issue 32): one velocity source, F_h after the
sensor chain beside the hand's applied force, the base's clearance to the wall."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mmctl.config import default_config
from mmctl.sim.human import Plane
from mmctl.study.config import StudyConfig
from mmctl.study.results import CSV_COLUMNS, csv_row
from mmctl.study.runner import _Deck, run_execution


def test_the_decks_clearance_is_its_nearest_corner_to_the_plane() -> None:
    cfg = default_config()
    sx, sy = cfg.robot.deck_size[0], cfg.robot.deck_size[1]
    cx = cfg.robot.deck_center[0]
    # a wall 2 m ahead along world +x, its normal toward the robot (-x)
    deck = _Deck(cfg, Plane((2.0, 0.0, 1.0), (-1.0, 0.0, 0.0)))
    q = np.zeros(9)
    assert deck.clearance(q) == pytest.approx(2.0 - (cx + sx / 2))
    q[8] = math.pi / 2  # turned 90 deg: base (x, y) is world (-y, x), its right side ahead
    cy = cfg.robot.deck_center[1]
    assert deck.clearance(q) == pytest.approx(2.0 - (sy / 2 - cy))
    q[:] = 0.0
    q[6] = 2.0 - cx  # the deck's centre on the plane: half the deck through it
    assert deck.clearance(q) == pytest.approx(-sx / 2)
    assert _Deck(cfg, None).clearance(q) == math.inf


def test_an_execution_measures_f_h_after_the_chain_and_v_from_the_same_velocities() -> None:
    """Admittance at steady state: the processed force is B v (75 N s/m), so F_h - 75 v
    is small; the hand pushes harder than that (bias, dead band before the chain)."""
    ex, _, _ = run_execution(StudyConfig.make(quick=True), 0, "min-energy")
    assert ex.completed
    assert abs(ex.F_h - 75.0 * ex.v) < 0.5, (ex.F_h, ex.v)
    assert ex.F_applied > ex.F_h + 1.0, (ex.F_applied, ex.F_h)
    assert math.isfinite(ex.wall_clearance) and ex.wall_clearance < 0.5
    assert math.isfinite(ex.E_base_near) and ex.E_base_near >= 0.0
    row = dict(zip(CSV_COLUMNS, csv_row(ex), strict=True))
    assert float(row["F_applied"]) == pytest.approx(ex.F_applied, rel=1e-9)
    assert float(row["limited"]) == pytest.approx(ex.limited, rel=1e-9, abs=1e-12)
