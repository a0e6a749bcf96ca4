"""`mmctl replay`: a daemon's inputs log run through the pure update again gives the
same commands, cycle by cycle -- the update is a function of its readings and inbox.

The daemon runs its real loop thread on the real transports against the simulated
robot's fakes (fake UR controller in its own process, CAN sensor and CiA 402 drives on
the in-process virtual bus), with a push, an enable, mode, profile and parameter
changes, a fault and a disable while it records; the replay then runs in this process
on the recorded numbers alone.
"""

from __future__ import annotations

import itertools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from loopback import free_loopback_host
from mmctl.cli import main
from mmctl.config import Config, config_from_dict
from mmctl.errors import FaultCause, MmctlError
from mmctl.runtime.factory import create_daemon
from mmctl.runtime.inputlog import VERSION, InputLog, LogError, iter_rows, read_log, replay
from mmctl.sim.world import SimWorld
from waiting import wait_for

pytestmark = pytest.mark.timeout(600)
_uid = itertools.count()


def replay_config() -> Config:
    uid = next(_uid)
    return config_from_dict({
        "name": "replay-tests",
        "sim": {"enabled": True, "human": False, "auto_enable": False},
        "arm": {"host": free_loopback_host(207), "stale_cycles": 10_000,
                "watchdog_min_frequency": 1.0},
        "sensor": {"transport": "can",
                   "can": {"interface": "virtual", "channel": f"rp-s-{uid}"},
                   "wrench": {"stale_timeout": 5.0}},
        "base": {"transport": "canopen",
                 "canopen": {"interface": "virtual", "channel": f"rp-b-{uid}",
                             "heartbeat_timeout": 5.0, "sdo_timeout": 2.0,
                             "stop_timeout": 10.0},
                 "command_watchdog": 10.0},
        "loop": {"max_consecutive_misses": 5_000, "max_total_misses": 1_000_000_000},
    })


def _enable(d: Any) -> None:
    """``enable``, again after a refusal: a starved machine can leave a link lost or a
    condition up for a while (seen: the arm's process ended on a stale link); an enable
    reconnects lost links.  What is recorded is replayed whatever it was."""
    for attempt in range(10):
        try:
            d.call("enable")
            return
        except MmctlError:
            if attempt == 9:
                raise
            time.sleep(1.0)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A log of a daemon that armed, moved, changed mode, profile and a parameter,
    faulted on a wrench over the limit and on a drive fault, re-armed and was
    disabled."""
    folder = tmp_path_factory.mktemp("replay") / "inputs"
    cfg = replay_config()
    sim = SimWorld(cfg)
    sim.start()
    log = InputLog(folder, cfg)
    log.open()
    d = create_daemon(cfg, socket_path=None, input_log=log)
    try:
        d.open()
        d.start()
        wait_for(lambda: d.cycles > 50 and not d.last_conditions, "healthy cycles")
        d.call("tare")
        wait_for(lambda: not d.core.taring, "the tare")
        d.call("enable")
        sim.set_push([15.0, 5.0, 0.0])
        n = d.cycles
        wait_for(lambda: d.cycles > n + 300, "cycles pushed")
        d.call("mode", mode="locomotion")
        d.call("profile", profile="reduced")
        d.call("set", key="admittance.damping", value=[60.0] * 6)
        n = d.cycles
        wait_for(lambda: d.cycles > n + 300, "cycles in locomotion")
        sim.set_push([0.0, 0.0, 200.0])  # over the wrench limit: a fault, the stop
        wait_for(lambda: d.safety.state.value == "fault", "the fault")
        sim.set_push(None)
        wait_for(lambda: FaultCause.WRENCH_LIMIT not in d.last_conditions,
                 "the wrench limit's condition to clear")
        _enable(d)
        sim.set_push([-10.0, 0.0, 0.0])
        n = d.cycles
        wait_for(lambda: d.cycles > n + 200, "cycles pushed again")
        sim.inject("drive_fault")  # found by a read or by the twist (then write_failed)
        wait_for(lambda: d.safety.state.value == "fault", "the drive fault")
        wait_for(lambda: d.last_conditions, "the drive's condition")
        _enable(d)  # resets the drive
        n = d.cycles
        wait_for(lambda: d.cycles > n + 200, "cycles pushed after the reset")
        d.call("disable")
        n = d.cycles
        wait_for(lambda: d.cycles > n + 20, "cycles after the disable")
    finally:
        d.shutdown()
        sim.close()
    return folder


def test_a_recorded_run_replays_to_identical_commands(recorded: Path) -> None:
    _cfg, rows, side = read_log(recorded)
    assert len(rows) > 1000
    kinds = {k for ev in side for k in ev if k != "cycle"}
    assert {"inbox", "conditions"} <= kinds, kinds
    inbox = [c["t"] for ev in side if "inbox" in ev for c in ev["inbox"]]
    for t in ("Tare", "BeginEnable", "EnableCheck", "Release", "EnableFinish", "SetMode",
              "SetProfile", "Install", "Disable"):
        assert t in inbox, inbox
    moving = [c for _, c in iter_rows(recorded) if c.qd_arm is not None and c.qd_arm.any()]
    assert len(moving) > 100 and any(c.stop for _, c in iter_rows(recorded))  # (a starved
    # loop holds the arm on repeated poses: fewer moving cycles than cycles pushed)
    result = replay(recorded)
    assert result.cycles == len(rows)
    assert result.first_difference is None, result


def test_replay_finds_the_first_cycle_that_differs(recorded: Path, tmp_path: Path) -> None:
    """A log whose recorded speedJ was changed in one cycle: replay names that cycle."""
    copy = tmp_path / "changed"
    copy.mkdir()
    for name in ("meta.json", "side.jsonl"):
        (copy / name).write_bytes((recorded / name).read_bytes())
    _, rows, _ = read_log(recorded)
    rows = rows.copy()
    moving = [k for k, (_, c) in enumerate(iter_rows(recorded))
              if c.qd_arm is not None and c.qd_arm.any()]
    k = moving[len(moving) // 2]
    from mmctl.runtime.inputlog import _AT  # the row layout

    rows[k, _AT["qd_arm"]] += 1e-9  # one joint, one nano-radian per second
    (copy / "rows.f64").write_bytes(rows.tobytes())
    result = replay(copy)
    assert result.first_difference == int(rows[k, 0]) and "speedJ" in result.detail, result


def test_the_replay_command(recorded: Path, tmp_path: Path,
                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(recorded)]) == 0
    out = capsys.readouterr().out
    assert "every command identical to the recording" in out, out
    assert main(["replay", str(recorded), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["first_difference"] is None
    assert main(["replay", str(tmp_path)]) == 2
    assert "not a readable inputs log" in capsys.readouterr().err


def test_a_log_of_a_newer_version_is_refused(recorded: Path, tmp_path: Path) -> None:
    """A log written by a newer mmctl may hold records this one would skip: refused,
    naming both versions, rather than replayed differently."""
    copy = tmp_path / "newer"
    copy.mkdir()
    for name in ("rows.f64", "side.jsonl"):
        (copy / name).write_bytes((recorded / name).read_bytes())
    meta = json.loads((recorded / "meta.json").read_text())
    assert meta["version"] == VERSION
    (copy / "meta.json").write_text(json.dumps({**meta, "version": VERSION + 1}))
    with pytest.raises(LogError, match=f"version {VERSION + 1}; this mmctl reads versions "
                                       f"1 to {VERSION}"):
        read_log(copy)


def test_a_log_folder_in_use_is_refused(recorded: Path) -> None:
    with pytest.raises(LogError, match="holds an inputs log already"):
        InputLog(recorded, replay_config()).open()


def test_rows_round_trip_exactly() -> None:
    """A row holds the readings and commands bit for bit (float64)."""
    from mmctl.control.update import Commands, Readings
    from mmctl.errors import FaultCause
    from mmctl.runtime.inputlog import WIDTH, fill_row, row_commands, row_readings
    from mmctl.types import ArmState, Odometry, Wrench

    rng = np.random.default_rng(3)
    arm = ArmState(rng.normal(size=6), rng.normal(size=6), 1234.5678901234, 2, 1, 0.4)
    w = Wrench(rng.normal(size=3), rng.normal(size=3), 99.123456789, 4242, 0x8000)
    o = Odometry(*rng.normal(size=7))
    r = Readings(17, 5.25, 0.002, arm, w, o, 0b1100000000, {}, (3, 9), 3, True, False)
    qd = rng.normal(size=6)
    c = Commands(False, qd, (0.1, -0.2, 0.3), False, None)
    row = np.zeros(WIDTH)
    fill_row(row, r, c)
    back = row_readings(row, {FaultCause.SENSOR_STALE: {"age_ms": 12.0}})
    assert back.index == 17 and back.now == 5.25 and back.inputs == 0b1100000000
    assert back.arm is not None and np.array_equal(back.arm.q, arm.q)
    assert back.arm.controller_time == arm.controller_time and back.arm.speed_scaling == 0.4
    assert back.wrench is not None and np.array_equal(back.wrench.torque, w.torque)
    assert back.wrench.sequence == 4242 and back.wrench.status == 0x8000
    assert back.odom == o and back.overrun == (3, 9) and back.misses == 3 and back.arm_busy
    rc = row_commands(row)
    assert rc.qd_arm is not None and np.array_equal(rc.qd_arm, qd)
    assert rc.twist == c.twist and not rc.stop and not rc.kick


def test_a_failed_write_is_replayed_through_the_updates_own_transition(tmp_path: Path) -> None:
    """A command the write could not send latches its fault in its own cycle through
    the update's pure ``write_failed`` transition; the log records the failure (not a
    changed state) and replay runs the same transition: identical commands.  Without
    that record the replay's robot moves on where the recorded one stopped."""
    from mmctl.control.update import BeginEnable, EnableCheck, EnableFinish, Release
    from test_update import DT, PUSH, rig

    r = rig()
    folder = tmp_path / "log"
    log = InputLog(folder, r.update.cfg)
    log.open()

    def step(inbox: list[Any] | None = None) -> int:
        r.t += DT
        r.index += 1
        readings = r.readings()
        r.state, cmds, _ = r.update(r.state, readings, inbox or [])
        log.append(readings, inbox or [], cmds)
        return readings.index

    step()
    for inbox in ([BeginEnable()], [EnableCheck()], [Release("base"), EnableFinish()]):
        step(inbox)
    assert r.state.safety.armed
    r.force = PUSH.copy()
    for _ in range(20):
        step()
    failed = step()  # this cycle's base twist does not go out: the link is closed
    details = {"device": "base", "error": "the socketcand connection closed"}
    r.state, events = r.update.write_failed(r.state, FaultCause.BASE_LINK, details)
    assert r.state.safety.latched is FaultCause.BASE_LINK and r.state.twist_sent is None
    assert events
    log.outcome(failed, "write_failed", {"cause": "base_link_lost", "details": details})
    for _ in range(20):
        step()
    log.close()
    side = (folder / "side.jsonl").read_text().splitlines()
    assert sum('"write_failed"' in ln for ln in side) == 1
    assert not any('"patch"' in ln for ln in side)
    ok = replay(folder)
    assert ok.first_difference is None and ok.cycles == r.index, ok
    # the record is what makes it equal
    (folder / "side.jsonl").write_text(
        "".join(ln + "\n" for ln in side if '"write_failed"' not in ln))
    res = replay(folder)
    assert res.first_difference == failed + 1 and "speedJ" in res.detail, res
