"""Programs sent to the script port (30003), and the emulated ur_rtde control script.

ur_rtde uploads one URScript program, ``def rtde_control(): ... end``.  Its main loop
runs once per controller cycle and talks to the client through RTDE registers
(offset 0, or 24 with ur_rtde's "upper range" flag):

* ``input_int_register_0`` holds the command number (0 = none, 9 = speedJ, 15 =
  speedStop, 255 = stop the script, ...), the input double registers its arguments;
* ``output_int_register_0`` is the handshake: 1 = ready for a command, 2 = done.

Real-time commands (speedJ, servoJ, ...) are executed and answered "ready" on every
cycle; any other command is executed once, answered "done", and the script answers
"ready" again after the client has cleared the command register (written 0).  Command
255 ends the program.  This module reproduces that behaviour; the motion itself is
:class:`~mmctl.sim.joints.JointPlant`'s.

Command 35 (ur_rtde's ``setWatchdog(min_frequency)``) runs the script's
``rtde_set_watchdog("input_int_register_<offset>", watchdog_min_frequency, "stop")``:
from then on the controller expects an update of that input register (any RTDE data
package that carries it: ``kickWatchdog()`` writes 0 into it, every command writes its
number) at least ``min_frequency`` times a second, and takes the action (URScript:
``"ignore"``, ``"pause"`` or ``"stop"`` the program) when one is late.  The URScript
manual: "All watchdogs are removed on program stop."  :class:`RtdeWatchdog` is that
watchdog; the controller model checks it every period.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

from mmctl.sim.joints import JointPlant

SPEEDJ = 9
SPEED_STOP = 15
SERVO_STOP = 16
STOPL = 33
STOPJ = 34
SET_WATCHDOG = 35
STOP_SCRIPT = 255
#: Commands the script executes every cycle and answers with "ready" at once.
REALTIME_COMMANDS = frozenset({24, 11, 9, 10, 6, 25, 26, 27, 38, 58, 66, 67, 68, 69, 70, 71})
READY = 1
DONE = 2

_DEF = re.compile(r"^def\s+(\w+)\s*\(\s*\)\s*:", re.MULTILINE)
_END = re.compile(r"^end\b", re.MULTILINE)
_OFFSET = re.compile(r"reg_offset_int\s*=\s*(?:#[^\n]*\n?)?\s*(\d+)")
_SET_WATCHDOG = re.compile(
    r'rtde_set_watchdog\(\s*"input_int_register_(\d+)"\s*,[^,]*,\s*"(\w+)"\s*\)')
WATCHDOG_ACTIONS = ("ignore", "pause", "stop")
DEFAULT_WATCHDOG_ACTION = "pause"
"""URScript's default action of ``rtde_set_watchdog``."""


@dataclass
class RtdeWatchdog:
    """An active ``rtde_set_watchdog``: input int ``register`` must be updated at least
    ``min_frequency`` [Hz] times a second, else ``action`` (ignore | pause | stop);
    ``last_update`` is the controller time [s] of the newest update."""

    register: int
    min_frequency: float
    action: str
    last_update: float

    def expired(self, now: float) -> bool:
        """No update for longer than 1 / min_frequency at controller time ``now`` [s]."""
        return (now - self.last_update) * self.min_frequency > 1.0


def watchdog_actions(program_text: str) -> dict[int, str]:
    """The action of each ``rtde_set_watchdog("input_int_register_N", ..., "action")``
    in a program, by register N (the first one written for a register wins)."""
    actions: dict[int, str] = {}
    for register, action in _SET_WATCHDOG.findall(program_text):
        actions.setdefault(int(register), action)
    return actions


class Registers:
    """The RTDE general purpose registers 0..47 in both directions."""

    def __init__(self) -> None:
        self.in_int = [0] * 48
        self.in_double = [0.0] * 48
        self.out_int = [0] * 48
        self.out_double = [0.0] * 48


class ScriptReceiver:
    """Reassembles programs from the bytes arriving on the script port."""

    def __init__(self) -> None:
        self._text = ""

    def feed(self, data: bytes) -> list[tuple[str, str]]:
        """Add bytes; return every complete ``(name, program text)`` (a single line that is
        not a ``def`` comes back with the name ``""``)."""
        self._text += data.decode("utf-8", errors="replace")
        programs: list[tuple[str, str]] = []
        while self._text:
            stripped = self._text.lstrip()
            if not stripped:
                self._text = ""
                break
            head = _DEF.match(stripped)
            if head is None:
                if "\n" not in stripped:
                    break
                line, _, rest = stripped.partition("\n")
                programs.append(("", line))
                self._text = rest
                continue
            end = _END.search(stripped, head.end())
            if end is None:
                break
            stop = stripped.find("\n", end.end())
            stop = len(stripped) if stop < 0 else stop + 1
            programs.append((head.group(1), stripped[:stop]))
            self._text = stripped[stop:]
        return programs


def register_offset(program_text: str) -> int:
    """The register offset ur_rtde injected into its control script (0 or 24)."""
    found = _OFFSET.search(program_text)
    return int(found.group(1)) if found else 0


class RtdeControlProgram:
    """The ur_rtde control script, one :meth:`cycle` per controller period.

    ``watchdog_actions``: what the script's ``rtde_set_watchdog`` calls do, by register
    (:func:`watchdog_actions` of the program text); ``clock()``: the controller time [s].
    """

    def __init__(self, regs: Registers, plant: JointPlant, offset: int = 0,
                 watchdog_actions: dict[int, str] | None = None,
                 clock: Callable[[], float] = lambda: 0.0):
        self.regs = regs
        self.plant = plant
        self.offset = offset
        self.executing = False
        self.running = True
        self.motion_allowed: Callable[[], bool] = lambda: True
        self.watchdog_actions = dict(watchdog_actions or {})
        self.clock = clock
        self.watchdog: RtdeWatchdog | None = None
        regs.out_int[offset] = READY  # signal_ready() before the main loop

    def cycle(self) -> None:
        """One pass of the script's main loop."""
        if not self.running:
            return
        regs, off = self.regs, self.offset
        cmd = regs.in_int[off]
        if cmd in REALTIME_COMMANDS:
            self._process(cmd)
            regs.out_int[off] = READY
        elif cmd == 0:
            self.executing = False
            regs.out_int[off] = READY
        else:
            if not self.executing:
                self._process(cmd)
            self.executing = True

    def _process(self, cmd: int) -> None:
        regs, off = self.regs, self.offset
        d = regs.in_double
        if cmd == SPEEDJ:
            if self.motion_allowed():
                self.plant.speed(d[off:off + 6], d[off + 6])
        elif cmd in (SPEED_STOP, SERVO_STOP, STOPJ, STOPL):
            self.plant.stop(d[off])
        elif cmd == SET_WATCHDOG:
            frequency = d[off]
            action = self.watchdog_actions.get(off, DEFAULT_WATCHDOG_ACTION)
            # URScript refuses a non-positive frequency; the fake removes the watchdog
            self.watchdog = (RtdeWatchdog(off, frequency, action, self.clock())
                             if frequency > 0.0 and action in WATCHDOG_ACTIONS else None)
        elif cmd == STOP_SCRIPT:
            self.running = False
            return
        if cmd not in REALTIME_COMMANDS:
            regs.out_int[off] = DONE
