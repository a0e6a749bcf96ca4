"""Virtual walls (``walls:``): the handle's box in the base frame and the base's keep-in
area in the world frame.  Closed loop on the simulated robot's own plant: a person who
pushes into a wall is stopped before it, the motion along it and away from it stays
free, and without the wall the same push goes through."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from mmctl.config import config_from_dict
from mmctl.control.step import Controller, StepInputs
from mmctl.errors import ConfigError
from mmctl.model.planar import world_to_base
from mmctl.sim.plant import Plant

T = 0.002
#: the tool point of the default q_des, base frame: (0.493, 0.174, 1.026) m
Z_MIN = 0.85  # a floor 0.18 m under the handle
BOX = [[0.1, -0.8, Z_MIN], [1.0, 0.8, 1.4]]
#: [m] how far the IDK's tracking error and the drives' lag may carry a point past the
#: bound (measured: 6 um for the handle sliding along the floor, 0.25 um for the base)
TRACK = 1e-4
LAG = 1e-3
AREA = [[-1.0, -1.0], [0.6, -1.0], [0.6, 1.5], [-1.0, 1.5]]  # x_max 0.6 m ahead


def _cfg(**walls: Any) -> Any:
    return config_from_dict({"limits": {"body_region": "none"}, "walls": walls})


def _run(ctl: Controller, force: list[float], seconds: float, mode: str = "min-energy",
         plant: Plant | None = None) -> tuple[Plant, list[Any]]:
    """The person pushes the handle with ``force`` (world frame) for ``seconds``: the
    plant and every cycle's outputs."""
    if plant is None:
        plant = Plant(ctl.cfg, np.concatenate((ctl.q_des[:6], np.zeros(3))))
    state = ctl.initial_state(mode)
    outs = []
    for _ in range(int(seconds / T)):
        q, qd = plant.state()
        f_h = np.concatenate((world_to_base(force, float(q[8])), np.zeros(3)))
        state, out = ctl.step(state, StepInputs(f_h, q, qd, T))
        assert out.fault is None, out.fault
        outs.append(out)
        plant.step(out.qdot_arm, out.base_twist, T)
    return plant, outs


def _tool_z(ctl: Controller, plant: Plant) -> float:
    return float(ctl.model.update(plant.state().q).p_base[2])


def test_a_push_down_stops_above_the_floor_of_the_box() -> None:
    ctl = Controller(_cfg(ee_box=BOX))
    _plant, outs = _run(ctl, [0.0, 0.0, -30.0], 4.0)
    zs = [float(o.p[2]) for o in outs]
    assert min(zs) > Z_MIN - TRACK, min(zs)  # never through
    assert zs[-1] < Z_MIN + 0.02, zs[-1]  # it got there: the band let it in
    assert abs(float(outs[-1].v_d[2])) < 0.01  # the admittance's state holds no push
    assert "wall" in {o.limit for o in outs}
    # without the wall the same push goes through the floor within the time (with the
    # self-collision check off: it alone stops the handle above the base's deck)
    free = config_from_dict({"limits": {"body_region": "none"},
                             "safety": {"collision_check": False}})
    _free, outs_free = _run(Controller(free), [0.0, 0.0, -30.0], 4.0)
    assert min(float(o.p[2]) for o in outs_free) < Z_MIN - 0.3


def test_along_and_away_from_a_wall_the_motion_is_free() -> None:
    ctl = Controller(_cfg(ee_box=BOX))
    plant, _ = _run(ctl, [0.0, 0.0, -30.0], 3.0)  # at the floor
    x0 = float(ctl.model.update(plant.state().q).p_base[0])
    # along it (pushing down and forward): the forward speed is the admittance's F / B
    plant, outs = _run(ctl, [15.0, 0.0, -30.0], 2.0, plant=plant)
    assert float(outs[-1].v_d[0]) == pytest.approx(15.0 / 75.0, rel=0.02)
    assert float(ctl.model.update(plant.state().q).p_base[0]) > x0 + 0.3
    assert min(float(o.p[2]) for o in outs) > Z_MIN - TRACK
    # away from it: up at once, at the full admittance speed
    z0 = _tool_z(ctl, plant)
    plant, outs = _run(ctl, [0.0, 0.0, 30.0], 1.0, plant=plant)
    assert float(outs[-1].v_d[2]) == pytest.approx(30.0 / 75.0, rel=0.02)
    # no wind-up against the wall: after 0.1 s as fast as from rest (0.4 (1 - e^-1.9))
    assert float(outs[49].v_d[2]) > 0.3, float(outs[49].v_d[2])
    assert _tool_z(ctl, plant) > z0 + 0.2


@pytest.mark.parametrize("mode", ["locomotion", "min-energy"])
def test_the_base_stays_in_its_area(mode: str) -> None:
    ctl = Controller(_cfg(base_area=AREA))
    plant, outs = _run(ctl, [40.0, 0.0, 0.0], 8.0, mode)
    base_x = float(plant.state().q[6])
    # in the band, not through: the drives' lag (the plant's velocity loop) carries the
    # base past the commanded approach by well under a millimetre
    assert 0.6 - 0.15 < base_x < 0.6 + LAG, base_x
    assert "wall" in {o.limit for o in outs}
    # sideways along the edge, the base moves freely
    y0 = float(outs[-1].p[1])
    plant, outs = _run(ctl, [40.0, 30.0, 0.0], 3.0, mode, plant=plant)
    assert float(outs[-1].p[1]) > y0 + 0.5  # the handle slides along at 30 N
    assert float(plant.state().q[6]) < 0.6 + LAG
    # without the area the same push takes the base past the edge
    free, _ = _run(Controller(_cfg()), [40.0, 0.0, 0.0], 8.0, mode)
    assert float(free.state().q[6]) > 0.9


def test_the_base_is_held_even_when_the_handle_moves_along_the_wall() -> None:
    """The IDK may move the base outward while the handle's own velocity has no
    outward part (here: the null-space return to q_des after the arm was pushed
    forward): the base's velocity is clamped after the IDK as well."""
    ctl = Controller(_cfg(base_area=AREA))
    q0 = np.concatenate((ctl.q_des[:6], [0.5, 0.0, 0.0]))  # 0.1 m from the edge
    q0[1] += 0.3  # the arm displaced from q_des: the return moves the base
    plant = Plant(ctl.cfg, q0)
    plant, _outs = _run(ctl, [0.0, 0.0, 0.0], 6.0, "locomotion", plant=plant)
    assert float(plant.state().q[6]) < 0.6 + LAG


@pytest.mark.parametrize(("walls", "message"), [
    ({"base_area": [[0, 0], [2, 2], [2, 0], [0, 2]]}, "convex"),
    ({"base_area": [[1, 1], [3, 1], [3, 3], [1, 3]]}, "must contain the origin"),
    ({"base_area": [[-1, -1], [1, -1]]}, "at least 3"),
    ({"ee_box": [[0, 0, 0], [1, -1, 1]]}, "below its maximum"),
    ({"ee_box": [[0, 0, 0], [1, 1, 1000]]}, "millimetres"),
])
def test_bad_walls_are_named(walls: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        _cfg(**walls)
    assert "walls." in str(err.value)


def test_a_box_without_the_preferred_pose_is_refused() -> None:
    with pytest.raises(ConfigError, match="walls.ee_box.*robot.q_des"):
        Controller(_cfg(ee_box=[[0.1, -0.8, 1.1], [1.0, 0.8, 1.4]]))


def test_a_start_outside_the_area_does_not_move_the_robot_by_itself() -> None:
    """Odometry starts at the origin, inside; a base that ends up far outside (an
    odometry reset elsewhere) is not pulled back by itself, one just past the edge
    (what the drives' lag leaves) is brought back, and pushing further out is refused."""
    ctl = Controller(_cfg(base_area=AREA))
    for x0, moved in ((0.6 + 0.5, False), (0.6 + 0.003, True)):
        q0 = np.concatenate((ctl.q_des[:6], [x0, 0.0, 0.0]))
        plant, _ = _run(ctl, [0.0, 0.0, 0.0], 1.0, "locomotion", plant=Plant(ctl.cfg, q0))
        x = float(plant.state().q[6])
        if moved:
            assert 0.6 - 1e-3 < x < 0.6 + 1e-4, x
        else:
            assert abs(x - x0) < 1e-6, x
        plant, _outs = _run(ctl, [40.0, 0.0, 0.0], 1.0, "locomotion", plant=plant)
        assert float(plant.state().q[6]) <= max(x, 0.6) + 1e-6  # not out (further)
