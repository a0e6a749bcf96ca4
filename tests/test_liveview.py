"""The live status block: render() on its own, and LiveView on a real pseudo-terminal.

The LiveView tests run a small Python program with its stdout on a pty (as `mmctl run`
in a terminal), read everything the terminal receives, and replay it on a minimal
terminal model (:class:`Screen`): what the user would see at the end is asserted, and
conditions (frames counted by the program), never durations.
"""

from __future__ import annotations

import fcntl
import math
import os
import re
import signal
import struct
import sys
import termios
import textwrap
import threading
from typing import NamedTuple

import numpy as np
import pytest

from mmctl.runtime.liveview import LiveView, render
from ptyrun import run_on_pty as pty_run

FULL = {
    "state": "armed", "mode": "min-energy", "fault": None, "taring": False,
    "f_h": [12.34, -0.4, 1.0, 0.01, 0.0, -0.02],
    "ee_speed": 0.0823, "base_speed": 0.004, "base_yaw_rate": -0.05, "ee_speed_desired": 0.09,
    "energy_arm": 0.412, "energy_base": 0.003,
    "loop": {"rate_hz": 500.0, "compute_p50_us": 180.2, "compute_p99_us": 290.4,
             "latency_p99_us": 22.1, "window_s": 5.0,
             "misses": {"window": 3, "window_pct": 0.12, "since_start": 7,
                        "since_start_pct": 0.114}},
    "cycles": 6150, "uptime_s": 12.3,
    "sim": {"person": "on", "faults": []},
    "hint": "mmctl sim push 20 0 0 · mmctl sim fault drive_fault · Ctrl-C stops",
}


# --- render ----------------------------------------------------------------------------

def test_render_full_snapshot_shows_every_value_with_its_unit() -> None:
    lines = render(FULL, width=100)
    text = "\n".join(lines)
    assert lines[0].startswith("mmctl ─ ARMED")
    for part in ("mode min-energy", "fault -", "up 12.3 s", "cycles 6150"):
        assert part in lines[0]
    force = next(line for line in lines if line.startswith("force"))
    assert re.search(r"fx\s+\+12\.3\b", force) and re.search(r"fy\s+-0\.4\b", force)
    assert re.search(r"fz\s+\+1\.0 N\b", force) and re.search(r"tz\s+-0\.02 N m$", force)
    assert "end-effector 0.082 m/s" in text and "base 0.004 m/s" in text
    assert "-0.05 rad/s" in text
    assert "arm 0.412 J" in text and "base 0.003 J" in text and "base share 0.7 %" in text
    assert "500 Hz" in text and "p50/p99 180/290 us" in text and "wake p99 22 us" in text
    assert "over the last 5 s" in text and "(measured; desired 0.090 m/s)" in text
    assert "misses 0.12 % of the last 5 s (3), 7 since start (0.11 %)" in text
    assert "person on" in text and "faults -" in text
    assert lines[-1].endswith("mmctl sim push 20 0 0 · mmctl sim fault drive_fault · Ctrl-C stops")
    assert 7 <= len(lines) <= 9
    assert all(len(line) <= 100 for line in lines)


def test_render_empty_snapshot_shows_dashes_and_no_sim_or_hint_line() -> None:
    lines = render({})
    assert lines[0].startswith("mmctl ─ -")
    assert "cycles -" in lines[0] and "up -" in lines[0]
    assert not any(line.startswith(("sim", "hint")) for line in lines)
    assert "fx      -" in lines[1] and "end-effector - m/s" in lines[2]
    assert "binding none" in lines[4] and "nearest" not in lines[4]
    assert "misses - % of the last - s (-), - since start (- %)" in lines[6]


def test_render_names_the_binding_limit_and_the_nearest_parts() -> None:
    lines = render({"limit": "self_collision",
                    "nearest_parts": {"pair": "deck-handle", "distance_m": 0.0501}})
    assert lines[4].split() == ["limit", "binding", "self_collision", "nearest", "parts",
                                "deck-handle", "0.050", "m"]


def test_render_none_nan_and_odd_types_show_dashes_and_never_raise() -> None:
    nan = math.nan
    snap = {
        "state": None, "mode": None, "fault": nan, "taring": np.array([True, False]),
        "f_h": np.array([nan, 1.5, np.inf]),  # short, NaN, infinite
        "ee_speed": nan, "base_speed": "fast", "base_yaw_rate": None,
        "energy_arm": nan, "energy_base": 1.0,
        "loop": {"rate_hz": nan, "compute_p50_us": None, "miss_rate": nan,
                 "total_misses": None},
        "cycles": np.int64(42), "uptime_s": np.float32(3.5),
        "sim": {"person": None, "faults": None}, "hint": None,
    }
    lines = render(snap, width=100)
    text = "\n".join(lines)
    assert "nan" not in text.lower() and "inf" not in text.lower()
    assert "cycles 42" in lines[0] and "up 3.5 s" in lines[0]
    assert re.search(r"fx\s+- ", lines[1]) and "fy   +1.5" in lines[1]
    assert re.search(r"fz\s+- N", lines[1]) and re.search(r"tz\s+- N m", lines[1])
    assert "end-effector - m/s" in text and "base - m/s" in text
    assert "arm - J" in text and "base 1.000 J" in text and "base share - %" in text
    assert "person -   faults -" in text
    assert not any(line.startswith("hint") for line in lines)
    assert render("not a mapping")[0].startswith("mmctl ─ -")  # type: ignore[arg-type]


def test_render_fault_stands_out_first_on_the_line() -> None:
    snap = {**FULL, "state": "fault", "fault": "drive_fault",
            "sim": {"person": "push", "faults": ["drive_fault", "sensor_stale"]}}
    lines = render(snap)
    assert lines[0].startswith("mmctl ─ FAULT: drive_fault")
    assert "faults drive_fault, sensor_stale" in "\n".join(lines)


def test_render_fits_every_width_and_a_newline_never_adds_a_row() -> None:
    snap = {**FULL, "fault": "line one\nline two", "hint": "x" * 300}
    for width in (10, 40, 79, 100, 200):
        lines = render(snap, width)
        assert all(len(line) <= width for line in lines), width
        assert all("\n" not in line and "\r" not in line for line in lines)
    assert render(snap, 40)[-1].endswith("…")


def test_render_long_uptimes_read_in_minutes_and_hours() -> None:
    assert "up 20 min 34 s" in render({"uptime_s": 1234.5})[0]
    assert "up 2 h 05 min" in render({"uptime_s": 2 * 3600 + 5 * 60 + 9})[0]


def test_rate_must_be_positive() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        LiveView(dict, rate_hz=0)


def test_stop_before_start_is_a_no_op() -> None:
    view = LiveView(dict)
    view.stop()
    view.stop()


# --- LiveView on a pseudo-terminal -----------------------------------------------------

class Screen:
    """What a terminal shows after a byte stream: text, CR, LF, cursor up (ESC [ n A),
    erase to the end of the screen (ESC [ J) or line (ESC [ K), SGR (ignored); the
    scrollback is unbounded, lines do not wrap.  Anything else fails the test."""

    def __init__(self) -> None:
        self.rows = [""]
        self.row = self.col = 0

    def feed(self, text: str) -> Screen:
        i = 0
        while i < len(text):
            ch = text[i]
            if ch == "\x1b":
                m = re.match(r"\x1b\[(\d*)([A-Za-z])", text[i:])
                assert m, f"unexpected escape {text[i:i + 8]!r}"
                n, cmd = int(m.group(1) or 1), m.group(2)
                if cmd == "A":
                    self.row = max(0, self.row - n)
                elif cmd in "JK":
                    self.rows[self.row] = self.rows[self.row][: self.col]
                    if cmd == "J":
                        del self.rows[self.row + 1:]
                else:
                    assert cmd == "m", f"unexpected escape {m.group(0)!r}"
                i += len(m.group(0))
                continue
            if ch == "\r":
                self.col = 0
            elif ch == "\n":
                self.row += 1
                if self.row == len(self.rows):
                    self.rows.append("")
            else:
                line = self.rows[self.row].ljust(self.col)
                self.rows[self.row] = line[: self.col] + ch + line[self.col + 1:]
                self.col += 1
            i += 1
        return self

    @property
    def lines(self) -> list[str]:
        rows = list(self.rows)
        while rows and not rows[-1]:
            rows.pop()
        return rows


PRELUDE = """
import os, subprocess, sys, time
from mmctl.runtime.liveview import LiveView

calls = [0]

def snapshot():
    calls[0] += 1
    return {"state": "armed", "mode": "min-energy", "cycles": 1000 + calls[0],
            "uptime_s": 0.5 * calls[0], "hint": "Ctrl-C stops"}

def wait_frames(n):
    # a condition, not a duration: n more snapshots taken (the painter draws each)
    target = calls[0] + n
    deadline = time.monotonic() + 120
    while calls[0] < target:
        assert time.monotonic() < deadline, "the painter did not draw"
        time.sleep(0.005)
"""


class Run(NamedTuple):
    raw: str  # everything the terminal received
    screen: Screen  # what it shows at the end
    err: str  # the program's stderr, when not on the terminal
    returncode: int


def run_on_pty(body: str, columns: int = 100, term: str = "dumb",
               stderr_on_pty: bool = False, returncode: int = 0) -> Run:
    """Run PRELUDE + body with stdout (and stderr if asked) on a fresh pty."""
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    env["TERM"] = term
    code, raw, errors = pty_run([sys.executable, "-c", PRELUDE + textwrap.dedent(body)],
                                columns=columns, env=env, stderr_on_pty=stderr_on_pty,
                                timeout=240)
    assert code == returncode, errors or raw[-3000:]
    return Run(raw, Screen().feed(raw), errors, code)


def test_log_lines_scroll_above_the_block_in_order_and_whole() -> None:
    raw, screen, *_ = run_on_pty("""
        import structlog
        from mmctl.runtime.logging import setup_logging

        setup_logging("info")  # before the view: the console renderer, as on a TTY
        view = LiveView(snapshot, rate_hz=20).start()
        wait_frames(2)
        print(f"during isatty={os.isatty(1)}")
        print("before child")
        subprocess.run([sys.executable, "-c", "print('from child')"], check=True)
        import multiprocessing  # as the arm's process: spawn, fd 1 inherited
        arm = multiprocessing.get_context("spawn").Process(target=print, args=("from spawn",))
        arm.start()
        arm.join()
        print("after child")
        structlog.get_logger("t").info("fault_event", cause="drive_fault")
        for i in range(3000):  # more than a pipe holds: the writer must not stall
            print(f"burst {i}")
        sys.stdout.write("open line")
        sys.stdout.flush()
        wait_frames(4)  # frames drawn while a line is open: it must wait for its end
        sys.stdout.write(" closed\\n")
        sys.stdout.write("tail without newline")
        sys.stdout.flush()
        view.stop()
        view.stop()
        print(f"after stop isatty={os.isatty(1)}")
        print("straight to the terminal")
    """)
    lines = screen.lines
    head = next(i for i, line in enumerate(lines) if line.startswith("mmctl ─"))
    logs, block, after = lines[:head], lines[head:-2], lines[-2:]
    assert logs[:5] == ["during isatty=False", "before child", "from child", "from spawn",
                        "after child"]
    assert "fault_event" in logs[5] and "cause=drive_fault" in logs[5]
    assert logs[6:3006] == [f"burst {i}" for i in range(3000)]
    assert logs[3006:] == ["open line closed", "tail without newline"]
    # the final block, printed once, below everything logged while the view ran
    assert block[0].startswith("mmctl ─ ARMED") and block[-1] == "hint    Ctrl-C stops"
    assert [line.split()[0] for line in block[1:-1]] == [
        "force", "speed", "energy", "limit", "loop", "misses"]
    assert sum(line.startswith("mmctl ─") for line in lines) == 1
    assert after == ["after stop isatty=True", "straight to the terminal"]
    assert all(len(line) < 100 for line in block)
    # redrawn while it ran: several frames, the changing value in them
    assert raw.count("mmctl ─") >= 5
    assert len(set(re.findall(r"cycles (\d+)", raw))) >= 5


def test_a_failing_snapshot_shows_status_unavailable() -> None:
    screen = run_on_pty("""
        def broken():
            calls[0] += 1
            raise RuntimeError("boom")

        view = LiveView(broken, rate_hz=50).start()
        print("still logging")
        wait_frames(3)  # the painter survives its snapshot raising
        view.stop()
    """).screen
    assert screen.lines == ["still logging", "status unavailable: RuntimeError: boom"]


def test_at_interpreter_exit_the_view_stops_itself_and_fits_the_terminal() -> None:
    raw, screen, *_ = run_on_pty("""
        def faulted():
            calls[0] += 1
            return {"state": "fault", "fault": "drive_fault " + "x" * 80,
                    "hint": "mmctl enable " + "y" * 80}

        LiveView(faulted, rate_hz=50).start()
        wait_frames(2)
        sys.stdout.write("last words")  # no newline, no stop(): atexit finishes both
    """, columns=40, term="xterm")
    lines = screen.lines
    assert lines[0] == "last words"
    assert lines[1].startswith("mmctl ─ FAULT: drive_fault")
    assert lines[-1].startswith("hint    mmctl enable")
    assert all(len(line) <= 39 for line in lines)
    assert "\x1b[7mFAULT\x1b[0m" in raw  # reverse video where TERM allows


def test_a_terminal_that_stops_reading_never_blocks_the_writer(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Nobody reads the terminal (Ctrl-S, a stalled ssh link) while megabytes are logged:
    the writes all complete, the oldest beyond the buffer are dropped and counted."""
    from mmctl.runtime import liveview

    monkeypatch.setattr(liveview, "BUFFER_LIMIT", 1 << 18)
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 100, 0, 0))
    received = bytearray()
    view = LiveView(lambda: {"state": "disarmed"}, fd=slave, rate_hz=50).start()
    try:
        names = {t.name: t.daemon for t in threading.enumerate()}
        assert names.get("mmctl-liveview-reader") is True
        assert names.get("mmctl-liveview-painter") is True
        line = b"%07d " + b"x" * 92 + b"\n"
        for i in range(40_000):  # 4 MB: far more than the pipe, the buffer and the pty
            os.write(slave, line % i)
    finally:
        def read_all() -> None:
            try:
                while chunk := os.read(master, 1 << 16):
                    received.extend(chunk)
            except OSError:  # EIO: the slave is closed and everything was read
                return

        reader = threading.Thread(target=read_all, daemon=True)
        reader.start()  # the terminal reads again: the painter and stop() can finish
        view.stop()
        os.close(slave)
        reader.join(timeout=120)
        os.close(master)
    assert not reader.is_alive()
    assert view.error is None
    lines = Screen().feed(received.decode()).lines
    head = lines.index(render({"state": "disarmed"})[0])
    assert lines[head - 1].startswith("0039999 ")  # the newest line, then the block
    assert sum(text.startswith("mmctl ─") for text in lines) == 1
    notes = [text for text in lines[:head] if text.startswith("[liveview: ")]
    assert notes and all(
        re.fullmatch(r"\[liveview: \d+ bytes of log dropped, the terminal was not reading\]",
                     note) for note in notes)
    logged = [text for text in lines[:head] if text not in notes]
    assert all(len(text) == 100 for text in logged)  # whole lines only
    numbers = [int(text[:7]) for text in logged]
    assert numbers == sorted(numbers) and len(numbers) < 40_000  # in order, some dropped


def test_a_snapshot_failing_at_the_end_leaves_the_last_good_block() -> None:
    screen = run_on_pty("""
        torn_down = [False]

        def daemon_snapshot():
            if torn_down[0]:
                raise RuntimeError("daemon closed")
            return snapshot()

        view = LiveView(daemon_snapshot, rate_hz=50).start()
        wait_frames(3)
        torn_down[0] = True  # the daemon shut down before the view was stopped
        view.stop()
    """).screen
    assert screen.lines[0].startswith("mmctl ─ ARMED")
    assert screen.lines[-1] == "hint    Ctrl-C stops"
    assert not any("status unavailable" in line for line in screen.lines)


def test_stderr_on_the_same_terminal_scrolls_above_the_block_when_asked() -> None:
    screen = run_on_pty("""
        import faulthandler
        faulthandler.enable()
        view = LiveView(snapshot, rate_hz=20, stderr=True).start()
        wait_frames(2)
        print("out 1")
        sys.stderr.write("err 1\\n")
        os.write(2, b"err 2\\n")
        subprocess.run([sys.executable, "-c", "import sys; print('child err', file=sys.stderr)"],
                       check=True)
        print("out 2")
        wait_frames(3)  # frames drawn after the stderr lines: none of them overdrawn
        view.stop()
        assert faulthandler.is_enabled()
        print(f"after stop isatty={os.isatty(2)}", file=sys.stderr)
    """, stderr_on_pty=True).screen
    lines = screen.lines
    assert lines[:5] == ["out 1", "err 1", "err 2", "child err", "out 2"]
    assert lines[5].startswith("mmctl ─ ARMED") and lines[-2] == "hint    Ctrl-C stops"
    assert lines[-1] == "after stop isatty=True"


def test_stderr_elsewhere_is_left_alone() -> None:
    run = run_on_pty("""
        view = LiveView(snapshot, rate_hz=20, stderr=True).start()
        print("out")
        print("err", file=sys.stderr)  # a pipe here, as with `mmctl run 2>file`
        view.stop()
    """)
    assert run.err == "err\n"
    assert run.screen.lines[0] == "out" and "err" not in run.screen.lines


def test_a_crash_report_reaches_the_terminal_while_stderr_is_taken_over() -> None:
    run = run_on_pty("""
        import faulthandler, resource, signal
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        faulthandler.enable()
        view = LiveView(snapshot, rate_hz=20, stderr=True).start()
        wait_frames(2)
        os.kill(os.getpid(), signal.SIGSEGV)  # the pipe's reader dies with the process
    """, stderr_on_pty=True, returncode=-signal.SIGSEGV)
    assert "Fatal Python error: Segmentation fault" in run.raw
