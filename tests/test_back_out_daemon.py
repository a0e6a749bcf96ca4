"""Backing out of the self-collision margin through the running daemon (issue 29,
point 3): the simulated robot starts with its handle 5 mm inside the margin above the
base's deck; `mmctl run` arms there (no fault: within the tolerance), a push deeper
does not take it deeper, and a push out moves it out; pushed on at speed there, the
reduced profile switched on brings the end-effector down to its cap, armed, with no
fault.  A start past the tolerance is
the ``self_collision`` fault present: `enable` is refused and says why.

The same guarantees for every limit over the pure update: tests/test_back_out.py."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mmctl.config import default_config
from mmctl.errors import IpcError
from mmctl.model.geometry import BodyModel
from mmctl.model.robot import RobotModel
from mmctl.runtime.ipc import request
from test_sim_process import Sim, _end, _run_daemon, _wait_auto_enabled

pytestmark = pytest.mark.timeout(600)
CFG = default_config()
MODEL = RobotModel(CFG.robot)
BODY = BodyModel(CFG.robot, MODEL.arm, MODEL.mount)
MARGIN = CFG.safety.collision_margin


def _host(n: int) -> str:
    digits = "".join(c for c in os.environ.get("PYTEST_XDIST_WORKER", "gw0") if c.isdigit())
    return f"127.{60 + int(digits or 0)}.{4 + os.getpid() % 40}.{n}"


def _deck_pose(distance: float) -> np.ndarray:
    """q_des with the shoulder lifted down until the deck and the handle are
    ``distance`` [m] apart."""
    q = np.asarray(CFG.robot.q_des, dtype=float).copy()
    lo, hi = 0.0, 1.2
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        x = q.copy()
        x[1] += mid
        lo, hi = (mid, hi) if _deck_handle(x) > distance else (lo, mid)
    q[1] += lo
    return q


def _deck_handle(q_a: Any) -> float:
    return {d.pair: d.distance for d in BODY.distances(np.asarray(q_a)[:6])}[("deck", "handle")]


def _normal(q_a: np.ndarray) -> list[float]:
    d = {x.pair: x for x in BODY.distances(q_a)}[("deck", "handle")]
    n = np.subtract(d.p2, d.p1)
    return (n / np.linalg.norm(n)).tolist()  # from the deck to the handle (base = world)


def _sim(tmp: Path, host: str, q_a: np.ndarray) -> Sim:
    return Sim(tmp, host, {"robot": {"q_init": [*q_a.tolist(), 0.0, 0.0, 0.0]}})


def test_inside_the_margin_the_daemon_arms_a_push_in_holds_and_a_push_out_moves(
        tmp_path: Path) -> None:
    q0 = _deck_pose(MARGIN - 0.005)
    sim = _sim(tmp_path, _host(2), q0)
    out, sock = tmp_path / "daemon.log", tmp_path / "mmctl.sock"
    daemon = _run_daemon(sim, out)
    try:
        _wait_auto_enabled(sim, sock, out)  # armed there: within the tolerance
        n = np.array(_normal(q0))

        def distance() -> float:
            return _deck_handle(sim.call("status")["arm_q"])

        start = distance()
        assert start == pytest.approx(MARGIN - 0.005, abs=2e-3)
        sim.call("push", force=(-40.0 * n).tolist())  # deeper: held
        time.sleep(1.5)
        assert distance() > start - 0.003
        sim.call("push", force=None)
        st = request(sock, "status", timeout=30.0)
        assert st["state"] == "armed", st
        assert st["robot"]["nearest_parts"]["pair"] == "deck-handle"
        sim.call("push", force=(40.0 * n).tolist())  # out: moves out
        sim.wait_for(lambda: distance() > MARGIN + 0.02, "the handle 2 cm out of the margin")
        sim.call("push", force=None)
        assert request(sock, "status", timeout=30.0)["state"] == "armed"

        # over an ISO cap: the reduced profile (0.25 m/s) switched on at speed
        def ee_speed() -> float:
            st = request(sock, "status", timeout=30.0)
            assert st["state"] == "armed" and st["fault"] is None, st
            return float(st["robot"]["ee_speed_m_s"] or 0.0)

        sim.call("push", force=[0.0, 80.0, 0.0])
        sim.wait_for(lambda: ee_speed() > 0.4, "the end-effector over 0.4 m/s")
        request(sock, "profile", profile="reduced", timeout=30.0)
        sim.wait_for(lambda: ee_speed() < 0.25 * 1.03, "the end-effector down to 0.25 m/s")
        speeds = [ee_speed() for _ in range(5)]  # pushed on: it stays there, and moves
        assert all(0.1 < v < 0.25 * 1.03 for v in speeds), speeds
        sim.call("push", force=None)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(120) == 0, out.read_text()[-3000:]
    finally:
        _end(daemon)
        sim.kill()


def test_past_the_tolerance_enable_is_refused_and_says_why(tmp_path: Path) -> None:
    q0 = _deck_pose(MARGIN - CFG.safety.collision_tolerance - 0.01)
    sim = _sim(tmp_path, _host(3), q0)
    out, sock = tmp_path / "daemon.log", tmp_path / "mmctl.sock"
    daemon = _run_daemon(sim, out)
    try:
        sim.wait_for(lambda: "auto_enable_failed" in out.read_text()
                     or "auto_enabled" in out.read_text(), "the daemon's auto-enable")
        assert "auto_enable_failed" in out.read_text(), out.read_text()[-3000:]
        with pytest.raises(IpcError, match="self_collision"):
            request(sock, "enable", timeout=60.0)
        st = request(sock, "status", timeout=30.0)
        assert st["state"] != "armed" and "self_collision" in st["conditions"], st
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(120) == 0, out.read_text()[-3000:]
    finally:
        _end(daemon)
        sim.kill()
