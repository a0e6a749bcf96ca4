"""The `Base` protocol every base transport implements, and its status value.

Lifecycle: construct (no I/O) -> :meth:`Base.connect` -> :meth:`Base.enable` ->
per cycle :meth:`Base.send_twist` then :meth:`Base.read_odometry` -> :meth:`Base.stop`
-> :meth:`Base.disable` -> :meth:`Base.close` (idempotent; also ``with base:``).

Health: **both per-cycle calls** (``send_twist``, ``read_odometry``) and
:meth:`Base.check` raise :class:`mmctl.errors.SafetyFault` when the base is
unhealthy, with ``cause`` one of:

* ``FaultCause.DRIVE_FAULT`` — a drive reports FAULT (or left OPERATION ENABLED, or
  its NMT state is not OPERATIONAL) while enabled;
* ``FaultCause.DRIVE_HEARTBEAT`` — a CANopen drive's heartbeat is older than
  ``base.canopen.heartbeat_timeout``;
* ``FaultCause.BASE_LINK`` — the serial bridge sent no valid frame for
  ``base.serial.link_timeout``.

A detected fault is latched: every later per-cycle call raises it again until
:meth:`Base.enable` succeeds (which resets drive faults).  ``send_twist`` commands zero
before raising.  :meth:`Base.stop` and :meth:`Base.disable` never raise SafetyFault
(they are the fault reaction); they raise :class:`mmctl.errors.TransportError` when
the link itself fails.  A non-finite twist sends zero and raises
``SafetyFault(FaultCause.NON_FINITE)``.

A link that fails under a connected base (an exception of the client library: a closed
socketcand connection, a CAN adapter or serial port gone) raises
:class:`mmctl.errors.LinkLost` (a TransportError with ``cause = FaultCause.BASE_LINK``
and the ``link``) from every call, at once and without waiting, until
:meth:`Base.reconnect` succeeds; one warning event (``base_link_lost``) per loss; no
helper thread dies.  :meth:`Base.stop` and ``disable(wait=False)`` only send frames
(never wait for an answer), so neither blocks on a silent bus.
"""

from __future__ import annotations

from types import TracebackType
from typing import TYPE_CHECKING, NamedTuple, Protocol, runtime_checkable

from mmctl.types import Odometry, Twist

if TYPE_CHECKING:
    from typing_extensions import Self

#: Wheel / drive order everywhere: front-left, front-right, back-left, back-right.
WHEEL_NAMES: tuple[str, ...] = ("FL", "FR", "BL", "BR")


class DriveStatus(NamedTuple):
    """One drive as the transport last saw it.

    name: wheel (FL, FR, BL, BR); address: CANopen node id or serial wheel index;
    link: NMT state ('OPERATIONAL', 'PRE-OPERATIONAL', ...; 'SILENT' when no heartbeat;
    'LINK UP'/'LINK DOWN' for the serial bridge); state: CiA 402 state name (or the
    bridge's 'OPERATION ENABLED' / 'DISABLED' / 'FAULT'); statusword: 0x6041 or the
    bridge's wheel status byte; error_code: last EMCY / fault code (0 = none).
    """

    name: str
    address: int
    link: str
    state: str
    statusword: int
    error_code: int = 0


@runtime_checkable
class Base(Protocol):
    """An omnidirectional base driven by four wheel drives."""

    def connect(self) -> None:
        """Open the link and bring the drives to a known, disabled state.

        Raises TransportError naming the channel/port and addresses when nothing
        answers."""

    def reconnect(self) -> None:
        """After a lost link: release what is left, connect again and leave the drives
        disabled (enable() arms them); no-op while the link works.  Raises LinkLost
        naming the link while it does not answer.  Blocks: never on the loop thread."""

    def enable(self) -> None:
        """Reset drive faults, then power the drives (CiA 402 OPERATION ENABLED)."""

    def send_twist(self, vx: float, vy: float, wz: float) -> Twist:
        """Command a base twist (vx, vy [m/s], wz [rad/s], base frame); returns the
        twist actually commanded after scaling to the wheel speed limit."""

    def read_odometry(self) -> Odometry:
        """The newest odometry (pose in the odometry frame, twist in the base frame)."""

    def check(self) -> None:
        """Raise SafetyFault if the base is unhealthy (see module doc)."""

    def drive_status(self) -> list[DriveStatus]:
        """Per-drive link/state/statusword as last seen."""

    def stop(self) -> None:
        """Command zero wheel speed now (drives stay enabled)."""

    def disable(self, wait: bool = True) -> None:
        """Command zero, then take the drives out of OPERATION ENABLED, each bringing its
        wheel to rest before its power stage goes off.  ``wait``: block until they have
        (bounded); False: only send the commands, frames only, never waiting for an
        answer (the loop thread, in a stop)."""

    def close(self) -> None:
        """Stop, disable (best effort) and release the link.  Safe to call twice."""

    def __enter__(self) -> Self: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None: ...
