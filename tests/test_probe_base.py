"""`mmctl probe base`: success (JSON and text) and the one-line "nothing answers" errors."""

from __future__ import annotations

import json
import os
import time
import tty
import uuid
from pathlib import Path

import pytest

from mmctl.cli import main
from mmctl.config import config_from_dict
from mmctl.sim.fake_serial_bridge import FakeSerialBridge


def _config(tmp_path: Path, serial_timeout: float = 1.0, **canopen: object) -> str:
    """A config file with generous timeouts (a loaded machine is not a dead link), the
    drives' own command watchdog included (a probe starved for 0.2 s under a full test
    run had its drives quick-stop: 0x8130, the master's heartbeat late)."""
    co = {"interface": "virtual", "channel": f"probe-{uuid.uuid4().hex[:10]}",
          "heartbeat_timeout": 5.0,
          "sdo_timeout": 5.0, **canopen}
    lines = ["base:", "  command_watchdog: 10.0", "  canopen:"]
    lines += [f"    {k}: {v}" for k, v in co.items()]
    lines += ["  serial:", "    link_timeout: 5.0", f"    timeout: {serial_timeout}"]
    path = tmp_path / "probe.yaml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def _check_report(rep: dict, transport: str) -> None:
    assert rep["transport"] == transport
    assert [d["state"] for d in rep["drives"]] == ["OPERATION ENABLED"] * 4
    assert [d["wheel"] for d in rep["drives"]] == ["FL", "FR", "BL", "BR"]
    assert rep["odometry_before"]["x"] == pytest.approx(0.0, abs=1e-6)
    assert rep["odometry_after"]["x"] > 0.005
    assert rep["odometry_after"]["vx"] == pytest.approx(0.0, abs=1e-3)  # stopped
    m = rep["motion"]
    assert m["cycles"] == 150 and m["twist"] == [0.1, 0.0, 0.0]
    assert set(m["cycle_us"]) == {"mean", "p50", "p99", "max"}


def test_probe_canopen_simulated_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["probe", "base", "--config", _config(tmp_path), "--simulate",
               "--twist", "0.1", "0", "0", "--seconds", "0.3", "--json"])
    assert rc == 0
    rep = json.loads(capsys.readouterr().out)
    _check_report(rep, "canopen")
    assert rep["node_ids"] == [1, 2, 3, 4] and rep["simulated"] is True
    assert [d["link"] for d in rep["drives"]] == ["OPERATIONAL"] * 4
    assert [d["statusword"] for d in rep["drives"]] == ["0x0637"] * 4
    assert [d["state"] for d in rep["before_enable"]] == ["SWITCH ON DISABLED"] * 4


def test_probe_serial_on_a_pty_port(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config_from_dict({})
    with FakeSerialBridge(cfg) as bridge:
        capsys.readouterr()  # the bridge's own start-up log line is not the probe's output
        rc = main(["probe", "base", "--config", _config(tmp_path), "--transport", "serial",
                   "--port", bridge.port, "--twist", "0.1", "0", "0", "--seconds", "0.3",
                   "--json"])
        assert rc == 0
        rep = json.loads(capsys.readouterr().out)
        _check_report(rep, "serial")
        assert rep["port"] == bridge.port
        assert rep["odometry_after"]["x"] == pytest.approx(bridge.pose()[0], abs=1e-3)
        deadline = time.monotonic() + 5.0
        while bridge.enabled:  # the probe disabled the base at the end (not waited for)
            assert time.monotonic() < deadline
            time.sleep(0.005)


def test_probe_text_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["probe", "base", "--config", _config(tmp_path), "--simulate", "--transport",
               "serial"])
    assert rc == 0
    out = capsys.readouterr().out
    assert out.startswith("base: serial on port /dev/pts/")
    assert out.count("OPERATION ENABLED") == 4
    assert "odometry after" in out


def test_probe_canopen_nothing_answers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["probe", "base", "--config", _config(tmp_path, sdo_timeout=0.1)])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("mmctl probe: error: no drive answers on channel 'probe-")
    assert err[0].endswith("(node ids 1, 2, 3, 4)")


def test_probe_serial_nothing_answers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        rc = main(["probe", "base", "--config", _config(tmp_path, serial_timeout=0.02),
                   "--transport", "serial", "--port", os.ttyname(slave)])
    finally:
        os.close(master)
        os.close(slave)
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no bridge answers on serial port" in err[0]


def test_probe_rejects_bad_seconds(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["probe", "base", "--twist", "0.1", "0", "0", "--seconds", "0"])
    assert "must be > 0" in capsys.readouterr().err
