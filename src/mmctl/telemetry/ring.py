"""The loop's telemetry samples as rows of a bounded single-producer ring.

One row of float64 per control cycle (:data:`WIDTH` columns, named below), in one
buffer with a small int64 header: the write count (head), the read count (tail), the
drop counter and the published counter.  The buffer is either a private numpy array
(the publisher is a thread of the daemon) or a memory-mapped file that a child process
maps too (``telemetry.process``): then the publisher's work, rerun's included, never
takes the daemon's interpreter lock.

Producer (the loop thread), :meth:`SampleRing.claim` / :meth:`~SampleRing.commit` (or
:meth:`~SampleRing.put` for a :class:`~mmctl.telemetry.sample.TelemetrySample`): if
``head - tail`` reaches the capacity the sample is dropped and counted; otherwise it
fills row ``head % size`` and only then stores ``head + 1``.  Consumer (the
publisher), :meth:`SampleRing.take`: copies rows ``tail .. head - 1`` and only then
stores the new tail.  Each counter has one writer, so no lock is taken and the loop
never waits.  Across processes this relies on stores becoming visible in program order
(x86-64's memory model; CPython does not reorder them).

Besides the sample, a row carries the loop timing of the *previous* cycle (the loop's
:attr:`TimingRing.newest <mmctl.runtime.timing.TimingRing.newest>` when the row is
written: the current cycle is not finished yet), so a publisher in another process
still plots loop slack and compute time.
"""

from __future__ import annotations

import math
import mmap
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from mmctl.config.control import STRATEGIES
from mmctl.control.limits import LIMIT_NAMES
from mmctl.telemetry.sample import TelemetrySample

F64 = NDArray[np.float64]

# -- row layout ----------------------------------------------------------------------------
# What the loop has at hand, copied as is: positions stay in the world (odometry) frame
# and the wheel speeds are not computed -- the consumer derives both
# (:func:`mmctl.telemetry.batch.base_frame`, :func:`~mmctl.telemetry.batch.wheel_speeds`).
CYCLE, T, MODE, SAFETY = 0, 1, 2, 3
#: timing of the previous cycle [ns]: latency, compute, slack, missed (NaN: unknown)
PREV_LATENCY, PREV_COMPUTE, PREV_SLACK, PREV_MISSED = 4, 5, 6, 7
Q_A = slice(8, 14)
BASE_POSE = slice(14, 17)
BASE_X, BASE_Y, BASE_YAW = 14, 15, 16
F_H = slice(17, 23)
V_D = slice(23, 29)
V = slice(29, 35)
QD_CMD = slice(35, 44)
BASE_TWIST = slice(41, 44)  #: the base part of QD_CMD: vx, vy [m/s], wz [rad/s]
E_TOTAL, E_ARM, E_BASE = 44, 45, 46
ENERGY = slice(44, 47)
P = slice(47, 50)  #: tool position in the world [m]
P_DES = slice(50, 53)  #: FK(q_des) in the world, base at its pose [m]
LIMIT = 53  #: the limit that bound the command (code in :data:`LIMITS`)
LIMIT_SCALE = 54  #: the scale the limits applied to the IDK's command (1: free)
NEAREST = 55  #: the robot's two nearest parts' distance [m] (NaN: not checked)
QD_A = slice(56, 62)  #: measured arm joint velocities [rad/s] (the ROS 2 joint states)
F_RAW = slice(62, 68)  #: the sensor's raw wrench, sensor frame [N, N m]
WIDTH = 68

#: mode labels a row can carry (``TelemetrySample.mode``), by code
MODES: tuple[str, ...] = tuple(
    label for s in STRATEGIES
    for label in ((f"{s}/manipulation", f"{s}/locomotion") if s == "switch" else (s,))
) + ("idle",)
#: safety states a row can carry (``TelemetrySample.safety``), by code
SAFETY_STATES: tuple[str, ...] = ("disarmed", "armed", "fault")
#: limits a row can carry (``TelemetrySample.limit``), by code ("": none)
LIMITS: tuple[str, ...] = LIMIT_NAMES
_MODE_CODE = {m: float(i) for i, m in enumerate(MODES)}
_LIMIT_CODE = {n: float(i) for i, n in enumerate(LIMITS)}
_SAFETY_CODE = {s: float(i) for i, s in enumerate(SAFETY_STATES)}
UNKNOWN = "?"

# -- header (int64) --------------------------------------------------------------------------
_HEAD, _TAIL, _DROPPED, _PUBLISHED = 0, 1, 2, 3
_HEADER = 8  #: int64 slots (4 spare)
_NAN4: tuple[float, ...] = (math.nan,) * 4


class _NoTiming:
    """Stands in for the loop's TimingRing where there is none: timing unknown (NaN)."""

    newest: tuple[float, ...] = _NAN4


NO_TIMING = _NoTiming()


def mode_code(label: str) -> float:
    """The row code of a mode label (-1: not one of :data:`MODES`)."""
    return _MODE_CODE.get(label, -1.0)


def safety_code(label: str) -> float:
    """The row code of a safety state (-1: not one of :data:`SAFETY_STATES`)."""
    return _SAFETY_CODE.get(label, -1.0)


def limit_code(name: str) -> float:
    """The row code of a limit's name (-1: not one of :data:`LIMITS`)."""
    return _LIMIT_CODE.get(name, -1.0)


def label(table: tuple[str, ...], code: float) -> str:
    """A code back to its label (:data:`UNKNOWN` when out of range)."""
    i = int(code) if math.isfinite(code) else -1
    return table[i] if 0 <= i < len(table) else UNKNOWN


class SampleRing:
    """Bounded ring of sample rows (see the module docstring).

    size: capacity in rows (> 0); buffer: where the header and rows live (None: a
    private array; see :meth:`create_file` / :meth:`attach_file`); timing: the loop's
    TimingRing, whose newest row is the previous cycle's timing (None:
    :data:`NO_TIMING`, NaN).
    """

    def __init__(self, size: int, buffer: Any = None, timing: Any = None):
        if size <= 0:
            raise ValueError(f"size must be > 0, got {size}")
        self.size = size
        nbytes = self.nbytes(size)
        if buffer is None:
            buffer = bytearray(nbytes)
        if len(buffer) < nbytes:
            raise ValueError(f"buffer holds {len(buffer)} bytes, {nbytes} needed for {size} rows")
        self._buffer = buffer
        #: the header as a memoryview of int64: reads and stores of single counters give
        #: and take Python ints (no numpy scalar per access on the loop)
        self._hv = memoryview(buffer)[:_HEADER * 8].cast("q")
        self.rows = np.frombuffer(buffer, np.float64, size * WIDTH,
                                  _HEADER * 8).reshape(size, WIDTH)
        self._views = list(self.rows)  #: one view per row, made once (claim returns them)
        self.timing = timing if timing is not None else NO_TIMING
        self._file: Path | None = None

    @staticmethod
    def nbytes(size: int) -> int:
        return 8 * (_HEADER + size * WIDTH)

    # -- shared between processes ------------------------------------------------------
    @classmethod
    def create_file(cls, size: int, directory: str | None = None,
                    timing: Any = None) -> SampleRing:
        """A ring in a new memory-mapped file that :meth:`attach_file` maps in another
        process; :meth:`unlink` removes the file.  It goes to ``directory``, else
        systemd's ``$RUNTIME_DIRECTORY`` (a tmpfs), else /dev/shm, else the temp dir."""
        base = (directory or os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
                or ("/dev/shm" if os.path.isdir("/dev/shm") else None))
        import tempfile

        fd, name = tempfile.mkstemp(prefix="mmctl-telemetry-", suffix=".ring", dir=base)
        try:
            os.ftruncate(fd, cls.nbytes(size))
            mm = mmap.mmap(fd, cls.nbytes(size))
        finally:
            os.close(fd)
        ring = cls(size, mm, timing)
        ring._file = Path(name)
        return ring

    @classmethod
    def attach_file(cls, path: str, size: int) -> SampleRing:
        """Map the ring another process created with :meth:`create_file`."""
        fd = os.open(path, os.O_RDWR)
        try:
            mm = mmap.mmap(fd, cls.nbytes(size))
        finally:
            os.close(fd)
        return cls(size, mm)

    @property
    def path(self) -> str | None:
        """The backing file (None: private memory, or already unlinked)."""
        return str(self._file) if self._file is not None else None

    def unlink(self) -> None:
        """Remove the backing file (the mappings stay valid); idempotent."""
        if self._file is not None:
            self._file.unlink(missing_ok=True)
            self._file = None

    # -- producer --------------------------------------------------------------------------
    def claim(self) -> F64 | None:
        """The next free row (the loop's hot path), or None when the ring is full (the
        sample is dropped and counted).  Fill it (:func:`encode`, or the loop's
        ``ControlCore.fill_row``), then :meth:`commit`.  Never blocks."""
        hv = self._hv
        head = hv[_HEAD]
        if head - hv[_TAIL] >= self.size:
            hv[_DROPPED] += 1
            return None
        return self._views[head % self.size]

    def commit(self) -> None:
        """Publish the row :meth:`claim` returned."""
        self._hv[_HEAD] += 1

    def put(self, s: TelemetrySample) -> bool:
        """Append one sample; False if the ring was full (dropped, counted)."""
        row = self.claim()
        if row is None:
            return False
        encode(s, row, self.timing.newest)
        self.commit()
        return True

    # -- consumer --------------------------------------------------------------------------
    def take(self, limit: int | None = None) -> F64:
        """Remove and return the queued rows, oldest first ((n, WIDTH) copy)."""
        hv = self._hv
        tail = hv[_TAIL]
        n = hv[_HEAD] - tail
        if limit is not None:
            n = min(n, limit)
        if n <= 0:
            return np.empty((0, WIDTH))
        idx = np.arange(tail, tail + n) % self.size
        out = self.rows[idx]  # fancy indexing copies
        hv[_TAIL] = tail + n
        return out

    def mark_published(self, n: int) -> None:
        """Count ``n`` rows as handed to the sink (consumer side)."""
        self._hv[_PUBLISHED] += n

    # -- counters (any side) -----------------------------------------------------------------
    @property
    def accepted(self) -> int:
        return self._hv[_HEAD]

    @property
    def dropped(self) -> int:
        return self._hv[_DROPPED]

    @property
    def published(self) -> int:
        return self._hv[_PUBLISHED]

    def __len__(self) -> int:
        return self._hv[_HEAD] - self._hv[_TAIL]


def encode(s: TelemetrySample, row: F64, prev: tuple[float, ...] = _NAN4) -> None:
    """Write a sample and the previous cycle's timing ``prev`` (latency, compute, slack,
    missed [ns]) into a row."""
    np.concatenate(((s.cycle, s.t, _MODE_CODE.get(s.mode, -1.0),
                     _SAFETY_CODE.get(s.safety, -1.0), *prev),
                    s.q_a, s.base_pose, s.f_h, s.v_d, s.v, s.qd_cmd,
                    (s.e_total, s.e_arm, s.e_base), s.p, s.p_des,
                    (_LIMIT_CODE.get(s.limit, -1.0), s.limit_scale, s.nearest), s.qd_a,
                    s.f_raw), out=row)


def sample_of(row: F64) -> TelemetrySample:
    """One row back to its :class:`TelemetrySample` (for the 3-D frame and tests)."""
    return TelemetrySample(
        cycle=int(row[CYCLE]), t=float(row[T]), q_a=row[Q_A].copy(),
        base_pose=row[BASE_POSE].copy(), f_h=row[F_H].copy(), v_d=row[V_D].copy(),
        v=row[V].copy(), qd_cmd=row[QD_CMD].copy(),
        e_total=float(row[E_TOTAL]), e_arm=float(row[E_ARM]), e_base=float(row[E_BASE]),
        p=row[P].copy(), p_des=row[P_DES].copy(), mode=label(MODES, float(row[MODE])),
        safety=label(SAFETY_STATES, float(row[SAFETY])),
        limit=label(LIMITS, float(row[LIMIT])), limit_scale=float(row[LIMIT_SCALE]),
        nearest=float(row[NEAREST]), qd_a=row[QD_A].copy(), f_raw=row[F_RAW].copy())


def rows_of(samples: list[TelemetrySample]) -> F64:
    """Samples as rows, the way :meth:`SampleRing.put` writes them (timing unknown)."""
    out = np.full((len(samples), WIDTH), math.nan)
    for s, row in zip(samples, out, strict=True):
        encode(s, row)
    return out
