"""Joint state shared between the fake controller's process and its parent.

A ``multiprocessing`` RawArray of doubles guarded by a sequence lock: the writer (the
fake, once per controller period) makes the sequence odd, writes, makes it even; a
reader retries while the sequence is odd or changed under it.  No lock is held across
processes, so a killed fake can never leave the parent blocked.

Layout: [seq, controller_time, q0..q5, qd0..qd5, runtime_state, safety_status_bits].
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence
from typing import Any

SIZE = 16
_SEQ, _TIME, _Q, _QD, _RUNTIME, _SAFETY = 0, 1, 2, 8, 14, 15


def new_block(ctx: Any) -> Any:
    """A zeroed shared block from a multiprocessing context (passed to the child)."""
    return ctx.RawArray(ctypes.c_double, SIZE)


def write(block: Any, time: float, q: Sequence[float], qd: Sequence[float],
          runtime_state: int, safety_bits: int) -> None:
    """Publish one sample (writer side: the fake's process only)."""
    seq = block[_SEQ] + 1.0
    block[_SEQ] = seq
    block[_TIME:_SAFETY + 1] = [time, *q, *qd, float(runtime_state), float(safety_bits)]
    block[_SEQ] = seq + 1.0


def read(block: Any, retries: int = 1000) -> tuple[float, list[float], list[float], int, int]:
    """A consistent (controller_time, q, qd, runtime_state, safety_bits) snapshot."""
    for _ in range(retries):
        before = block[_SEQ]
        if before % 2.0:
            continue
        values = block[_TIME:_SAFETY + 1]
        if block[_SEQ] == before:
            break
    else:
        values = block[_TIME:_SAFETY + 1]
    return (values[0], list(values[1:7]), list(values[7:13]), int(values[13]), int(values[14]))
