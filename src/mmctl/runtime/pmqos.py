"""CPU wake-up latency request through Linux PM QoS (``/dev/cpu_dma_latency``).

While a process holds ``/dev/cpu_dma_latency`` open with a 32-bit value written to it,
the kernel's cpuidle governor only picks idle states whose exit latency is at most that
many microseconds; 0 keeps idle CPUs polling instead of halting.  Closing the file
withdraws the request.  This is what real-time tools (cyclictest, robot drivers'
tuning guides) do: a CPU that halts between two control cycles wakes slowly and, in a
virtual machine, runs the next cycle's code measurably slower (``mmctl bench loop
--cpu-dma-latency 0`` against ``-1`` shows it on the machine at hand).

The request is best effort: without write access to the device (non-root, no udev rule;
see ``systemd/mmctl.service``) it is logged as a warning and the daemon runs on.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import TYPE_CHECKING

import structlog

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing_extensions import Self

log = structlog.get_logger("mmctl.pmqos")

DEVICE = Path("/dev/cpu_dma_latency")
MAX_US = 2_000_000
"""The largest request value accepted here [us] (2 s: no constraint in practice)."""


class CpuLatencyRequest:
    """One PM QoS CPU-latency request, held from :meth:`acquire` to :meth:`release`.

    us: the largest acceptable wake-up latency [us] (0 = poll, never halt); path: the
    PM QoS device (tests pass a plain file).  No I/O here.
    """

    def __init__(self, us: int, path: Path = DEVICE):
        if not 0 <= us <= MAX_US:
            raise ValueError(f"us must be in [0, {MAX_US}], got {us}")
        self.us = us
        self.path = Path(path)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        """The request is in force (the device is open with our value written)."""
        return self._fd is not None

    def acquire(self) -> bool:
        """Open the device and write the value; False (and a warning) when not allowed."""
        if self._fd is not None:
            return True
        try:
            fd = os.open(self.path, os.O_WRONLY)
        except OSError as exc:
            log.warning("cpu_latency_not_applied", device=str(self.path), us=self.us,
                        error=exc.strerror or str(exc),
                        hint="needs write access to the device (root, or the udev rule in "
                        "systemd/mmctl.service)")
            return False
        try:
            os.write(fd, struct.pack("=i", self.us))
        except OSError as exc:
            os.close(fd)
            log.warning("cpu_latency_not_applied", device=str(self.path), us=self.us,
                        error=exc.strerror or str(exc))
            return False
        self._fd = fd
        log.info("cpu_latency_requested", device=str(self.path), us=self.us)
        return True

    def release(self) -> None:
        """Withdraw the request (safe to call twice)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    def __enter__(self) -> Self:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def current_limit(path: Path = DEVICE) -> int | None:
    """The latency limit in force [us] (the smallest of all requests), or None when the
    device cannot be read."""
    try:
        with open(path, "rb") as f:
            data = f.read(4)
    except OSError:
        return None
    return struct.unpack("=i", data)[0] if len(data) == 4 else None
