"""`mmctl probe arm` against the fake UR controller: success (text and JSON with a jog)
and the one-line failures (nothing answers, remote control off, protective stop)."""

from __future__ import annotations

import json
import random
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from mmctl.cli import main
from mmctl.sim.fake_ur import CommandKind, FakeURController, start_fake_ur

Q0 = [0.3, -1.7, 1.6, -1.5, -1.57, 0.2]
MMCTL = Path(sys.executable).with_name("mmctl")
pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def config(tmp_path: Path) -> str:
    """Tolerant stale detection: a loaded test machine may stall the fake for a few ms."""
    path = tmp_path / "arm.yaml"
    path.write_text("arm:\n  stale_cycles: 50\n")
    return str(path)


@pytest.fixture
def fake(loopback_host: str) -> Iterator[FakeURController]:
    with start_fake_ur(loopback_host, q_init=Q0) as f:
        yield f


def test_probe_jogs_one_joint_and_prints_json(fake: FakeURController, config: str) -> None:
    out = subprocess.run(
        [str(MMCTL), "probe", "arm", "--host", fake.host, "--config", config,
         "--jog-joint", "5", "--speed", "0.2", "--seconds", "0.5", "--json"],
        check=False, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    report = json.loads(out.stdout)  # stdout holds exactly one JSON object
    assert report["q_start"] == pytest.approx(Q0)
    assert report["cycles_sent"] == 250
    assert report["runtime_state"] == 2 and report["safety_status_bits"] == 1
    moved = [e - s for s, e in zip(report["q_start"], report["q_end"])]
    assert moved[:5] == [0.0] * 5 and moved[5] > 0.05
    assert report["q_end"] == pytest.approx(fake.state().q.tolist(), abs=1e-6)
    assert report["controller_version"] == "5.11.0.108249"
    assert report["qd"] == [0.0] * 6
    jog = fake.commands(CommandKind.SPEEDJ)
    assert len(jog) == 250 and all(c.qd == (0, 0, 0, 0, 0, 0.2) for c in jog)
    assert fake.commands(CommandKind.SPEED_STOP)[0].deceleration == 10.0  # arm.stop_deceleration
    assert fake.commands(CommandKind.STOP_SCRIPT)  # close() ends the control script


def test_probe_prints_the_arm_state(fake: FakeURController, config: str,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["probe", "arm", "--host", fake.host, "--config", config]) == 0
    text = capsys.readouterr().out
    assert f"UR controller {fake.host}  PolyScope 5.11.0.108249" in text
    assert "runtime state 2 (2 = PLAYING), safety status bits 0x1" in text
    assert "0.3" in text and "-1.7" in text
    assert fake.commands(CommandKind.SPEEDJ) == []  # no jog asked


def _fails(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("mmctl probe: error: ")
    return err


def test_probe_nothing_answers(capsys: pytest.CaptureFixture[str]) -> None:
    host = f"127.{random.randint(100, 254)}.{random.randint(0, 255)}.{random.randint(2, 254)}"
    err = _fails(["probe", "arm", "--host", host], capsys)
    assert f"nothing answers at {host}:29999" in err and "refused" in err


def test_probe_remote_control_off(fake: FakeURController,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    fake.set_remote_control(False)
    err = _fails(["probe", "arm", "--host", fake.host], capsys)
    assert "remote control is off" in err
    assert fake.commands(CommandKind.SCRIPT) == []  # refused before any upload


@pytest.mark.parametrize("inject, words", [
    ("set_protective_stop", "protective stop"),
    ("set_emergency_stop", "emergency stop"),
])
def test_probe_safety_stop(fake: FakeURController, capsys: pytest.CaptureFixture[str],
                           inject: str, words: str) -> None:
    getattr(fake, inject)(True)
    err = _fails(["probe", "arm", "--host", fake.host, "--jog-joint", "0"], capsys)
    assert f"the arm is in {words}" in err
    assert fake.commands(CommandKind.SPEEDJ) == []


def test_mmctl_fake_ur_serves_the_probe(config: str, capsys: pytest.CaptureFixture[str]) -> None:
    """`mmctl fake-ur` in the foreground of its own process, probed by `mmctl probe arm`."""
    for _ in range(5):
        host = f"127.{random.randint(100, 254)}.{random.randint(0, 255)}.{random.randint(2, 254)}"
        proc = subprocess.Popen([str(MMCTL), "fake-ur", "--host", host, "--q-init", *map(str, Q0)],
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert proc.stdout is not None
        banner = proc.stdout.readline()
        listening = proc.stdout.readline()
        if "fake_ur_listening" in listening:
            break
        proc.wait(30)  # address taken by someone else: try another
    # drain the rest of its output: a full pipe would block the fake's next log line, and
    # with it its exit on SIGINT (seen in full CI runs under load)
    out = proc.stdout
    assert out is not None
    drain = threading.Thread(target=out.read, daemon=True)
    drain.start()
    try:
        assert banner.startswith(f"fake UR controller on {host}: dashboard 29999")
        assert main(["probe", "arm", "--host", host, "--config", config, "--json"]) == 0
        report = json.loads(capsys.readouterr().out)
        assert report["q_start"] == pytest.approx(Q0) and report["runtime_state"] == 2
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(30)
        except subprocess.TimeoutExpired:  # never left serving after the test
            proc.kill()
            proc.wait()
            raise
        assert code == 130
