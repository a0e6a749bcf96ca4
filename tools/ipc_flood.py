#!/usr/bin/env python3
"""Control-socket floods against the armed daemon on the simulated robot: do they cost
the loop deadlines?

Runs the daemon in this process on the simulated robot (its own `mmctl sim` child, the
fake UR process, CAN over socketcand, the simulated person pushing), armed, with its
control socket, and alternates windows of ``--window`` seconds, ``--rounds`` times:

* quiet: nothing on the socket (the machine's own noise);
* hold: ``--hold`` clients (default 1000) connect at once from a child process, each
  asks for the status once and keeps its connection open for the window;
* quiet;
* burst: ``--burst`` status requests (default 200) at once, from ``--burst-procs``
  child processes, each on its own connection.

Per window: deadline misses, the loop's wake-latency and compute-time p99, the daemon
process's CPU time (less noisy than misses on a shared machine: what the socket's
work adds is the difference to a quiet window), the clients' replies and their
latency p50/p99/max.  The clients run in child processes, so their own
work is not on the daemon's interpreter.  Afterwards, with the hold flood still
connected: a ``status`` and a ``stop`` on the socket (they must get through), then the
figures and the faults.  The miss budget is the robot's (``--budget robot``, 5
consecutive misses) unless ``--budget sim``.

    PYTHONPATH=src .venv/bin/python tools/ipc_flood.py [--rounds 3] [--window 3] [--json]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import resource
import selectors
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

STATUS = b'{"cmd": "status"}\n'


# -- the clients (child processes) --------------------------------------------------------
def _connect_all(path: str, n: int, deadline: float) -> list[socket.socket]:
    """``n`` non-blocking connections, retrying a full backlog until ``deadline``."""
    socks: list[socket.socket] = []
    while len(socks) < n and time.monotonic() < deadline:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.setblocking(False)
        try:
            s.connect(path)
        except BlockingIOError:
            s.close()
            time.sleep(0.002)
            continue
        except OSError:
            s.close()
            break
        socks.append(s)
    return socks


def client_main(mode: str, path: str, n: int, seconds: float) -> None:
    """hold: ``n`` connections each asking once, held ``seconds``; burst: ``n`` requests
    at once, each timed.  Prints one JSON line of counts (and latencies [ms])."""
    _soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    print("ready", flush=True)
    sys.stdin.readline()  # started, imported: the flood begins when the window does
    t0 = time.monotonic()
    end = t0 + seconds
    socks = _connect_all(path, n, end)
    sel = selectors.DefaultSelector()
    sent: dict[int, float] = {}
    for s in socks:
        try:
            s.send(STATUS)
            sent[s.fileno()] = time.monotonic()
        except OSError:
            pass
        sel.register(s, selectors.EVENT_READ)
    ok = evicted = errors = closed = 0
    lat: list[float] = []
    pending = len(socks)
    while time.monotonic() < end and (mode == "hold" or pending):
        for key, _ in sel.select(0.05):
            s = key.fileobj
            assert isinstance(s, socket.socket)
            try:
                data = s.recv(65536)
            except OSError:
                data = b""
            if not data:
                closed += 1
                sel.unregister(s)
                pending -= 1
                continue
            line = data.split(b"\n", 1)[0]
            try:
                reply = json.loads(line)
            except ValueError:
                errors += 1
                continue
            if reply.get("ok"):
                ok += 1
                lat.append((time.monotonic() - sent.get(s.fileno(), t0)) * 1e3)
            elif reply.get("evicted") or "too many" in str(reply.get("error")):
                evicted += 1
            else:
                errors += 1
            if mode == "burst":
                sel.unregister(s)
                pending -= 1
    print(json.dumps({"connected": len(socks), "ok": ok, "evicted": evicted,
                      "errors": errors, "closed": closed, "latency_ms": lat}), flush=True)
    for s in socks:
        s.close()


#: niceness of the client processes (``--client-nice``): 0, or e.g. 19 to tell what the
#: daemon's socket work costs the loop from what the clients' own CPU use costs it on a
#: machine with few cores
CLIENT_NICE = 0
#: the CPUs the client processes may run on (``--loop-cpu``: all but the loop's)
CLIENT_CPUS = ""


def _spawn(mode: str, path: Path, n: int, seconds: float) -> subprocess.Popen[bytes]:
    """A client process, started and waiting (its start-up is not in any window)."""
    prefix = ["nice", "-n", str(CLIENT_NICE)] if CLIENT_NICE else []
    if CLIENT_CPUS:
        prefix = ["taskset", "-c", CLIENT_CPUS, *prefix]
    p = subprocess.Popen([*prefix, sys.executable, __file__, "--client", mode, str(path),
                          str(n), str(seconds)], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    assert p.stdout is not None
    if p.stdout.readline() != b"ready\n":
        raise RuntimeError("a flood client did not start")
    return p


def _go(procs: list[subprocess.Popen[bytes]]) -> list[subprocess.Popen[bytes]]:
    for p in procs:
        assert p.stdin is not None
        p.stdin.write(b"go\n")
        p.stdin.flush()
    return procs


def _collect(procs: list[subprocess.Popen[bytes]]) -> dict[str, Any]:
    import numpy as np

    out: dict[str, Any] = {"connected": 0, "ok": 0, "evicted": 0, "errors": 0, "closed": 0}
    lat: list[float] = []
    for p in procs:
        assert p.stdout is not None
        raw = p.stdout.read()
        p.wait(120)
        r = json.loads(raw.decode().strip().splitlines()[-1])
        lat += r.pop("latency_ms")
        for k in out:
            out[k] += r[k]
    if lat:
        a = np.asarray(lat)
        out["latency_ms"] = {"p50": round(float(np.percentile(a, 50)), 2),
                             "p99": round(float(np.percentile(a, 99)), 2),
                             "max": round(float(a.max()), 2)}
    return out


# -- the daemon (this process) ---------------------------------------------------------------
def _window(daemon: Any, seconds: float, flood: list[subprocess.Popen[bytes]] | None
            ) -> dict[str, Any]:
    import numpy as np

    from mmctl.runtime.driver import PHASES
    from mmctl.runtime.timing import cycle_rows, summarize

    ring = daemon.ring
    c0 = ring.count
    cpu0 = _cpu()
    gw = getattr(daemon.server, "pid", None)
    gw0 = _proc_cpu(gw)
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        time.sleep(0.05)
    cpu = _cpu() - cpu0
    gw_cpu = _proc_cpu(gw) - gw0
    snap = ring.snapshot(ring.count - c0)
    st = summarize(snap)
    phases = {}
    for k, name in enumerate(PHASES):  # where the compute time went, per device
        us = cycle_rows(daemon.phase_ns[k], snap) / 1e3
        us = us[us > 0]
        if len(us):
            phases[name] = round(float(np.percentile(us, 99)), 1)
    step = cycle_rows(daemon.step_ns, snap) / 1e3
    if (step > 0).any():
        phases["step"] = round(float(np.percentile(step[step > 0], 99)), 1)
    fig: dict[str, Any] = {"cycles": st.cycles, "misses": st.missed,
                           "overrun_cycles": int((snap.missed > 0).sum()),
                           "latency_p99_us": round(float(st.latency_p99_us), 1),
                           "compute_p99_us": round(float(st.compute_p99_us), 1),
                           "daemon_cpu_s": round(cpu, 3),
                           "socket_process_cpu_s": round(gw_cpu, 3),
                           "phase_p99_us": phases}
    if flood is not None:
        fig["clients"] = _collect(flood)
    return fig


def _cpu() -> float:
    """CPU time of this process so far (the daemon: loop, socket, telemetry) [s]."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _realtime(root: int, priority: int) -> list[int]:
    """SCHED_FIFO ``priority`` for process ``root`` and its descendants, all threads."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    todo, done = [root], []
    while todo:
        pid = todo.pop()
        done.append(pid)
        todo += children.get(pid, [])
        for tid in os.listdir(f"/proc/{pid}/task"):
            with contextlib.suppress(OSError):
                os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
    return done


def _proc_cpu(pid: int | None) -> float:
    """CPU time of another process so far (the control socket's own process) [s]; 0 for
    none."""
    if pid is None:
        return 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from mmctl.errors import MmctlError
    from mmctl.runtime.client import load
    from mmctl.runtime.factory import create_daemon, open_sim
    from mmctl.runtime.ipc import request
    from mmctl.runtime.logging import setup_logging

    setup_logging("warning", stream=sys.stderr)
    cfg: Any = load(args.config)
    tmp = Path(tempfile.mkdtemp(prefix="mmctl-flood-"))
    budget = ({"max_consecutive_misses": 5, "max_total_misses": 1000} if args.budget == "robot"
              else {})
    cfg = dataclasses.replace(
        cfg,
        arm=dataclasses.replace(cfg.arm, host=args.host),
        sensor=dataclasses.replace(cfg.sensor, can=dataclasses.replace(
            cfg.sensor.can, interface="socketcand", host=args.host)),
        base=dataclasses.replace(cfg.base, canopen=dataclasses.replace(
            cfg.base.canopen, interface="socketcand", host=args.host)),
        loop=dataclasses.replace(cfg.loop, rt_priority=args.rt_priority,
                                 cpu_affinity=() if args.loop_cpu is None else (args.loop_cpu,),
                                 timing_samples=int(cfg.loop.rate_hz * 3 *
                                                               args.window) + 2000, **budget),
        sim=dataclasses.replace(cfg.sim, enabled=True, human=True, auto_enable=False,
                                host=args.host, socket_path=str(tmp / "sim.sock")),
    )
    path = tmp / "mmctl.sock"
    sim = open_sim(cfg)  # the caller's, never the daemon's: before it connects
    assert sim is not None
    try:
        daemon = create_daemon(cfg, socket_path=path, sim=sim)
    except BaseException:
        sim.close()
        raise
    out: dict[str, Any] = {"socket_process": True,
                           "rt_priority": args.rt_priority, "loop_cpu": args.loop_cpu,
                           "sim_priority": args.sim_priority, "client_nice": args.client_nice,
                           "window_s": args.window, "rounds": args.rounds, "hold": args.hold,
                           "burst": args.burst, "budget": args.budget,
                           "cpus": os.cpu_count(), "loadavg_1min": os.getloadavg()[0],
                           "windows": {"quiet": [], "hold": [], "burst": []}}
    held: list[subprocess.Popen[bytes]] = []
    try:
        daemon.open()
        daemon.start()
        if args.sim_priority:  # the simulated devices answer like hardware: whatever the load
            assert daemon.sim is not None and daemon.sim.pid is not None
            out["sim_processes"] = _realtime(daemon.sim.pid, args.sim_priority)
        daemon.tare_and_enable(30.0)
        assert daemon.sim is not None
        daemon.sim.start_human()
        time.sleep(1.0)
        w = out["windows"]
        per = max(1, args.burst // args.burst_procs)
        for _ in range(args.rounds):
            w["quiet"].append(_window(daemon, args.window, None))
            hold = [_spawn("hold", path, args.hold, args.window)]
            w["hold"].append(_window(daemon, args.window, _go(hold)))
            w["quiet"].append(_window(daemon, args.window, None))
            burst = [_spawn("burst", path, per, args.window) for _ in range(args.burst_procs)]
            w["burst"].append(_window(daemon, args.window, _go(burst)))
        # what one rebuild of the status snapshot costs the daemon (at most 10 a second)
        t = time.perf_counter()
        for _ in range(20):
            daemon.status()
        out["status_build_us"] = round((time.perf_counter() - t) / 20 * 1e6, 1)
        out["armed_before_stop"] = daemon.safety.armed
        out["faults"] = daemon.safety.faults
        out["fault"] = daemon.safety.as_dict().get("fault")
        # The socket still serves, with a hold flood connected: status, then stop.
        held = _go([_spawn("hold", path, args.hold, 20.0)])
        time.sleep(1.0)
        t = time.monotonic()
        try:
            st = request(path, "status", timeout=10.0)
            out["status_after"] = {"ok": True, "seconds": round(time.monotonic() - t, 3),
                                   "state": st.get("state")}
        except (MmctlError, OSError) as exc:  # (a client without the backlog retry)
            out["status_after"] = {"ok": False, "error": repr(exc)}
        t = time.monotonic()
        try:
            request(path, "stop", timeout=10.0)
            daemon_stopped = daemon._stop_requested.wait(10.0)
            out["stop_after"] = {"ok": daemon_stopped, "seconds": round(time.monotonic() - t, 3)}
        except (MmctlError, OSError) as exc:
            out["stop_after"] = {"ok": False, "error": repr(exc)}
        srv = daemon.server
        if srv is not None and hasattr(srv, "counters"):
            out["server"] = dict(srv.counters)
    finally:
        try:
            daemon.shutdown()
        finally:
            sim.close()
        for p in held:
            p.kill()
            p.wait()
    for kind, ws in out["windows"].items():
        out[f"{kind}_misses"] = [x["misses"] for x in ws]
    return out


def _print(r: dict[str, Any]) -> None:
    where = "its own process" if r["socket_process"] else "the daemon's process"
    print(f"control socket served in {where} (cpu s: the daemon's; sock s: the socket's "
          "own process)")
    print(f"control-socket floods, {r['rounds']} rounds of {r['window_s']:g} s windows, "
          f"{r['cpus']} CPUs, load {r['loadavg_1min']:.2f}, miss budget: {r['budget']}")
    print(f"{'window':8} {'misses':>7} {'lat p99 us':>11} {'comp p99 us':>12} "
          f"{'cpu s':>6} {'sock s':>6}  clients")
    for kind in ("quiet", "hold", "burst"):
        for x in r["windows"][kind]:
            c = x.get("clients")
            extra = ""
            if c:
                extra = (f"connected {c['connected']} ok {c['ok']} evicted {c['evicted']} "
                         f"errors {c['errors']}")
                if "latency_ms" in c:
                    lm = c["latency_ms"]
                    extra += f"; reply ms p50 {lm['p50']} p99 {lm['p99']} max {lm['max']}"
            print(f"{kind:8} {x['misses']:>7} {x['latency_p99_us']:>11} "
                  f"{x['compute_p99_us']:>12} {x['daemon_cpu_s']:>6} "
                  f"{x['socket_process_cpu_s']:>6}  {extra}")
    for kind in ("quiet", "hold", "burst"):
        cpu = [x["daemon_cpu_s"] for x in r["windows"][kind]]
        print(f"{kind} misses per window: {r[f'{kind}_misses']}; daemon CPU s: {cpu}")
    print(f"armed through the floods: {r['armed_before_stop']}; faults: {r['faults']} "
          f"({r['fault']})")
    print(f"with {r['hold']} clients held: status {r['status_after']}, stop {r['stop_after']}")
    if "server" in r:
        print(f"server counters: {r['server']}")


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--client":
        client_main(sys.argv[2], sys.argv[3], int(sys.argv[4]), float(sys.argv[5]))
        return 0
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--window", type=float, default=3.0, help="seconds per window")
    p.add_argument("--hold", type=int, default=1000, help="clients held open")
    p.add_argument("--burst", type=int, default=200, help="status requests in a burst")
    p.add_argument("--burst-procs", type=int, default=10,
                   help="processes sending the burst (each its own client)")
    p.add_argument("--budget", choices=("robot", "sim"), default="robot",
                   help="miss budget: the robot's (5 consecutive) or the config's")
    p.add_argument("--config", help="base config (default: config/sim.yaml)")
    p.add_argument("--host", default="127.0.0.7", help="the fake UR's loopback address")
    p.add_argument("--client-nice", type=int, default=0, metavar="N",
                   help="run the flood's client processes at this niceness (e.g. 19: their "
                   "own CPU use then yields to the daemon and the simulated robot)")
    p.add_argument("--rt-priority", type=int, default=0, metavar="P",
                   help="the loop's SCHED_FIFO priority (loop.rt_priority; the robot's "
                   "configuration; 0: the simulated robot's, the ordinary scheduler)")
    p.add_argument("--sim-priority", type=int, default=0, metavar="P",
                   help="run the simulated robot's processes SCHED_FIFO at this priority "
                   "(below --rt-priority): its devices then answer as hardware does, "
                   "whatever the clients' CPU use (0: the ordinary scheduler)")
    p.add_argument("--loop-cpu", type=int, metavar="N",
                   help="pin the loop to CPU N (loop.cpu_affinity, as on the robot) and run "
                   "everything else (the simulated robot, the socket's process, the "
                   "clients) on the other CPUs")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    global CLIENT_NICE, CLIENT_CPUS
    CLIENT_NICE = args.client_nice
    if args.loop_cpu is not None:
        CLIENT_CPUS = ",".join(str(c) for c in sorted(os.sched_getaffinity(0) - {args.loop_cpu}))
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)  # the daemon's and the fakes' logs stay off stdout
    try:
        r = run(args)
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
    if args.json:
        print(json.dumps(r, indent=2))
    else:
        _print(r)
    ok = r["stop_after"].get("ok") and r["status_after"].get("ok")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
