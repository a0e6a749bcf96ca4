"""`mmctl run` on the simulated robot, then Ctrl-C, N times in a row: figures.

    .venv/bin/python tools/ctrl_c_runs.py [--runs 10] [--moving-s 3]

Each run starts `mmctl run --sim-log DIR` as a terminal would run it in the foreground
(a process group of its own), waits until the robot is armed and the simulated person
moves it (``sim.auto_enable``), then sends SIGINT to the whole group, as a terminal's
Ctrl-C does.  Printed per run: exit status, seconds to exit, whether the fake UR
controller got a stop (speedStop or speedJ(0)) after the last motion command, whether
every drive's last target was 0, and whether the output holds a traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]


def one_run(i: int, moving_s: float) -> tuple[bool, str]:
    tmp = Path(tempfile.mkdtemp(prefix=f"ctrlc-{i}-"))
    cfg = yaml.safe_load((ROOT / "config" / "sim.yaml").read_text())
    cfg["arm"]["host"] = f"127.0.{150 + i}.2"
    cfg["sensor"]["can"]["channel"] = f"ctrlc-s-{i}"
    cfg["base"]["canopen"]["channel"] = f"ctrlc-b-{i}"
    cfg["daemon"] = {"socket_path": str(tmp / "mmctl.sock")}
    (tmp / "sim.yaml").write_text(yaml.safe_dump(cfg))
    out = (tmp / "out.log").open("wb")
    proc = subprocess.Popen([sys.executable, "-m", "mmctl.cli", "run", "--config",
                             str(tmp / "sim.yaml"), "--sim-log", str(tmp / "simlog")],
                            stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                            start_new_session=True)
    deadline = time.monotonic() + 120
    while b"auto_enabled" not in (tmp / "out.log").read_bytes():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            return False, f"run {i}: never armed (exit {proc.returncode})"
        time.sleep(0.1)
    time.sleep(moving_s)
    t0 = time.monotonic()
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
    code = proc.wait(60)
    took = time.monotonic() - t0
    text = (tmp / "out.log").read_text(errors="replace")
    ur = [json.loads(x) for x in (tmp / "simlog" / "ur_commands.jsonl").open()]
    motion = [c for c in ur if c["kind"] in ("speedj", "speed_stop")]
    moving = [k for k, c in enumerate(motion) if c["kind"] == "speedj" and any(c["qd"])]
    after = motion[moving[-1] + 1:] if moving else []
    arm_stop = bool(after) and all(c["kind"] == "speed_stop" or not any(c["qd"]) for c in after)
    drives = [json.loads(x) for x in (tmp / "simlog" / "drive_commands.jsonl").open()]
    last: dict[int, int] = {}
    for d in drives:
        last[d["node_id"]] = d["counts"]
    base_zero = bool(last) and not any(last.values())
    traceback = "Traceback" in text or "KeyboardInterrupt" in text
    ok = code == 0 and arm_stop and base_zero and not traceback
    return ok, (f"run {i}: exit {code} after {took:.2f} s; arm stop after the last motion: "
                f"{arm_stop}; drives' last target 0: {base_zero}; traceback: {traceback}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--moving-s", type=float, default=3.0, help="robot moving before Ctrl-C")
    args = p.parse_args()
    good = 0
    for i in range(args.runs):
        ok, line = one_run(i, args.moving_s)
        good += ok
        print(line, flush=True)
    print(f"{good}/{args.runs} clean")
    sys.exit(0 if good == args.runs else 1)


if __name__ == "__main__":
    main()
