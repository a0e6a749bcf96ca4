"""A simulated ATI Ethernet F/T sensor: an RDT server on UDP (loopback in tests).

Speaks the protocol documented in :mod:`mmctl.transports.sensor.rdt` with its own
encoding: 8-byte requests ``0x1234, command, count`` (0x0002 start streaming ``count``
records, 0 = forever; 0x0000 stop; 0x0042 bias), 36-byte records ``rdt_sequence,
ft_sequence, status, 6 x int32 counts`` streamed at ``rate_hz`` to the address that
asked.  ``rdt_sequence`` restarts at 1 with every start command; ``ft_sequence`` counts
the records sent since power-up (the fake's internal sample counter).  Counts =
round(wrench * counts-per-unit) - bias counts.  When the thread is late it skips periods
instead of bursting (no sequence gap from that).

:meth:`reboot` is the device's power cycle: streaming stops and stays stopped until a
new start request (the device does not remember its client), both sequences restart,
the bias is cleared, and for ``down_for`` seconds the device is booting and ignores
every request.  Counters for tests: ``starts`` (start requests obeyed), ``reboots``,
``ignored_while_down``.

Fault injection (plain attributes read by the thread): ``status`` (sent in every
record), ``silent`` (send nothing, sequence frozen), ``garbage`` (13-byte datagrams
instead of records), ``drop`` (set of RDT sequence numbers never sent), ``swap`` (set of
sequence numbers ``s`` sent after ``s + 1``).

Usage::

    with FakeRdtServer(ConstantWrench([0, 0, 10, 0, 0, 0]), port=0) as fake:
        host, port = fake.address
"""

from __future__ import annotations

import math
import select
import socket
import struct
import threading
import time
from types import TracebackType
from typing import TYPE_CHECKING

import numpy as np
import structlog

from mmctl.sim.wrench_source import WrenchSource, as_wrench6

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self

log = structlog.get_logger("mmctl.sim.fake_rdt")

STATUS_ERROR = 0x80000000
STATUS_SATURATION = 0x00020000
_REQUEST = struct.Struct(">HHI")
_RECORD = struct.Struct(">III6i")


class FakeRdtServer:
    """The sensor end of the RDT link (see module doc); start()/stop() or ``with``.

    source: what the sensor measures; host/port: where to listen (port 0 = ephemeral,
    read :attr:`address` after start); rate_hz: record rate [Hz]; counts_per_force
    [counts/N], counts_per_torque [counts/(N m)].
    """

    def __init__(
        self,
        source: WrenchSource,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        rate_hz: float = 1000.0,
        counts_per_force: float = 1e6,
        counts_per_torque: float = 1e6,
    ) -> None:
        self.source = source
        self.host = host
        self.port = port
        self.period = 1.0 / rate_hz
        self._cpu = np.array((counts_per_force,) * 3 + (counts_per_torque,) * 3, dtype=np.float64)
        self.status = 0
        self.silent = False
        self.garbage = False
        self.drop: set[int] = set()
        self.swap: set[int] = set()
        self.records_sent = 0
        self.bias_commands = 0
        self.bad_requests = 0
        self.starts = 0
        self.reboots = 0
        self.ignored_while_down = 0
        self._lock = threading.Lock()  # the thread's state against reboot()
        self._down_until = 0.0
        self.error: BaseException | None = None
        self._bias = np.zeros(6, dtype=np.int64)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._client: tuple[str, int] | None = None
        self._remaining: int | None = None
        self._seq = 0
        self._ft_seq = 0
        self._held: bytes | None = None
        self._t0 = 0.0

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) actually bound (valid after :meth:`start`)."""
        return self.host, self.port

    def counts_for(self, wrench: np.ndarray) -> np.ndarray:
        """The int32 counts (6,) this sensor sends for ``wrench`` (before bias)."""
        w = as_wrench6(wrench)
        if not np.all(np.isfinite(w)):
            raise ValueError(f"the simulated sensor cannot measure a non-finite wrench {w}")
        return np.clip(np.rint(w * self._cpu), -(2**31), 2**31 - 1).astype(np.int64)

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> Self:
        """Bind the socket and start serving."""
        if self._thread is not None:
            return self
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((self.host, self.port))
        sock.setblocking(False)
        self.host, self.port = sock.getsockname()[:2]
        self._sock = sock
        self._stop.clear()
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, name=f"fake-rdt-{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving, close the socket; re-raise an error the thread met.  Idempotent."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=5.0)
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        self.check()

    def check(self) -> None:
        """Re-raise the exception that ended the thread, if any."""
        if self.error is not None:
            raise RuntimeError(f"fake RDT server failed: {self.error!r}") from self.error

    def reboot(self, down_for: float = 0.0) -> None:
        """Power-cycle the sensor (see module doc): from now on nothing is streamed until
        a start request arrives after ``down_for`` seconds [s]."""
        with self._lock:
            self._client = None
            self._remaining = None
            self._seq = 0
            self._ft_seq = 0
            self._held = None
            self._bias = np.zeros(6, dtype=np.int64)
            self._down_until = time.monotonic() + down_for
            self.reboots += 1
        log.info("fake_rdt_rebooted", port=self.port, down_for=down_for)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    # -- the thread --------------------------------------------------------------------

    def _run(self) -> None:
        sock = self._sock
        assert sock is not None
        next_t = time.monotonic()
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                timeout = max(0.0, next_t - now) if self._client is not None else 0.05
                readable, _, _ = select.select([sock], [], [], min(timeout, 0.05))
                with self._lock:
                    if readable:
                        next_t = self._serve_requests(sock, next_t)
                    now = time.monotonic()
                    if self._client is not None and now >= next_t:
                        next_t += self.period * (math.floor((now - next_t) / self.period) + 1)
                        self._emit(sock)
        except Exception as exc:  # noqa: BLE001 - stored, re-raised by stop()/check()
            self.error = exc
            log.error("fake_rdt_failed", port=self.port, error=repr(exc))

    def _serve_requests(self, sock: socket.socket, next_t: float) -> float:
        while True:
            try:
                data, addr = sock.recvfrom(64)
            except BlockingIOError:
                return next_t
            if time.monotonic() < self._down_until:  # booting: nothing listens yet
                self.ignored_while_down += 1
                continue
            if len(data) != _REQUEST.size:
                self.bad_requests += 1
                continue
            header, command, count = _REQUEST.unpack(data)
            if header != 0x1234:
                self.bad_requests += 1
            elif command == 0x0002:
                self.starts += 1
                self._client = addr
                self._remaining = count or None
                self._seq = 0
                self._held = None
                next_t = time.monotonic()
            elif command == 0x0000:
                self._client = None
            elif command == 0x0042:
                self.bias_commands += 1
                self._bias = self.counts_for(self._measure())
            else:
                self.bad_requests += 1

    def _measure(self) -> np.ndarray:
        return self.source.wrench(time.monotonic() - self._t0)

    def _emit(self, sock: socket.socket) -> None:
        if self.silent:
            return
        self._ft_seq = (self._ft_seq + 1) & 0xFFFFFFFF
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        seq = self._seq
        client = self._client
        assert client is not None
        if self._remaining is not None:
            self._remaining -= 1
            if self._remaining <= 0:
                self._client = None
        if seq in self.drop:
            return
        if self.garbage:
            sock.sendto(b"\x12\x34" + bytes(11), client)
            return
        counts = np.clip(self.counts_for(self._measure()) - self._bias, -(2**31), 2**31 - 1)
        record = _RECORD.pack(seq, self._ft_seq, self.status & 0xFFFFFFFF, *counts.tolist())
        if seq in self.swap:
            self._held = record
            return
        sock.sendto(record, client)
        self.records_sent += 1
        if self._held is not None:
            sock.sendto(self._held, client)
            self.records_sent += 1
            self._held = None
