"""`mmctl run` as a real subprocess on the simulated robot, driven through the socket/CLI.

The daemon gets its own socket in tmp_path, its own fake-UR loopback address and its own
virtual CAN channel names; ``NOTIFY_SOCKET`` points at a datagram socket the test binds,
so the systemd notify protocol is observed as systemd would see it.  The fakes run under
the daemon (``--sim-log`` makes it write their command logs on shutdown).  The tests in
this module share one daemon and run in order; the last one stops it with SIGTERM.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from loopback import free_loopback_host
from mmctl.cli import main
from mmctl.config import load_config
from mmctl.errors import IpcError
from mmctl.runtime.ipc import ControlClient, request
from simconfig import LOAD_PROOF, write_sim_config

pytestmark = pytest.mark.timeout(900)
ROOT = Path(__file__).resolve().parents[1]


@dataclass
class Proc:
    proc: subprocess.Popen[bytes]
    socket: Path
    config: Path
    sim_log: Path
    out: Path
    notify: socket.socket
    messages: list[str] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def read_notify(self, stop: threading.Event) -> None:
        """Take the notify datagrams as they come, as systemd does (its socket queues 10,
        net.unix.max_dgram_qlen: a test busy elsewhere would see the newest dropped)."""
        while not stop.is_set():
            try:
                ready = select.select([self.notify], [], [], 0.05)[0]
            except (OSError, ValueError):
                return
            if ready:
                try:
                    msg = self.notify.recv(4096).decode()
                except (BlockingIOError, OSError):
                    continue
                with self.lock:
                    self.messages.extend(msg.split("\n"))

    def call(self, cmd: str, **args: Any) -> Any:
        return request(self.socket, cmd, timeout=60.0, **args)

    def status(self) -> dict[str, Any]:
        return self.call("status")

    def sim(self, cmd: str, **args: Any) -> Any:
        """A request to the simulated robot's own control socket."""
        return request(self.config.parent / "sim.sock", cmd, timeout=60.0, **args)

    def drain_notify(self) -> list[str]:
        """Every notify line the daemon sent so far."""
        with self.lock:
            return list(self.messages)

    def log_text(self) -> str:
        return self.out.read_text(errors="replace")


def wait_for(pred: Callable[[], Any], what: str, proc: Proc | None = None,
             timeout: float = 120.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        if proc is not None and proc.proc.poll() is not None:
            raise AssertionError(f"daemon exited ({proc.proc.returncode}) while waiting for "
                                 f"{what}:\n{proc.log_text()[-4000:]}")
        time.sleep(0.05)
    tail = proc.log_text()[-4000:] if proc is not None else ""
    raise AssertionError(f"timed out waiting for {what}\n{tail}")


def write_config(tmp: Path, host: str) -> Path:
    """config/sim.yaml for this test, with every staleness timeout, the devices' own
    watchdogs and the loop's miss budget beyond what a loaded 2-core machine can
    exhaust in these tests (it starves the loop, the arm's process, the simulated
    robot's process and its socketcand traffic for a while): any fault fails them."""
    return write_sim_config(host, tmp, {
        **LOAD_PROOF, "name": "cli-test", "sim": {"human": False, "auto_enable": False},
        "daemon": {**LOAD_PROOF["daemon"], "socket_path": str(tmp / "run" / "mmctl.sock")}})


def spawn(cfg: Path, out: Path, env: dict[str, str], *extra: str) -> subprocess.Popen[bytes]:
    with out.open("ab") as f:
        return subprocess.Popen(
            [sys.executable, "-m", "mmctl.cli", "run", "--config", str(cfg), *extra],
            stdout=f, stderr=subprocess.STDOUT, env=env, cwd=str(ROOT))


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Proc]:
    tmp = tmp_path_factory.mktemp("daemon")
    host = free_loopback_host(202)
    cfg = write_config(tmp, host)
    notify_path = tmp / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    notify.setblocking(False)
    env = {**os.environ, "NOTIFY_SOCKET": str(notify_path), "WATCHDOG_USEC": "1000000",
           "PYTHONUNBUFFERED": "1"}
    env.pop("WATCHDOG_PID", None)
    out = tmp / "daemon.log"
    sim_log = tmp / "simlog"
    p = Proc(spawn(cfg, out, env, "--sim-log", str(sim_log), "--log-json"),
             Path(yaml.safe_load(cfg.read_text())["daemon"]["socket_path"]), cfg, sim_log,
             out, notify)
    stop = threading.Event()
    reader = threading.Thread(target=p.read_notify, args=(stop,), daemon=True)
    reader.start()
    try:
        wait_for(lambda: "READY=1" in p.drain_notify(), "READY=1", p, timeout=180.0)
        yield p
    finally:
        if p.proc.poll() is None:
            p.proc.kill()
            p.proc.wait(30)
        stop.set()
        reader.join(5)
        notify.close()


def test_ready_then_watchdog_and_status_over_the_socket(daemon: Proc) -> None:
    msgs = daemon.drain_notify()
    assert any(m.startswith("STATUS=state=disarmed") for m in msgs), msgs
    wait_for(lambda: "WATCHDOG=1" in daemon.drain_notify(), "WATCHDOG=1", daemon)
    st = daemon.status()
    assert st["state"] == "disarmed" and st["mode"] == "min-energy" and st["fault"] is None
    assert st["cycles"] > 0 and st["loop"]["running"]
    assert st["config"] == "cli-test"
    assert stat.S_IMODE(daemon.socket.stat().st_mode) == 0o660


def test_cli_status_and_errors(daemon: Proc, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--socket", str(daemon.socket)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("state=disarmed mode=min-energy")
    assert main(["status", "--json", "--config", str(daemon.config)]) == 0
    assert json.loads(capsys.readouterr().out)["state"] == "disarmed"
    assert main(["switch", "locomotion", "--socket", str(daemon.socket)]) == 2
    assert "needs mode 'switch'" in capsys.readouterr().err


def test_malformed_and_unknown_requests_get_errors(daemon: Proc) -> None:
    with ControlClient(daemon.socket, timeout=60.0) as c:
        assert c.raw(b"{oops")["error"].startswith("malformed request")
        assert c.raw(b'{"cmd": "explode"}')["error"] == (
            "unknown command 'explode'; known: status, enable, disable, mode, profile, switch, "
            "tare, stop, trial, calibrate, set, get")  # the command table itself: no "sim" (the simulation's own)
        assert "needs 'mode'" in c.raw(b'{"cmd": "mode"}')["error"]
        assert "unknown mode 'fastest'" in c.raw(b'{"cmd": "mode", "mode": "fastest"}')["error"]
        assert c.call("status")["state"] == "disarmed"  # carries on, same connection


def _listening_tcp(pid: int) -> list[str]:
    """The TCP ports process ``pid`` listens on (its socket inodes in /proc/net/tcp)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                ports.append(f[1])
    return ports


def test_the_daemons_process_holds_no_simulation(daemon: Proc) -> None:
    """The simulated robot runs in its own process: the daemon's holds no fake, no
    simulated person, serves no device port, and never imported the simulation."""
    st = daemon.status()
    proc = st["process"]
    assert proc["pid"] == daemon.proc.pid
    assert proc["simulation_loaded"] is False
    # the loop, the control socket, the canopen master's notifier and heartbeat, the
    # summary line off a terminal: nothing of the simulation's (its person, fakes,
    # socketcand server threads)
    known = ("MainThread", "mmctl-loop", "mmctl-ipc", "Notifier for bus", "Cyclic send task",
             "mmctl-summary")
    assert all(t.startswith(known) for t in proc["threads"]), proc
    assert not [t for t in proc["threads"] if "sim" in t or "fake" in t], proc
    assert _listening_tcp(daemon.proc.pid) == []  # RTDE, dashboard, socketcand: elsewhere
    sim = daemon.sim("status")
    assert sim["pid"] == st["sim"]["pid"] != daemon.proc.pid and st["sim"]["owned"]
    assert sim["socketcand"]["clients"] == 2  # the daemon's sensor and its canopen master
    assert _listening_tcp(sim["pid"])  # the socketcand server


def test_second_daemon_refuses_to_start(daemon: Proc, tmp_path: Path) -> None:
    out = tmp_path / "second.log"
    second = spawn(daemon.config, out, {**os.environ, "NOTIFY_SOCKET": ""})
    assert second.wait(120) == 2
    text = out.read_text()
    assert "another mmctl daemon is already running on" in text, text
    assert daemon.status()["cycles"] > 0  # the first one is unharmed


def _ee(daemon: Proc) -> np.ndarray:
    return np.array(daemon.status()["robot"]["ee_position"])


def test_enable_and_a_push_moves_the_end_effector_that_way(daemon: Proc) -> None:
    assert daemon.call("tare")["taring"]
    with pytest.raises(IpcError, match="tare is in progress"):
        daemon.call("enable")
    wait_for(lambda: not daemon.status()["taring"], "the tare", daemon)
    assert daemon.call("enable")["state"] == "armed"
    p0 = _ee(daemon)
    push = np.array([0.0, 25.0, 0.0])  # +y in the world
    daemon.sim("push", force=push.tolist())
    moved = _moves(daemon, p0, 0.05, "the end-effector to move 5 cm")
    assert moved[1] > 3 * abs(moved[0]) and moved[1] > 3 * abs(moved[2]), moved
    assert daemon.status()["state"] == "armed"


def test_the_socket_process_restarts_and_the_robot_carries_on(daemon: Proc) -> None:
    """The control socket is served by a process of its own; a crash of it (SIGKILL)
    is not the robot's business: it stays armed, moving, and a new one serves."""
    assert _armed(daemon)
    first = daemon.status()["process"]["socket_process"]
    assert first["pid"] not in (None, daemon.proc.pid)
    p0 = _ee(daemon)
    os.kill(first["pid"], signal.SIGKILL)
    st = daemon.status()  # waits in the listen backlog for the next one
    assert st["state"] == "armed", st
    now = st["process"]["socket_process"]
    assert now["starts"] == first["starts"] + 1 and now["pid"] not in (None, first["pid"])
    _moves(daemon, p0, 0.02, "the end-effector to go on moving")
    assert "ipc_process_restarted" in daemon.log_text()


def _armed(daemon: Proc) -> bool:
    """Armed (a fault of any cause fails)."""
    st = daemon.status()
    assert st["state"] == "armed", (st, daemon.log_text()[-3000:])
    return True


def _moves(daemon: Proc, p0: np.ndarray, dy: float, what: str) -> np.ndarray:
    """Wait until the end-effector moved ``dy`` [m] along +y from ``p0``, armed all along."""
    box: list[np.ndarray] = []

    def moved() -> bool:
        assert _armed(daemon)
        box.append(_ee(daemon) - p0)
        return bool(box[-1][1] > dy)

    wait_for(moved, what, daemon)
    return box[-1]


def test_mode_changes_at_run_time(daemon: Proc, capsys: pytest.CaptureFixture[str]) -> None:
    sock = ["--socket", str(daemon.socket)]
    assert main(["mode", "locomotion", *sock]) == 0
    assert "mode=locomotion" in capsys.readouterr().out
    _moves(daemon, _ee(daemon), 0.02, "motion in locomotion")
    assert main(["mode", "switch", *sock]) == 0
    assert main(["switch", "locomotion", *sock]) == 0
    assert _armed(daemon)
    st = daemon.status()
    assert st["mode"] == "switch" and st["switch"] == "locomotion"
    daemon.sim("press")  # the handle button (the fake UR's tool input) toggles
    wait_for(lambda: daemon.status()["switch"] == "manipulation", "the button's toggle", daemon)
    assert main(["mode", "min-energy", *sock]) == 0
    capsys.readouterr()
    assert _armed(daemon)
    msgs = daemon.drain_notify()
    assert any(m == "STATUS=state=armed mode=locomotion" for m in msgs), msgs


def test_pose_record_writes_the_arms_pose_into_a_config(
        daemon: Proc, capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """`mmctl pose record --write`: the daemon's newest arm sample becomes robot.q_des of
    a copy of config/robot.yaml, which keeps its comments and still loads.  Recorded at
    rest (let go, disarmed): under the push the arm moves on, and not along a line (the
    redundancy turns joints back and forth), so a moving pose cannot be pinned."""
    target = tmp_path / "robot.yaml"
    text = (ROOT / "config" / "robot.yaml").read_text()
    target.write_text(text)
    push = daemon.sim("status")["push"]
    daemon.sim("push", force=None)
    # disarmed: the arm speed-stops and stays (armed, the redundancy can creep on for long)
    assert daemon.call("disable")["state"] == "disarmed"
    wait_for(lambda: np.abs(daemon.sim("status")["arm_qd"]).max() < 1e-6, "the arm at rest",
             daemon)
    at_rest = np.array(daemon.sim("status")["arm_q"])
    wait_for(lambda: np.abs(np.array(daemon.status()["robot"]["q"][:6]) - at_rest).max()
             < 1e-4, "the daemon's status at the rest pose", daemon)
    assert main(["pose", "record", "--write", str(target), "--socket", str(daemon.socket)]) == 0
    out = capsys.readouterr().out
    assert out.startswith("robot:\n  q_des: [") and f"written to {target}" in out, out
    q = np.array(load_config(target).robot.q_des)
    np.testing.assert_allclose(q, at_rest, atol=1e-4)  # (5 decimals written)
    assert target.read_text().count("#") == text.count("#") + 1
    assert daemon.call("enable")["state"] == "armed"  # the tests after this one push on
    daemon.sim("push", force=push)


def test_the_reduced_profile_at_run_time(daemon: Proc,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """`mmctl profile reduced` caps the end-effector at 0.25 m/s on top of the whole-body
    caps; status shows the profile and the caps; `normal` lifts it again."""
    sock = ["--socket", str(daemon.socket)]
    state = daemon.status()["state"]
    assert main(["profile", "reduced", *sock]) == 0
    out = capsys.readouterr().out
    assert "profile=reduced" in out and "end-effector <= 0.25 m/s" in out, out
    st = daemon.status()
    assert st["profile"] == "reduced" and st["caps"]["ee_speed_m_s"] == 0.25
    assert st["caps"]["energy_J"] == pytest.approx(280.0 ** 2 / 50e3, abs=1e-4)  # chest
    assert st["state"] == state  # a profile change neither arms nor disarms
    assert main(["status", *sock]) == 0
    assert "limits: profile reduced" in capsys.readouterr().out
    assert main(["profile", "normal", *sock]) == 0
    assert daemon.status()["caps"]["ee_speed_m_s"] > 0.25
    with ControlClient(daemon.socket, timeout=60.0) as c:
        err = c.raw(b'{"cmd": "profile", "profile": "ludicrous"}')["error"]
    assert "unknown profile 'ludicrous'" in err, err


def test_parameters_change_at_run_time(daemon: Proc,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """`mmctl set` changes a parameter of the running daemon (validated as the config
    is, logged, shown by status), `mmctl get` reads it; what needs a restart is refused."""
    sock = ["--socket", str(daemon.socket)]
    state = daemon.status()["state"]
    assert main(["set", "admittance.damping", "60", *sock]) == 0
    assert capsys.readouterr().out.strip() == (
        "admittance.damping: [75.0, 75.0, 75.0, 75.0, 75.0, 75.0] -> "
        "[60.0, 60.0, 60.0, 60.0, 60.0, 60.0]")
    assert main(["get", "admittance.damping", *sock]) == 0
    assert "[60.0, 60.0" in capsys.readouterr().out
    assert main(["set", "limits.ee_speed", "0.3", *sock]) == 0
    capsys.readouterr()
    st = daemon.status()
    assert st["changed"] == {"admittance.damping": [60.0] * 6, "limits.ee_speed": 0.3}
    assert st["caps"]["ee_speed_m_s"] == 0.3 and st["state"] == state
    assert main(["set", "limits.ee_speed", "null", *sock]) == 0  # back to the derived cap
    capsys.readouterr()
    assert daemon.status()["caps"]["ee_speed_m_s"] > 0.3
    for argv, message in (
            (["set", "admittance.damping", "-5"], "admittance.damping[0] = -5"),
            (["set", "loop.rate_hz", "250"], "loop.rate_hz = 250: cannot change while"),
            (["set", "admittance.dampin", "5"], "admittance.dampin: unknown key"),
            (["set", "admittance.mass", "[1, 2"], "cannot read '[1, 2' as a YAML value"),
            (["get", "nothing"], "nothing: unknown key")):
        assert main([*argv, *sock]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert daemon.status()["changed"]["admittance.damping"] == [60.0] * 6  # kept
    assert "param_set" in daemon.log_text()


def test_sigterm_stops_with_the_stop_commands_sent(daemon: Proc) -> None:
    assert _armed(daemon)  # still moving under the push
    socket_pid = daemon.status()["process"]["socket_process"]["pid"]
    daemon.proc.send_signal(signal.SIGTERM)
    assert daemon.proc.wait(120) == 0, daemon.log_text()[-3000:]
    wait_for(lambda: "STOPPING=1" in daemon.drain_notify(), "STOPPING=1")
    events = [json.loads(line) for line in daemon.log_text().splitlines()
              if line.startswith("{")]
    names = [e["event"] for e in events]
    assert names.index("daemon_stopping") < names.index("daemon_stopped")
    assert next(e for e in events if e["event"] == "daemon_stopping")["reason"] == "SIGTERM"
    arm = [json.loads(line) for line in (daemon.sim_log / "ur_commands.jsonl").open()]
    arm = [c for c in arm if c["kind"] in ("speedj", "speed_stop")]
    last_motion = max(i for i, c in enumerate(arm) if c["kind"] == "speedj" and any(c["qd"]))
    after = arm[last_motion + 1:]
    # speedStop, or (when the newest RTDE sample is not fresh) its real-time fallback:
    # speedJ(0) with the stop deceleration (UrRtdeArm.stop)
    decel = load_config(daemon.config).arm.stop_deceleration
    assert after and (after[0]["kind"] == "speed_stop"
                      or (after[0]["kind"] == "speedj" and not any(after[0]["qd"])
                          and after[0]["acceleration"] == pytest.approx(decel))), after[:3]
    assert all(c["kind"] == "speed_stop" or not any(c["qd"]) for c in after)
    drives = [json.loads(line) for line in (daemon.sim_log / "drive_commands.jsonl").open()]
    for nid in {d["node_id"] for d in drives}:
        mine = [d for d in drives if d["node_id"] == nid]
        assert any(d["counts"] for d in mine), "the base never moved"
        assert mine[-1]["counts"] == 0
    assert not daemon.socket.exists()
    assert not Path(f"/proc/{socket_pid}").exists()  # the socket's process ended with it


def test_no_daemon_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["status", "--socket", str(tmp_path / "nobody.sock")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no mmctl daemon is running" in err
