"""The service unit passes systemd's own checker and has what the daemon relies on."""

from __future__ import annotations

import configparser
import shutil
import subprocess
from pathlib import Path

import pytest

UNIT = Path(__file__).resolve().parents[1] / "systemd" / "mmctl.service"


def _unit() -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # type: ignore[assignment]
    cp.read(UNIT)
    return cp


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze is not installed here (.ci/run installs systemd)")
def test_systemd_analyze_verify() -> None:
    res = subprocess.run(["systemd-analyze", "verify", str(UNIT)], capture_output=True,
                         check=False, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "Unknown" not in res.stderr and "ignoring" not in res.stderr, res.stderr


def test_unit_declares_the_notify_watchdog_and_rt_contract() -> None:
    svc = _unit()["Service"]
    assert svc["Type"] == "notify" and svc["NotifyAccess"] == "main"
    assert svc["WatchdogSec"] and svc["Restart"] == "on-failure"
    assert svc["User"] == "mmctl" and svc["RuntimeDirectory"] == "mmctl"
    families = svc["RestrictAddressFamilies"].split()
    assert {"AF_UNIX", "AF_CAN", "AF_NETLINK", "AF_INET"} <= set(families)
    assert "CAP_SYS_NICE" in svc["AmbientCapabilities"] and int(svc["LimitRTPRIO"]) >= 80
    assert "mmctl run" in svc["ExecStart"]
    # fd exhaustion must not end the control socket (issue 17): a limit well above the
    # daemon's descriptors and its connection cap
    assert int(svc["LimitNOFILE"]) >= 1024
