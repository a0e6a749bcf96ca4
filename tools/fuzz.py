#!/usr/bin/env python3
"""Fuzz every decoder and parser with random, mutated and valid-then-mutated inputs.

    .venv/bin/python tools/fuzz.py [--inputs N] [--seed S] [--json]
        [--targets NAME ...] [--jobs J] [--list]

Each target is fed ``N x scale`` inputs (the scale is 1 for the decoders; the targets
that go through a real socket or re-connect a real client take fewer, see ``--list``) in
a process of its own, ``--jobs`` processes at a time.  Per target it reports:

* ``inputs``: how many inputs were fed;
* ``crashes``: exceptions outside the module's documented errors (each target names
  them: e.g. ``ProtocolError`` for a decoder, ``SafetyFault`` / ``TransportError`` for
  a device client, ``ConfigError`` for the config loader, none at all for the control
  socket's dispatcher, which must always reply);
* ``non_finite``: NaN or inf in an output (a wrench, an odometry, a decoded value);
* ``invariant``: a property the module documents broken (a negative counter, a valid
  packet that does not decode back, no reply on the control socket, a loaded config
  whose timeout Python refuses: ``OverflowError``);
* ``slowest``: the slowest single call and its input.

The first failures of each kind are listed with their input (``repr``, cut at 300
characters) and the place that raised.  The exit status is 1 when any target failed.
Progress goes to stderr every few seconds.  Every input comes from ``random.Random``
seeded from ``--seed`` and the target's name: a run is reproducible, except for the
stateful clients, whose timing (time-outs, staleness) depends on the machine.

Targets (the module under test in brackets):

========================  ===========================================================
``can_frames``            gauge, matrix-row, counts and unit frames through the
                          decoders, the status check and the conversion [can_ft]
``can_client``            the real ``CanForceSensor`` (connect, read, request_next)
                          over python-can's in-process ``virtual`` bus, a peer
                          answering every request with fuzzed frames [can_ft]
``rdt_records``           36-byte records (and other lengths) through
                          ``decode_record`` and the client's conversion [rdt]
``rdt_sequence``          sequence-number streams (in order, gaps, wraps, restarts,
                          repeats, random) through ``SequenceTracker`` [rdt]
``serial_packets``        COBS frames and packets through ``cobs_decode``,
                          ``decode_packet`` and the payload decoders [serial_protocol]
``serial_stream``         byte streams cut at random places through
                          ``FrameDecoder.feed`` [serial_protocol]
``serial_base``           the real ``SerialBase`` (connect, enable, send_twist,
                          read_odometry) against a fake port answering like the
                          bridge, its bytes fuzzed [serial_base]
``ipc_dispatch``          request lines through ``ControlServer._dispatch`` with a
                          handler that accepts anything [ipc]
``ipc_socket``            the same lines through a real ``ControlServer`` on a Unix
                          socket: every line must get a reply [ipc]
``config_values``         mutated configuration mappings through
                          ``config_from_dict`` [config]
``config_yaml``           YAML text (mutated valid configs, random YAML) through
                          ``load_config`` [config]
========================  ===========================================================
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import re
import socket
import struct
import sys
import tempfile
import threading
import time
import traceback
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

#: failures of each kind kept with their input
KEEP = 5
#: characters of an input's repr kept in the report
REPR = 300
PROGRESS_EVERY = 5.0  # s


class Invariant(Exception):
    """A documented property of the module does not hold for this input."""


# -- mutation ---------------------------------------------------------------------------

_INTERESTING = (0x00, 0x01, 0x02, 0x7F, 0x80, 0xFE, 0xFF)


def rand_bytes(rng: random.Random, n: int) -> bytes:
    return rng.getrandbits(8 * n).to_bytes(n, "little") if n else b""


def mutate(rng: random.Random, data: bytes, max_ops: int = 4) -> bytes:
    """A few byte-level mutations: bit flips, interesting bytes, inserts, deletes,
    truncation, duplicated or random slices."""
    b = bytearray(data)
    for _ in range(rng.randint(1, max_ops)):
        op = rng.randrange(8)
        n = len(b)
        if op == 0 and n:
            i = rng.randrange(n)
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and n:
            b[rng.randrange(n)] = rng.choice(_INTERESTING)
        elif op == 2 and n:
            b[rng.randrange(n)] = rng.randrange(256)
        elif op == 3:
            i = rng.randint(0, n)
            b[i:i] = rand_bytes(rng, rng.randint(1, 8))
        elif op == 4 and n:
            i = rng.randrange(n)
            del b[i:i + rng.randint(1, 8)]
        elif op == 5 and n:
            del b[rng.randrange(n):]
        elif op == 6 and n:
            i = rng.randrange(n)
            j = rng.randint(i, min(n, i + 16))
            k = rng.randint(0, n)
            b[k:k] = b[i:j]
        else:
            b += rand_bytes(rng, rng.randint(1, 8))
    return bytes(b)


def check_finite(values: Any, what: str = "output") -> None:
    """Raise ``FloatingPointError`` naming the first non-finite value in ``values``
    (floats, arrays, nested tuples/lists/dicts)."""
    if isinstance(values, float):
        if not math.isfinite(values):
            raise FloatingPointError(f"{what} = {values!r}")
    elif isinstance(values, np.ndarray):
        if values.dtype.kind in "fc" and not np.all(np.isfinite(values)):
            raise FloatingPointError(f"{what} = {values!r}")
    elif isinstance(values, dict):
        for k, v in values.items():
            check_finite(v, f"{what}.{k}")
    elif isinstance(values, (tuple, list)):
        for i, v in enumerate(values):
            check_finite(v, f"{what}[{i}]")


# -- the target interface ---------------------------------------------------------------


class Target:
    """One decoder or parser under fuzz.

    ``generate(rng)`` makes an input, ``feed(x)`` runs it and returns the outputs to
    check for NaN/inf (or raises: one of ``documented`` is fine, :class:`Invariant` is a
    broken property, anything else a crash).
    """

    name = ""
    module = ""
    scale = 1.0
    documented: tuple[type[BaseException], ...] = ()

    def setup(self) -> None:
        """Open what the target needs (a bus, a socket, a temp dir)."""

    def teardown(self) -> None:
        """Release it."""

    def generate(self, rng: random.Random) -> Any:
        raise NotImplementedError

    def feed(self, x: Any) -> Any:
        raise NotImplementedError

    def describe(self, x: Any) -> str:
        text = repr(x)
        return text if len(text) <= REPR else text[:REPR] + f"... ({len(text)} chars)"


@dataclass
class Problem:
    kind: str  # crash | non_finite | invariant
    error: str
    where: str
    input: str


def run_one(target: Target, x: Any) -> Problem | None:
    """Feed one input; the problem it shows, or None."""
    try:
        out = target.feed(x)
        check_finite(out)
    except target.documented:
        return None
    except FloatingPointError as exc:
        return Problem("non_finite", str(exc), "", target.describe(x))
    except Invariant as exc:
        return Problem("invariant", str(exc), "", target.describe(x))
    except Exception as exc:  # noqa: BLE001 -- that is what we are looking for
        return Problem("crash", f"{type(exc).__name__}: {str(exc)[:200]}", _where(exc),
                       target.describe(x))
    return None


def _where(exc: BaseException) -> str:
    """The innermost frame in mmctl's code (else the innermost one) of a traceback."""
    frames = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in frames if "/mmctl/" in f.filename]
    f = (ours or frames or [None])[-1]
    if f is None:
        return "?"
    return f"{f.filename.split('/src/')[-1]}:{f.lineno} ({f.name})"


@dataclass
class Result:
    target: str
    module: str
    inputs: int = 0
    crashes: int = 0
    non_finite: int = 0
    invariant: int = 0
    tool_errors: int = 0  # this tool's own generators failed (a bug here, not in mmctl)
    seconds: float = 0.0
    slowest_s: float = 0.0
    slowest_input: str = ""
    distinct: dict[str, int] = field(default_factory=dict)  # "kind: error @ where" -> count
    examples: list[dict[str, str]] = field(default_factory=list)

    @property
    def failures(self) -> int:
        return self.crashes + self.non_finite + self.invariant + self.tool_errors


def fuzz_target(target: Target, inputs: int, seed: int, progress: bool = True) -> Result:
    rng = random.Random(f"{seed}:{target.name}")
    res = Result(target.name, target.module)
    kept: dict[str, int] = {}
    target.setup()
    t_start = time.perf_counter()
    next_report = t_start + PROGRESS_EVERY
    perf = time.perf_counter
    try:
        for i in range(inputs):
            try:
                x = target.generate(rng)
            except Exception as exc:  # noqa: BLE001 -- a bug of this tool: count it, go on
                res.tool_errors += 1
                res.distinct[f"tool: generate() raised {exc!r}"] = 1
                continue
            t0 = perf()
            problem = run_one(target, x)
            dt = perf() - t0
            if dt > res.slowest_s:
                res.slowest_s = dt
                res.slowest_input = target.describe(x)
            if problem is not None:
                setattr(res, _COUNTER[problem.kind], getattr(res, _COUNTER[problem.kind]) + 1)
                key = _group(problem)
                res.distinct[key] = res.distinct.get(key, 0) + 1
                if kept.get(problem.kind, 0) < KEEP:
                    kept[problem.kind] = kept.get(problem.kind, 0) + 1
                    res.examples.append(problem.__dict__.copy())
            res.inputs = i + 1
            if progress and t0 > next_report:
                next_report = t0 + PROGRESS_EVERY
                print(f"[{target.name}] {res.inputs}/{inputs} inputs, {res.failures} failures, "
                      f"{t0 - t_start:.0f} s", file=sys.stderr, flush=True)
    finally:
        target.teardown()
    res.seconds = time.perf_counter() - t_start
    return res


def _group(p: Problem) -> str:
    """The kind of a problem: a crash by exception type and place, other problems by
    their message with the numbers taken out."""
    if p.kind == "crash":
        return f"crash: {p.error.split(':')[0]} @ {p.where}"
    return f"{p.kind}: " + re.sub(r"(0x[0-9a-fA-F]+|[-+]?\d[\d.e+-]*)", "#", p.error)[:100]


_COUNTER = {"crash": "crashes", "non_finite": "non_finite", "invariant": "invariant"}


# -- CAN F/T ----------------------------------------------------------------------------

def _can() -> Any:
    from mmctl.transports.sensor import can_ft
    return can_ft


def _f32(rng: random.Random) -> float:
    r = rng.random()
    if r < 0.05:
        return rng.choice((math.inf, -math.inf, math.nan, 3.4e38, -3.4e38, 1e-45, 0.0))
    if r < 0.1:
        return struct.unpack(">f", rand_bytes(rng, 4))[0]  # type: ignore[no-any-return]
    return rng.uniform(-10.0, 10.0)


def _gauge(rng: random.Random) -> int:
    r = rng.random()
    if r < 0.05:
        return rng.choice((-32768, 32767, -32767, 32766, 0))
    return rng.randint(-32768, 32767)


class CanFrames(Target):
    """Gauge pairs, matrix rows, counts and units through the decoders, the status check
    and ``conversion_matrix @ gauges``."""

    name = "can_frames"
    module = "mmctl.transports.sensor.can_ft"

    def setup(self) -> None:
        from mmctl.errors import ProtocolError, SafetyFault
        self.ft = _can()
        self.documented = (ProtocolError, SafetyFault)
        rng = random.Random(0)
        self.conv = self.ft.conversion_matrix(
            [[rng.uniform(-2, 2) for _ in range(6)] for _ in range(6)], 40, 2000)

    def _valid(self, rng: random.Random, kind: str) -> list[bytes]:
        if kind == "gauges":
            status = 0 if rng.random() < 0.7 else rng.getrandbits(16)
            g = [_gauge(rng) for _ in range(6)]
            return [struct.pack(">Hhhh", status, g[0], g[2], g[4]),
                    struct.pack(">hhh", g[1], g[3], g[5]) + rand_bytes(rng, rng.choice((0, 0, 1, 2)))]
        if kind == "matrix":
            return [struct.pack(">ff", _f32(rng), _f32(rng)) for _ in range(3)]
        if kind == "counts":
            return [struct.pack(">II", rng.choice((0, 1, 40, 2000, 1_000_000, 2**32 - 1,
                                                   rng.getrandbits(32))),
                                rng.choice((0, 1, 2000, 2**32 - 1, rng.getrandbits(32))))]
        return [bytes((rng.choice((2, 2, 3, 0, 255, rng.randrange(256))),
                       rng.choice((3, 3, 2, 0, 255, rng.randrange(256)))))]

    def generate(self, rng: random.Random) -> tuple[str, list[bytes]]:
        kind = rng.choice(("gauges", "gauges", "matrix", "counts", "units"))
        mode = rng.random()
        if mode < 0.2:  # random frames
            n = {"gauges": 2, "matrix": 3}.get(kind, 1)
            if rng.random() < 0.2:
                n = rng.randint(0, 4)
            return kind, [rand_bytes(rng, rng.randint(0, 9)) for _ in range(n)]
        frames = self._valid(rng, kind)
        if mode < 0.6:  # valid then mutated
            i = rng.randrange(len(frames))
            frames[i] = mutate(rng, frames[i], 2)
        return kind, frames

    def feed(self, x: tuple[str, list[bytes]]) -> Any:
        kind, frames = x
        ft = self.ft
        if kind == "gauges":
            if len(frames) != 2:
                raise ft.ProtocolError("a gauge reply is two frames")
            status, gauges = ft.decode_gauges(frames[0], frames[1])
            if not 0 <= status <= 0xFFFF:
                raise Invariant(f"status word {status} outside uint16")
            ft.status_bit_names(status)
            ft.check_status(status, gauges)
            return (gauges, self.conv @ gauges)
        if kind == "matrix":
            row = ft.decode_matrix_row(frames)
            conv = ft.conversion_matrix([row] * 6, 1, 1)
            return (row, conv, conv @ np.full(6, 32767.0))
        if kind == "counts":
            if len(frames) != 1:
                raise ft.ProtocolError("one frame")
            cpf, cpt = ft.decode_counts(frames[0])
            conv = ft.conversion_matrix(np.eye(6), cpf, cpt)
            return (conv,)
        if len(frames) != 1:
            raise ft.ProtocolError("one frame")
        ft.decode_units(frames[0])
        return None


class _CanPeer:
    """The sensor's side of the virtual bus: answers each request with valid frames,
    then applies the input's fuzz operations to them (synchronously: the client's
    ``_send`` calls :meth:`answer`, so there is no thread and no timing between them)."""

    def __init__(self, channel: str, base_id: int) -> None:
        import can
        self.can = can
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.base = base_id
        self.rng = random.Random(0)
        self.ops: list[str] = []
        self.sent: list[tuple[int, str]] = []
        r = random.Random(1)
        self.matrix = [[r.uniform(-2.0, 2.0) for _ in range(6)] for _ in range(6)]

    def fid(self, op: int) -> int:
        return ((self.base << 4) | op) & 0x7FF

    def valid_replies(self, msg: Any) -> list[tuple[int, bytes]]:
        op = msg.arbitration_id & 0xF
        rng = self.rng
        if op == 0x8:
            return [(msg.arbitration_id, bytes((2, 3)))]
        if op == 0x7:
            return [(msg.arbitration_id, struct.pack(">II", 40, 2000))]
        if op == 0x2 and len(msg.data) == 1:
            r = msg.data[0] % 6
            c = self.matrix[r]
            return [(self.fid(2 + k), struct.pack(">ff", c[2 * k], c[2 * k + 1]))
                    for k in range(3)]
        if op == 0x0 and len(msg.data) == 0:
            g = [rng.randint(-2000, 2000) for _ in range(6)]
            return [(self.fid(0), struct.pack(">Hhhh", 0, g[0], g[2], g[4])),
                    (self.fid(1), struct.pack(">hhh", g[1], g[3], g[5]))]
        return []

    def fuzz(self, frames: list[tuple[int, bytes]]) -> list[tuple[int, bytes]]:
        rng = self.rng
        out = list(frames)
        for op in self.ops:
            if op == "drop" and out:
                del out[rng.randrange(len(out))]
            elif op == "dup" and out:
                out.insert(rng.randint(0, len(out)), out[rng.randrange(len(out))])
            elif op == "swap" and len(out) > 1:
                i = rng.randrange(len(out) - 1)
                out[i], out[i + 1] = out[i + 1], out[i]
            elif op == "mutate" and out:
                i = rng.randrange(len(out))
                aid, data = out[i]
                out[i] = (aid, mutate(rng, data, 2)[:8])
            elif op == "status" and out:
                i = rng.randrange(len(out))
                aid, data = out[i]
                if aid == self.fid(0) and len(data) == 8:
                    out[i] = (aid, struct.pack(">H", 1 << rng.randrange(16)) + data[2:])
            elif op == "rail" and out:
                i = rng.randrange(len(out))
                aid, data = out[i]
                if len(data) >= 6:
                    k = rng.randrange(len(data) // 2) * 2
                    out[i] = (aid, data[:k] + struct.pack(">h", rng.choice((-32768, 32767)))
                              + data[k + 2:])
            elif op == "stray":
                out.insert(rng.randint(0, len(out)),
                           (self.fid(rng.randrange(16)), rand_bytes(rng, rng.randint(0, 8))))
            elif op == "id" and out:
                i = rng.randrange(len(out))
                aid, data = out[i]
                out[i] = (self.fid(rng.randrange(16)), data)
            elif op == "silent":
                out = []
        return out

    def odd_frames(self) -> list[Any]:
        """Remote, extended-id and error frames on our ids (ops ``rtr``, ``ext``, ``err``)."""
        rng, msgs = self.rng, []
        for op in self.ops:
            aid = self.fid(rng.choice((0, 1, 2, 3, 4, 7, 8)))
            if op == "rtr":
                msgs.append(self.can.Message(arbitration_id=aid, is_remote_frame=True,
                                             dlc=rng.choice((0, 6, 8)), is_extended_id=False))
            elif op == "ext":
                msgs.append(self.can.Message(arbitration_id=aid, data=rand_bytes(rng, 8),
                                             is_extended_id=True))
            elif op == "err":
                msgs.append(self.can.Message(arbitration_id=aid, is_error_frame=True,
                                             is_extended_id=False))
        return msgs

    def answer(self) -> None:
        while True:
            msg = self.bus.recv(0.0)
            if msg is None:
                return
            for odd in self.odd_frames():
                self.sent.append((odd.arbitration_id, repr(odd)[:60]))
                self.bus.send(odd)
            for aid, data in self.fuzz(self.valid_replies(msg)):
                self.sent.append((aid, data.hex()))
                self.bus.send(self.can.Message(arbitration_id=aid, data=data,
                                               is_extended_id=False))


_CAN_OPS = ("drop", "dup", "swap", "mutate", "status", "rail", "stray", "id", "silent", "rtr",
            "ext", "err")


class CanClient(Target):
    """The real client over the virtual bus.  An input: an action (``connect``, ``read``
    or ``read+request_next``) and the fuzz operations the peer applies to its answers."""

    name = "can_client"
    module = "mmctl.transports.sensor.can_ft"
    scale = 0.2

    def setup(self) -> None:
        import dataclasses

        from mmctl.config import default_config
        from mmctl.errors import SafetyFault, TransportError
        self.documented = (TransportError, SafetyFault)
        ft = _can()
        channel = f"mmctl-fuzz-{os.getpid()}-{id(self)}"
        self.cfg = dataclasses.replace(default_config().sensor.can, interface="virtual",
                                       channel=channel, timeout=0.0005, connect_timeout=0.002)
        self.peer = _CanPeer(channel, self.cfg.base_id)
        peer = self.peer

        class Fuzzed(ft.CanForceSensor):  # type: ignore[name-defined,misc]
            def _send(self, msg: Any) -> None:
                super()._send(msg)
                peer.answer()

        self.cls = Fuzzed
        self.client: Any = None
        self.reads = 0

    def teardown(self) -> None:
        if self.client is not None:
            self.client.close()
        self.peer.bus.shutdown()

    def generate(self, rng: random.Random) -> tuple[str, int, tuple[str, ...]]:
        action = rng.choice(("read", "read", "read", "read+request_next", "connect"))
        ops: tuple[str, ...] = ()
        if rng.random() < 0.4:
            ops = tuple(rng.choice(_CAN_OPS) for _ in range(rng.randint(1, 3)))
            if "silent" in ops and rng.random() < 0.8:  # silence costs a time-out: rarer
                ops = tuple(o for o in ops if o != "silent")
        return action, rng.getrandbits(32), ops

    def describe(self, x: Any) -> str:
        return super().describe((*x, self.peer.sent[:12]))

    def feed(self, x: tuple[str, int, tuple[str, ...]]) -> Any:
        action, seed, ops = x
        peer = self.peer
        peer.rng.seed(seed)
        peer.sent = []
        if action == "connect" or self.client is None or self.client._bus is None:
            if self.client is not None:
                self.client.close()
            self.client = self.cls(self.cfg, stale_timeout=0.05)
            peer.ops = list(ops) if action == "connect" else []
            self.client.connect()
            return None
        peer.ops = list(ops)
        w = self.client.read()
        if action == "read+request_next":
            self.client.request_next()
        s = self.client.stats()
        if min(s) < 0:
            raise Invariant(f"negative counter in {s}")
        return (w.force, w.torque)


# -- RDT --------------------------------------------------------------------------------

def _rdt() -> Any:
    from mmctl.transports.sensor import rdt
    return rdt


class RdtRecords(Target):
    """Datagrams through ``decode_record`` and the conversion ``RdtForceSensor`` applies
    (counts x 1/counts-per-unit, the status masks)."""

    name = "rdt_records"
    module = "mmctl.transports.sensor.rdt"

    def setup(self) -> None:
        from mmctl.config import default_config
        from mmctl.errors import ProtocolError, SafetyFault
        self.rdt = _rdt()
        self.documented = (ProtocolError, SafetyFault)
        self.cfg = default_config().sensor.rdt
        self.per_count = 1.0 / np.array((self.cfg.counts_per_force,) * 3
                                        + (self.cfg.counts_per_torque,) * 3)

    def generate(self, rng: random.Random) -> bytes:
        mode = rng.random()
        if mode < 0.15:
            return rand_bytes(rng, rng.choice((0, 8, 35, 36, 36, 37, 72, rng.randint(0, 80))))
        counts = [rng.choice((0, 2**31 - 1, -2**31, rng.randint(-2**31, 2**31 - 1),
                              rng.randint(-10**7, 10**7))) for _ in range(6)]
        status = rng.choice((0, 0, 0, 1 << rng.randrange(32), rng.getrandbits(32)))
        data = self.rdt.RECORD.pack(rng.getrandbits(32), rng.getrandbits(32), status, *counts)
        if mode < 0.6:
            data = mutate(rng, data, 3)
        return bytes(data)

    def feed(self, data: bytes) -> Any:
        rec = self.rdt.decode_record(data)
        if not (0 <= rec.rdt_sequence < 2**32 and 0 <= rec.status < 2**32):
            raise Invariant(f"header field outside uint32: {rec}")
        if rec.status & self.cfg.status_saturation_mask or rec.status & self.cfg.status_error_mask:
            return None  # the client raises SafetyFault here
        return np.array(rec.counts, dtype=np.float64) * self.per_count


class RdtSequence(Target):
    """Streams of RDT sequence numbers through a fresh ``SequenceTracker``."""

    name = "rdt_sequence"
    module = "mmctl.transports.sensor.rdt"

    def setup(self) -> None:
        self.rdt = _rdt()

    def generate(self, rng: random.Random) -> list[int]:
        n = rng.randint(1, 40)
        start = rng.choice((0, 1, 2**32 - 1, 2**32 - rng.randint(1, 50), 2**31,
                            rng.getrandbits(32)))
        seqs = [(start + i) % 2**32 for i in range(n)]
        for _ in range(rng.randint(0, 4)):
            op = rng.randrange(7)
            i = rng.randrange(n)
            if op == 0:  # gap
                jump = rng.choice((2, 3, 255, 256, 257, 1000, 2**31 - 1, 2**31, 2**31 + 1))
                seqs[i:] = [(s + jump) % 2**32 for s in seqs[i:]]
            elif op == 1:  # restart
                base = rng.choice((0, 1, rng.getrandbits(32)))
                seqs[i:] = [(base + k) % 2**32 for k in range(len(seqs) - i)]
            elif op == 2 and i + 1 < len(seqs):  # swap
                seqs[i], seqs[i + 1] = seqs[i + 1], seqs[i]
            elif op == 3:  # repeat
                seqs.insert(i, seqs[i])
            elif op == 4:  # random
                seqs[i] = rng.getrandbits(32)
            elif op == 5:  # late
                seqs.insert(i, (seqs[i] - rng.randint(1, 300)) % 2**32)
            else:
                rng.shuffle(seqs)
        return seqs

    def feed(self, seqs: list[int]) -> Any:
        tracker = self.rdt.SequenceTracker()
        for s in seqs:
            newer = tracker.observe(s)
            if not isinstance(newer, bool):
                raise Invariant(f"observe({s}) returned {newer!r}, not a bool")
            if tracker.lost < 0 or tracker.out_of_order < 0:
                raise Invariant(f"negative counter after {s}: lost {tracker.lost}, "
                                f"out_of_order {tracker.out_of_order}")
        return None


# -- serial bridge ----------------------------------------------------------------------

def _sp() -> Any:
    from mmctl.transports.base import serial_protocol
    return serial_protocol


def _payload(rng: random.Random, sp: Any, msg_type: int) -> bytes:
    if msg_type == sp.MsgType.STATE:
        return sp.pack_state(sp.WheelState(
            rng.getrandbits(32), rng.getrandbits(16), rng.getrandbits(8), rng.getrandbits(8),
            tuple(rng.getrandbits(8) for _ in range(4)),
            tuple(rng.randint(-2**31, 2**31 - 1) for _ in range(4)),
            tuple(rng.randint(-2**31, 2**31 - 1) for _ in range(4))))
    if msg_type == sp.MsgType.FAULT:
        return sp.pack_fault(rng.getrandbits(16), rng.choice((0, 1, 2, 3, 0xFF, rng.getrandbits(8))))
    if msg_type == sp.MsgType.WHEEL_CMD:
        return sp.pack_wheel_cmd([rng.uniform(-50, 50) for _ in range(4)])
    return rand_bytes(rng, rng.choice((0, 0, 1, rng.randint(0, 255))))


_TYPES = (0x01, 0x02, 0x03, 0x04, 0x81, 0x82)


class SerialPackets(Target):
    """COBS frames through ``cobs_decode`` -> ``decode_packet`` -> the payload decoder of
    the frame's type; a valid frame must decode back to what was encoded."""

    name = "serial_packets"
    module = "mmctl.transports.base.serial_protocol"

    def setup(self) -> None:
        self.sp = _sp()
        self.documented = (self.sp.ProtocolError,)

    def generate(self, rng: random.Random) -> tuple[bytes, tuple[int, int, bytes] | None]:
        sp = self.sp
        mode = rng.random()
        if mode < 0.15:
            return rand_bytes(rng, rng.randint(0, 300)), None
        t = rng.choice(_TYPES) if rng.random() < 0.95 else rng.getrandbits(8)
        seq = rng.getrandbits(16)
        payload = _payload(rng, sp, t)
        wire = sp.cobs_encode(sp.encode_packet(seq, t, payload))
        if mode < 0.6:
            return mutate(rng, wire), None
        return wire, (seq, t, payload)

    def feed(self, x: tuple[bytes, tuple[int, int, bytes] | None]) -> Any:
        sp = self.sp
        wire, expect = x
        frame = sp.decode_packet(sp.cobs_decode(wire))
        if expect is not None and tuple(frame) != expect:
            raise Invariant(f"decoded {frame} from a frame encoding {expect}")
        if frame.type == sp.MsgType.STATE:
            s = sp.unpack_state(frame.payload)
            return (s.time_us / 1e6, np.array(s.position) / sp.ANGLE_SCALE,
                    np.array(s.velocity) / sp.SPEED_SCALE)
        if frame.type == sp.MsgType.FAULT:
            sp.unpack_fault(frame.payload)
            return None
        if frame.type == sp.MsgType.WHEEL_CMD:
            return sp.unpack_wheel_cmd(frame.payload)
        return None


class SerialStream(Target):
    """A stream of frames (valid, mutated, garbage between them) cut into random chunks,
    through one ``FrameDecoder``."""

    name = "serial_stream"
    module = "mmctl.transports.base.serial_protocol"

    def setup(self) -> None:
        self.sp = _sp()
        self.documented = ()

    def generate(self, rng: random.Random) -> tuple[list[bytes], bool]:
        sp = self.sp
        stream = bytearray()
        seq = rng.getrandbits(16)
        for _ in range(rng.randint(1, 6)):
            r = rng.random()
            if r < 0.1:
                stream += rand_bytes(rng, rng.randint(1, 40))
                continue
            seq = (seq + rng.choice((1, 1, 1, 2, 0, -1, 40000, rng.getrandbits(16)))) & 0xFFFF
            t = rng.choice(_TYPES)
            frame = sp.encode_frame(seq, t, _payload(rng, sp, t))
            if r < 0.35:
                frame = mutate(rng, frame, 2)
            elif r < 0.4:
                frame = frame.replace(b"\x00", b"")  # delimiters lost
            stream += frame
        if rng.random() < 0.02:
            stream += rand_bytes(rng, rng.randint(300, 2000)).replace(b"\x00", b"\x01")
        chunks = []
        i = 0
        while i < len(stream):
            j = i + rng.choice((1, 5, 16, 32, 64, len(stream), len(stream)))
            chunks.append(bytes(stream[i:j]))
            i = j
        return chunks, rng.random() < 0.5

    def feed(self, x: tuple[list[bytes], bool]) -> Any:
        chunks, resync_enable = x
        sp = self.sp
        dec = sp.FrameDecoder(frozenset({sp.MsgType.ENABLE}) if resync_enable else frozenset())
        n = 0
        for chunk in chunks:
            frames = dec.feed(chunk)
            n += len(frames)
            for f in frames:
                if not (0 <= f.seq <= 0xFFFF and 0 <= f.type <= 0xFF and len(f.payload) <= 255):
                    raise Invariant(f"frame out of range: {f}")
            if len(dec._buf) > sp.MAX_FRAME + len(chunk):
                raise Invariant(f"decoder buffer grew to {len(dec._buf)} bytes")
        s = dec.stats
        if min(s.frames, s.crc_errors, s.malformed, s.out_of_sequence, s.lost,
               s.garbage_bytes) < 0 or s.frames != n:
            raise Invariant(f"counters {s} after {n} frames")
        return None


class _FakePort:
    """A pyserial-like port answering the host like the bridge: every HEARTBEAT, ENABLE,
    DISABLE and WHEEL_CMD gets a STATE; the bytes it queues go through the input's fuzz
    operations."""

    def __init__(self) -> None:
        sp = _sp()
        self.sp = sp
        self.dec = sp.FrameDecoder()
        self.rx = bytearray()
        self.seq = 0
        self.enabled = False
        self.pos = [0, 0, 0, 0]
        self.vel = [0, 0, 0, 0]
        self.rng = random.Random(0)
        self.ops: list[str] = []
        self.is_open = True

    @property
    def in_waiting(self) -> int:
        return len(self.rx)

    def read(self, n: int) -> bytes:
        out = bytes(self.rx[:n])
        del self.rx[:n]
        return out

    def close(self) -> None:
        self.is_open = False

    def write(self, data: bytes) -> int:
        sp = self.sp
        for f in self.dec.feed(data):
            if f.type == sp.MsgType.ENABLE:
                self.enabled = True
            elif f.type == sp.MsgType.DISABLE:
                self.enabled = False
            elif f.type == sp.MsgType.WHEEL_CMD:
                self.vel = [int(w * 1000) for w in sp.unpack_wheel_cmd(f.payload)]
                self.pos = [(p + v * 2 + 2**31) % 2**32 - 2**31 for p, v in zip(self.pos, self.vel)]
            self.queue(f.seq)
        return len(data)

    def queue(self, ack: int) -> None:
        sp, rng = self.sp, self.rng
        st = sp.Status.ENABLED if self.enabled else 0
        wheels = (st,) * 4
        pos, vel = tuple(self.pos), tuple(self.vel)
        frames: list[bytes] = []
        self.seq = (self.seq + 1) & 0xFFFF
        seq = self.seq
        msg_type = sp.MsgType.STATE
        for op in self.ops:
            if op == "fault_bits":
                st |= sp.Status.FAULT
            elif op == "wheel_bits":
                wheels = tuple(rng.getrandbits(8) for _ in range(4))
            elif op == "jump":
                pos = tuple(rng.randint(-2**31, 2**31 - 1) for _ in range(4))
            elif op == "velocity":
                vel = tuple(rng.randint(-2**31, 2**31 - 1) for _ in range(4))
            elif op == "seq":
                seq = rng.getrandbits(16)
            elif op == "fault_frame":
                frames.append(sp.encode_frame(seq, sp.MsgType.FAULT,
                                              sp.pack_fault(rng.getrandbits(16), rng.getrandbits(8))))
            elif op == "type":
                msg_type = rng.getrandbits(8)
        payload = sp.pack_state(sp.WheelState(int(time.monotonic() * 1e6), ack, 0, st, wheels,
                                              pos, vel))
        if msg_type != sp.MsgType.STATE:
            payload = _payload(rng, sp, msg_type)
        frames.append(sp.encode_frame(seq, msg_type, payload))
        data = b"".join(frames)
        for op in self.ops:
            if op == "mutate":
                data = mutate(rng, data, 3)
            elif op == "drop":
                data = b""
            elif op == "garbage":
                data = rand_bytes(rng, rng.randint(1, 64)) + data
            elif op == "cut":
                data = data[:rng.randint(0, len(data))]
        self.rx += data


_SERIAL_OPS = ("fault_bits", "wheel_bits", "jump", "velocity", "seq", "fault_frame", "type",
               "mutate", "drop", "garbage", "cut")


class SerialBaseClient(Target):
    """The real ``SerialBase`` on a fake port (``serial.serial_for_url`` returns it).  An
    input: an action (connect, enable, send_twist, read_odometry, check) and the fuzz
    operations applied to what the port answers."""

    name = "serial_base"
    module = "mmctl.transports.base.serial_base"
    scale = 0.2

    def setup(self) -> None:
        import serial

        from mmctl.config import config_from_dict
        from mmctl.errors import SafetyFault, TransportError
        from mmctl.transports.base import serial_base
        self.documented = (SafetyFault, TransportError)
        cfg = config_from_dict({"base": {"transport": "serial", "serial": {
            "timeout": 0.001, "link_timeout": 0.5}}})
        self.port = _FakePort()
        self._orig = serial.serial_for_url
        serial.serial_for_url = lambda *a, **k: self._new_port()
        self.base = serial_base.SerialBase(cfg.base, cfg.limits, port="fuzz://")

    def _new_port(self) -> _FakePort:
        ops, rng = self.port.ops, self.port.rng
        self.port = _FakePort()
        self.port.ops, self.port.rng = ops, rng
        return self.port

    def teardown(self) -> None:
        import serial
        self.base.close()
        serial.serial_for_url = self._orig

    def generate(self, rng: random.Random) -> tuple[str, int, tuple[str, ...], tuple[float, ...]]:
        action = rng.choice(("send_twist", "send_twist", "read_odometry", "check",
                             "drive_status", "enable", "connect"))
        ops: tuple[str, ...] = ()
        if rng.random() < 0.4:
            ops = tuple(rng.choice(_SERIAL_OPS) for _ in range(rng.randint(1, 3)))
        twist = tuple(rng.choice((0.0, rng.uniform(-2, 2), 1e300, -1e300, 1.7e308, -1e308,
                                   5e-324, math.nan, math.inf))
                      if rng.random() < 0.1 else rng.uniform(-1, 1) for _ in range(3))
        return action, rng.getrandbits(32), ops, twist

    def feed(self, x: tuple[str, int, tuple[str, ...], tuple[float, ...]]) -> Any:
        action, seed, ops, twist = x
        base = self.base
        self.port.rng.seed(seed)
        self.port.ops = list(ops)
        if action == "connect" or base._ser is None:
            base.close()
            base.connect()
            return None
        if action == "enable" or not base._enabled:
            base.enable()
            return None
        if action == "send_twist":
            t = base.send_twist(*twist)
            out: Any = tuple(t)
        elif action == "read_odometry":
            out = tuple(base.read_odometry())
        elif action == "check":
            base.check()
            out = None
        else:
            out = [d.state for d in base.drive_status()]
        s = base.stats
        if min(s.frames, s.crc_errors, s.malformed, s.out_of_sequence, s.lost) < 0:
            raise Invariant(f"negative counter in {s}")
        return out


# -- control socket ---------------------------------------------------------------------

def _json_value(rng: random.Random, depth: int = 0) -> Any:
    r = rng.random()
    if depth > 4 or r < 0.4:
        return rng.choice((None, True, False, 0, -1, 2**63, 10**40, 1.5, -0.0, math.nan,
                           math.inf, "", "x", "status", "é\u2028\ud800"[: rng.randint(0, 3)],
                           rng.random()))
    if r < 0.7:
        return [_json_value(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    return {rng.choice(("cmd", "timeout_s", "on", "duration", "mode", "x", "")):
            _json_value(rng, depth + 1) for _ in range(rng.randint(0, 4))}


_CMDS = ("status", "enable", "disable", "stop", "mode", "tare", "trial", "switch", "sim",
         "metrics", "")


def _request_line(rng: random.Random) -> bytes:
    """A request line without its newline: valid, valid-then-mutated, random JSON,
    deep nesting, random bytes."""
    r = rng.random()
    if r < 0.3:
        req: dict[str, Any] = {"cmd": rng.choice(_CMDS)}
        for _ in range(rng.randint(0, 3)):
            req[rng.choice(("timeout_s", "on", "duration", "mode", "strategy", "x"))] = \
                _json_value(rng, 2)
        line = json.dumps(req).encode()
        if rng.random() < 0.5:
            line = mutate(rng, line, 3)
    elif r < 0.6:
        line = json.dumps(_json_value(rng)).encode()
        if rng.random() < 0.3:
            line = mutate(rng, line, 2)
    elif r < 0.615:  # deep nesting: the issue's ~5 kB of '['
        depth = rng.choice((100, 999, 1000, 3000, 5000, 20000))
        opener, closer = rng.choice((("[", "]"), ('{"a":', "}"), ('{"cmd":"x","y":', "}")))
        line = (opener * depth + "0" + closer * depth * rng.choice((0, 1))).encode()
    elif r < 0.65:
        line = rng.choice((b"NaN", b"-Infinity", b"1e999", b'{"cmd": "status", "x": 1e999}',
                           b'{"cmd": "status", "x": NaN}', b"\xff\xfe", b'"\\ud800"',
                           b'{"cmd": "\\u0000"}', b"{" * 10, b"[]" * 1000))
    else:
        line = rand_bytes(rng, rng.randint(0, 120))
    return line.replace(b"\n", b" ")


class IpcDispatch(Target):
    """Request lines through ``ControlServer._dispatch``: it must always return a reply
    that is a dict with a bool ``ok`` and serialises as strict JSON."""

    name = "ipc_dispatch"
    module = "mmctl.runtime.ipc"

    def setup(self) -> None:
        from mmctl.runtime.ipc import ControlServer, Peer
        self.tmp = tempfile.TemporaryDirectory(prefix="mmctl-fuzz-")
        self.server = ControlServer(Path(self.tmp.name) / "never-opened.sock", _accept_anything)
        self.peer = Peer(os.getpid(), os.getuid(), os.getgid())

    def teardown(self) -> None:
        self.tmp.cleanup()

    def generate(self, rng: random.Random) -> bytes:
        return _request_line(rng)

    def feed(self, line: bytes) -> Any:
        reply = self.server._dispatch(line, self.peer)
        _check_reply(reply)
        return None


def _accept_anything(req: Any, peer: Any) -> Any:
    return {"cmd": req["cmd"], "keys": len(req)}


def _check_reply(reply: Any) -> None:
    if not isinstance(reply, dict) or not isinstance(reply.get("ok"), bool):
        raise Invariant(f"reply is not {{'ok': bool, ...}}: {reply!r:.200}")
    try:
        json.dumps(reply, allow_nan=False)
    except ValueError as exc:
        raise Invariant(f"reply is not strict JSON ({exc}): {reply!r:.200}") from None


class IpcSocket(Target):
    """Request lines through a real ``ControlServer`` on a Unix socket in a temp dir:
    every line gets one reply line (a line over ``MAX_LINE`` an error, then the server
    closes the connection), and the server keeps accepting."""

    name = "ipc_socket"
    module = "mmctl.runtime.ipc"
    scale = 0.02

    def setup(self) -> None:
        from mmctl.runtime.ipc import MAX_LINE, ControlServer
        self.max_line = MAX_LINE
        self.tmp = tempfile.TemporaryDirectory(prefix="mmctl-fuzz-")
        self.path = Path(self.tmp.name) / "fuzz.sock"
        self.server = ControlServer(self.path, _accept_anything)
        self.thread_errors: list[str] = []
        self._excepthook = threading.excepthook
        threading.excepthook = lambda a: self.thread_errors.append(
            f"{a.exc_type.__name__} in thread {a.thread.name if a.thread else '?'}")
        self.server.start()
        self.conn: socket.socket | None = None
        self.rfile: Any = None

    def teardown(self) -> None:
        self._disconnect()
        self.server.close()
        self.tmp.cleanup()
        threading.excepthook = self._excepthook

    def _disconnect(self) -> None:
        if self.conn is not None:
            self.rfile.close()
            self.conn.close()
            self.conn = self.rfile = None

    def generate(self, rng: random.Random) -> bytes:
        if rng.random() < 0.005:
            return b"x" * (self.max_line + rng.randint(0, 10))
        return _request_line(rng)

    def feed(self, line: bytes) -> Any:
        if self.conn is None:
            self.conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self.conn.settimeout(10.0)
            self.conn.connect(str(self.path))
            self.rfile = self.conn.makefile("rb")
        if not line.strip():
            line = b'{"cmd": "status"}'  # a blank line gets no reply: nothing to wait for
        try:
            self.conn.sendall(line + b"\n")
            reply = self.rfile.readline(self.max_line * 4)
        except TimeoutError:
            self._disconnect()
            raise Invariant("no reply within 10 s") from None
        except (BrokenPipeError, ConnectionResetError) as exc:
            self._disconnect()
            if len(line) + 1 > self.max_line:
                return None  # the server answered the first MAX_LINE bytes and closed
            raise Invariant(f"the server dropped the connection: {exc!r}") from None
        if not reply.endswith(b"\n"):
            self._disconnect()
            time.sleep(0.01)  # the server's thread reports its death
            died = f"; {self.thread_errors.pop()}" if self.thread_errors else ""
            raise Invariant(f"no complete reply line (got {reply[:80]!r}){died}")
        if len(line) + 1 > self.max_line:
            self._disconnect()  # the server closes after the error reply
        try:
            obj = json.loads(reply)
        except ValueError:
            raise Invariant(f"the reply is not JSON: {reply[:120]!r}") from None
        _check_reply(obj)
        return None


# -- configuration ----------------------------------------------------------------------

def _config_sources() -> list[dict[str, Any]]:
    import yaml

    from mmctl.config import default_config, to_dict
    out = [to_dict(default_config())]
    root = Path(__file__).resolve().parent.parent / "config"
    for p in sorted(root.glob("*.yaml")):
        out.append(yaml.safe_load(p.read_text()))
    return out


def _config_texts() -> list[str]:
    import yaml
    root = Path(__file__).resolve().parent.parent / "config"
    texts = [p.read_text() for p in sorted(root.glob("*.yaml"))]
    from mmctl.config import default_config, to_dict
    full = to_dict(default_config())
    texts.append(yaml.safe_dump(full, sort_keys=False))
    # each section on its own (most inputs: a short text, as a real config is)
    texts += [yaml.safe_dump({k: v}, sort_keys=False) for k, v in full.items()]
    return texts


_NUMBERS: tuple[Any, ...] = (0, -1, 1, 0.0, -0.0, 1e-300, 5e-324, 1e300, -1e300, 1e20, 10**30,
                             -(10**30), 2**63, 2**31, 0x7FF, math.inf, -math.inf, math.nan,
                             0.5, 1000.0, 1e6, 1e-9)


def _odd_value(rng: random.Random) -> Any:
    r = rng.random()
    if r < 0.6:
        return rng.choice(_NUMBERS)
    return rng.choice((None, True, False, "", "x", "can", "1.0", [], {}, [1, 2], [[1]],
                       {"a": 1}, [0.0] * 6, [[0.0] * 6] * 6, [True] * 6, "0x20"))


def _paths(d: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    if isinstance(d, dict):
        for k, v in d.items():
            yield (*prefix, k)
            yield from _paths(v, (*prefix, k))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield (*prefix, i)
            yield from _paths(v, (*prefix, i))


def _mutated_mapping(rng: random.Random, sources: list[dict[str, Any]],
                     paths: list[list[tuple[Any, ...]]], trim: bool = False) -> Any:
    """A copy of one of ``sources`` with 1-3 values replaced, keys removed or added;
    ``trim``: only the top-level sections touched."""
    k = rng.randrange(len(sources))
    data = json.loads(json.dumps(sources[k]))  # deep copy (plain data)
    pool = paths[k]
    touched = set()
    for _ in range(rng.randint(1, 3)):
        path = rng.choice(pool)
        touched.add(path[0])
        parent: Any = data
        try:
            for key in path[:-1]:
                parent = parent[key]
            key = path[-1]
            r = rng.random()
            if r < 0.7:
                old = parent[key]
                if isinstance(old, (int, float)) and not isinstance(old, bool) and r < 0.35:
                    parent[key] = old * rng.choice((-1, 0, 1e-3, 1e3, 1e6, 1e300, 1e-300, 1.5))
                else:
                    parent[key] = _odd_value(rng)
            elif r < 0.85 and isinstance(parent, dict):
                del parent[key]
            elif isinstance(parent, dict):
                parent[rng.choice(("bogus", "", 1, None))] = _odd_value(rng)
            elif isinstance(parent, list):
                parent.append(_odd_value(rng)) if rng.random() < 0.5 else parent.pop()
        except (KeyError, IndexError, TypeError):
            continue
    if trim and isinstance(data, dict):
        data = {key: v for key, v in data.items() if key in touched}
    return data


def _check_loaded(cfg: Any) -> None:
    """Every number finite; every time in seconds (and the period of every rate or
    frequency in Hz) usable as a timeout: ``threading`` raises ``OverflowError`` on a
    time it cannot represent."""
    import dataclasses
    lock = threading.Lock()

    def walk(obj: Any, path: str) -> None:
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            key = f"{path}.{f.name}" if path else f.name
            if dataclasses.is_dataclass(v):
                walk(v, key)
                continue
            check_finite(v, key)
            unit = str(f.metadata.get("unit", ""))
            if unit == "Hz" and "rate" not in f.name and "frequency" not in f.name:
                unit = ""  # a filter's cut-off, not a rate anything waits for
            if isinstance(v, (int, float)) and not isinstance(v, bool) and unit in ("s", "Hz"):
                t = float(v) if unit == "s" else (1.0 / v if v else math.inf)
                try:
                    if t > 0 and lock.acquire(timeout=t):
                        lock.release()
                except OverflowError:
                    raise Invariant(f"{key} = {v!r} [{unit}] is accepted, but a time of "
                                    f"{t:g} s overflows Python's timeouts") from None
    walk(cfg, "")


def _cache_type_hints() -> Callable[[], None]:
    """``config.schema.build`` asks ``typing.get_type_hints`` for every section of every
    build (70 % of a load's time); the answer never changes for a class, so this process
    caches it.  Nothing else about the loader changes.  Returns what undoes it."""
    import functools
    import typing
    if hasattr(typing.get_type_hints, "cache_info"):
        return lambda: None
    plain = typing.get_type_hints

    @functools.cache
    def cached(obj: Any, globalns: Any = None, localns: Any = None,
               include_extras: bool = False) -> Any:
        return plain(obj, globalns, localns, include_extras)

    def get_type_hints(obj: Any, globalns: Any = None, localns: Any = None,
                       include_extras: bool = False) -> Any:
        try:
            return dict(cached(obj, globalns, localns, include_extras))
        except TypeError:  # unhashable arguments
            return plain(obj, globalns, localns, include_extras)

    get_type_hints.cache_info = cached.cache_info  # type: ignore[attr-defined]
    typing.get_type_hints = get_type_hints  # type: ignore[assignment]

    def undo() -> None:
        typing.get_type_hints = plain
    return undo


class ConfigValues(Target):
    """Mutated configuration mappings (defaults, config/*.yaml; values replaced by odd
    numbers and types, keys removed or added) through ``config_from_dict``."""

    name = "config_values"
    module = "mmctl.config"
    scale = 0.5

    def setup(self) -> None:
        from mmctl.config import ConfigError, config_from_dict
        self._undo_hints = _cache_type_hints()
        self.documented = (ConfigError,)
        self.load = config_from_dict
        self.sources = _config_sources()
        self.paths = [list(_paths(s)) for s in self.sources]

    def generate(self, rng: random.Random) -> Any:
        if rng.random() < 0.05:
            return _odd_value(rng)
        return _mutated_mapping(rng, self.sources, self.paths)

    def teardown(self) -> None:
        self._undo_hints()

    def feed(self, data: Any) -> Any:
        _check_loaded(self.load(data))
        return None


class ConfigYaml(Target):
    """YAML text through ``load_config`` (a file in a temp dir): valid configs mutated at
    the text level (bytes, lines, values), mutated mappings dumped, random YAML."""

    name = "config_yaml"
    module = "mmctl.config"
    scale = 0.05

    def setup(self) -> None:
        from mmctl.config import ConfigError, load_config
        self._undo_hints = _cache_type_hints()
        self.documented = (ConfigError,)
        self.load = load_config
        self.texts = _config_texts()
        self.sources = _config_sources()
        self.paths = [list(_paths(s)) for s in self.sources]
        self.tmp = tempfile.TemporaryDirectory(prefix="mmctl-fuzz-")
        self.file = Path(self.tmp.name) / "fuzz.yaml"

    def teardown(self) -> None:
        self.tmp.cleanup()
        self._undo_hints()

    def generate(self, rng: random.Random) -> bytes:
        import yaml
        r = rng.random()
        if r < 0.3:
            data = mutate(rng, rng.choice(self.texts).encode(), 3)
            if rng.random() < 0.9:  # mostly text, so most inputs reach the YAML parser
                data = data.decode("utf-8", "replace").encode()
            return data
        if r < 0.55:
            lines = rng.choice(self.texts).splitlines()
            for _ in range(rng.randint(1, 3)):
                if not lines:
                    break
                i = rng.randrange(len(lines))
                op = rng.randrange(4)
                if op == 0:
                    lines.insert(i, lines[rng.randrange(len(lines))])  # duplicate key
                elif op == 1:
                    del lines[i]
                elif op == 2 and ":" in lines[i]:
                    head = lines[i].split(":", 1)[0]
                    lines[i] = f"{head}: " + rng.choice((
                        "1.0e+300", "1.0e-300", ".nan", ".inf", "-.inf", "0x7FFFFFFFFFFFFFFF",
                        "~", "[", "{a: 1}", "*x", "&x 1", "!!binary aGk=", "!!python/none",
                        "'", "0o777", "1_000", "2001-01-01", "yes", "[1, 2, [3]]", "-1",
                        "99999999999999999999999999"))
                else:
                    lines[i] = " " * rng.randint(0, 4) + lines[i]
            return "\n".join(lines).encode()
        if r < 0.85:
            data = _mutated_mapping(rng, self.sources, self.paths, trim=True)
            return yaml.safe_dump(data, sort_keys=False).encode()
        if r < 0.95:
            return yaml.safe_dump(_json_value(rng)).encode()
        return rand_bytes(rng, rng.randint(0, 200))

    def feed(self, text: bytes) -> Any:
        self.file.write_bytes(text)
        _check_loaded(self.load(self.file))
        return None


TARGETS: dict[str, Callable[[], Target]] = {
    t.name: t for t in (CanFrames, CanClient, RdtRecords, RdtSequence, SerialPackets,
                        SerialStream, SerialBaseClient, IpcDispatch, IpcSocket, ConfigValues,
                        ConfigYaml)
}


# -- the command ------------------------------------------------------------------------

def _quiet_logs() -> None:
    """The clients log every fault they see: keep the fuzz run's output readable."""
    import logging

    import structlog
    logging.disable(logging.CRITICAL)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))


def _run_in_worker(name: str, inputs: int, seed: int) -> dict[str, Any]:
    _quiet_logs()
    warnings.simplefilter("ignore")  # numpy's overflow warnings: the outputs are checked
    sys.setrecursionlimit(max(sys.getrecursionlimit(), 1000))
    res = fuzz_target(TARGETS[name](), inputs, seed)
    d = res.__dict__.copy()
    d["failures"] = res.failures
    return d


def count_for(name: str, inputs: int) -> int:
    return max(1, round(inputs * TARGETS[name].scale)) if inputs else 0


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--inputs", type=int, default=10_000,
                    help="inputs per target (times the target's scale, see --list)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true", help="print the results as JSON")
    ap.add_argument("--targets", nargs="+", choices=sorted(TARGETS), default=list(TARGETS),
                    metavar="NAME", help=f"targets to run (default all: {', '.join(TARGETS)})")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1),
                    help="targets fuzzed at the same time, one process each")
    ap.add_argument("--list", action="store_true", help="list the targets and exit")
    args = ap.parse_args(argv)
    if args.list:
        for name, cls in TARGETS.items():
            print(f"{name:16s} scale {cls.scale:<5g} {cls.module:42s} "
                  f"{(cls.__doc__ or '').split(chr(10))[0]}")
        return 0
    t0 = time.perf_counter()
    results: dict[str, dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = {pool.submit(_run_in_worker, n, count_for(n, args.inputs), args.seed): n
                   for n in sorted(args.targets, key=lambda n: -TARGETS[n].scale)}
        for fut in as_completed(futures):
            name = futures[fut]
            results[name] = fut.result()
            r = results[name]
            print(f"[{name}] done: {r['inputs']} inputs, {r['failures']} failures, "
                  f"{r['seconds']:.1f} s", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    ordered = [results[n] for n in args.targets]
    failed = sum(r["failures"] for r in ordered)
    if args.json:
        print(json.dumps({"inputs_per_target": args.inputs, "seed": args.seed,
                          "wall_s": round(wall, 1), "failures": failed, "targets": ordered},
                         indent=2))
    else:
        _print_table(ordered, args, wall)
    return 1 if failed else 0


def _print_table(results: list[dict[str, Any]], args: argparse.Namespace, wall: float) -> None:
    print(f"fuzz: --inputs {args.inputs} --seed {args.seed}, {args.jobs} jobs, "
          f"wall {wall:.1f} s")
    head = f"{'target':16s} {'inputs':>9s} {'crashes':>8s} {'non-fin':>8s} {'invar.':>7s} " \
           f"{'time s':>8s} {'us/input':>9s} {'slowest ms':>11s}"
    print(head)
    print("-" * len(head))
    for r in results:
        per = r["seconds"] / r["inputs"] * 1e6 if r["inputs"] else 0.0
        print(f"{r['target']:16s} {r['inputs']:9d} {r['crashes']:8d} {r['non_finite']:8d} "
              f"{r['invariant']:7d} {r['seconds']:8.1f} {per:9.1f} {r['slowest_s'] * 1e3:11.2f}")
    for r in results:
        print(f"\n{r['target']}: slowest call {r['slowest_s'] * 1e3:.2f} ms on "
              f"{r['slowest_input'][:200]}")
        for key, n in sorted(r["distinct"].items(), key=lambda kv: -kv[1]):
            print(f"  {n:8d} x {key}")
        for ex in r["examples"]:
            print(f"  e.g. {ex['kind']}: {ex['error'][:160]} @ {ex['where']}\n"
                  f"       input {ex['input']}")


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
    sys.exit(130)
