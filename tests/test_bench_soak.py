"""`mmctl bench soak`: a short soak's JSON (its keys, samples taken, faults injected and
floods sent, everything it started stopped), a clean Ctrl-C, and the analysis on
made-up samples.  Nothing about timing or the verdict of a real run is asserted (a
loaded machine may fault the robot: that is the soak's finding, not the test's)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from mmctl.bench import soak
from mmctl.cli import main
from waiting import wait_for

ROOT = Path(__file__).resolve().parents[1]


def _gone(pid: int | None) -> bool:
    """The process no longer runs (or is a zombie nobody reaped yet)."""
    if pid is None:
        return True
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def _check_report(rep: dict[str, Any]) -> None:
    assert rep["verdict"] in ("PASS", "FAIL")
    assert isinstance(rep["verdict_reasons"], list)
    assert (rep["verdict"] == "PASS") == (not rep["verdict_reasons"])
    assert rep["samples"] >= 2 and len(rep["series"]) == rep["samples"]
    for s in rep["series"]:
        assert s["rss_mb"] > 0 and s["threads"] > 0 and s["fds"] > 0
        assert s["children"] >= 1 and s["descendants"] >= s["children"]
        assert s["soak_rss_mb"] > 0
    d = rep["daemon"]
    for key in ("rss_mb", "sim_rss_mb", "soak_rss_mb"):
        assert {"min", "max", "first", "last", "growth_mb_per_hour",
                "growth_after_warmup_mb"} <= set(d[key]), key
        assert d[key]["min"] <= d[key]["max"]
    for key in ("threads", "fds", "children", "descendants"):
        assert d[key]["min"] <= d[key]["max"], key
    assert any("mmctl.cli sim" in c for c in rep["children_at_start"])
    assert rep["fds_at_start"] and sum(rep["fds_at_start"].values()) > 0
    f = rep["faults"]
    assert {"injected", "as_expected", "unexpected", "unexpected_by_cause", "not_detected",
            "not_reenabled", "by_fault", "unexpected_events"} <= set(f)
    assert f["unexpected"] == sum(f["unexpected_by_cause"].values())
    fl = rep["floods"]
    assert fl["requests"] == fl["ok"] + fl["errors"] == fl["bursts"] * fl["clients_per_burst"]
    assert rep["loop"]["cycles"] > 0 and rep["loop"]["misses"] >= 0
    # everything the soak started is gone: the daemon, its simulated robot
    assert _gone(rep["daemon_pid"])
    wait_for(lambda: _gone(rep["sim_pid"]), "the simulated robot to exit", timeout=60.0)


@pytest.mark.timeout(400)
def test_a_short_soak_reports_its_samples(loopback_host: str,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["bench", "soak", "--seconds", "24", "--interval", "1", "--json",
               "--host", loopback_host, "--load-proof", "--fault-every", "6",
               "--faults", "wrench_over_limit,drive_fault", "--flood-every", "5",
               "--flood-clients", "8", "--push-every", "2", "--seed", "3"])
    out, err = capsys.readouterr()
    assert rc in (0, 1), err[-3000:]
    rep = json.loads(out)
    assert not rep["interrupted"], err[-3000:]
    assert rep["load_proof"] is True and rep["planned_seconds"] == 24.0
    assert rep["warmup_s"] == pytest.approx(0.2 * 24)  # 20 % of a short run
    _check_report(rep)
    assert rep["faults"]["injected"] >= 1
    assert set(rep["faults"]["by_fault"]) <= {"wrench_over_limit", "drive_fault"}
    assert rep["floods"]["bursts"] >= 1
    assert rep["pushes"] >= 1
    assert rep["daemon_log"] is None or Path(rep["daemon_log"]).is_file()
    if rep["daemon_log"]:  # kept (FAIL) in the soak's temporary directory: remove both
        log = Path(rep["daemon_log"])
        log.unlink()
        assert log.parent.name.startswith("mmctl-soak-")
        log.parent.rmdir()


@pytest.mark.timeout(400)
def test_ctrl_c_stops_everything_and_prints_what_it_has(loopback_host: str,
                                                         tmp_path: Path) -> None:
    log = tmp_path / "daemon.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT / "src"), *filter(None, [os.environ.get("PYTHONPATH")])])}
    err = (tmp_path / "stderr").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "mmctl.cli", "bench", "soak", "--minutes", "30", "--json",
         "--interval", "1", "--host", loopback_host, "--load-proof", "--fault-every", "0",
         "--flood-every", "2", "--flood-clients", "4", "--daemon-log", str(log)],
        stdout=subprocess.PIPE, stderr=err, cwd=ROOT, env=env)
    try:
        # the first sample's progress line, then a few more samples
        wait_for(lambda: b"soak 00:00/30:00" in (tmp_path / "stderr").read_bytes()
                 or proc.poll() is not None, "the soak's first sample", timeout=240.0)
        assert proc.poll() is None, (tmp_path / "stderr").read_text()[-3000:]
        time.sleep(4.0)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=240.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        err.close()
    assert proc.returncode in (0, 1), (tmp_path / "stderr").read_text()[-3000:]
    rep = json.loads(out)
    assert rep["interrupted"] is True
    assert rep["elapsed_seconds"] < 30 * 60
    _check_report(rep)
    assert rep["daemon_log"] == str(log) and log.is_file()  # asked for: kept


def _samples(rss: list[float], step: float = 10.0, **const: Any) -> list[dict[str, Any]]:
    base = {"threads": 7, "fds": 13, "children": 3, "descendants": 5, "sim_rss_mb": 100.0,
            "soak_rss_mb": 40.0, "quiet": True}
    return [{"t": i * step, "rss_mb": r, **base, **const} for i, r in enumerate(rss)]


def _report(samples: list[dict[str, Any]], warmup: float, **faults: Any) -> dict[str, Any]:
    f = {"unexpected": 0, "unexpected_by_cause": {}, "not_detected": 0, "not_reenabled": 0,
         "enabled_while_present": 0, **faults}
    return {"daemon": soak.analyse(samples, warmup), "faults": f}


def test_rss_growth_is_a_regression_after_the_warm_up() -> None:
    # a big warm-up step, then flat: no growth; then a steady 1 MB per 10 s: 360 MB/h
    flat = _samples([50.0] + [120.0] * 30)
    fig = soak.analyse(flat, warmup=5.0)
    assert fig["rss_mb"]["growth_mb_per_hour"] == 0.0
    assert soak.verdict(_report(flat, 5.0)) == (True, [])
    leak = _samples([100.0 + i for i in range(31)])
    fig = soak.analyse(leak, warmup=0.0)
    assert fig["rss_mb"]["growth_mb_per_hour"] == pytest.approx(360.0)
    assert fig["rss_mb"]["growth_after_warmup_mb"] == pytest.approx(30.0)
    ok, why = soak.verdict(_report(leak, 0.0))
    assert not ok and "RSS grew 30.00 MB" in why[0]


def test_the_verdict_names_each_failure() -> None:
    s = _samples([100.0] * 20)
    s[-1]["fds"] = 14  # one more fd at the end, in a quiet sample
    s[5]["threads"] = 9  # a burst under way: not judged
    s[5]["quiet"] = False
    ok, why = soak.verdict(_report(s, 0.0, unexpected=2,
                                   unexpected_by_cause={"sensor_stale": 2}, not_detected=1))
    assert not ok
    assert why == ["fds not constant after the warm-up: 13..14",
                   "2 unexpected fault(s): sensor_stale x2",
                   "1 injected fault(s) not detected"]
    ok, why = soak.verdict(_report(_samples([100.0]), 0.0))
    assert not ok and "too few" in why[0]


def test_warm_up_is_five_minutes_or_a_fifth_of_a_short_run() -> None:
    assert soak.warmup_seconds(3600.0) == 300.0
    assert soak.warmup_seconds(600.0) == 120.0
    assert soak.warmup_seconds(600.0, given=30.0) == 30.0


def test_the_kept_samples_stay_bounded(monkeypatch: pytest.MonkeyPatch,
                                       tmp_path: Path) -> None:
    """A run of any length keeps at most MAX_SAMPLES samples, spread over all of it."""
    monkeypatch.setattr(soak, "MAX_SAMPLES", 100)
    args = soak.argparse.Namespace(seed=0, faults="", host="127.0.0.1", warmup=None)
    run = soak.Soak(args, 1e6, tmp_path, tmp_path / "log")
    for i in range(10_000):
        run._keep({"t": float(i)})
    assert len(run.samples) < 100
    ts = [s["t"] for s in run.samples]
    assert ts[0] == 0.0 and ts[-1] > 9000 and ts == sorted(ts)


def test_own_fds_and_processes_from_proc() -> None:
    kinds = soak.fd_summary(os.getpid())
    # (listing its own fds, a process sees the listing's directory fd too)
    assert abs(sum(kinds.values()) - (soak.open_fds(os.getpid()) or 0)) <= 1
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        kids, tree = soak.descendants(os.getpid())
        assert child.pid in kids and child.pid in tree
    finally:
        child.kill()
        child.wait()
    assert (soak.rss_mb(os.getpid()) or 0) > 0 and (soak.threads(os.getpid()) or 0) >= 1


def test_bad_options_are_one_line_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "soak", "--seconds", "0"]) == 2
    assert main(["bench", "soak", "--faults", "no_such_fault"]) == 2
    assert main(["bench", "soak", "--host", "10.0.0.1"]) == 2
    err = capsys.readouterr().err
    assert "must be > 0" in err and "unknown no_such_fault" in err and "loopback" in err
