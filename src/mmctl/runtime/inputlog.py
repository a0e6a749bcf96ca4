"""The inputs log: every cycle's readings, inbox and commands, so that ``mmctl replay``
can run them through the pure update again (SPEC §7) -- the proof that the update is
pure, and how a field incident is debugged.

A log is a folder:

- ``meta.json``: the format version, the configuration (its plain form, read back with
  :func:`~mmctl.config.config_from_dict`), the row layout;
- ``rows.f64``: one row of :data:`WIDTH` float64 per cycle whose update ran (native byte
  order): the readings (:class:`~mmctl.control.update.Readings`, arrays and numbers
  exact) and the update's commands (:class:`~mmctl.control.update.Commands`);
- ``side.jsonl``: what is rare and not a number, one JSON object a line keyed by the
  cycle: the conditions the reads raised, the inbox's commands, the write's outcome (a
  command that failed: ``write_failed``; a cycle that raised: ``cycle_failed``; replay
  runs the update's transitions of those names on them).  Version 1 logs also hold
  ``patch`` objects, the runtime's own changes to the update's state, which replay
  still applies; since version 2 the runtime makes none (the write's outcome is the
  update's transition).

The loop thread only copies numbers into a preallocated block (:meth:`InputLog.append`);
a writer thread writes full blocks.  Replay (:func:`replay`) rebuilds the update from
the configuration and compares each cycle's commands with the recorded ones.
"""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import structlog
from numpy.typing import NDArray

from mmctl.config import Config, config_from_dict
from mmctl.config.schema import to_dict
from mmctl.control.safety import Safety, SafetyState, plain
from mmctl.control.update import (
    BeginEnable,
    Command,
    Commands,
    Disable,
    EnableCheck,
    EnableFinish,
    Install,
    Readings,
    Release,
    SetMode,
    SetProfile,
    SetSwitch,
    Tare,
    Update,
    UpdateState,
)
from mmctl.errors import FaultCause, MmctlError, SafetyFault
from mmctl.types import ArmState, Odometry, Wrench

log = structlog.get_logger("mmctl.inputlog")

VERSION = 2
#: The row's fields, in order (arrays by their length).
FIELDS: tuple[tuple[str, int], ...] = (
    ("index", 1), ("now", 1), ("dt", 1),
    ("arm", 1), ("q", 6), ("qd", 6), ("controller_time", 1), ("runtime_state", 1),
    ("safety_bits", 1), ("speed_scaling", 1),
    ("wrench", 1), ("force", 3), ("torque", 3), ("w_timestamp", 1), ("w_sequence", 1),
    ("w_status", 1),
    ("odom", 1), ("pose", 3), ("twist_meas", 3), ("o_timestamp", 1),
    ("inputs", 1), ("overrun", 1), ("overrun_consecutive", 1), ("overrun_total", 1),
    ("misses", 1), ("arm_busy", 1), ("calibrating", 1),
    ("stop", 1), ("has_qd", 1), ("qd_arm", 6), ("has_twist", 1), ("twist", 3), ("kick", 1),
)
WIDTH = sum(n for _, n in FIELDS)
_AT = {}
_i = 0
for _name, _n in FIELDS:
    _AT[_name] = _i
    _i += _n
BLOCK = 500  # rows per block handed to the writer (1 s at 500 Hz)
F64 = NDArray[np.float64]
#: One JSON object of the log's side file (a command, a state patch, an exception) as
#: this module writes it and reads it back: its schema is this module's own, so its
#: values are taken as written (a log that does not parse is a LogError).
Record = dict[str, Any]


class LogError(MmctlError):
    """The folder is not a readable inputs log."""


# -- commands and state patches as JSON ---------------------------------------------------

def _plain_map(d: Mapping[str, object]) -> Record:
    """A details mapping as JSON values."""
    return {k: plain(v) for k, v in d.items()}


def _exc(e: BaseException | None) -> Record | None:
    if e is None:
        return None
    out: Record = {"type": type(e).__name__, "message": str(e)}
    if isinstance(e, SafetyFault):
        out["cause"] = e.cause.value
        out["details"] = _plain_map(e.details)
    return out


def _unexc(d: Record | None) -> BaseException | None:
    if d is None:
        return None
    if d.get("cause") is not None:
        return SafetyFault(d["cause"], **dict(d.get("details") or {}))
    return MmctlError(str(d.get("message", "")))


def encode_command(cmd: Command) -> Record:
    """A plain-JSON form of one inbox command (``Install``: its key and value)."""
    match cmd:
        case EnableFinish(failure=failure, fault=fault):
            return {"t": "EnableFinish", "failure": _exc(failure), "fault": _exc(fault)}
        case Install(cfg=cfg, key=key):
            from mmctl.control.params import get_value

            return {"t": "Install", "key": key, "value": plain(get_value(cfg, key))}
        case _:
            return {"t": type(cmd).__name__, **{k: plain(v) for k, v in cmd._asdict().items()}}


def decode_command(d: Record, cfg: Config) -> tuple[Command, Config]:
    """The command back (an ``Install`` rebuilt from ``cfg`` with its key set); returns
    it with the configuration in force after it."""
    t = d["t"]
    simple: Record = {"Disable": Disable, "Tare": Tare, "BeginEnable": BeginEnable,
                              "EnableCheck": EnableCheck}
    if t in simple:
        return simple[t](), cfg
    if t == "SetMode":
        return SetMode(d["mode"]), cfg
    if t == "Release":
        return Release(d["link"]), cfg
    if t == "SetSwitch":
        return SetSwitch(d["to"]), cfg
    if t == "SetProfile":
        return SetProfile(d["profile"]), cfg
    if t == "EnableFinish":
        fault = _unexc(d.get("fault"))
        return EnableFinish(_unexc(d.get("failure")),
                            fault if isinstance(fault, SafetyFault) else None), cfg
    if t == "Install":
        from mmctl.control.params import with_value
        from mmctl.control.step import Controller
        from mmctl.model.robot import RobotModel

        new = with_value(cfg, d["key"], d["value"])
        return Install(new, Controller(new, RobotModel(new.robot)), d["key"]), new
    raise LogError(f"unknown command {t!r} in the log")


def _encode_safety(s: Safety) -> Record:
    return {"state": s.state.value, "latched": s.latched.value if s.latched else None,
            "latched_details": _plain_map(s.latched_details),
            "active": _encode_conditions(s.active), "faults": s.faults}


def _decode_safety(d: Record) -> Safety:
    return Safety(SafetyState(d["state"]),
                  None if d["latched"] is None else FaultCause(d["latched"]),
                  dict(d["latched_details"]), _decode_conditions(d["active"]), int(d["faults"]))


def _encode_conditions(c: Mapping[FaultCause, Mapping[str, object]]) -> Record:
    return {cause.value: _plain_map(d) for cause, d in c.items()}


def _decode_conditions(d: Record) -> dict[FaultCause, Mapping[str, object]]:
    return {FaultCause(k): dict(v) for k, v in d.items()}


def apply_patch(s: UpdateState, patch: Record) -> UpdateState:
    if "safety" in patch:
        s = s._replace(safety=_decode_safety(patch["safety"]))
    if "twist_sent" in patch:
        t = patch["twist_sent"]
        s = s._replace(twist_sent=None if t is None else (float(t[0]), float(t[1]), float(t[2])))
    return s


# -- rows ---------------------------------------------------------------------------------

def fill_row(row: F64, r: Readings, c: Commands) -> None:
    """One cycle's readings and commands into ``row`` (:data:`FIELDS`)."""
    row[:] = 0.0
    row[0], row[1], row[2] = r.index, r.now, r.dt
    a = r.arm
    if a is not None:
        i = _AT["arm"]
        row[i] = 1.0
        row[i + 1:i + 7] = a.q
        row[i + 7:i + 13] = a.qd
        row[i + 13:i + 17] = (a.controller_time, a.runtime_state, a.safety_bits,
                              a.speed_scaling)
    w = r.wrench
    if w is not None:
        i = _AT["wrench"]
        row[i] = 1.0
        row[i + 1:i + 4] = w.force
        row[i + 4:i + 7] = w.torque
        row[i + 7:i + 10] = (w.timestamp, w.sequence, w.status)
    o = r.odom
    if o is not None:
        i = _AT["odom"]
        row[i:i + 8] = (1.0, o.x, o.y, o.yaw, o.vx, o.vy, o.wz, o.timestamp)
    i = _AT["inputs"]
    row[i] = r.inputs
    if r.overrun is not None:
        row[i + 1:i + 4] = (1.0, r.overrun[0], r.overrun[1])
    row[i + 4:i + 7] = (r.misses, r.arm_busy, r.calibrating)
    i = _AT["stop"]
    row[i] = c.stop
    if c.qd_arm is not None:
        row[i + 1] = 1.0
        row[i + 2:i + 8] = c.qd_arm
    if c.twist is not None:
        row[i + 8:i + 12] = (1.0, *c.twist)
    row[i + 12] = c.kick


def row_readings(row: F64, conditions: Mapping[FaultCause, Mapping[str, object]]) -> Readings:
    """The readings back from a row (and the cycle's conditions from the side file)."""
    arm = wrench = odom = None
    i = _AT["arm"]
    if row[i]:
        arm = ArmState(row[i + 1:i + 7].copy(), row[i + 7:i + 13].copy(), float(row[i + 13]),
                       int(row[i + 14]), int(row[i + 15]), float(row[i + 16]))
    i = _AT["wrench"]
    if row[i]:
        wrench = Wrench(row[i + 1:i + 4].copy(), row[i + 4:i + 7].copy(), float(row[i + 7]),
                        int(row[i + 8]), int(row[i + 9]))
    i = _AT["odom"]
    if row[i]:
        odom = Odometry(*(float(x) for x in row[i + 1:i + 8]))
    i = _AT["inputs"]
    overrun = (int(row[i + 2]), int(row[i + 3])) if row[i + 1] else None
    return Readings(int(row[0]), float(row[1]), float(row[2]), arm, wrench, odom,
                    int(row[i]), dict(conditions), overrun, int(row[i + 4]), bool(row[i + 5]),
                    bool(row[i + 6]))


class RecordedCommands(NamedTuple):
    stop: bool
    qd_arm: F64 | None
    twist: tuple[float, float, float] | None
    kick: bool


def row_commands(row: F64) -> RecordedCommands:
    i = _AT["stop"]
    qd = row[i + 2:i + 8].copy() if row[i + 1] else None
    tw = (float(row[i + 9]), float(row[i + 10]), float(row[i + 11])) if row[i + 8] else None
    return RecordedCommands(bool(row[i]), qd, tw, bool(row[i + 12]))


# -- the writer ---------------------------------------------------------------------------

class InputLog:
    """Append-only inputs log in ``folder`` (created; must not hold a log already).

    :meth:`append` and :meth:`patch` on the loop thread (no I/O: a copy into a block);
    a writer thread writes each full block; :meth:`close` writes the rest (idempotent).
    """

    def __init__(self, folder: str | Path, cfg: Config):
        self.folder = Path(folder)
        self.cfg = cfg
        self.rows = 0
        self._block: F64 = np.zeros((BLOCK, WIDTH))
        self._n = 0
        self._side: list[Record] = []
        self._q: queue.SimpleQueue[tuple[F64, list[Record]] | None] = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.error: BaseException | None = None

    def open(self) -> None:
        """Create the folder and its meta file, start the writer."""
        if (self.folder / "meta.json").exists():
            raise LogError(f"{self.folder}: holds an inputs log already (choose a new folder)")
        self.folder.mkdir(parents=True, exist_ok=True)
        meta = {"format": "mmctl-inputs", "version": VERSION, "width": WIDTH,
                "fields": [list(f) for f in FIELDS], "config": to_dict(self.cfg)}
        (self.folder / "meta.json").write_text(json.dumps(meta, indent=1))
        (self.folder / "rows.f64").write_bytes(b"")
        (self.folder / "side.jsonl").write_text("")
        self._thread = threading.Thread(target=self._write, name="mmctl-inputlog",
                                        daemon=True)
        self._thread.start()
        log.info("inputs_log_open", folder=str(self.folder))

    def append(self, r: Readings, inbox: Sequence[Command], c: Commands) -> None:
        """One cycle whose update ran (loop thread)."""
        if self._closed:
            return
        fill_row(self._block[self._n], r, c)
        if r.conditions:
            self._side.append({"cycle": r.index, "conditions": _encode_conditions(r.conditions)})
        if inbox:
            self._side.append({"cycle": r.index, "inbox": [encode_command(x) for x in inbox]})
        self._n += 1
        self.rows += 1
        if self._n == BLOCK:
            self._flush()

    def outcome(self, cycle: int, kind: str, record: Record) -> None:
        """The write's outcome in cycle ``cycle``: ``write_failed`` (cause, details) or
        ``cycle_failed`` (error), the inputs of the update's transitions of that name."""
        if not self._closed:
            self._side.append({"cycle": cycle, kind: {
                k: _plain_map(v) if isinstance(v, Mapping) else plain(v)
                for k, v in record.items()}})

    def _flush(self) -> None:
        self._q.put((self._block[:self._n], self._side))
        self._block = np.zeros((BLOCK, WIDTH))
        self._n = 0
        self._side = []

    def _write(self) -> None:
        try:
            with open(self.folder / "rows.f64", "ab") as rows, \
                    open(self.folder / "side.jsonl", "a") as side:
                while True:
                    item = self._q.get()
                    if item is None:
                        return
                    block, events = item
                    rows.write(np.ascontiguousarray(block).tobytes())
                    side.writelines(json.dumps(ev) + "\n" for ev in events)
                    rows.flush()
                    side.flush()
        except OSError as exc:
            self.error = exc
            log.error("inputs_log_failed", folder=str(self.folder), error=str(exc))

    def close(self) -> None:
        """Write what is left and stop the writer (idempotent)."""
        if self._closed:
            return
        self._flush()
        self._closed = True
        self._q.put(None)
        if self._thread is not None:
            self._thread.join(30.0)
        log.info("inputs_log_closed", folder=str(self.folder), cycles=self.rows)


# -- replay -------------------------------------------------------------------------------

class ReplayResult(NamedTuple):
    """cycles: how many were replayed; first_difference: the first cycle whose commands
    differ (None: none), with what differs in ``detail``."""

    cycles: int
    first_difference: int | None
    detail: str


def read_log(folder: str | Path) -> tuple[Config, F64, list[Record]]:
    """The configuration, the rows and the side events of a log."""
    folder = Path(folder)
    try:
        meta = json.loads((folder / "meta.json").read_text())
        raw = (folder / "rows.f64").read_bytes()
        side = [json.loads(line) for line in (folder / "side.jsonl").read_text().splitlines()
                if line.strip()]
    except (OSError, ValueError) as exc:
        raise LogError(f"{folder}: not a readable inputs log ({exc})") from exc
    version = meta.get("version")
    if meta.get("format") == "mmctl-inputs" and not (isinstance(version, int)
                                                     and 1 <= version <= VERSION):
        raise LogError(f"{folder}: an inputs log of version {version!r}; this mmctl reads "
                       f"versions 1 to {VERSION} (replay it with the mmctl that wrote it)")
    if meta.get("format") != "mmctl-inputs" or meta.get("width") != WIDTH:
        raise LogError(f"{folder}: not an inputs log of this version (format "
                       f"{meta.get('format')!r}, width {meta.get('width')!r}; this mmctl "
                       f"reads width {WIDTH})")
    rows = np.frombuffer(raw[:len(raw) - len(raw) % (8 * WIDTH)], np.float64).reshape(-1, WIDTH)
    return config_from_dict(meta["config"]), rows, side


def _differs(a: float | F64, b: float | F64) -> bool:
    return not np.array_equal(np.asarray(a), np.asarray(b))


def replay(folder: str | Path, progress: Callable[[int, int], None] | None = None
           ) -> ReplayResult:
    """Run a log's readings and inbox through a new update; compare the commands."""
    from mmctl.control.cycle import CycleChain

    cfg, rows, side = read_log(folder)
    by_cycle: dict[int, list[Record]] = {}
    for ev in side:
        by_cycle.setdefault(int(ev["cycle"]), []).append(ev)
    update = Update(cfg, CycleChain(cfg))
    state = update.initial_state()
    done: set[int] = set()
    for k, row in enumerate(rows):
        cycle = int(row[0])
        for c in sorted(x for x in by_cycle if x < cycle and x not in done):  # no row
            state = _patches(update, state, by_cycle[c])
            done.add(c)
        events = by_cycle.get(cycle, [])
        conditions: dict[FaultCause, Mapping[str, object]] = {}
        inbox: list[Command] = []
        for ev in events:
            if "conditions" in ev:
                conditions = _decode_conditions(ev["conditions"])
            if "inbox" in ev:
                for d in ev["inbox"]:
                    cmd, cfg = decode_command(d, cfg)
                    inbox.append(cmd)
        state, cmds, _ = update(state, row_readings(row, conditions), inbox)
        rec = row_commands(row)
        what = []
        if cmds.stop != rec.stop:
            what.append(f"stop {cmds.stop} vs recorded {rec.stop}")
        if (cmds.qd_arm is None) != (rec.qd_arm is None) or (
                cmds.qd_arm is not None and _differs(cmds.qd_arm, rec.qd_arm)):  # type: ignore[arg-type]
            what.append(f"speedJ {cmds.qd_arm} vs recorded {rec.qd_arm}")
        if cmds.twist != rec.twist:
            what.append(f"twist {cmds.twist} vs recorded {rec.twist}")
        if cmds.kick != rec.kick:
            what.append(f"kick {cmds.kick} vs recorded {rec.kick}")
        if what:
            return ReplayResult(k + 1, cycle, "; ".join(what))
        state = _patches(update, state, events)
        done.add(cycle)
        if progress is not None and (k + 1) % 5000 == 0:
            progress(k + 1, len(rows))
    return ReplayResult(len(rows), None, "")


def _patches(update: Update, state: UpdateState, events: list[Record]) -> UpdateState:
    """What happened after the cycle's update: the write's outcome through the update's
    own transitions, and the runtime's changes to its state (patches)."""
    for ev in events:
        if "write_failed" in ev:
            d = ev["write_failed"]
            state, _ = update.write_failed(state, FaultCause(d["cause"]), dict(d["details"]))
        if "cycle_failed" in ev:
            state, _, _ = update.cycle_failed(state, str(ev["cycle_failed"]["error"]))
        if "patch" in ev:
            state = apply_patch(state, ev["patch"])
    return state


def iter_rows(folder: str | Path) -> Iterator[tuple[Readings, RecordedCommands]]:
    """Each cycle's readings and commands (for a look at an incident)."""
    _, rows, side = read_log(folder)
    cond = {int(e["cycle"]): _decode_conditions(e["conditions"]) for e in side
            if "conditions" in e}
    for row in rows:
        yield row_readings(row, cond.get(int(row[0]), {})), row_commands(row)


__all__ = [
    "VERSION",
    "WIDTH",
    "InputLog",
    "LogError",
    "ReplayResult",
    "iter_rows",
    "read_log",
    "replay",
]
