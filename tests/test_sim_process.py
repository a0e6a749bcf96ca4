"""`mmctl sim`: the simulated robot as a process of its own, and its CLI.

One `mmctl sim` subprocess per module (its own loopback address and control socket);
`mmctl run` attaches to it from another process and leaves it running; the CLI
pushes, switches the person and injects faults over the simulation's socket; Ctrl-C
ends it cleanly.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mmctl.cli import main
from mmctl.errors import IpcError
from mmctl.runtime.ipc import ControlClient, request
from simconfig import LOAD_PROOF, write_sim_config
from waiting import wait_while_alive, with_ur_program

pytestmark = pytest.mark.timeout(600)
ROOT = Path(__file__).resolve().parents[1]


def _host(n: int) -> str:
    digits = "".join(c for c in os.environ.get("PYTEST_XDIST_WORKER", "gw0") if c.isdigit())
    return f"127.{10 + int(digits or 0)}.{204 + os.getpid() % 40}.{n}"


class Sim:
    def __init__(self, tmp: Path, host: str, extra: dict[str, Any] | None = None) -> None:
        self.tmp = tmp
        # load-proof timeouts: the daemons run here test no fault that a loaded machine
        # could cause (the enabling switch's fault is its contacts, not a timeout)
        self.config = write_sim_config(host, tmp, {
            **LOAD_PROOF, "name": "sim-test", "sim": {"human": False, "auto_enable": True},
            "daemon": {**LOAD_PROOF["daemon"], "socket_path": str(tmp / "mmctl.sock")},
            **(extra or {})})
        self.socket = tmp / "sim.sock"
        self.out = tmp / "sim.log"
        with self.out.open("ab") as f:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "mmctl.cli", "sim", "--config", str(self.config),
                 "--log-json"], stdout=f, stderr=subprocess.STDOUT, cwd=str(ROOT),
                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.wait_for(lambda: self.call("status"), "the simulation's socket")

    def call(self, cmd: str, **args: Any) -> Any:
        return request(self.socket, cmd, timeout=60.0, **args)

    def log_text(self) -> str:
        return self.out.read_text(errors="replace")

    def wait_for(self, pred: Any, what: str, timeout: float = 180.0) -> Any:
        return wait_while_alive(pred, what, self.proc, "mmctl sim",
                                with_ur_program(self.log_text, self.socket), timeout)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(30)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Sim]:
    s = Sim(tmp_path_factory.mktemp("sim"), _host(2))
    try:
        yield s
    finally:
        s.kill()


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_status_and_push_from_the_cli(sim: Sim, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = ["--config", str(sim.config)]
    rc, out, _ = _cli(capsys, "sim", "status", *cfg)
    assert rc == 0 and out.startswith("person: off"), out
    assert "socketcand: " in out and "(0 client(s))" in out
    rc, out, _ = _cli(capsys, "sim", "push", "0", "30", "0", "--seconds", "5", *cfg)
    assert rc == 0 and "person: push (push [0.0, 30.0, 0.0] N)" in out, out
    rc, out, _ = _cli(capsys, "sim", "status", "--json", *cfg)
    st = json.loads(out)
    assert st["push"] == [0.0, 30.0, 0.0] and st["person"] == "push"
    rc, out, _ = _cli(capsys, "sim", "person", "off", *cfg)
    assert rc == 0 and out.startswith("person: off"), out


@pytest.mark.parametrize("argv, message", [
    (["push", "1", "2"], "push needs three numbers FX FY FZ"),
    (["push", "1", "x", "2"], "push needs three numbers FX FY FZ"),
    (["person", "maybe"], "person needs on or off"),
    (["fault"], "fault needs one NAME"),
    (["fault", "gremlins"], "fault: name = 'gremlins': must be one of: sensor_silent"),
    (["push", "0", "1", "0", "--seconds", "-1"], "push: seconds = -1.0: must be > 0"),
    (["status", "extra"], "status takes no arguments"),
])
def test_cli_errors_are_one_line(sim: Sim, capsys: pytest.CaptureFixture[str],
                                 argv: list[str], message: str) -> None:
    rc, _, err = _cli(capsys, "sim", *argv, "--config", str(sim.config))
    assert rc == 2 and err.count("\n") == 1 and message in err, err
    assert sim.call("status")["pid"] == sim.proc.pid  # carries on


def test_fault_list_and_injection(sim: Sim, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = ["--config", str(sim.config)]
    rc, out, _ = _cli(capsys, "sim", "fault", "--list")
    assert rc == 0 and "drive_reboot" in out and "sensor_garbage" in out
    assert _cli(capsys, "sim", "fault", "sensor_garbage", *cfg)[0] == 0
    assert sim.call("status")["faults"] == ["sensor_garbage"]
    assert _cli(capsys, "sim", "fault", "sensor_garbage", "--off", *cfg)[0] == 0
    assert sim.call("status")["faults"] == []


def test_malformed_requests_get_errors_and_the_sim_carries_on(sim: Sim) -> None:
    with ControlClient(sim.socket, timeout=60.0) as c:
        assert c.raw(b"{oops")["error"].startswith("malformed request")
        assert c.raw(b'{"cmd": "explode"}')["error"] == (
            "unknown command 'explode'; known: status, push, person, press, enabling, slider, "
            "fault, log, stop")
        assert c.raw(b'{"cmd": "push", "force": [1, "NaN", 2]}')["error"] == (
            "push: force[1] = 'NaN': must be a number [N]")
        assert c.raw(b'{"cmd": "push", "force": [1, 2, 3], "seconds": -1}')["error"] == (
            "push: seconds = -1: must be > 0 and <= 3600 [s]")
        # issue 17: an unknown field left the push on forever; a string "false" was true
        assert c.raw(b'{"cmd": "push", "force": [0, 30, 0], "duration": "x"}')["error"] == (
            "push: duration = 'x': unknown field; push takes: force, seconds")
        assert c.raw(b'{"cmd": "person", "on": "false"}')["error"] == (
            "person: on = 'false': must be true or false (a JSON boolean)")
        assert c.raw(b'{"cmd": "fault", "name": "sensor_silent", "on": "off"}')["error"] == (
            "fault: on = 'off': must be true or false (a JSON boolean)")
        assert c.raw(b'{"cmd": "person", "hold": "long"}')["error"] == (
            "person: hold = 'long': must be a number [s]")
        st = c.call("status")
        assert st["person"] == "off" and st["push"] is None and st["faults"] == []


def test_a_second_sim_on_the_same_socket_refuses(sim: Sim) -> None:
    out = sim.tmp / "second.log"
    with out.open("wb") as f:
        rc = subprocess.run([sys.executable, "-m", "mmctl.cli", "sim", "--config",
                             str(sim.config)], check=False, stdout=f, stderr=subprocess.STDOUT,
                            cwd=str(ROOT), timeout=120).returncode
    assert rc == 2, out.read_text()
    assert "already running on" in out.read_text()
    assert sim.call("status")["pid"] == sim.proc.pid


def _run_daemon(sim: Sim, out: Path) -> subprocess.Popen[bytes]:
    """`mmctl run` on the simulation's configuration, its JSON log appended to ``out``."""
    with out.open("ab") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "mmctl.cli", "run", "--config", str(sim.config),
             "--log-json"], stdout=f, stderr=subprocess.STDOUT, cwd=str(ROOT),
            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _end(daemon: subprocess.Popen[bytes]) -> None:
    """Kill a daemon a test left running (its link processes end on the pipe's EOF):
    first in a test's ``finally``, so that nothing before it can leave it orphaned (seen:
    a simulation that no longer answered its socket left a daemon running for an hour)."""
    if daemon.poll() is None:
        daemon.kill()
        daemon.wait(30)


def _enable_eventually(sim: Sim, sock: Path, attempts: int = 5) -> dict[str, Any]:
    """``enable`` until it arms: on a loaded machine a starved simulation can miss the
    base's SDO answers during an enable (refused: "the base did not enable"); any other
    refusal is a failure."""
    for attempt in range(attempts):
        try:
            st: dict[str, Any] = request(sock, "enable", timeout=60.0)
            return st
        except IpcError as exc:
            if "the base did not enable" not in str(exc) or attempt == attempts - 1:
                raise
            time.sleep(1.0)  # the simulation catches up
    raise AssertionError("unreachable")


def _wait_auto_enabled(sim: Sim, sock: Path, out: Path) -> None:
    """Until the daemon's auto-enable (sim.auto_enable) armed it.  On a loaded machine a
    starved simulation can make it fail as an operator's ``enable`` can ("the base did not
    enable": seen in CI with both cores busy); the daemon then stays up, disarmed, and
    the operator enables: so does this, as :func:`_enable_eventually` does."""
    def settled() -> str | None:
        text = out.read_text()
        if "auto_enable_failed" in text:
            return "failed"
        return "armed" if request(sock, "status", timeout=30.0)["state"] == "armed" else None

    try:
        how = sim.wait_for(settled, "the daemon's auto-enable")
    except AssertionError as exc:
        raise AssertionError(f"{exc}\ndaemon log: {out.read_text()[-4000:]}") from None
    if how == "failed":
        line = next(ln for ln in out.read_text().splitlines() if "auto_enable_failed" in ln)
        if "the base did not enable" not in line:
            raise AssertionError(f"the auto-enable failed: {line}")
        _enable_eventually(sim, sock)


def test_run_attaches_to_a_running_sim_and_leaves_it_running(sim: Sim) -> None:
    """`mmctl run` finds the simulation on its socket: it starts none of its own, tares
    and arms (sim.auto_enable), the push that was on all along moves the handle (the
    person let go of the handle while the daemon tared: the tare did not absorb it), and
    the simulation outlives the daemon."""
    out = sim.tmp / "daemon.log"
    sock = sim.tmp / "mmctl.sock"
    sim.call("push", force=[0.0, 30.0, 0.0])  # before the daemon starts, through its tare
    p0 = np.array(sim.call("status")["handle_world"])
    daemon = _run_daemon(sim, out)
    try:
        _wait_auto_enabled(sim, sock, out)
        st = request(sock, "status", timeout=30.0)
        assert st["sim"] == {"socket": str(sim.socket), "pid": sim.proc.pid, "owned": False}
        try:
            sim.wait_for(lambda: np.array(sim.call("status")["handle_world"])[1] - p0[1] > 0.03,
                         "the handle to move 3 cm along +y")
        except AssertionError as exc:  # (seen once with both cores busy: say why)
            raise AssertionError(f"{exc}\ndaemon status: {request(sock, 'status', timeout=30.0)}"
                                 f"\ndaemon log: {out.read_text()[-4000:]}") from None
        sim.call("push", force=None)
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(120) == 0, out.read_text()[-3000:]
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait(30)
    events = [json.loads(line)["event"] for line in out.read_text().splitlines()
              if line.startswith("{")]
    assert "sim_attached" in events and "sim_spawned" not in events, events
    assert events.index("auto_enabled") > 0
    assert sim.call("status")["pid"] == sim.proc.pid  # still running


def test_the_enabling_switch_through_the_fake_urs_inputs(sim: Sim) -> None:
    """config/sim.yaml's two-contact enabling switch on the fake UR's inputs 8 and 9,
    read by the daemon through RTDE: released under a push, the armed robot comes to
    rest and stays armed; held again, it follows the push; one contact broken is the
    fault ``enabling_device_fault``, refused while present, re-armed by enable after."""
    out = sim.tmp / "daemon-enabling.log"
    sock = sim.tmp / "mmctl.sock"

    def daemon_status() -> dict[str, Any]:
        st: dict[str, Any] = request(sock, "status", timeout=30.0)
        return st

    def handle() -> np.ndarray:
        return np.array(sim.call("status")["handle_world"])

    def at_rest() -> bool:
        st = sim.call("status")
        return bool(max(abs(v) for v in st["arm_qd"] + st["wheel_velocities"]) < 1e-6)

    daemon = _run_daemon(sim, out)
    try:
        _wait_auto_enabled(sim, sock, out)
        assert daemon_status()["enabling"] == "held"
        sim.call("push", force=[0.0, 30.0, 0.0])
        p0 = handle()
        sim.wait_for(lambda: handle()[1] - p0[1] > 0.02, "the handle to move 2 cm along +y")
        assert sim.call("enabling", held=False)["enabling"] == "released"
        sim.wait_for(at_rest, "the arm and the wheels to come to rest")
        st = daemon_status()
        assert st["state"] == "armed" and st["enabling"] == "released" and st["faults"] == 0
        p1 = handle()
        sim.wait_for(lambda: daemon_status()["cycles"] > st["cycles"] + 250, "half a second")
        assert np.abs(handle() - p1).max() < 1e-4  # still, while the person pushes on
        sim.call("enabling", held=True)
        try:
            sim.wait_for(lambda: handle()[1] - p1[1] > 0.02, "the handle to move on along +y")
        except AssertionError as exc:  # (seen once under a heavy load: say why)
            raise AssertionError(f"{exc}\ndaemon status: {daemon_status()}\ndaemon log:\n"
                                 f"{out.read_text()[-4000:]}") from None
        # the pendant's speed slider: the daemon reads it through RTDE (and scales the
        # base with it, tests/test_cycle.py)
        assert sim.call("slider", fraction=0.4)["speed_slider"] == 0.4
        sim.wait_for(lambda: daemon_status()["robot"]["speed_scaling"] == 0.4,
                     "the daemon to see the slider")
        sim.call("slider", fraction=1.0)
        sim.call("push", force=None)
        # a broken contact: a fault, refused while present, enable once repaired
        sim.call("fault", name="enabling_contact", on=True)
        sim.wait_for(lambda: daemon_status()["state"] == "fault", "the fault")
        st = daemon_status()
        assert st["fault"] == "enabling_device_fault", st
        assert st["fault_details"]["inputs"] == [8, 9], st
        with pytest.raises(Exception, match="enabling_device_fault"):
            request(sock, "enable", timeout=30.0)
        sim.call("fault", name="enabling_contact", on=False)
        sim.wait_for(lambda: daemon_status()["enabling"] == "held", "the contacts to agree")
        assert _enable_eventually(sim, sock)["state"] == "armed"
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(120) == 0, out.read_text()[-3000:]
    finally:
        _end(daemon)  # first: a simulation that no longer answers must not leave it
        sim.call("push", force=None)
        sim.call("enabling", held=True)
        sim.call("slider", fraction=1.0)


@pytest.mark.parametrize("device, cause", [("sensor", "sensor_link_lost"),
                                           ("base", "base_link_lost")])
def test_a_can_link_cut_under_the_armed_daemon_stops_and_comes_back_on_enable(
        sim: Sim, device: str, cause: str) -> None:
    """The CAN adapter of one device pulled under the armed, moving daemon (the fake's
    socketcand connections dropped, its channel refused): the fault names the link, the
    robot stops, one fault event and no traceback; enable is refused while the adapter
    is out; plugged back, enable reconnects the real client over socketcand and the
    robot moves again."""
    out = sim.tmp / f"daemon-cut-{device}.log"
    sock = sim.tmp / "mmctl.sock"

    def daemon_status() -> dict[str, Any]:
        st: dict[str, Any] = request(sock, "status", timeout=30.0)
        return st

    def handle() -> np.ndarray:
        return np.array(sim.call("status")["handle_world"])

    def at_rest() -> bool:
        st = sim.call("status")
        return bool(max(abs(v) for v in st["arm_qd"] + st["wheel_velocities"]) < 1e-6)

    daemon = _run_daemon(sim, out)
    try:
        _wait_auto_enabled(sim, sock, out)
        sim.call("push", force=[0.0, 30.0, 0.0])
        p0 = handle()
        sim.wait_for(lambda: handle()[1] - p0[1] > 0.02, "the handle to move 2 cm along +y")
        sim.call("fault", name=f"{device}_unplugged", on=True)
        sim.wait_for(lambda: daemon_status()["state"] == "fault", "the fault")
        st = daemon_status()
        assert st["fault"] == cause, with_ur_program(lambda: str(st), sim.socket)()
        sim.wait_for(at_rest, "the arm and the wheels to come to rest")
        with pytest.raises(Exception, match="did not reconnect|refused to enable"):
            request(sock, "enable", timeout=60.0)
        assert daemon_status()["state"] == "fault"
        sim.call("fault", name=f"{device}_unplugged", on=False)
        assert _enable_eventually(sim, sock)["state"] == "armed"
        p1 = handle()
        sim.wait_for(lambda: handle()[1] - p1[1] > 0.02, "the handle to move on along +y")
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(120) == 0, out.read_text()[-3000:]
        events = [json.loads(line) for line in out.read_text().splitlines()
                  if line.startswith("{")]
        faults = [e for e in events if e.get("event") == "fault"]
        assert [e["cause"] for e in faults] == [cause], faults
        assert not [e for e in events if e.get("event") == "cycle_failed"], events
        assert "Traceback" not in out.read_text()
    finally:
        _end(daemon)
        sim.call("push", force=None)
        sim.call("fault", name=f"{device}_unplugged", on=False)


def test_a_hung_sensor_link_does_not_stop_the_loop(sim: Sim) -> None:
    """The sensor's link process frozen (SIGSTOP) under the armed daemon: the loop keeps
    its cycles (counted), the sample's own age makes it sensor_stale, the robot stops;
    thawed, enable re-arms and the robot moves."""
    out = sim.tmp / "daemon-hung-sensor.log"
    sock = sim.tmp / "mmctl.sock"

    def daemon_status() -> dict[str, Any]:
        st: dict[str, Any] = request(sock, "status", timeout=30.0)
        return st

    daemon = _run_daemon(sim, out)
    pid = None
    try:
        _wait_auto_enabled(sim, sock, out)
        pid = daemon_status()["process"]["links"]["sensor"]
        assert isinstance(pid, int) and pid != daemon.pid, daemon_status()["process"]
        sim.call("push", force=[0.0, 30.0, 0.0])
        os.kill(pid, signal.SIGSTOP)
        sim.wait_for(lambda: daemon_status()["state"] == "fault", "the fault")
        st = daemon_status()
        assert st["fault"] == "sensor_stale", st
        c0 = st["cycles"]
        # the loop cycles on while the sensor's process stays frozen (500 more cycles)
        sim.wait_for(lambda: daemon_status()["cycles"] > c0 + 500, "500 more cycles")
        assert daemon_status()["state"] == "fault"
        os.kill(pid, signal.SIGCONT)
        pid = None
        sim.wait_for(lambda: "sensor_stale" not in daemon_status()["conditions"],
                     "fresh samples again")
        assert _enable_eventually(sim, sock)["state"] == "armed"
        p1 = np.array(sim.call("status")["handle_world"])
        sim.wait_for(lambda: np.array(sim.call("status")["handle_world"])[1] - p1[1] > 0.02,
                     "the handle to move on along +y")
        daemon.send_signal(signal.SIGTERM)
        assert daemon.wait(120) == 0, out.read_text()[-3000:]
    finally:
        if pid is not None:
            os.kill(pid, signal.SIGCONT)
        _end(daemon)
        sim.call("push", force=None)


def test_ctrl_c_ends_the_sim_cleanly(tmp_path: Path) -> None:
    s = Sim(tmp_path, _host(3))
    try:
        ur_pid = s.call("status")["ur_pid"]
        s.proc.send_signal(signal.SIGINT)
        assert s.proc.wait(120) == 0, s.log_text()[-3000:]
    finally:
        s.kill()
    text = s.log_text()
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-3000:]
    assert not s.socket.exists()
    with pytest.raises(ProcessLookupError):
        os.kill(ur_pid, 0)
    stopping = [json.loads(line) for line in text.splitlines() if '"sim_stopping"' in line]
    assert stopping and stopping[0]["reason"] == "SIGINT"
