"""The seam every force/torque transport implements: :class:`ForceSensor`.

Error contract shared by all transports:

* ``connect()`` raises :class:`~mmctl.errors.TransportError` when nothing answers
  (the message names the link and the timeout) and
  :class:`~mmctl.errors.ProtocolError` when the peer answers with bytes that do not
  follow the protocol.
* ``read()`` raises :class:`~mmctl.errors.SafetyFault` with
  ``FaultCause.SENSOR_STATUS`` / ``SENSOR_SATURATION`` when the device flags it, and
  ``FaultCause.SENSOR_STALE`` when no new sample arrived for longer than the
  configured ``sensor.wrench.stale_timeout``; ``ProtocolError`` on malformed frames;
  ``TransportError`` when the link itself fails or the sensor is not connected.
* A link that fails under a connected sensor (an exception of the client library: a
  closed socketcand connection, a CAN adapter gone, a socket error) raises
  :class:`~mmctl.errors.LinkLost` (a ``TransportError`` with ``cause =
  FaultCause.SENSOR_LINK`` and the ``link``) from that call and from every later one,
  at once and without I/O, until ``reconnect()`` succeeds.  One warning event
  (``sensor_link_lost``) is logged per loss; no helper thread dies.
* ``reconnect()`` does nothing while the link works; after a loss it closes what is
  left and connects again (what ``connect()`` reads, read again), raising ``LinkLost``
  naming the link while the sensor does not answer.  It blocks (up to the connect
  timeouts): never on the loop thread.
  Until a sample is stale, a ``read()`` that got nothing new returns the previous
  sample again (same ``sequence``, same ``timestamp``).
* ``close()`` is idempotent; the context manager connects on entry and closes on exit.
"""

from __future__ import annotations

from types import TracebackType
from typing import TYPE_CHECKING, NamedTuple, Protocol, runtime_checkable

from mmctl.types import Wrench

if TYPE_CHECKING:  # typing.Self is 3.11+; the package supports 3.10
    from typing import Self


class SensorStats(NamedTuple):
    """Link counters since ``connect()``.

    received: fresh samples decoded; lost: CAN requests that got no reply in time, or
    RDT sequence numbers skipped and not filled by a late record; out_of_order: RDT
    records older than the newest one (discarded; always 0 on CAN); resets: RDT
    sequence restarts taken as a new stream (0 on CAN); restarts: RDT start requests
    re-sent because the stream fell silent (0 on CAN).
    """

    received: int
    lost: int
    out_of_order: int
    resets: int = 0
    restarts: int = 0


@runtime_checkable
class ForceSensor(Protocol):
    """A 6-axis force/torque sensor (wrench in the sensor frame, SI units)."""

    @property
    def link(self) -> str:
        """Where the sensor is expected, for messages (``virtual:chan@0x20``, ``udp://h:p``)."""

    def connect(self) -> None:
        """Open the link, read what the conversion needs, prove the sensor answers."""

    def read(self) -> Wrench:
        """The newest sample: force [N], torque [N m] in the sensor frame. Cheap (500 Hz)."""

    def reconnect(self) -> None:
        """After a lost link: connect again (see the module doc); no-op while it works."""

    def close(self) -> None:
        """Release the link; safe to call twice."""

    def stats(self) -> SensorStats:
        """Link counters since ``connect()``."""

    def __enter__(self) -> Self: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...
