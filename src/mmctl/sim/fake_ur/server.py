"""The fake UR controller's network side: three listening ports and a 500 Hz clock.

:class:`FakeURServer` serves RTDE (30004), the dashboard (29999) and the script port
(30003) on one loopback address from a single thread: a selector waits for sockets and
the parent's control pipe until the next controller period, then the model steps and
every started RTDE session streams.  If the process falls behind (a loaded machine),
the missed periods are stepped back to back (up to :data:`MAX_CATCH_UP`) so that the
controller clock keeps pace with the wall clock; only the newest package is streamed.

The script port only accepts programs; unlike a real controller it streams no state.
"""

from __future__ import annotations

import selectors
import socket
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import structlog

from mmctl.sim.fake_ur import dashboard, shared
from mmctl.sim.fake_ur.log import CommandKind, CommandLog
from mmctl.sim.fake_ur.model import PERIOD, ControllerModel
from mmctl.sim.fake_ur.program import ScriptReceiver
from mmctl.sim.fake_ur.rtde_session import RtdeSession

log = structlog.get_logger("mmctl.fake_ur")

DASHBOARD_PORT = 29999
SCRIPT_PORT = 30003
RTDE_PORT = 30004
PORTS = (DASHBOARD_PORT, SCRIPT_PORT, RTDE_PORT)


def ports_free(host: str, ports: Sequence[int] = PORTS) -> bool:
    """Whether every TCP port of ``ports`` can be bound on ``host`` right now (where a
    fake UR, and a simulated robot's socketcand server, may go)."""
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind((host, port))
            except OSError:
                return False
    return True
PERIOD_NS = int(PERIOD * 1e9)
MAX_CATCH_UP = 50
"""Controller periods stepped back to back at most after a stall; beyond, the clock skips."""
MAX_OUTBOX = 4 << 20
"""[bytes] a client that stops reading is disconnected once this much is queued."""


@dataclass
class _Conn:
    sock: socket.socket
    port: int
    peer: str
    outbox: bytearray = field(default_factory=bytearray)
    rtde: RtdeSession | None = None
    script: ScriptReceiver | None = None
    text: bytearray = field(default_factory=bytearray)
    closing: bool = False


class FakeURServer:
    """Serve one :class:`ControllerModel` on ``host``.

    control: the child end of a ``multiprocessing`` pipe for the parent's requests
    (None when run standalone); block: the shared state block (None: not published).
    """

    def __init__(self, host: str, model: ControllerModel, control: Any = None, block: Any = None):
        self.host = host
        self.model = model
        self.control = control
        self.block = block
        self.tick = 0
        self.overruns = 0
        self._sel = selectors.DefaultSelector()
        self._listeners: list[socket.socket] = []
        self._conns: dict[int, _Conn] = {}
        self._running = False
        self._shut = False  # shutdown() asked (also before serve() began)

    # -- lifecycle -----------------------------------------------------------------------

    def open(self) -> None:
        """Bind and listen on the three ports (raises OSError when one is taken)."""
        try:
            for port in PORTS:
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self._listeners.append(s)
                s.bind((self.host, port))
                s.listen(8)
                s.setblocking(False)
                self._sel.register(s, selectors.EVENT_READ, ("listen", port))
        except OSError:
            self.close()
            raise
        if self.control is not None:
            self._sel.register(self.control, selectors.EVENT_READ, ("control", 0))
        self._publish()

    def close(self) -> None:
        """Close every socket (idempotent)."""
        for conn in list(self._conns.values()):
            self._drop(conn, "server closing")
        for s in self._listeners:
            try:
                self._sel.unregister(s)
            except (KeyError, ValueError):
                pass
            s.close()
        self._listeners.clear()

    def serve(self) -> None:
        """Run until the parent asks to shut down (or its pipe closes) or :meth:`shutdown`."""
        self._running = True
        next_ns = time.perf_counter_ns() + PERIOD_NS
        # (_shut too: a shutdown() between the two lines above is not lost)
        while self._running and not self._shut:
            timeout = max(0.0, (next_ns - time.perf_counter_ns()) * 1e-9)
            for key, mask in self._sel.select(timeout):
                self._event(key, mask)
            now = time.perf_counter_ns()
            if now < next_ns:
                continue
            behind = (now - next_ns) // PERIOD_NS
            if behind > MAX_CATCH_UP:
                self.overruns += 1
                steps, next_ns = 1, now + PERIOD_NS
            else:
                steps = behind + 1
                next_ns += steps * PERIOD_NS
            for _ in range(steps):
                self.model.step()
                self.tick += 1
            self._publish()
            self._stream()

    def shutdown(self) -> None:
        self._shut = True
        self._running = False

    # -- per period ----------------------------------------------------------------------

    def _publish(self) -> None:
        if self.block is not None:
            m = self.model
            shared.write(self.block, m.time, m.plant.q, m.plant.qd, m.runtime_state,
                         m.safety_status_bits)

    def _stream(self) -> None:
        if self.model.frozen:
            return
        for conn in list(self._conns.values()):
            if conn.rtde is not None and conn.rtde.started:
                data = conn.rtde.data_packages(self.tick)
                if data:
                    self._send(conn, data)

    # -- sockets -------------------------------------------------------------------------

    def _event(self, key: selectors.SelectorKey, mask: int) -> None:
        kind, port = key.data
        if kind == "listen":
            self._accept(key.fileobj, port)  # type: ignore[arg-type]
        elif kind == "control":
            self._control()
        else:
            conn = self._conns.get(key.fd)
            if conn is None:
                return
            if mask & selectors.EVENT_WRITE:
                self._flush(conn)
            if mask & selectors.EVENT_READ and conn.sock.fileno() >= 0:
                self._receive(conn)

    def _accept(self, listener: socket.socket, port: int) -> None:
        try:
            sock, addr = listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn = _Conn(sock, port, f"{addr[0]}:{addr[1]}")
        if port == RTDE_PORT:
            conn.rtde = RtdeSession(self.model, conn.peer)
        elif port == SCRIPT_PORT:
            conn.script = ScriptReceiver()
        self._conns[sock.fileno()] = conn
        self._sel.register(sock, selectors.EVENT_READ, ("conn", port))
        self.model.log.add(self.model.time, CommandKind.CONNECTION, code=port, text="open")
        if port == DASHBOARD_PORT:
            self._send(conn, (dashboard.WELCOME + "\n").encode())

    def _receive(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._drop(conn, f"recv failed: {exc}")
            return
        if not data:
            self._drop(conn, "peer closed")
            return
        if conn.rtde is not None:
            try:
                reply = conn.rtde.feed(data)
            except (ValueError, IndexError) as exc:
                log.warning("rtde_protocol_error", peer=conn.peer, error=str(exc))
                self._drop(conn, "protocol error")
                return
            if reply:
                self._send(conn, reply)
        elif conn.script is not None:
            for name, text in conn.script.feed(data):
                self.model.log.add(self.model.time, CommandKind.SCRIPT,
                                   text=name or text.strip(), code=len(text))
                if name:
                    self.model.start_program(name, text)
        else:
            self._dashboard(conn, data)

    def _dashboard(self, conn: _Conn, data: bytes) -> None:
        conn.text += data
        while b"\n" in conn.text and not conn.closing:
            raw, _, rest = bytes(conn.text).partition(b"\n")
            conn.text = bytearray(rest)
            line = raw.decode("utf-8", errors="replace").strip()
            reply, close = dashboard.answer(self.model, line)
            self.model.log.add(self.model.time, CommandKind.DASHBOARD, text=line, reply=reply)
            self._send(conn, (reply + "\n").encode())
            if close:
                conn.closing = True
        if conn.closing and not conn.outbox:
            self._drop(conn, "quit")

    def _send(self, conn: _Conn, data: bytes) -> None:
        conn.outbox += data
        if len(conn.outbox) > MAX_OUTBOX:
            self._drop(conn, "client not reading")
            return
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        if conn.sock.fileno() < 0:
            return
        try:
            n = conn.sock.send(conn.outbox)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self._drop(conn, f"send failed: {exc}")
            return
        del conn.outbox[:n]
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if conn.outbox else 0)
        self._sel.modify(conn.sock, events, ("conn", conn.port))
        if conn.closing and not conn.outbox:
            self._drop(conn, "quit")

    def _drop(self, conn: _Conn, why: str) -> None:
        fd = conn.sock.fileno()
        if fd < 0:
            return
        self._conns.pop(fd, None)
        try:
            self._sel.unregister(conn.sock)
        except (KeyError, ValueError):
            pass
        conn.sock.close()
        self.model.log.add(self.model.time, CommandKind.CONNECTION, code=conn.port,
                           text=f"closed: {why}")

    # -- parent requests -----------------------------------------------------------------

    def _control(self) -> None:
        try:
            while self.control.poll():
                request = self.control.recv()
                try:
                    reply = ("ok", self.model.time, self._apply(request))
                except (ValueError, TypeError, IndexError) as exc:
                    reply = ("error", self.model.time, f"{type(exc).__name__}: {exc}")
                self.control.send(reply)
        except (EOFError, OSError):
            log.info("fake_ur_parent_gone", host=self.host)
            self._sel.unregister(self.control)
            self.control = None
            self._running = False

    def _apply(self, request: tuple[Any, ...]) -> Any:
        m = self.model
        op, *args = request
        if op == "protective_stop":
            m.set_protective_stop(args[0])
        elif op == "emergency_stop":
            m.set_emergency_stop(args[0])
        elif op == "stop_program":
            m.stop_program("stopped by a test")
        elif op == "freeze":
            m.frozen = bool(args[0])
        elif op == "remote_control":
            m.remote_control = bool(args[0])
        elif op == "digital_inputs":  # several at once: one sample has them all
            bits = m.digital_inputs
            for index, on in args[0]:
                bits = (bits | (1 << index)) if on else (bits & ~(1 << index))
            m.digital_inputs = bits
        elif op == "speed_slider":
            m.plant.scale = min(max(float(args[0]), 0.0), 1.0)
        elif op == "set_q":
            m.plant.set_q(list(args[0]))
            self._publish()
        elif op == "log":  # the encoded entries from seq args[0] on, args[1] at most
            return m.log.rows(args[0], args[1])
        elif op == "shutdown":
            self._running = False
        else:
            raise ValueError(f"unknown request {op!r}")
        return None


def run(host: str, q_init: Sequence[float], block: Any = None, control: Any = None,
        log_capacity: int = 200_000, first_seq: int = 0, stop_signals: bool = False
        ) -> int | None:
    """Entry point of the fake's process: serve until asked to stop.

    Reports ``("ready", pid)`` or ``("error", message)`` on ``control`` first.  The
    process leaves its parent's session first: a terminal's Ctrl-C (SIGINT to the whole
    foreground process group) must reach only the daemon, which sends its stop commands
    to this controller and then ends it.  A parent that dies closes the control pipe,
    which ends this process too.  ``first_seq``: the seq of the command log's first
    entry (a restarted controller numbers on from its predecessor's log).
    ``stop_signals`` (run in the foreground, ``mmctl fake-ur``): SIGINT and SIGTERM end
    the serving loop through a flag it checks every period, never as an exception (a
    KeyboardInterrupt that lands in a finalizer is swallowed: seen once in a loaded CI
    run, where the fake then served on for 20 minutes); returns the signal's number.
    """
    import os

    try:
        os.setsid()
    except OSError:  # already a session leader (run standalone)
        pass
    model = ControllerModel(q_init, CommandLog(log_capacity, first_seq))
    server = FakeURServer(host, model, control, block)
    try:
        server.open()
    except OSError as exc:
        if control is not None:
            control.send(("error", f"cannot listen on {host}: {exc.strerror or exc}"))
        raise
    if control is not None:
        control.send(("ready", os.getpid()))
    got: list[int] = []
    if stop_signals:
        import signal

        def _stop(signum: int, _frame: object) -> None:
            got.append(signum)
            server.shutdown()

        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, _stop)
    log.info("fake_ur_listening", host=host, ports=PORTS)
    try:
        server.serve()
    finally:
        server.close()
    return got[0] if got else None
