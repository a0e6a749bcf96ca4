"""What a new user sees of `mmctl run` (issue 31): one log format per output for every
process the command starts, a summary line where no live block shows, a failed start
that names its error and leaves no block, and the simulation's own fault list.

Each test runs the real `mmctl run` (or `mmctl sim`) on its own loopback address; the
conditions are waited for, never timed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from ptyrun import run_on_pty
from simconfig import LOAD_PROOF, write_sim_config
from test_liveview import Screen
from test_sim_process import Sim

pytestmark = pytest.mark.timeout(600)

ROOT = Path(__file__).resolve().parents[1]

#: events that only the processes `mmctl run` starts log: the simulated robot's
#: process (sim_ready), its fake UR controller's child (fake_ur_listening: it came out
#: in structlog's default console format among JSON lines) and the daemon's own
#: socket process (ipc_process_started is the daemon's; the child answers over it)
CHILD_EVENTS = ("sim_ready", "fake_ur_listening", "socketcand_listening",
                "fake_drives_started")


def _config(tmp: Path, host: str, **extra: Any) -> Path:
    return write_sim_config(host, tmp, {
        **LOAD_PROOF, "name": "first-run-test",
        "daemon": {**LOAD_PROOF["daemon"], "socket_path": str(tmp / "run" / "mmctl.sock")},
        **extra})


def _run_cmd(cfg: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "mmctl.cli", "run", "--config", str(cfg), *extra]


def test_off_a_terminal_every_process_logs_json_and_a_summary_shows_the_motion(
        tmp_path: Path, loopback_host: str) -> None:
    """Piped, as `make run | tee run.log` or journald: every line of every process is
    one JSON object, and `summary` events (state, mode, speeds, E_K, misses) come
    every --summary-every seconds, one of them with the robot armed."""
    cfg = _config(tmp_path, loopback_host)
    out = tmp_path / "run.log"
    with out.open("wb") as f:
        proc = subprocess.Popen(_run_cmd(cfg, "--duration", "4", "--summary-every", "0.5"),
                                stdout=f, stderr=subprocess.STDOUT, cwd=str(ROOT),
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert proc.wait(300) == 0, out.read_text()[-4000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(30)
    lines = [line for line in out.read_text().splitlines() if line.strip()]
    events = []
    for line in lines:
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            raise AssertionError(f"not a JSON line: {line!r}") from None
    names = [e["event"] for e in events]
    for name in CHILD_EVENTS:
        assert name in names, (name, sorted(set(names)))
    summaries = [e for e in events if e["event"] == "summary"]
    assert len(summaries) >= 2, names
    for s in summaries:
        assert {"state", "mode", "ee_speed_m_s", "base_speed_m_s", "e_k_J", "misses_pct",
                "cycles"} <= set(s), s
    armed = [s for s in summaries if s["state"] == "armed"]
    assert armed and all(s["mode"] == "min-energy" for s in armed), summaries
    assert any(isinstance(s["ee_speed_m_s"], float) and isinstance(s["e_k_J"], float)
               for s in armed), armed
    stopped = [e for e in events if e["event"] == "daemon_stopped"]
    assert stopped and stopped[-1]["error"] is None, stopped


def _on_pty(cmd: list[str], columns: int = 160) -> tuple[int, str]:
    """Run ``cmd`` with stdout and stderr on a fresh pty: (exit code, what it received)."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    env.update(TERM="dumb", PYTHONUNBUFFERED="1")
    code, raw, _ = run_on_pty(cmd, columns=columns, rows=40, env=env, cwd=str(ROOT))
    return code, raw


def test_on_a_terminal_every_process_logs_console_lines(tmp_path: Path,
                                                        loopback_host: str) -> None:
    """On a terminal (--no-live: the lines as they come): console lines from every
    process, the fake controller's included, and not one JSON line; the summary shows
    there too, since no block does."""
    cfg = _config(tmp_path, loopback_host)
    code, raw = _on_pty(_run_cmd(cfg, "--duration", "3", "--no-live",
                                 "--summary-every", "0.5"))
    assert code == 0, raw[-4000:]
    lines = [line.strip() for line in raw.replace("\r", "").splitlines() if line.strip()]
    assert not [line for line in lines if line.startswith("{")], lines[:20]
    for name in (*CHILD_EVENTS, "summary", "daemon_stopped"):
        assert any(f"] {name} " in line or line.endswith(f"] {name}") for line in lines), \
            (name, lines[:40])


def test_a_failed_start_names_its_error_and_leaves_no_live_block(
        tmp_path: Path, loopback_host: str) -> None:
    """config/robot.yaml with no robot there (its arm's address on loopback, nobody
    listening): the last event says why, the live block is erased, the command fails."""
    data = yaml.safe_load((ROOT / "config" / "robot.yaml").read_text())
    data["arm"]["host"] = loopback_host
    data["daemon"]["socket_path"] = str(tmp_path / "run" / "mmctl.sock")
    data["loop"] = {"rt_priority": 0, "cpu_affinity": [], "cpu_dma_latency": -1}
    cfg = tmp_path / "robot.yaml"
    cfg.write_text(yaml.safe_dump(data))
    code, raw = _on_pty(_run_cmd(cfg))
    assert code != 0, raw[-4000:]
    screen = [line.rstrip() for line in Screen().feed(raw).lines]
    stopped = [line for line in screen if "daemon_stopped" in line]
    assert stopped and "error=" in stopped[-1] and "error=None" not in stopped[-1], screen
    assert f"{loopback_host}:29999" in stopped[-1], stopped
    # no block: neither its header nor its hint line is left on the screen
    assert not [line for line in screen if line.startswith(("mmctl ─", "hint"))], screen
    assert screen[-1].startswith("mmctl run: error:"), screen[-5:]


def test_the_simulations_status_lists_the_injected_faults_in_effect(
        tmp_path: Path, loopback_host: str) -> None:
    """`mmctl sim fault drive_fault` is an event, not a state: listed while the drive
    is in FAULT; a state fault is listed until switched off; a reboot for a while."""
    sim = Sim(tmp_path, loopback_host)
    try:
        assert sim.call("status")["faults"] == []
        sim.call("fault", name="drive_fault")
        sim.wait_for(lambda: "drive_fault" in sim.call("status")["faults"],
                     "drive_fault listed while drive 1 is in FAULT")
        sim.call("fault", name="sensor_saturation", on=True)
        assert sim.call("status")["faults"] == ["drive_fault", "sensor_saturation"]
        sim.call("fault", name="sensor_saturation", on=False)
        sim.call("fault", name="drive_reboot")  # the reboot clears the drive's FAULT
        faults = sim.call("status")["faults"]
        assert "drive_reboot" in faults, faults
        sim.wait_for(lambda: sim.call("status")["faults"] == ["drive_reboot"],
                     "the rebooted drive's FAULT gone, the reboot listed")
        out = subprocess.run([sys.executable, "-m", "mmctl.cli", "sim", "status",
                              "--config", str(sim.config)], check=False, capture_output=True,
                             text=True,
                             cwd=str(ROOT), timeout=120)
        assert "faults: drive_reboot" in out.stdout, out.stdout + out.stderr
    finally:
        sim.kill()



def test_make_run_installs_the_package_without_the_test_extra(tmp_path: Path) -> None:
    """`make run` on a fresh clone: the package alone (about a third of the test venv);
    `make test`: the test extra.  Read from make's own plan (-n), nothing installed."""
    venv = tmp_path / "venv"

    def plan(target: str) -> str:
        out = subprocess.run(["make", "-n", target, f"VENV={venv}"], cwd=str(ROOT),
                             capture_output=True, text=True, check=True, timeout=60)
        return out.stdout

    run, test = plan("run"), plan("test")
    assert "pip install -q -e .\n" in run and "[test]" not in run, run
    assert "mmctl run" in run
    assert "pip install -q -e '.[test]'" in test and "pytest" in test, test
