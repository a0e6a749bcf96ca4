"""Soak the daemon on the simulated robot: armed, pushed, flooded and faulted for minutes.

The daemon runs as a child process (`mmctl run`, on a configuration moved to the soak's
own loopback address and temporary directory), which starts its own simulated robot
(`mmctl sim`): what is measured is exactly the process that runs on the robot.  It arms
itself; the simulated person does the task.  Meanwhile one thread of this process, with
a random schedule (``--seed``):

* pushes the handle (10-40 N along a random horizontal direction for 0.2-2 s) and lets
  the person go and come back now and then (the simulation's ``push`` and ``person``);
* floods the control socket: bursts of ``--flood-clients`` concurrent ``status``
  requests through the public client, every ``--flood-every`` seconds; errors are
  counted by kind, never fatal, and the loop misses during each burst are summed;
* every ``--fault-every`` seconds injects the next fault of the rotation into the
  simulation (``fault NAME``), waits for the daemon's FAULT, checks that the latched
  cause is the one that fault must cause and that ``enable`` is refused while a state
  fault is present, removes the fault (``fault NAME --off``) and enables again.  Every
  other fault (the daemon's fault counter) is unexpected: it is recorded and the robot
  is enabled again, so the run goes on.

Every ``--interval`` seconds the main thread samples, from /proc: the daemon's RSS,
threads, open fds, child processes and all its descendants, the simulation's RSS, this
process's own RSS; from the daemon's status: loop misses, cycles, faults.  Threads, fds
and children are the least of three readings 50 ms apart (a status request's
connection thread is not a leak), and samples taken while a burst or a fault is under
way are marked not quiet (their threads and fds are not judged).

At the end (or on Ctrl-C / SIGTERM: everything started is stopped and what was measured
is printed): RSS growth by linear regression over the samples after the warm-up
(``--warmup``; default the first 5 minutes, or the first 20 % of a shorter run), per
hour and over the post-warm-up span; threads/fds/children min/max; injected and
unexpected faults; a verdict: PASS when the RSS grew less than 5 MB after the warm-up,
threads/fds/children stayed constant (quiet samples after the warm-up), and no fault
happened but the injected ones, each latching its expected cause and re-enabled.

A run of any length keeps at most a few thousand samples (older ones are thinned out)
and the last records of each kind: this process's memory stays bounded.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

#: the verdict's limits: RSS growth after the warm-up [MB]
RSS_GROWTH_LIMIT_MB = 5.0
#: the warm-up: the first 5 minutes, or the first 20 % of a shorter run
WARMUP_MAX_S, WARMUP_FRACTION = 300.0, 0.2
#: at most this many samples are kept (beyond it every other one of the older half goes)
MAX_SAMPLES = 4000
#: at most this many fault / error records are kept (the counters count them all)
MAX_RECORDS = 200

#: each simulated fault (`mmctl sim fault --list`) and the causes the daemon may latch for
#: it; "event" faults have no --off (the enable resets them)
FAULT_CAUSES: dict[str, frozenset[str]] = {
    "wrench_over_limit": frozenset({"wrench_limit"}),
    "arm_protective_stop": frozenset({"arm_protective_stop"}),
    "sensor_status": frozenset({"sensor_status_error"}),
    "drive_fault": frozenset({"drive_fault"}),
    "arm_emergency_stop": frozenset({"arm_emergency_stop"}),
    "sensor_saturation": frozenset({"sensor_saturation"}),
    "sensor_silent": frozenset({"sensor_stale", "sensor_link_lost"}),
    # a frozen stream: stale timestamps, or the arm's process gives the link up first
    "arm_frozen": frozenset({"arm_timestamp_stale", "arm_disconnected"}),
    "drive_silent": frozenset({"drive_heartbeat_lost"}),
    "arm_not_playing": frozenset({"arm_not_playing"}),
    # the controller's process dies: its stream stops before its sockets close
    "arm_disconnected": frozenset({"arm_disconnected", "arm_timestamp_stale"}),
    "sensor_garbage": frozenset({"sensor_link_lost", "sensor_stale"}),
    "drive_reboot": frozenset({"drive_heartbeat_lost", "drive_fault", "base_link_lost"}),
    # one contact of a two-contact enabling switch stays open (a config with one: skipped)
    "enabling_contact": frozenset({"enabling_device_fault"}),
}
EVENT_FAULTS = frozenset({"drive_fault", "arm_not_playing", "drive_reboot"})
DEFAULT_FAULTS = tuple(FAULT_CAUSES)

#: ``--load-proof``: config/sim.yaml's tight timeouts (a loaded 2-core machine starves
#: the loop, the arm's process and the simulated robot for 50-200 ms now and then) x10-20
LOAD_PROOF: dict[str, Any] = {
    "arm": {"stale_cycles": 1000, "watchdog_min_frequency": 1.0},
    "sensor": {"wrench": {"stale_timeout": 1.0}},
    "base": {"canopen": {"heartbeat_timeout": 2.0}, "command_watchdog": 5.0},
    "loop": {"max_consecutive_misses": 1000},
}

_MAX_KINDS = 30  # distinct error kinds counted apart (the rest: "other")

_PORTS = (29999, 30003, 30004, 29536)  # the fake UR's and the simulation's socketcand


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--minutes", type=float, default=10.0, help="how long (default 10)")
    g.add_argument("--seconds", type=float, help="how long, in seconds (short runs, tests)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--config", metavar="FILE", help="base config (default: config/sim.yaml)")
    p.add_argument("--host", default="127.0.0.4",
                   help="loopback address of the soak's simulated robot (default 127.0.0.4)")
    p.add_argument("--interval", type=float, default=5.0, metavar="S",
                   help="seconds between samples (default 5)")
    p.add_argument("--warmup", type=float, metavar="S",
                   help="seconds not judged for RSS growth and constant counts (default: "
                        "5 minutes, or 20 %% of a shorter run)")
    p.add_argument("--flood-clients", type=int, default=50, metavar="N",
                   help="concurrent status requests per burst (default 50; 0: no floods)")
    p.add_argument("--flood-every", type=float, default=30.0, metavar="S",
                   help="seconds between bursts (default 30)")
    p.add_argument("--fault-every", type=float, default=60.0, metavar="S",
                   help="seconds between injected faults (default 60; 0: none)")
    p.add_argument("--faults", metavar="LIST",
                   help="the injected faults' rotation, comma-separated (default: all of "
                        "`mmctl sim fault --list` the configuration can have)")
    p.add_argument("--push-every", type=float, default=6.0, metavar="S",
                   help="mean seconds between random pushes (default 6; 0: none)")
    p.add_argument("--seed", type=int, default=0, help="the schedule's random seed")
    p.add_argument("--load-proof", action="store_true",
                   help="widen the staleness timeouts, the devices' watchdogs and the "
                        "loop's miss budget (LOAD_PROOF below) beyond what a loaded shared "
                        "machine exhausts, so that only a real defect faults unexpectedly; "
                        "the injected faults are still detected within seconds")
    p.add_argument("--daemon-log", metavar="FILE",
                   help="keep the daemon's and the simulation's log here (default: a "
                        "temporary file, kept only when the verdict is FAIL)")


# --------------------------------------------------------------------------- /proc --
def _status_fields(pid: int) -> dict[str, str]:
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key, _, value = line.partition(":")
            out[key] = value.strip()
    return out


def rss_mb(pid: int) -> float | None:
    """Resident set size of a process [MB] (None: gone)."""
    try:
        return int(_status_fields(pid)["VmRSS"].split()[0]) / 1024.0
    except (OSError, KeyError, ValueError, IndexError):
        return None


def threads(pid: int) -> int | None:
    try:
        return int(_status_fields(pid)["Threads"])
    except (OSError, KeyError, ValueError):
        return None


def open_fds(pid: int) -> int | None:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return None


def _cmdline(pid: int) -> str:
    """A process's command line, shortened (its pid when unreadable)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            argv = f.read().split(b"\0")
    except OSError:
        return str(pid)
    text = " ".join(a.decode(errors="replace") for a in argv if a)
    return text if len(text) <= 120 else text[:117] + "..."


def _socket_names(pid: int) -> dict[str, str]:
    """socket inode -> "tcp 127.0.0.1:30004->127.0.0.1:51234" / "unix PATH" (the
    process's network namespace tables)."""
    out: dict[str, str] = {}
    for proto in ("tcp", "udp", "tcp6"):
        try:
            with open(f"/proc/{pid}/net/{proto}") as f:
                next(f)
                for line in f:
                    c = line.split()
                    if len(c) > 9:
                        out[c[9]] = f"{proto} {_addr(c[1])}->{_addr(c[2])}"
        except (OSError, StopIteration):
            pass
    try:
        with open(f"/proc/{pid}/net/unix") as f:
            next(f)
            for line in f:
                c = line.split()
                if len(c) > 6:
                    out[c[6]] = f"unix {c[7] if len(c) > 7 else '(unnamed)'}"
    except (OSError, StopIteration):
        pass
    return out


def _addr(hexaddr: str) -> str:
    host, _, port = hexaddr.partition(":")
    if len(host) == 8:
        host = ".".join(str(int(host[i:i + 2], 16)) for i in (6, 4, 2, 0))
    return f"{host}:{int(port, 16)}"


def fd_summary(pid: int) -> dict[str, int]:
    """What a process's open fds are, counted by kind: files by path, sockets by
    protocol and address (a leak names itself)."""
    kinds: collections.Counter[str] = collections.Counter()
    names: dict[str, str] | None = None
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return {}
    for fd in fds:
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            names = _socket_names(pid) if names is None else names
            kinds[names.get(target[8:-1], "socket (other)")] += 1
        elif target.startswith(("pipe:", "anon_inode:")):
            kinds[target.split("[")[0] if target.startswith("pipe:") else target] += 1
        else:
            kinds[target] += 1
    return dict(sorted(kinds.items()))


def parents() -> dict[int, int]:
    """pid -> parent pid of every process (from /proc/*/stat)."""
    out = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                stat = f.read()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2:].split()
        if len(fields) > 1:
            out[int(name)] = int(fields[1])
    return out


def descendants(pid: int, ppids: dict[int, int] | None = None) -> tuple[list[int], list[int]]:
    """(children, all descendants) of ``pid``."""
    ppids = parents() if ppids is None else ppids
    kids: dict[int, list[int]] = collections.defaultdict(list)
    for p, pp in ppids.items():
        kids[pp].append(p)
    out, todo = [], list(kids.get(pid, []))
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(kids.get(p, []))
    return sorted(kids.get(pid, [])), sorted(out)


# ----------------------------------------------------------------------- analysis --
def regression_slope(ts: list[float], ys: list[float]) -> float | None:
    """Least-squares slope of ys over ts (None: fewer than 2 distinct times)."""
    n = len(ts)
    if n < 2:
        return None
    mt, my = sum(ts) / n, sum(ys) / n
    var = sum((t - mt) ** 2 for t in ts)
    if var <= 0:
        return None
    return sum((t - mt) * (y - my) for t, y in zip(ts, ys, strict=True)) / var


def warmup_seconds(duration: float, given: float | None = None) -> float:
    """The first 5 minutes, or the first 20 % of a run shorter than 25 minutes."""
    if given is not None:
        return given
    return min(WARMUP_MAX_S, WARMUP_FRACTION * duration)


def _span(values: list[Any]) -> dict[str, Any]:
    vals = [v for v in values if v is not None]
    if not vals:
        return {"min": None, "max": None, "first": None, "last": None}
    return {"min": min(vals), "max": max(vals), "first": vals[0], "last": vals[-1]}


def _growth(samples: list[dict[str, Any]], key: str, warmup: float) -> dict[str, Any]:
    pts = [(s["t"], s[key]) for s in samples if s["t"] >= warmup and s.get(key) is not None]
    out: dict[str, Any] = {**_span([s.get(key) for s in samples]), "samples_after_warmup": len(pts)}
    slope = regression_slope([p[0] for p in pts], [p[1] for p in pts])
    out["growth_mb_per_hour"] = None if slope is None else round(slope * 3600.0, 3)
    out["growth_after_warmup_mb"] = (None if slope is None
                                     else round(slope * (pts[-1][0] - pts[0][0]), 3))
    for k in ("min", "max", "first", "last"):
        if out[k] is not None:
            out[k] = round(out[k], 2)
    return out


def analyse(samples: list[dict[str, Any]], warmup: float) -> dict[str, Any]:
    """The figures of a list of samples (see the module docstring)."""
    out: dict[str, Any] = {"rss_mb": _growth(samples, "rss_mb", warmup),
                           "sim_rss_mb": _growth(samples, "sim_rss_mb", warmup),
                           "soak_rss_mb": _growth(samples, "soak_rss_mb", warmup)}
    judged = [s for s in samples if s["t"] >= warmup and s.get("quiet")]
    for key in ("threads", "fds", "children", "descendants"):
        out[key] = {"min": _span([s.get(key) for s in samples])["min"],
                    "max": _span([s.get(key) for s in samples])["max"],
                    "quiet_after_warmup": {k: v for k, v in _span(
                        [s.get(key) for s in judged]).items() if k in ("min", "max")}}
    out["quiet_samples_after_warmup"] = len(judged)
    return out


def verdict(report: dict[str, Any]) -> tuple[bool, list[str]]:
    """PASS and why not (see the module docstring)."""
    why = []
    fig, faults = report["daemon"], report["faults"]
    growth = fig["rss_mb"]["growth_after_warmup_mb"]
    if growth is None:
        why.append("too few samples after the warm-up to judge the RSS")
    elif growth >= RSS_GROWTH_LIMIT_MB:
        why.append(f"RSS grew {growth:.2f} MB after the warm-up (limit "
                   f"{RSS_GROWTH_LIMIT_MB:g} MB)")
    if fig["quiet_samples_after_warmup"] < 2:
        why.append("too few quiet samples after the warm-up to judge threads/fds/children")
    for key in ("threads", "fds", "children"):
        q = fig[key]["quiet_after_warmup"]
        if q["min"] != q["max"]:
            why.append(f"{key} not constant after the warm-up: {q['min']}..{q['max']}")
    if faults["unexpected"]:
        causes = ", ".join(f"{c} x{n}" for c, n in faults["unexpected_by_cause"].items())
        why.append(f"{faults['unexpected']} unexpected fault(s): {causes}")
    if faults["not_detected"]:
        why.append(f"{faults['not_detected']} injected fault(s) not detected")
    if faults["not_reenabled"]:
        why.append(f"{faults['not_reenabled']} fault(s) not re-enabled")
    if faults["enabled_while_present"]:
        why.append(f"{faults['enabled_while_present']} enable(s) accepted while the "
                   "injected fault was present")
    if report.get("soak_errors"):
        why.append("the soak's own schedule failed (see unexpected_events: soak_error)")
    if report.get("daemon_exit") is not None and not report.get("interrupted"):
        why.append(f"the daemon exited during the run (status {report['daemon_exit']})")
    return not why, why


# ------------------------------------------------------------------------ the run --


class Soak:
    """One soak run (see the module docstring)."""

    def __init__(self, args: argparse.Namespace, duration: float, tmp: Path,
                 log_path: Path) -> None:
        self.args = args
        self.duration = duration
        self.tmp = tmp
        self.log_path = log_path
        self.sock = tmp / "mmctl.sock"
        self.stop = threading.Event()
        self.rng = random.Random(args.seed)
        self.proc: subprocess.Popen[bytes] | None = None
        self.t0 = 0.0
        self.samples: list[dict[str, Any]] = []
        self._keep_every = 1  # thinning: every n-th new sample is kept
        self._seen = 0
        self._lock = threading.Lock()
        self._busy = 0
        self._settle_until = 0.0
        self.faults_seen = 0  # the daemon's fault counter, as last accounted for
        self.fault_stats: dict[str, dict[str, int]] = {}
        self.counts = collections.Counter[str]()
        self.unexpected: collections.deque[dict[str, Any]] = collections.deque(maxlen=MAX_RECORDS)
        self.unexpected_by_cause = collections.Counter[str]()
        self.flood_errors = collections.Counter[str]()
        self.flood_error_examples: dict[str, str] = {}
        self.flood_misses = 0
        self.status_errors = collections.Counter[str]()
        self.warmup = warmup_seconds(duration, args.warmup)
        self.rotation = [f.strip() for f in args.faults.split(",") if f.strip()]
        self.sim_pid: int | None = None
        self.last_status: dict[str, Any] = {}
        self.misses = 0  # the loop's misses since the start (its counter resets on enable)
        self._misses_seen: int | None = None
        self.fds_first: dict[str, int] | None = None
        self.fds_at_max: dict[str, Any] | None = None
        self.children_first: list[str] | None = None
        self._undo: tuple[list[float], float] | None = None  # the next push (its opposite)
        self.notes: collections.deque[dict[str, Any]] = collections.deque(maxlen=MAX_RECORDS)

    # -- the daemon --------------------------------------------------------------------
    def start_daemon(self, cfg_file: Path) -> None:
        logf = open(self.log_path, "ab")  # noqa: SIM115 -- the child's, closed below
        # its own session: a terminal's Ctrl-C reaches this process only, which stops the
        # daemon (and it its simulation) in order; --duration: a soak killed outright
        # leaves no daemon behind for long
        cmd = [sys.executable, "-m", "mmctl.cli", "run", "--config", str(cfg_file),
               "--socket", str(self.sock), "--no-live", "--log-level", "warning",
               "--duration", f"{self.duration + 600:.0f}"]
        try:
            self.proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=logf,
                                         stderr=logf, start_new_session=True)
        finally:
            logf.close()

    def call(self, cmd: str, timeout: float = 10.0, **params: Any) -> Any:
        """One request to the daemon (its loop misses accounted from every status)."""
        from mmctl.runtime.ipc import request

        r = request(self.sock, cmd, timeout=timeout, **params)
        if isinstance(r, dict):
            n = ((r.get("loop") or {}).get("misses") or {}).get("since_start")
            if isinstance(n, int):
                with self._lock:
                    last = self._misses_seen
                    if last is not None:  # (never reset: the daemon's since its start)
                        self.misses += max(n - last, 0)
                    self._misses_seen = n
        return r

    def sim(self, cmd: str, **params: Any) -> Any:
        from mmctl.runtime.ipc import request

        return request(self.tmp / "sim.sock", cmd, timeout=10.0, **params)

    def wait_armed(self, timeout: float) -> dict[str, Any]:
        """Until the daemon answers and is ARMED (it arms itself); enable if it does not."""
        from mmctl.errors import IpcError

        deadline = time.monotonic() + timeout
        st: dict[str, Any] = {}
        asked = False
        while not self.stop.is_set():
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise _DaemonGone(self.proc.returncode)
            try:
                st = self.call("status", timeout=5.0)
                if st.get("state") == "armed":
                    return st
                if st.get("state") == "fault" or (
                        time.monotonic() > deadline - timeout / 2 and not asked):
                    asked = True
                    self.call("enable", timeout=20.0)
            except IpcError:
                pass
            if time.monotonic() > deadline:
                raise TimeoutError(f"the daemon was not armed within {timeout:g} s: "
                                   f"{st.get('state')} {st.get('fault')} {st.get('conditions')}")
            self.stop.wait(0.25)
        return st

    def stop_daemon(self) -> int | None:
        """Ask the daemon to stop, then SIGTERM, then SIGKILL; its exit status."""
        proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            try:
                self.call("stop", timeout=5.0)
            except Exception as exc:  # noqa: BLE001 -- then the signals
                _progress(f"mmctl bench soak: the stop request failed ({exc}): signals")
            for sig, wait in ((None, 30.0), (signal.SIGTERM, 15.0), (signal.SIGKILL, 10.0)):
                if sig is not None:
                    try:
                        os.killpg(proc.pid, sig)
                    except ProcessLookupError:
                        pass
                try:
                    proc.wait(wait)
                    break
                except subprocess.TimeoutExpired:
                    continue
        return proc.returncode

    # -- busy marks (samples taken meanwhile are not quiet) ------------------------------
    def _busy_enter(self) -> None:
        with self._lock:
            self._busy += 1

    def _busy_exit(self, settle: float = 1.0) -> None:
        with self._lock:
            self._busy -= 1
            self._settle_until = max(self._settle_until, time.monotonic() + settle)

    def _quiet(self) -> bool:
        with self._lock:
            return self._busy == 0 and time.monotonic() >= self._settle_until

    # -- sampling (main thread) ----------------------------------------------------------
    def sample(self) -> dict[str, Any]:
        from mmctl.errors import IpcError

        assert self.proc is not None
        pid = self.proc.pid
        quiet = self._quiet()
        readings = []
        for i in range(3):
            ppids = parents()
            kids, tree = descendants(pid, ppids)
            readings.append((threads(pid), open_fds(pid), len(kids), len(tree), tree))
            if i < 2:
                time.sleep(0.05)
        s: dict[str, Any] = {"t": round(time.monotonic() - self.t0, 2)}
        s["rss_mb"] = rss_mb(pid)
        for k, key in enumerate(("threads", "fds", "children", "descendants")):
            vals = [r[k] for r in readings if r[k] is not None]
            s[key] = min(vals) if vals else None  # type: ignore[type-var]
        tree = readings[-1][4]
        if self.children_first is None:
            self.children_first = [_cmdline(p) for p in descendants(pid)[0]]
        if s["fds"] is not None:
            if self.fds_first is None:
                self.fds_first = fd_summary(pid)
            if self.fds_at_max is None or s["fds"] > self.fds_at_max["fds"]:
                self.fds_at_max = {"t": s["t"], "fds": s["fds"], "kinds": fd_summary(pid)}
        sim_pid = self.sim_pid
        s["sim_rss_mb"] = rss_mb(sim_pid) if sim_pid is not None else None
        s["sim_tree_rss_mb"] = (round(sum(rss_mb(p) or 0.0 for p in tree), 2) if tree else None)
        s["soak_rss_mb"] = rss_mb(os.getpid())
        try:
            st = self.call("status", timeout=10.0)
            self.last_status = st
            s["state"] = st.get("state")
            s["faults"] = st.get("faults")
            s["cycles"] = st.get("cycles")
            s["misses"] = self.misses
            simst = st.get("sim") or {}
            if simst.get("pid"):
                self.sim_pid = int(simst["pid"])
        except IpcError as exc:
            kind = _kind(exc)
            if kind not in self.status_errors and len(self.status_errors) >= _MAX_KINDS:
                kind = "other"
            self.status_errors[kind] += 1
            s["state"] = None
        s["quiet"] = quiet and self._quiet()
        for key in ("rss_mb", "sim_rss_mb", "soak_rss_mb"):
            if s[key] is not None:
                s[key] = round(s[key], 2)
        self._keep(s)
        return s

    def _keep(self, s: dict[str, Any]) -> None:
        self._seen += 1
        if (self._seen - 1) % self._keep_every:
            return
        self.samples.append(s)
        if len(self.samples) >= MAX_SAMPLES:  # thin out: every other sample from now on
            self.samples = self.samples[::2]
            self._keep_every *= 2

    # -- the chaos thread ------------------------------------------------------------------
    def chaos(self) -> None:
        try:
            self._chaos()
        except _Stopped:
            pass
        except Exception as exc:  # noqa: BLE001 -- reported, the run ends
            self.counts["chaos_errors"] += 1
            self.unexpected.append({"t": self._t(), "cause": "soak_error", "error": repr(exc)})
            self.stop.set()

    def _t(self) -> float:
        return round(time.monotonic() - self.t0, 2)

    def _sleep(self, seconds: float) -> None:
        if self.stop.wait(max(0.0, seconds)):
            raise _Stopped

    def _chaos(self) -> None:
        a = self.args
        now = time.monotonic()
        nxt: dict[str, float | None] = {"push": now + self._exp(a.push_every) if a.push_every > 0 else None,
               "person": now + self.rng.uniform(45.0, 120.0),
               "flood": now + a.flood_every if a.flood_clients > 0 else None,
               "fault": (now + self._fault_gap(0) if a.fault_every > 0 and self.rotation
                         else None),
               "check": now + 1.0}
        person_back: float | None = None
        k = 0
        while True:
            self._sleep(0.1)
            now = time.monotonic()
            if now - self.t0 >= self.duration:
                return
            if person_back is not None and now >= person_back:
                self._try(lambda: self.sim("person", on=True), "person")
                person_back = None
            if nxt["check"] is not None and now >= nxt["check"]:
                self._check_faults()
                nxt["check"] = now + 1.0
            if nxt["push"] is not None and now >= nxt["push"]:
                self._push()
                nxt["push"] = now + self._exp(a.push_every)
            person_at = nxt["person"]
            if person_at is not None and now >= person_at and person_back is None:
                self._try(lambda: self.sim("person", on=False), "person")
                self.counts["person_off"] += 1
                person_back = now + self.rng.uniform(3.0, 10.0)
                nxt["person"] = now + self.rng.uniform(45.0, 120.0)
            if nxt["flood"] is not None and now >= nxt["flood"]:
                self._flood(a.flood_clients)
                nxt["flood"] = time.monotonic() + a.flood_every
            if nxt["fault"] is not None and now >= nxt["fault"]:
                if person_back is not None:  # the person back first: a fault while pushing
                    self._try(lambda: self.sim("person", on=True), "person")
                    person_back = None
                self._inject(self.rotation[k % len(self.rotation)])
                k += 1
                nxt["fault"] = time.monotonic() + self._fault_gap(k)

    def _fault_gap(self, done: int) -> float:
        """Seconds to the next injected fault: during the warm-up every fault of the
        rotation is injected once, spread over it (their first runs' allocations —
        imports, first exceptions — fall in the warm-up, not in the judged growth);
        then every ``--fault-every`` seconds."""
        every = float(self.args.fault_every)
        if done < len(self.rotation):
            return min(every, self.warmup / (len(self.rotation) + 1))
        return every

    def _exp(self, mean: float) -> float:
        return min(5 * mean, self.rng.expovariate(1.0 / mean))

    def _try(self, fn: Callable[[], Any], what: str) -> Any:
        from mmctl.errors import IpcError

        try:
            return fn()
        except IpcError as exc:
            self.counts[f"{what}_errors"] += 1
            self._note(f"{what}: {exc}")
            return None

    def _note(self, text: str) -> None:
        self.notes.append({"t": self._t(), "note": text})

    def _push(self) -> None:
        """A random push, then (next time) the same push the other way: pushes in
        opposite pairs, so the handle does not random-walk the arm into its joint
        limits (the fake UR's protective stop) over a long run."""
        import math

        if self._undo is None:
            force = self.rng.uniform(10.0, 40.0)
            angle = self.rng.uniform(0.0, 2 * math.pi)
            seconds = self.rng.uniform(0.2, 2.0)
            f = [force * math.cos(angle), force * math.sin(angle), 0.0]
            self._undo = ([-x for x in f], seconds)
        else:
            f, seconds = self._undo
            self._undo = None
        self._try(lambda: self.sim("push", force=f, seconds=seconds), "push")
        self.counts["pushes"] += 1

    def _flood(self, n: int) -> None:
        from mmctl.runtime.ipc import request

        before = self._misses()
        gate = threading.Event()
        results: list[str | None] = [None] * n

        def client(i: int) -> None:
            gate.wait()
            try:
                request(self.sock, "status", timeout=10.0)
                results[i] = "ok"
            except Exception as exc:  # noqa: BLE001 -- counted, never fatal
                kind = _kind(exc)
                if kind not in self.flood_error_examples:
                    if len(self.flood_error_examples) >= _MAX_KINDS:
                        kind = "other"
                    self.flood_error_examples.setdefault(kind, str(exc)[:200])
                results[i] = kind

        self._busy_enter()
        try:
            workers = [threading.Thread(target=client, args=(i,), name=f"soak-flood-{i}",
                                        daemon=True) for i in range(n)]
            for w in workers:
                w.start()
            gate.set()
            for w in workers:
                w.join(30.0)
        finally:
            self._busy_exit()
        self.counts["flood_bursts"] += 1
        self.counts["flood_requests"] += n
        for r in results:
            if r == "ok":
                self.counts["flood_ok"] += 1
            else:
                self.flood_errors[r or "no_answer"] += 1
        after = self._misses()
        if before is not None and after is not None:
            self.flood_misses += after - before

    def _misses(self) -> int | None:
        st = self._try(lambda: self.call("status", timeout=10.0), "status")
        return None if st is None else self.misses

    def _check_faults(self) -> None:
        """A fault the soak did not inject: record it, enable again."""
        st = self._try(lambda: self.call("status", timeout=10.0), "status")
        if st is None:
            return
        n = int(st.get("faults", 0))
        if n > self.faults_seen:
            new = n - self.faults_seen
            self.faults_seen = n
            cause = st.get("fault") or "unknown"
            self.unexpected_by_cause[cause] += new
            sim = self._try(lambda: self.sim("status"), "sim_status") or {}
            self.unexpected.append({"t": self._t(), "cause": cause, "count": new,
                                    "details": st.get("fault_details"),
                                    "conditions": st.get("conditions"),
                                    # where the simulated arm is (a joint at its limit?)
                                    "sim_arm_q": sim.get("arm_q"),
                                    "sim_faults": sim.get("faults")})
        if st.get("state") != "armed":
            self._busy_enter()
            try:
                if not self._reenable(30.0):
                    self.counts["not_reenabled"] += 1
            finally:
                self._busy_exit()

    def _reenable(self, timeout: float) -> bool:
        from mmctl.errors import IpcError

        deadline = time.monotonic() + timeout
        while True:
            try:
                st = self.call("enable", timeout=20.0)
                if st.get("state") == "armed":
                    return True
            except IpcError as exc:
                last = str(exc)
            if time.monotonic() > deadline:
                self._note(f"enable failed for {timeout:g} s: {last}")
                return False
            self._sleep(0.5)

    def _inject(self, name: str) -> None:
        """Inject, see the fault, check it, remove it, enable (see the module docstring)."""
        from mmctl.errors import IpcError

        stats = self.fault_stats.setdefault(name, collections.Counter())
        self._check_faults()  # whatever happened before is not this fault's
        self._busy_enter()
        try:
            stats["injected"] += 1
            t_inj = time.monotonic()
            self._try(lambda: self.sim("fault", name=name, on=True), "fault")
            st: dict[str, Any] = {}
            deadline = t_inj + 15.0
            while time.monotonic() < deadline:
                st = self._try(lambda: self.call("status", timeout=10.0), "status") or {}
                if st.get("state") == "fault":
                    break
                self._sleep(0.05)
            detected = st.get("state") == "fault"
            if detected:
                stats["detected"] += 1
                n = int(st.get("faults", 0))
                cause = st.get("fault") or "unknown"
                extra = n - self.faults_seen - 1
                self.faults_seen = n
                if cause in FAULT_CAUSES.get(name, frozenset()):
                    stats["expected_cause"] += 1
                    self.counts["injected_faults"] += 1
                else:
                    extra += 1
                    stats["wrong_cause"] += 1
                if extra > 0:
                    self.unexpected_by_cause[cause] += extra
                    self.unexpected.append({"t": self._t(), "cause": cause, "count": extra,
                                            "while_injecting": name,
                                            "details": st.get("fault_details")})
                if name not in EVENT_FAULTS and cause in FAULT_CAUSES[name]:  # refused
                    # while present (another cause first: the injected one may not have
                    # reached the daemon yet)
                    try:
                        r = self.call("enable", timeout=20.0)
                        if isinstance(r, dict) and r.get("state") == "armed":
                            stats["enabled_while_present"] += 1
                            self.counts["enabled_while_present"] += 1
                            self._note(f"{name}: enable accepted while injected "
                                       f"(latched {cause}, {st.get('fault_details')})")
                    except IpcError:
                        stats["refused_while_present"] += 1
            else:
                stats["not_detected"] += 1
                self.counts["not_detected"] += 1
                self._note(f"{name}: no fault within 15 s ({st.get('state')})")
            if name not in EVENT_FAULTS:
                self._try(lambda: self.sim("fault", name=name, on=False), "fault")
            if self._reenable(60.0):
                stats["reenabled"] += 1
                stats["reenable_ms_total"] += int(1000 * (time.monotonic() - t_inj))
            else:
                self.counts["not_reenabled"] += 1
            # faults between the detection and the end of the re-enable (a refused enable
            # latches nothing; an accepted one may fault again before it returns)
            after = self._try(lambda: self.call("status", timeout=10.0), "status") or {}
            n = int(after.get("faults", self.faults_seen))
            if n > self.faults_seen:
                cause = after.get("fault") or "unknown"
                self.unexpected_by_cause[cause] += n - self.faults_seen
                self.unexpected.append({"t": self._t(), "cause": cause,
                                        "count": n - self.faults_seen,
                                        "while_reenabling_after": name,
                                        "details": after.get("fault_details")})
                self.faults_seen = n
        finally:
            self._busy_exit(settle=2.0)

    # -- the report ----------------------------------------------------------------------
    def report(self, interrupted: bool, daemon_exit: int | None) -> dict[str, Any]:
        elapsed = time.monotonic() - self.t0 if self.t0 else 0.0
        warmup = warmup_seconds(min(self.duration, elapsed), self.args.warmup)
        first_misses = next((s["misses"] for s in self.samples if s.get("misses") is not None),
                            None)
        last_misses = next((s["misses"] for s in reversed(self.samples)
                            if s.get("misses") is not None), None)
        by_fault = {}
        for name, st in self.fault_stats.items():
            d: dict[str, Any] = {k: int(v) for k, v in st.items() if k != "reenable_ms_total"}
            if st.get("reenabled"):
                d["reenable_mean_s"] = round(st["reenable_ms_total"] / st["reenabled"] / 1e3, 2)
            d["expected_causes"] = sorted(FAULT_CAUSES.get(name, ()))
            by_fault[name] = d
        unexpected = sum(self.unexpected_by_cause.values())
        out: dict[str, Any] = {
            "planned_seconds": round(self.duration, 1),
            "elapsed_seconds": round(elapsed, 1),
            "interrupted": interrupted,
            "host": self.args.host,
            "interval_s": self.args.interval,
            "warmup_s": round(warmup, 1),
            "seed": self.args.seed,
            "load_proof": self.args.load_proof,
            "samples": len(self.samples),
            "samples_taken": self._seen,
            "daemon_pid": self.proc.pid if self.proc else None,
            "sim_pid": self.sim_pid,
            "daemon_exit": daemon_exit,
            "daemon": analyse(self.samples, warmup),
            "children_at_start": self.children_first,
            "fds_at_start": self.fds_first,
            "fds_at_max": self.fds_at_max,
            "loop": {"misses": (None if first_misses is None or last_misses is None
                                else last_misses - first_misses),
                     "misses_total": last_misses,
                     "misses_during_floods": self.flood_misses,
                     "cycles": next((s["cycles"] for s in reversed(self.samples)
                                     if s.get("cycles") is not None), None)},
            "faults": {"injected": sum(int(s["injected"]) for s in self.fault_stats.values()),
                       "as_expected": self.counts["injected_faults"],
                       "unexpected": unexpected,
                       "unexpected_by_cause": dict(self.unexpected_by_cause),
                       "not_detected": self.counts["not_detected"],
                       "not_reenabled": self.counts["not_reenabled"],
                       "enabled_while_present": self.counts["enabled_while_present"],
                       "by_fault": by_fault,
                       "unexpected_events": list(self.unexpected)},
            "floods": {"bursts": self.counts["flood_bursts"],
                       "clients_per_burst": self.args.flood_clients,
                       "requests": self.counts["flood_requests"],
                       "ok": self.counts["flood_ok"],
                       "errors": sum(self.flood_errors.values()),
                       "errors_by_kind": dict(self.flood_errors),
                       "error_examples": dict(self.flood_error_examples)},
            "pushes": self.counts["pushes"],
            "person_off": self.counts["person_off"],
            "status_errors": dict(self.status_errors),
            "soak_errors": self.counts["chaos_errors"],
            "notes": list(self.notes),
            "series": self.samples,
        }
        ok, why = verdict(out)
        out["verdict"] = "PASS" if ok else "FAIL"
        out["verdict_reasons"] = why
        return out


class _Stopped(Exception):
    """The run is over (the stop event): leave the chaos thread."""


class _DaemonGone(Exception):
    def __init__(self, status: int | None):
        super().__init__(f"the daemon exited with status {status}")
        self.status = status


def _kind(exc: BaseException) -> str:
    """An error's kind for the counters: its class and the first words of its text."""
    text = str(exc)
    for marker in (" on /", " within ", ": "):
        text = text.split(marker)[0]
    return f"{type(exc).__name__}: {text[:60]}"


def _config_file(args: argparse.Namespace, tmp: Path) -> Path:
    import dataclasses

    import yaml

    from mmctl.config import config_from_dict, to_dict
    from mmctl.runtime.client import load

    cfg: Any = load(args.config)
    h = args.host
    cfg = dataclasses.replace(
        cfg,
        arm=dataclasses.replace(cfg.arm, host=h),
        sensor=dataclasses.replace(cfg.sensor, can=dataclasses.replace(
            cfg.sensor.can, interface="socketcand", host=h)),
        base=dataclasses.replace(cfg.base, canopen=dataclasses.replace(
            cfg.base.canopen, interface="socketcand", host=h)),
        sim=dataclasses.replace(cfg.sim, enabled=True, human=True, auto_enable=True, host=h,
                                socket_path=str(tmp / "sim.sock")),
    )
    data = to_dict(cfg)
    if args.load_proof:
        _merge(data, LOAD_PROOF)
    config_from_dict(data)  # a bad combination fails here, not in the child
    path = tmp / "soak.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _merge(into: dict[str, Any], extra: dict[str, Any]) -> None:
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(into.get(key), dict):
            _merge(into[key], value)
        else:
            into[key] = value


@contextlib.contextmanager
def _stop_signals(stop: threading.Event) -> Iterator[None]:
    """SIGINT/SIGTERM set ``stop`` (in the main thread only) for the duration."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    old = {s: signal.getsignal(s) for s in sigs}
    for s in sigs:
        signal.signal(s, lambda _n, _f: stop.set())
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import MmctlError

    duration = args.seconds if args.seconds is not None else 60.0 * args.minutes
    if not duration > 0:
        raise MmctlError("--minutes/--seconds: must be > 0")
    if not args.interval > 0:
        raise MmctlError(f"--interval {args.interval:g}: must be > 0")
    for opt in ("flood_every", "fault_every", "push_every"):
        if getattr(args, opt) < 0:
            raise MmctlError(f"--{opt.replace('_', '-')}: must be >= 0")
    if args.flood_clients < 0:
        raise MmctlError("--flood-clients: must be >= 0")
    if args.flood_clients and not args.flood_every > 0:
        raise MmctlError("--flood-every: must be > 0 with floods")
    if args.faults is None:
        from mmctl.runtime.client import load

        two_contacts = len(load(args.config).enabling.inputs) == 2
        args.faults = ",".join(f for f in DEFAULT_FAULTS
                               if f != "enabling_contact" or two_contacts)
    unknown = [f for f in args.faults.split(",") if f.strip() and f.strip() not in FAULT_CAUSES]
    if unknown:
        raise MmctlError(f"--faults: unknown {', '.join(unknown)}; known: "
                         f"{', '.join(FAULT_CAUSES)}")
    if not args.host.startswith("127."):
        raise MmctlError(f"--host {args.host}: a loopback address (127.x.y.z)")
    from mmctl.sim.fake_ur.server import ports_free

    if not ports_free(args.host, _PORTS):
        raise MmctlError(f"--host {args.host}: the fake UR's or socketcand's ports are in "
                         "use there (another simulated robot?); choose another 127.x.y.z")
    tmp = Path(tempfile.mkdtemp(prefix="mmctl-soak-"))
    log_path = Path(args.daemon_log) if args.daemon_log else tmp / "daemon.log"
    soak = Soak(args, duration, tmp, log_path)
    interrupted = False
    daemon_exit: int | None = None
    chaos: threading.Thread | None = None
    with _stop_signals(soak.stop):
        try:
            soak.start_daemon(_config_file(args, tmp))
            _progress(f"mmctl bench soak: {duration / 60:g} min on {args.host}, daemon pid "
                      f"{soak.proc.pid if soak.proc else '?'}, log {log_path}")
            st = soak.wait_armed(120.0)
            if soak.stop.is_set():
                raise _Stopped
            soak.faults_seen = int(st.get("faults", 0))
            soak.sim_pid = (st.get("sim") or {}).get("pid")
            soak.t0 = time.monotonic()
            chaos = threading.Thread(target=soak.chaos, name="soak-chaos", daemon=True)
            chaos.start()
            next_sample = soak.t0
            next_line = soak.t0
            while not soak.stop.is_set():
                now = time.monotonic()
                if now - soak.t0 >= duration:
                    break
                assert soak.proc is not None
                if soak.proc.poll() is not None:
                    raise _DaemonGone(soak.proc.returncode)
                if now >= next_sample:
                    s = soak.sample()
                    next_sample += args.interval
                    if now >= next_line:
                        _progress(_line(soak, s, duration))
                        next_line = now + max(args.interval, 30.0)
                soak.stop.wait(max(0.0, min(next_sample, soak.t0 + duration)
                                   - time.monotonic()))
            interrupted = soak.stop.is_set() and time.monotonic() - soak.t0 < duration
            if soak.proc is not None and soak.proc.poll() is None and soak.samples:
                soak.sample()  # the end's figures
        except _Stopped:
            interrupted = True
        except _DaemonGone as exc:
            daemon_exit = exc.status
            _progress(f"mmctl bench soak: {exc} (its log: {log_path})")
        except TimeoutError as exc:
            _progress(f"mmctl bench soak: {exc} (its log: {log_path})")
            interrupted = True
        finally:
            soak.stop.set()
            if chaos is not None:
                chaos.join(90.0)
            _progress("mmctl bench soak: stopping the daemon")
            status = soak.stop_daemon()
            if daemon_exit is None and status not in (None, 0):
                _progress(f"mmctl bench soak: the daemon ended with status {status}")
    report = soak.report(interrupted, daemon_exit)
    keep_log = args.daemon_log or report["verdict"] != "PASS"
    report["daemon_log"] = str(log_path) if keep_log else None
    if not keep_log:
        log_path.unlink(missing_ok=True)
    for f in tmp.iterdir():
        if f != log_path:
            f.unlink(missing_ok=True)
    if not any(tmp.iterdir()):
        tmp.rmdir()
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        print(format_report(report))
    return 0 if report["verdict"] == "PASS" else 1


def _progress(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _line(soak: Soak, s: dict[str, Any], duration: float) -> str:
    def mmss(t: float) -> str:
        return f"{int(t // 60):02d}:{int(t % 60):02d}"

    inj = soak.counts["injected_faults"]
    unexp = sum(soak.unexpected_by_cause.values())
    return (f"soak {mmss(s['t'])}/{mmss(duration)}  rss {s['rss_mb']} MB  threads "
            f"{s['threads']}  fds {s['fds']}  children {s['children']}  sim rss "
            f"{s['sim_rss_mb']} MB  misses {s.get('misses')}  faults {inj} injected / "
            f"{unexp} unexpected  floods {soak.counts['flood_bursts']} "
            f"({sum(soak.flood_errors.values())} errors)  state {s.get('state')}")


def format_report(r: dict[str, Any]) -> str:
    d, f, fl, lp = r["daemon"], r["faults"], r["floods"], r["loop"]

    def growth(g: dict[str, Any]) -> str:
        if g["growth_mb_per_hour"] is None:
            return f"{g['first']} -> {g['last']} MB (too few samples for a slope)"
        return (f"{g['first']} -> {g['last']} MB (min {g['min']}, max {g['max']}); after "
                f"the warm-up {g['growth_mb_per_hour']:+.2f} MB/h, "
                f"{g['growth_after_warmup_mb']:+.2f} MB over the run")

    def mm(key: str) -> str:
        q = d[key]["quiet_after_warmup"]
        return (f"{d[key]['min']}..{d[key]['max']} (quiet, after the warm-up: "
                f"{q['min']}..{q['max']})")

    lines = [
        (f"mmctl bench soak: {r['elapsed_seconds'] / 60:.1f} of {r['planned_seconds'] / 60:g} "
         f"min{' (interrupted)' if r['interrupted'] else ''} on {r['host']}"
         f"{' (--load-proof)' if r['load_proof'] else ''}, "
         f"{r['samples_taken']} samples every {r['interval_s']:g} s, warm-up "
         f"{r['warmup_s']:g} s"),
        f"daemon RSS:     {growth(d['rss_mb'])}",
        f"sim RSS:        {growth(d['sim_rss_mb'])}",
        f"soak tool RSS:  {growth(d['soak_rss_mb'])}",
        (f"threads {mm('threads')}; fds {mm('fds')}; children {mm('children')}; "
         f"descendants {mm('descendants')}"),
        (f"loop: {lp['misses']} misses over the run ({lp['misses_during_floods']} during "
         f"floods), {lp['cycles']} cycles"),
        f"faults: {f['injected']} injected, {f['as_expected']} latched the expected cause, "
        f"{f['unexpected']} unexpected"
        + (f" ({', '.join(f'{c} x{n}' for c, n in f['unexpected_by_cause'].items())})"
           if f["unexpected"] else "")
        + f", {f['not_detected']} not detected, {f['not_reenabled']} not re-enabled",
    ]
    for name, st in f["by_fault"].items():
        lines.append(f"  {name:22} injected {st.get('injected', 0)}, as expected "
                     f"{st.get('expected_cause', 0)}, refused while present "
                     f"{st.get('refused_while_present', 0)}, re-enabled "
                     f"{st.get('reenabled', 0)} (mean {st.get('reenable_mean_s', '-')} s)")
    lines.append(f"floods: {fl['bursts']} bursts of {fl['clients_per_burst']} concurrent "
                 f"status requests, {fl['ok']} ok, {fl['errors']} errors"
                 + (f" ({', '.join(f'{k} x{n}' for k, n in fl['errors_by_kind'].items())})"
                    if fl["errors"] else ""))
    lines.append(f"pushes: {r['pushes']}, person let go {r['person_off']} time(s)")
    if r.get("daemon_log"):
        lines.append(f"daemon log: {r['daemon_log']}")
    lines.append(f"verdict: {r['verdict']}"
                 + "".join(f"\n  - {why}" for why in r["verdict_reasons"]))
    return "\n".join(lines)
