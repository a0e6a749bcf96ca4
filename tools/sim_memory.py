"""The simulated robot's memory under the soak's injected faults, round by round.

`mmctl bench soak` (docs/soak.md) saw the simulation's process (`mmctl sim`) grow by
about 270 MB over an hour, in steps.  This runs the daemon on the simulated robot the
way the soak does (its configuration, ``--load-proof``, its own loopback address), then
injects faults with the soak's own cycle (inject, wait for the daemon's FAULT, remove,
enable again) and prints the simulation's RSS (``/proc/PID/status`` VmRSS) after each
injection, and per round:

    python tools/sim_memory.py                              # 3 rounds of the default faults
    python tools/sim_memory.py --rounds 4 --faults arm_disconnected
    python tools/sim_memory.py --faults all --ur-commands 0  # the soak's whole rotation

Each line: the round, the fault, the simulation's RSS after it [MB] and its change.  A
fault whose injections step the RSS up round after round names the leak.  Under about
three minutes with the defaults on a 2-core machine.

The step it found: ``arm_disconnected`` kills the fake UR controller's process, and the
simulation first copies the controller's command log (up to 200 000 entries, about 150
a second while armed) into its own process, which keeps it
(:class:`~mmctl.sim.fake_ur.FakeURController`).  In the soak, 14 minutes of commands
pile up between two disconnections; here each round first sends ``--ur-commands``
dashboard lines to the fake controller (each one a log entry, as a speedJ is) so that a
round's fetch is as large as a soak's in seconds instead of minutes.
"""

from __future__ import annotations

import argparse
import shutil
import socket
import sys
import tempfile
import time
from pathlib import Path

from mmctl.bench import soak as soak_mod

#: the faults whose paths touch the most of the simulation: the controller's process
#: killed and restarted (its command log fetched), a drive rebooted, the sensor silent
DEFAULT_FAULTS = "arm_disconnected,drive_reboot,sensor_silent"


def flood_dashboard(host: str, lines: int, window: int = 500) -> None:
    """Send ``lines`` dashboard commands to the fake UR on ``host`` (each one an entry
    of its command log), at most ``window`` unanswered at a time (its 500 Hz clock
    keeps serving the daemon's RTDE stream in between)."""
    with socket.create_connection((host, 29999), timeout=30.0) as s, s.makefile("rb") as f:
        f.readline()  # the welcome line
        sent = answered = 0
        while answered < lines:
            n = min(window - (sent - answered), lines - sent)
            if n > 0:
                s.sendall(b"robotmode\n" * n)
                sent += n
            f.readline()
            answered += 1


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--host", default="127.77.0.1", help="loopback address (default 127.77.0.1)")
    p.add_argument("--rounds", type=int, default=3, help="rounds of the faults (default 3)")
    p.add_argument("--faults", default=DEFAULT_FAULTS,
                   help=f"comma-separated faults, or 'all' (default {DEFAULT_FAULTS})")
    p.add_argument("--settle", type=float, default=2.0, metavar="S",
                   help="seconds armed before each RSS reading (default 2)")
    p.add_argument("--ur-commands", type=int, default=60_000, metavar="N",
                   help="dashboard lines sent to the fake UR before each round: its command "
                        "log as ~7 minutes of a soak fill it (default 60000; 0: none)")
    p.add_argument("--idle", type=float, default=0.0, metavar="S",
                   help="first watch the RSS for S seconds armed, no fault (default 0)")
    p.add_argument("--keep-log", action="store_true", help="keep the daemon's log")
    a = p.parse_args()

    soak_args = argparse.ArgumentParser()
    soak_mod.add_arguments(soak_args)
    args = soak_args.parse_args(["--host", a.host, "--load-proof", "--seconds", "600"])
    rotation = (list(soak_mod.DEFAULT_FAULTS) if a.faults == "all"
                else [f.strip() for f in a.faults.split(",") if f.strip()])
    unknown = [f for f in rotation if f not in soak_mod.FAULT_CAUSES]
    if unknown:
        p.error(f"unknown fault(s): {', '.join(unknown)}")
    args.faults = ",".join(rotation)
    from mmctl.sim.fake_ur.server import ports_free

    if not ports_free(a.host, soak_mod._PORTS):
        p.error(f"the fake UR's or socketcand's ports are in use on {a.host}")

    tmp = Path(tempfile.mkdtemp(prefix="mmctl-simmem-"))
    log_path = tmp / "daemon.log"
    soak = soak_mod.Soak(args, 600.0, tmp, log_path)
    t0 = time.monotonic()
    try:
        soak.start_daemon(soak_mod._config_file(args, tmp))
        st = soak.wait_armed(120.0)
        soak.faults_seen = int(st.get("faults", 0))
        sim_pid = (st.get("sim") or {}).get("pid")
        if sim_pid is None:
            print("the daemon's status names no simulation pid", file=sys.stderr)
            return 1
        soak.t0 = time.monotonic()
        time.sleep(a.settle)
        first = last = soak_mod.rss_mb(sim_pid) or 0.0
        print(f"sim pid {sim_pid}, armed after {soak.t0 - t0:.1f} s, RSS {first:.1f} MB",
              flush=True)
        t_idle = time.monotonic()
        while time.monotonic() - t_idle < a.idle:
            time.sleep(min(10.0, a.idle))
            now = soak_mod.rss_mb(sim_pid) or 0.0
            print(f"idle {time.monotonic() - t_idle:5.0f} s  sim RSS {now:7.1f} MB  "
                  f"{now - last:+6.1f}", flush=True)
            last = now
        for r in range(1, a.rounds + 1):
            start = last
            if a.ur_commands > 0:
                flood_dashboard(a.host, a.ur_commands)
            for name in rotation:
                soak._inject(name)
                time.sleep(a.settle)
                now = soak_mod.rss_mb(sim_pid) or 0.0
                print(f"round {r}  {name:20} sim RSS {now:7.1f} MB  {now - last:+6.1f}",
                      flush=True)
                last = now
            print(f"round {r}: {start:.1f} -> {last:.1f} MB ({last - start:+.1f})", flush=True)
        print(f"total: {first:.1f} -> {last:.1f} MB ({last - first:+.1f}) over {a.rounds} "
              f"round(s) in {time.monotonic() - t0:.0f} s; injected "
              f"{sum(int(s['injected']) for s in soak.fault_stats.values())}, as expected "
              f"{soak.counts['injected_faults']}, unexpected "
              f"{sum(soak.unexpected_by_cause.values())}", flush=True)
        return 0
    finally:
        soak.stop.set()
        soak.stop_daemon()
        if a.keep_log:
            print(f"daemon log: {log_path}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
