#!/usr/bin/env python3
"""Render a PNG of the rerun viewer showing a recording (for docs/telemetry.png).

The real rerun viewer opens the ``.rrd`` with the blueprint mmctl stored in it and
saves a screenshot (``rerun --screenshot-to``).  Without a display it starts a virtual
X server (``Xvfb``; Debian: ``apt-get install xvfb mesa-vulkan-drivers`` for the
software renderer) for the duration.  The viewer's own server is bound to 127.0.0.1.

    .venv/bin/python tools/telemetry_screenshot.py run.rrd docs/telemetry.png
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def start_xvfb(size: str) -> tuple[subprocess.Popen[bytes], str]:
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise SystemExit("no DISPLAY and no Xvfb: install xvfb (and mesa-vulkan-drivers)")
    for n in range(90, 120):
        if not Path(f"/tmp/.X11-unix/X{n}").exists() and not Path(f"/tmp/.X{n}-lock").exists():
            proc = subprocess.Popen([xvfb, f":{n}", "-screen", "0", f"{size}x24", "-nolisten",
                                     "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(50):
                if Path(f"/tmp/.X11-unix/X{n}").exists():
                    return proc, f":{n}"
                time.sleep(0.1)
            proc.terminate()
    raise SystemExit("could not start Xvfb")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd", help="recording to show")
    ap.add_argument("png", help="where to write the screenshot")
    ap.add_argument("--size", default="1600x1000", help="viewer window WxH (default 1600x1000)")
    ap.add_argument("--width", type=int, default=1600, help="downscale the PNG to this width")
    args = ap.parse_args()
    rerun = Path(sys.executable).parent / "rerun"
    exe = str(rerun) if rerun.exists() else (shutil.which("rerun") or "rerun")
    xvfb = None
    env = dict(os.environ)
    if not env.get("DISPLAY") and not env.get("WAYLAND_DISPLAY"):
        xvfb, env["DISPLAY"] = start_xvfb(args.size)
    tmp = tempfile.TemporaryDirectory(prefix="mmctl-shot-")
    env.setdefault("XDG_RUNTIME_DIR", tmp.name)
    raw = Path(tmp.name) / "shot.png"
    try:
        cmd = [exe, args.rrd, "--bind", "127.0.0.1", "--port", str(free_port()),
               "--window-size", args.size, "--screenshot-to", str(raw)]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300,
                             check=False)
        if out.returncode != 0 or not raw.exists():
            print(out.stderr[-2000:], file=sys.stderr)
            return 1
        from PIL import Image

        img = Image.open(raw)
        if img.width > args.width:
            img = img.resize((args.width, round(img.height * args.width / img.width)),
                             Image.LANCZOS)
        Path(args.png).parent.mkdir(parents=True, exist_ok=True)
        img.save(args.png, optimize=True)
        print(f"{args.png}: {img.width}x{img.height}, {Path(args.png).stat().st_size} bytes")
    finally:
        if xvfb is not None:
            xvfb.terminate()
            xvfb.wait(10)
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
