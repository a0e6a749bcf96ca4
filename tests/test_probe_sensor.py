"""`mmctl probe sensor`: success (JSON) and "nothing answers", both transports."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.commands.probe_sensor import SIMULATED_WRENCH
from mmctl.sim.fake_ft_can import FakeFtCanSensor
from mmctl.sim.fake_rdt import FakeRdtServer
from mmctl.sim.wrench_source import ConstantWrench

W = (1.25, -2.5, 20.0, 0.125, -0.25, 0.5)
# stale timeout generous: these runs share two cores with other test suites
COMMON = ["--samples", "30", "--stale-timeout", "2"]


def test_can_simulated_json(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["probe", "sensor", "--transport", "can", "--channel", "test-probe-can",
               "--simulate", "--json", *COMMON])
    out = capsys.readouterr().out
    assert rc == 0
    report = json.loads(out)
    assert report["transport"] == "can" and report["simulated"] is True
    assert report["link"] == "virtual:test-probe-can@0x20"
    assert report["samples"] == 30 and report["reads"] >= 30
    assert isinstance(report["lost"], int) and report["out_of_order"] == 0
    for key, sl in (("force", slice(0, 3)), ("torque", slice(3, 6))):
        for which in ("mean", "last"):
            # 16-bit gauges through the fake's calibration: within a few counts
            np.testing.assert_allclose(report[key][which], SIMULATED_WRENCH[sl], atol=0.05)
    assert set(report["read_us"]) == {"mean", "p99", "max"}


def test_can_nothing_answers(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["probe", "sensor", "--transport", "can", "--interface", "virtual",
               "--channel", "test-probe-nobody", "--base-id", "0x21", *COMMON])
    err = capsys.readouterr().err
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("mmctl probe: error: no reply from the F/T sensor "
                               "virtual:test-probe-nobody@0x21")


def test_can_missing_matrix_frame_is_one_line_naming_it(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """A sensor that leaves out the middle frame (CAN id base|3) of its matrix-row
    answer: the probe says which row and which frame, not "no reply"."""
    cfg = tmp_path / "sensor.yaml"
    cfg.write_text("sensor:\n  can:\n    connect_timeout: 1.0\n", encoding="utf-8")
    with FakeFtCanSensor(ConstantWrench(W), channel="test-probe-matrix", base_id=0x22) as fake:
        fake.matrix_opcodes = (0x2, 0x4)
        rc = main(["probe", "sensor", "--transport", "can", "--interface", "virtual",
                   "--channel", "test-probe-matrix", "--base-id", "0x22", "--config", str(cfg),
                   *COMMON])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0] == ("mmctl probe: error: calibration matrix row 0 (Fx) from the F/T sensor "
                      "virtual:test-probe-matrix@0x22 is incomplete: no frame on CAN id 0x223 "
                      "(c[0][2], c[0][3]) within 1000 ms (got 0x222, 0x224)")


def test_can_simulate_refuses_a_real_interface(capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["probe", "sensor", "--transport", "can", "--interface", "socketcan",
               "--simulate", *COMMON])
    assert rc == 2
    assert "virtual" in capsys.readouterr().err


def test_rdt_against_the_fake_server_json(capsys: pytest.CaptureFixture[str]) -> None:
    with FakeRdtServer(ConstantWrench(W)) as fake:
        host, port = fake.address
        rc = main(["probe", "sensor", "--transport", "rdt", "--host", host, "--port", str(port),
                   "--json", *COMMON])
    report = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert report["link"] == f"udp://{host}:{port}" and report["simulated"] is False
    assert report["samples"] == 30
    np.testing.assert_allclose(report["force"]["mean"], W[:3], atol=1e-6)
    np.testing.assert_allclose(report["torque"]["last"], W[3:], atol=1e-6)
    assert report["lost"] == 0 and report["out_of_order"] == 0


def test_rdt_real_cli_process_human_output() -> None:
    """The installed CLI in its own process against the fake server in this one."""
    with FakeRdtServer(ConstantWrench(W)) as fake:
        host, port = fake.address
        proc = subprocess.run(
            [sys.executable, "-m", "mmctl.cli", "probe", "sensor", "--transport", "rdt",
             "--host", host, "--port", str(port), *COMMON],
            check=False, capture_output=True, text=True, timeout=120,
        )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith(f"sensor rdt udp://{host}:{port}: 30 samples")
    assert lines[1].split()[:3] == ["force", "[N]", "mean"]
    assert [float(x) for x in lines[1].split()[3:6]] == pytest.approx(W[:3], abs=1e-4)


def test_rdt_nothing_listening(capsys: pytest.CaptureFixture[str]) -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    rc = main(["probe", "sensor", "--transport", "rdt", "--host", "127.0.0.1", "--port",
               str(port), *COMMON])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert err[0] == (f"mmctl probe: error: nothing answers at udp://127.0.0.1:{port} "
                      "(connection refused)")


def test_rdt_silent_peer(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        rc = main(["probe", "sensor", "--transport", "rdt", "--host", "127.0.0.1", "--port",
                   str(port), *COMMON])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1
    assert "nothing answers at udp://127.0.0.1" in err[0] and "0/1 RDT records" in err[0]


def test_bad_arguments_are_one_line_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["probe", "sensor", "--samples", "0"]) == 2
    assert "--samples" in capsys.readouterr().err
