"""A live status block at the bottom of the terminal, with the log scrolling above it.

``mmctl run`` on a TTY shows a handful of status lines redrawn a few times a second
(:func:`render` draws them from a snapshot dict), while every line written to stdout
(structlog's events, ``print``, the child processes' logs) still scrolls above the
block and is never torn by it.

How: :meth:`LiveView.start` keeps a duplicate of the terminal's fd and points fd 1 at
a pipe (``dup2``), so whatever this process *and the child processes started
afterwards* write to stdout goes into the pipe.  Two daemon threads do the rest:

- ``mmctl-liveview-reader`` drains the pipe into memory as soon as bytes arrive, and
  never touches the terminal, so a writer (the loop thread logging a fault) blocks
  for no longer than a pipe write even if the terminal is slow or frozen (Ctrl-S);
- ``mmctl-liveview-painter`` owns the terminal: on new complete lines, and on each
  frame (``rate_hz``), it erases the block (cursor up, ``ESC [ J``), writes the lines,
  and draws the block again: one ``write()`` per update.

:meth:`LiveView.stop` drains the rest, points fd 1 back at the terminal and leaves
the last block printed.  stderr (fd 2) is left alone unless asked for (``stderr=True``).
"""

from __future__ import annotations

import atexit
import faulthandler
import math
import os
import selectors
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from enum import Enum
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing_extensions import Self

#: Bytes of log held in memory while the terminal does not take them (frozen with
#: Ctrl-S, a stalled ssh link); beyond it the oldest are dropped, and counted.
BUFFER_LIMIT = 8 * 1024 * 1024

_STOP_READS = 64  # reads of 64 KiB that stop() drains at most, before and after the dup2
_PAINT_GAP = 0.02  # [s] the least time between two repaints for log lines
_ERASE = "\x1b[J"  # clear from the cursor to the end of the screen
_REVERSE, _PLAIN = "\x1b[7m", "\x1b[0m"
_LABEL = 8  # width of the line labels ("force   ", "loop    ")


# --- the block, from a snapshot --------------------------------------------------------

def render(snap: Mapping[str, object], width: int = 100) -> list[str]:
    """The status block's lines for one snapshot of the daemon; pure, never raises.

    snap: the daemon's snapshot (keys in the module's tests and in ``mmctl run``);
    any key may be missing or None, any number NaN: shown as ``-``.
    width: the longest line allowed [characters]; longer lines end in ``…``.
    """
    snap = snap if isinstance(snap, Mapping) else {}
    loop = snap.get("loop")
    loop = loop if isinstance(loop, Mapping) else {}
    lines = [_header(snap), _force(snap.get("f_h")), _speed(snap), _energy(snap),
             _limit(snap), _loop(loop), f"{'':<{_LABEL}}{misses_text(loop)}"]
    sim = snap.get("sim")
    if isinstance(sim, Mapping):
        lines.append(f"{'sim':<{_LABEL}}person {_text(sim.get('person'))}   "
                     f"faults {_names(sim.get('faults'))}")
    hint = _text(snap.get("hint"))
    if hint != "-":
        lines.append(f"{'hint':<{_LABEL}}{hint}")
    return [_fit(line, width) for line in lines]


def _header(snap: Mapping[str, object]) -> str:
    state = _text(snap.get("state"))
    fault = _text(snap.get("fault"))
    mode = f"mode {_text(snap.get('mode'))}"
    if state.lower() == "fault":  # first thing on the line, and the cause with it
        parts = [f"FAULT: {fault}", mode]
    else:
        parts = [f"{state.upper():<8}", mode, f"fault {fault}"]
    if _flag(snap.get("taring")):
        parts.append("taring")
    parts += [f"up {_duration(snap.get('uptime_s'))}", f"cycles {_num(snap.get('cycles'), 'd')}"]
    return "mmctl ─ " + "   ".join(parts)


def _force(f_h: object) -> str:
    values = _items(f_h, 6)
    force = "  ".join(f"{axis} {_num(v, '+6.1f'):>6}"
                      for axis, v in zip(("fx", "fy", "fz"), values[:3]))
    torque = "  ".join(f"{axis} {_num(v, '+6.2f'):>6}"
                       for axis, v in zip(("tx", "ty", "tz"), values[3:]))
    return f"{'force':<{_LABEL}}{force} N     {torque} N m"


def _speed(snap: Mapping[str, object]) -> str:
    """Measured speeds (``-`` while a device is not read), the desired one labelled."""
    return (f"{'speed':<{_LABEL}}end-effector {_num(snap.get('ee_speed'), '.3f')} m/s   "
            f"base {_num(snap.get('base_speed'), '.3f')} m/s  "
            f"{_num(snap.get('base_yaw_rate'), '+.2f')} rad/s   (measured; desired "
            f"{_num(snap.get('ee_speed_desired'), '.3f')} m/s)")


def _limit(snap: Mapping[str, object]) -> str:
    """The limit that binds the command now, and the robot's two nearest parts."""
    limit = snap.get("limit")
    near = snap.get("nearest_parts")
    parts = f"binding {limit if isinstance(limit, str) and limit else 'none'}"
    if isinstance(near, Mapping):
        parts += (f"   nearest parts {_text(near.get('pair'))} "
                  f"{_num(near.get('distance_m'), '.3f')} m")
    return f"{'limit':<{_LABEL}}{parts}"


def _energy(snap: Mapping[str, object]) -> str:
    arm, base = _finite(snap.get("energy_arm")), _finite(snap.get("energy_base"))
    share = "-"
    if arm is not None and base is not None and arm + base > 0:
        share = f"{100 * base / (arm + base):.1f}"
    return (f"{'energy':<{_LABEL}}arm {_num(arm, '.3f')} J   base {_num(base, '.3f')} J   "
            f"(base share {share} %)")


def misses_text(loop: Mapping[str, object]) -> str:
    """The loop's misses as status and the live view both say them: deadlines missed /
    (cycles run + deadlines missed), over the labelled window and since the start."""
    m = loop.get("misses")
    m = m if isinstance(m, Mapping) else {}
    return (f"misses {_num(m.get('window_pct'), '.2f')} % of the last "
            f"{_num(loop.get('window_s'), '.0f')} s ({_num(m.get('window'), 'd')}), "
            f"{_num(m.get('since_start'), 'd')} since start "
            f"({_num(m.get('since_start_pct'), '.2f')} %)")


def _loop(loop: object) -> str:
    loop = loop if isinstance(loop, Mapping) else {}
    return (f"{'loop':<{_LABEL}}{_num(loop.get('rate_hz'), '.0f')} Hz   "
            f"compute p50/p99 {_num(loop.get('compute_p50_us'), '.0f')}/"
            f"{_num(loop.get('compute_p99_us'), '.0f')} us   "
            f"wake p99 {_num(loop.get('latency_p99_us'), '.0f')} us   "
            f"over the last {_num(loop.get('window_s'), '.0f')} s")


def _finite(value: object) -> float | None:
    """``value`` as a finite float, else None (missing, NaN, infinite, not a number)."""
    if value is None or isinstance(value, (str, bytes)):
        return None
    try:
        x = float(value)  # type: ignore[arg-type]  # (anything: a failure is None)
    except (TypeError, ValueError, OverflowError):
        return None
    return x if math.isfinite(x) else None


def _num(value: object, fmt: str) -> str:
    x = _finite(value)
    if x is None:
        return "-"
    return format(round(x), fmt) if fmt.endswith("d") else format(x, fmt)


def _duration(value: object) -> str:
    s = _finite(value)
    if s is None:
        return "-"
    if s < 60:
        return f"{s:.1f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


def _text(value: object) -> str:
    """One printable line: '-' for nothing, an Enum's value, control characters blanked
    (a newline in a fault message must not make the block a row taller)."""
    if isinstance(value, Enum):
        value = value.value
    if value is None or (isinstance(value, str) and not value):
        return "-"
    if isinstance(value, float) and not math.isfinite(value):
        return "-"
    return "".join(ch if ch.isprintable() else " " for ch in str(value))


def _flag(value: object) -> bool:
    try:
        return bool(value)
    except (TypeError, ValueError):  # a numpy array, say: no single truth value
        return False


def _names(value: object) -> str:
    if isinstance(value, str):
        return _text(value)
    items = [_text(v) for v in value] if isinstance(value, Iterable) else []
    return ", ".join(items) if items else "-"


def _items(value: object, n: int) -> list[object]:
    """The first ``n`` items of a sequence (list, tuple, numpy array), None-padded."""
    try:
        items = (list(value)[:n] if isinstance(value, Iterable) and not isinstance(value, str)
                 else [])
    except TypeError:
        items = []
    return items + [None] * (n - len(items))


def _fit(line: str, width: int) -> str:
    if len(line) <= width:
        return line
    return line[: width - 1] + "…" if width >= 2 else line[: max(width, 0)]


# --- the terminal ----------------------------------------------------------------------

class LiveView:
    """The block at the bottom of the terminal on ``fd``, the log scrolling above it.

    snapshot: called by the painter thread once per frame; must be cheap and must not
    block (it runs next to the control loop); an exception it raises is shown as
    ``status unavailable: ...`` in place of the block.
    fd: the terminal's fd to take over (1: stdout).  rate_hz: block redraws per second.
    stderr: also take fd 2 over when it is the same terminal as ``fd`` (warnings and
    tracebacks then scroll above the block instead of being overdrawn by the next
    frame); an enabled :mod:`faulthandler` is pointed at the terminal meanwhile, so a
    crash report never waits in the pipe of a dying process.

    Start it after logging is set up (structlog's TTY check must still see the
    terminal) and before any child process whose output should join the log; stop it
    after those children have exited (they keep the pipe's write end).
    """

    def __init__(self, snapshot: Callable[[], Mapping[str, object]], *, fd: int = 1,
                 rate_hz: float = 5.0, stderr: bool = False):
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise ValueError(f"rate_hz = {rate_hz!r}: a positive, finite number of frames/s")
        self._snapshot = snapshot
        self._fd = fd
        self._want_stderr = stderr and fd != 2
        self._period = 1.0 / rate_hz
        self._life = threading.Lock()  # start/stop
        self._term = threading.Lock()  # every write to the terminal
        self._buf = threading.Lock()  # _pending, _dropped
        self._pending = bytearray()
        self._dropped = 0
        self._halt = threading.Event()
        self._wake = threading.Event()
        self._threads: list[threading.Thread] = []
        self._started = self._stopped = False
        self._tty = self._pipe_r = self._pipe_w = self._wake_r = self._wake_w = -1
        self._saved: dict[int, int] = {}  # fd taken over -> a dup of what it was
        self._faulthandler = False  # re-pointed at the terminal by start()
        self._encoding = "utf-8"
        self._highlight = False
        self._block: list[str] = []  # the newest block drawn (or to draw)
        self._drawn: list[int] = []  # lengths of the block's lines now on the screen
        self.error: BaseException | None = None
        """What ended a thread early (the terminal went away: EIO); None if nothing."""

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> Self:
        """Take ``fd`` over (see the module's docstring) and start the two threads."""
        with self._life:
            if self._started:
                raise RuntimeError("LiveView.start(): already started (a view starts once)")
            self._started = True
            _flush_stdio()
            self._encoding = getattr(sys.stdout, "encoding", None) or "utf-8"
            self._highlight = os.environ.get("TERM", "dumb") not in ("", "dumb")
            opened: list[int] = []
            try:
                fds = [self._fd] + ([2] if self._want_stderr and _same_file(self._fd, 2) else [])
                for fd in fds:  # not inherited: children only see the pipe
                    self._saved[fd] = os.dup(fd)
                    opened.append(self._saved[fd])
                self._tty = self._saved[self._fd]
                self._pipe_r, self._pipe_w = os.pipe()
                opened += (self._pipe_r, self._pipe_w)
                self._wake_r, self._wake_w = os.pipe()
                opened += (self._wake_r, self._wake_w)
                _grow_pipe(self._pipe_w)
                os.set_blocking(self._pipe_r, False)
                if 2 in self._saved and faulthandler.is_enabled():
                    faulthandler.enable(self._tty, all_threads=True)
                    self._faulthandler = True
                for fd in fds:  # inheritable: child processes write there too
                    os.dup2(self._pipe_w, fd)
                self._threads = [
                    threading.Thread(target=self._read_loop, name="mmctl-liveview-reader",
                                     daemon=True),
                    threading.Thread(target=self._paint_loop, name="mmctl-liveview-painter",
                                     daemon=True),
                ]
                for t in self._threads:
                    t.start()
            except BaseException:  # out of fds or threads: the terminal as it was
                self._halt.set()
                self._wake.set()
                if self._wake_w >= 0:
                    os.write(self._wake_w, b"x")
                for t in self._threads:
                    if t.ident is not None:
                        t.join()
                self._restore()
                for fd in opened:
                    os.close(fd)
                raise
            atexit.register(self.stop)
        return self

    def stop(self, keep_block: bool = True) -> None:
        """Drain the log, give ``fd`` back to the terminal, print the last block once
        (``keep_block``; False: erase it, for a daemon that never ran, whose block
        would show a robot that was never there).

        Idempotent; a no-op before :meth:`start`.  Call it from the shutdown path (not
        from a signal handler); it also runs at interpreter exit if nobody called it.
        """
        with self._life:
            if not self._started or self._stopped:
                return
            self._stopped = True
        atexit.unregister(self.stop)
        self._halt.set()
        self._wake.set()
        _write_all(self._wake_w, b"x")
        for t in self._threads:
            t.join(timeout=5.0)
        _flush_stdio()
        # a painter stuck writing to a frozen terminal must not hang the shutdown
        painted = self._term.acquire(timeout=5.0)
        try:
            self._drain(_STOP_READS)
            self._restore()
            self._drain(_STOP_READS)  # what came in between; children may still write
            with self._buf:
                tail, self._pending = bytes(self._pending), bytearray()
            if tail and not tail.endswith(b"\n"):
                tail += b"\n"  # a line still open at the end
            if painted:
                try:
                    self._paint(self._take_note() + tail,
                                self._frame(final=True) if keep_block else [], final=True)
                except OSError as exc:  # the terminal went away (hang-up)
                    self.error = self.error or exc
        finally:
            if painted:
                self._term.release()
            for fd in (self._pipe_r, self._pipe_w, self._wake_r, self._wake_w):
                os.close(fd)
            for saved in self._saved.values():
                if painted or saved != self._tty:  # the painter may still write to it
                    os.close(saved)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _restore(self) -> None:
        """Every fd taken over back to what it was; faulthandler back on fd 2."""
        for fd, saved in self._saved.items():
            os.dup2(saved, fd)
        if self._faulthandler:
            faulthandler.enable(2, all_threads=True)
            self._faulthandler = False

    # -- the threads ---------------------------------------------------------------------

    def _read_loop(self) -> None:
        """Drain the pipe into memory as soon as anything arrives; never blocks a writer."""
        with selectors.DefaultSelector() as sel:
            sel.register(self._pipe_r, selectors.EVENT_READ)
            sel.register(self._wake_r, selectors.EVENT_READ)
            try:
                while not self._halt.is_set():
                    ready = {key.fd for key, _ in sel.select()}
                    if self._wake_r in ready:
                        return  # stop() drains the rest itself
                    self._drain()
            except OSError as exc:  # kept for the caller, like the painter's
                self.error = exc

    def _paint_loop(self) -> None:
        """Frames at ``rate_hz`` (absolute deadlines; behind: skip, never burst) and the
        log lines as they come."""
        deadline = time.monotonic()
        try:
            while not self._halt.is_set():
                left = deadline - time.monotonic()
                if left > 0:
                    self._wake.wait(left)
                self._wake.clear()  # before taking the lines: a later line wakes us again
                if self._halt.is_set():
                    return
                block = None
                now = time.monotonic()
                if now >= deadline:
                    block = self._frame()
                    deadline += self._period
                    if deadline <= now:
                        deadline = now + self._period
                lines = self._take_lines()
                if block is not None or lines:
                    with self._term:
                        self._paint(lines, block)
                if lines:  # a flood of lines: a repaint per _PAINT_GAP, not per line
                    self._halt.wait(_PAINT_GAP)
        except OSError as exc:  # the terminal went away; the reader keeps draining
            self.error = exc

    # -- helpers -------------------------------------------------------------------------

    def _drain(self, max_reads: int | None = None) -> None:
        """Read what the pipe holds now into ``_pending`` (at most ``max_reads`` reads:
        stop() must end even while a child process keeps writing)."""
        reads = 0
        while max_reads is None or reads < max_reads:
            reads += 1
            try:
                chunk = os.read(self._pipe_r, 1 << 16)
            except BlockingIOError:
                return
            if not chunk:
                return
            with self._buf:
                self._pending += chunk
                over = len(self._pending) - BUFFER_LIMIT
                if over > 0:  # the oldest go, up to a line's end: the rest stays whole
                    end = self._pending.find(b"\n", over - 1) + 1
                    cut = end if end > 0 else over
                    del self._pending[:cut]
                    self._dropped += cut
            self._wake.set()

    def _take_lines(self) -> bytes:
        """The complete lines received so far (an open last line stays behind)."""
        with self._buf:
            end = self._pending.rfind(b"\n") + 1
            lines = bytes(self._pending[:end])
            del self._pending[:end]
        return self._take_note() + lines

    def _take_note(self) -> bytes:
        with self._buf:
            dropped, self._dropped = self._dropped, 0
        if not dropped:
            return b""
        return f"[liveview: {dropped} bytes of log dropped, the terminal was not reading]\n" \
            .encode()

    def _frame(self, final: bool = False) -> list[str]:
        """A block from a fresh snapshot, fitted to the terminal's width now.

        A snapshot that raises shows ``status unavailable: ...``; at the end (``final``,
        the daemon perhaps half torn down) the last block drawn stays instead, if any.
        """
        width = self._columns() - 1  # never the last column: no pending-wrap surprises
        try:
            return render(self._snapshot(), width)
        except Exception as exc:  # noqa: BLE001 -- shown in the block, never kills the painter
            if final and self._block:
                return self._block
            return [_fit(_text(f"status unavailable: {type(exc).__name__}: {exc}"), width)]

    def _paint(self, lines: bytes, block: list[str] | None, final: bool = False) -> None:
        """Erase the block, write ``lines`` (complete lines), draw ``block`` (None: the
        previous one); under ``_term``."""
        cols = self._columns()
        out = bytearray()
        rows = sum(max(1, math.ceil(n / cols)) for n in self._drawn)
        if rows:
            out += f"\r\x1b[{rows}A{_ERASE}".encode()
        out += lines
        if block is not None:
            self._block = block  # ([] at a final paint: the block erased, none drawn)
        text = "".join(self._decorate(line) + "\n" for line in self._block)
        out += text.encode(self._encoding, errors="replace")
        _write_all(self._tty, bytes(out))
        self._drawn = [] if final else [len(line) for line in self._block]

    def _decorate(self, line: str) -> str:
        if self._highlight and line.startswith("mmctl ─ FAULT"):
            return line.replace("FAULT", f"{_REVERSE}FAULT{_PLAIN}", 1)
        return line

    def _columns(self) -> int:
        try:
            cols = os.get_terminal_size(self._tty).columns
        except OSError:
            cols = 0
        if cols <= 0:  # not a terminal, or a pty nobody sized: $COLUMNS, else 80
            cols = shutil.get_terminal_size().columns
        return max(cols, 2)


def _same_file(a: int, b: int) -> bool:
    try:
        return os.path.samestat(os.fstat(a), os.fstat(b))
    except OSError:  # closed
        return False


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _flush_stdio() -> None:
    """Python's buffered stdout goes out before fd 1 changes hands."""
    for stream in (sys.stdout, sys.__stdout__):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):  # closed, or its fd already gone
            pass


def _grow_pipe(fd: int) -> None:
    """Linux: a 1 MiB pipe absorbs a burst of log lines while the reader is descheduled."""
    try:
        import fcntl
    except ImportError:
        return
    if hasattr(fcntl, "F_SETPIPE_SZ"):
        try:
            fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, 1 << 20)
        except OSError:
            pass  # over /proc/sys/fs/pipe-max-size: the default (64 KiB) is only less roomy


def summary_fields(snap: Mapping[str, object]) -> dict[str, object]:
    """The live block in one log event's fields: state, mode, fault, the measured
    end-effector and base speeds [m/s], E_K [J] (arm + base, measured), the loop's
    misses over its window [%] and cycles; None where the snapshot has no number."""
    loop = snap.get("loop")
    loop = loop if isinstance(loop, Mapping) else {}
    misses = loop.get("misses")
    misses = misses if isinstance(misses, Mapping) else {}
    arm, base = _finite(snap.get("energy_arm")), _finite(snap.get("energy_base"))

    def r(value: object, nd: int) -> float | None:
        x = _finite(value)
        return None if x is None else round(x, nd)

    out: dict[str, object] = {
        "state": _text(snap.get("state")), "mode": _text(snap.get("mode")),
        "ee_speed_m_s": r(snap.get("ee_speed"), 4),
        "base_speed_m_s": r(snap.get("base_speed"), 4),
        "e_k_J": None if arm is None or base is None else round(arm + base, 4),
        "misses_pct": r(misses.get("window_pct"), 2),
        "cycles": snap.get("cycles")}
    fault = _text(snap.get("fault"))
    if fault != "-":
        out["fault"] = fault
    sim = snap.get("sim")
    if isinstance(sim, Mapping) and sim.get("faults"):
        out["sim_faults"] = _names(sim.get("faults"))
    return out


class SummaryLog:
    """Off a terminal (a pipe, journald), where no live block shows: every ``every``
    seconds one ``summary`` event with :func:`summary_fields` of ``snapshot()``, so a
    piped run still shows whether the robot moves.  A snapshot that raises is logged
    once per failure, never ends the thread."""

    def __init__(self, snapshot: Callable[[], Mapping[str, object]], every: float,
                 log: object):
        if not (every > 0 and math.isfinite(every)):
            raise ValueError(f"every = {every!r}: a positive, finite number of seconds")
        self._snapshot = snapshot
        self._every = every
        self._log = log
        self._halt = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mmctl-summary", daemon=True)

    def start(self) -> Self:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._halt.set()
        if self._thread.ident is not None:
            self._thread.join(5.0)

    def _run(self) -> None:
        log: Any = self._log
        while not self._halt.wait(self._every):
            try:
                fields = summary_fields(self._snapshot())
            except Exception as exc:  # noqa: BLE001 -- a summary never ends the run
                log.warning("summary_unavailable", error=f"{type(exc).__name__}: {exc}")
                continue
            log.info("summary", **fields)
