"""The daemon on the simulated robot with --record: the .rrd, read back with rerun's own
API, holds the documented entities with the expected sample counts, and the metrics
recomputed from it equal the ones the daemon logged for a bracketed trial."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mmctl.config import config_from_dict
from mmctl.errors import IpcError
from mmctl.runtime.factory import create_daemon, open_sim
from mmctl.runtime.ipc import request
from mmctl.telemetry import layout
from mmctl.telemetry.recording import column_name, load_recording, recording_metrics
from mmctl.telemetry.rerun_sink import Destinations
from mmctl.telemetry.service import TelemetryService
from simconfig import LOAD_PROOF, sim_config
from waiting import wait_for

WAIT = 90.0  # generous: a loaded machine starts the fake UR process slowly


def _wait(pred: Any, what: str, timeout: float = WAIT) -> Any:
    return wait_for(pred, what, timeout, interval=0.05)


def _status(sock: Path) -> dict[str, Any] | None:
    try:
        return request(sock, "status", timeout=5.0)
    except IpcError:
        return None


@pytest.mark.timeout(300)
def test_daemon_records_trial_and_metrics_match(tmp_path: Path, loopback_host: str) -> None:
    # no fault may interrupt the samples (a loaded machine's starved sensor reads would)
    cfg = config_from_dict(sim_config(loopback_host, tmp_path,
                                      {**LOAD_PROOF, "telemetry": {"scene_rate": 20.0}}))
    rrd = tmp_path / "run.rrd"
    sock = tmp_path / "mmctl.sock"
    service = TelemetryService(cfg, Destinations(record=str(rrd)))
    sim = open_sim(cfg)  # the simulated robot's process: the caller's, as `mmctl run`'s
    assert sim is not None
    daemon = create_daemon(cfg, sock, telemetry=service, sim=sim)
    result: dict[str, Any] = {}
    publisher: dict[str, Any] = {}
    runner = threading.Thread(target=lambda: result.update(rc=daemon.run(install_signals=False)),
                              daemon=True)
    runner.start()
    try:
        _wait(lambda: _status(sock), "the daemon's control socket")
        publisher["pub"] = service.publisher
        _wait(lambda: daemon.cycles > 100, "100 cycles")
        assert request(sock, "trial", action="start")["trial"] == 1
        start = daemon.cycles
        _wait(lambda: daemon.cycles > start + 600, "600 more cycles")
        logged = request(sock, "trial", action="stop", timeout=30.0)
        status = request(sock, "status")
        assert status["telemetry"]["enabled"] and status["telemetry"]["record"] == str(rrd)
        assert status["telemetry"]["trial_active"] is False
    finally:
        daemon.request_stop("test")
        runner.join(WAIT)
        sim.close()
    assert not runner.is_alive() and result.get("rc") == 0

    pub = publisher["pub"]
    assert pub.error is None and pub.published == pub.ring.accepted > 0

    # -- rerun's own reader --------------------------------------------------------------
    from rerun.chunk import RrdReader

    store = RrdReader(rrd).stream().collect()
    table = store.reader(index=layout.TIMELINE_CYCLE).to_arrow_table()
    counts = {s.path: len(table) - table.column(column_name(s.path)).null_count
              for s in layout.FULL_RATE + layout.PLOT_RATE + (layout.LOOP_TIMING,)
              if column_name(s.path) in table.column_names}
    assert set(counts) == {s.path for s in layout.FULL_RATE + layout.PLOT_RATE
                           + (layout.LOOP_TIMING,)}
    full = counts[layout.ENERGY.path]
    assert all(counts[s.path] == full for s in layout.FULL_RATE)
    rec = load_recording(rrd)
    assert len(rec.cycle) == full
    # every sample the loop handed over is in the file, or was counted as dropped:
    assert full == pub.published and rec.dropped == pub.ring.dropped
    assert full + rec.dropped == pub.ring.accepted + pub.ring.dropped
    stride = round(cfg.loop.rate_hz / cfg.telemetry.plot_rate)
    assert counts[layout.FORCE.path] == int((rec.cycle % stride == 0).sum())
    # the robot's nearest parts (the self-collision check's) at plot rate; NaN here: the
    # robot stays disarmed, so the controller runs no check (tests/test_urdf.py and
    # test_status_snapshot.py check the values)
    near = [float(np.ravel(v)[0]) for v in
            table.column(column_name(layout.NEAREST.path)).to_pylist() if v is not None]
    assert counts[layout.NEAREST.path] == counts[layout.FORCE.path] == len(near)
    assert all(np.isnan(d) or 0.0 < d < 0.5 for d in near)
    # loop timing: each sample row carries its previous cycle's (the very first has none):
    assert counts[layout.LOOP_TIMING.path] in (full - 1, full)
    assert daemon.loop.cycles >= full
    for entity in (layout.BASE, layout.ARM, layout.ARM_JOINTS, layout.HANDLE,
                   layout.TWIST_ARROW, layout.FORCE_ARROW, layout.P_DES, layout.EVENTS,
                   *layout.ARM_JOINT_ENTITIES):
        assert any(c.startswith(f"/{entity}:") for c in table.column_names), entity
    # the robot drawn from its URDF (tests/test_recording.py checks its pose)
    static = store.reader(index=None).to_arrow_table()
    assert any(c.startswith(f"/{layout.ROBOT}/") and "/deck:Boxes3D" in c
               for c in static.column_names)

    # -- metrics: recording == what the daemon logged -------------------------------------
    (trial,) = rec.trials
    assert (trial.start_cycle, trial.stop_cycle) == (logged["start_cycle"], logged["stop_cycle"])
    (again,) = recording_metrics(rec)
    assert again.samples == logged["samples"] > 500
    m = again.metrics
    assert (m.E_mean, m.F_mean, m.v_mean, m.x_f, m.T_f) == (
        logged["E"], logged["F_h"], logged["v"], logged["x_f"], logged["T_f"])
