"""CiA 402 (drives and motion control) as the base's drives speak it — pure, no I/O.

Object indices, the controlword commands, statusword decoding, the drive-side state
machine (used by the simulated drives) and the object dictionary both the master and
the simulated drives use (built in code, no EDS file).

Mode of operation: **profile velocity** (0x6060 = 3).  Target velocity 0x60FF and
actual velocity 0x606C are INTEGER32 in encoder counts per second [counts/s]; actual
position 0x6064 is INTEGER32 in encoder counts (wraps at 2^32); profile acceleration
0x6083 / deceleration 0x6084 and quick-stop deceleration 0x6085 are UNSIGNED32 in
[counts/s^2].

The drive's own watchdog (CiA 301 / CiA 402): consumer heartbeat time 0x1016:01
(``producer node id << 16 | time [ms]``, 0 = off), the RPDO deadline 0x1400:05 (an
RPDO's event timer [ms]: one not received within it is an error, 0 = off), and the
abort connection option code 0x6007 (what either event does in OPERATION ENABLED).
How the drive stops: quick stop option code 0x605A, shutdown option code 0x605B
(OPERATION ENABLED -> READY TO SWITCH ON), disable operation option code 0x605C
(-> SWITCHED ON), fault reaction option code 0x605E.  The values are below.
"""

from __future__ import annotations

from enum import Enum, IntEnum

from canopen import objectdictionary as od
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable

DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
CONSUMER_HEARTBEAT_TIME = 0x1016
PRODUCER_HEARTBEAT_TIME = 0x1017
RPDO1_COMMUNICATION = 0x1400
#: Sub-index of a PDO communication record holding the event timer [ms] (an RPDO's deadline).
EVENT_TIMER_SUBINDEX = 5
ABORT_CONNECTION_OPTION = 0x6007
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
SHUTDOWN_OPTION = 0x605B
DISABLE_OPERATION_OPTION = 0x605C
FAULT_REACTION_OPTION = 0x605E
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
QUICK_STOP_DECELERATION = 0x6085
TARGET_VELOCITY = 0x60FF
SUPPORTED_DRIVE_MODES = 0x6502

#: Modes of operation (0x6060); we use profile velocity.
MODE_PROFILE_VELOCITY = 3
#: 0x1000: device profile 402, servo drive (additional information 0x0002).
DEVICE_TYPE_402 = 0x0002_0192

#: 0x6007 abort connection option code (heartbeat / RPDO deadline event in OPERATION
#: ENABLED): 0 no action, 1 fault, 2 disable voltage, 3 quick stop.
ABORT_NO_ACTION = 0
ABORT_FAULT = 1
ABORT_DISABLE_VOLTAGE = 2
ABORT_QUICK_STOP = 3
#: 0x605A quick stop option code: 0 disable drive function (coast), 1 / 2 slow down on
#: the slow-down (0x6084) / quick-stop (0x6085) ramp then SWITCH ON DISABLED, 5 / 6 the
#: same ramps and stay in QUICK STOP ACTIVE.  (3, 4, 7, 8, current/voltage limit: not
#: supported by the drives here.)
QUICK_STOP_COAST = 0
QUICK_STOP_SLOW_DOWN_RAMP = 1
QUICK_STOP_QUICK_STOP_RAMP = 2
QUICK_STOP_SLOW_DOWN_RAMP_STAY = 5
QUICK_STOP_QUICK_STOP_RAMP_STAY = 6
#: 0x605B shutdown / 0x605C disable operation option codes: 0 disable the drive function
#: at once (power stage off: the motor coasts), 1 slow down on the slow-down ramp
#: (0x6084), then disable.
STOP_OPTION_COAST = 0
STOP_OPTION_SLOW_DOWN_RAMP = 1
#: 0x605E fault reaction option code: 0 coast, 1 slow-down ramp, 2 quick-stop ramp
#: (FAULT REACTION ACTIVE lasts while the wheel comes to rest; then FAULT).
FAULT_REACTION_COAST = 0
FAULT_REACTION_SLOW_DOWN_RAMP = 1
FAULT_REACTION_QUICK_STOP_RAMP = 2

#: EMCY error codes (CiA 301) for the watchdog events.
EMCY_HEARTBEAT = 0x8130  # life guard or heartbeat error
EMCY_RPDO_TIMEOUT = 0x8250

#: Statusword bits beyond the state pattern.
SW_VOLTAGE_ENABLED = 0x0010
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400


class Controlword(IntEnum):
    """Controlword (0x6040) commands; FAULT_RESET acts on its rising edge (bit 7)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007  # also "disable operation"
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


class Cia402State(Enum):
    """The power drive state machine's states (value = the name CiA 402 gives them)."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"
    UNKNOWN = "UNKNOWN"


S = Cia402State

# (mask, value, state): the statusword patterns of CiA 402, checked in this order.
_SW_PATTERNS: tuple[tuple[int, int, Cia402State], ...] = (
    (0x4F, 0x00, S.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, S.SWITCH_ON_DISABLED),
    (0x6F, 0x21, S.READY_TO_SWITCH_ON),
    (0x6F, 0x23, S.SWITCHED_ON),
    (0x6F, 0x27, S.OPERATION_ENABLED),
    (0x6F, 0x07, S.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, S.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, S.FAULT),
)

_SW_VALUE = {state: value for _, value, state in _SW_PATTERNS}


def decode_statusword(statusword: int) -> Cia402State:
    """The drive state a statusword (0x6041) reports."""
    for mask, value, state in _SW_PATTERNS:
        if statusword & mask == value:
            return state
    return S.UNKNOWN


def encode_statusword(state: Cia402State, *, target_reached: bool = False) -> int:
    """The statusword a drive in ``state`` reports (remote bit set, voltage when powered)."""
    word = _SW_VALUE[state] | SW_REMOTE
    if state in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):
        word |= SW_VOLTAGE_ENABLED
    if target_reached:
        word |= SW_TARGET_REACHED
    return word


def _command(cw: int) -> str:
    """Decode the controlword's state command (bits 0-3 and 7, CiA 402 table)."""
    if cw & 0x82 == 0x00:
        return "disable_voltage"
    if cw & 0x86 == 0x02:
        return "quick_stop"
    if cw & 0x87 == 0x06:
        return "shutdown"
    if cw & 0x8F == 0x07:
        return "switch_on"
    if cw & 0x8F == 0x0F:
        return "enable_operation"
    return "none"


_TRANSITIONS: dict[tuple[Cia402State, str], Cia402State] = {
    (S.SWITCH_ON_DISABLED, "shutdown"): S.READY_TO_SWITCH_ON,  # 2
    (S.READY_TO_SWITCH_ON, "switch_on"): S.SWITCHED_ON,  # 3
    (S.READY_TO_SWITCH_ON, "enable_operation"): S.OPERATION_ENABLED,  # 3 + 4
    (S.SWITCHED_ON, "enable_operation"): S.OPERATION_ENABLED,  # 4
    (S.OPERATION_ENABLED, "switch_on"): S.SWITCHED_ON,  # 5
    (S.SWITCHED_ON, "shutdown"): S.READY_TO_SWITCH_ON,  # 6
    (S.READY_TO_SWITCH_ON, "disable_voltage"): S.SWITCH_ON_DISABLED,  # 7
    (S.READY_TO_SWITCH_ON, "quick_stop"): S.SWITCH_ON_DISABLED,  # 7
    (S.OPERATION_ENABLED, "shutdown"): S.READY_TO_SWITCH_ON,  # 8
    (S.OPERATION_ENABLED, "disable_voltage"): S.SWITCH_ON_DISABLED,  # 9
    (S.SWITCHED_ON, "disable_voltage"): S.SWITCH_ON_DISABLED,  # 10
    (S.SWITCHED_ON, "quick_stop"): S.SWITCH_ON_DISABLED,  # 10
    (S.OPERATION_ENABLED, "quick_stop"): S.QUICK_STOP_ACTIVE,  # 11
    (S.QUICK_STOP_ACTIVE, "disable_voltage"): S.SWITCH_ON_DISABLED,  # 12
    (S.QUICK_STOP_ACTIVE, "enable_operation"): S.OPERATION_ENABLED,  # 16
}


def next_state(state: Cia402State, controlword: int, previous_controlword: int) -> Cia402State:
    """Drive side: the state after the master writes ``controlword``.

    A rising edge of the fault-reset bit (7) leaves FAULT for SWITCH ON DISABLED
    (transition 15); in FAULT REACTION ACTIVE nothing the master writes has any effect
    (the drive leaves it by itself, for FAULT: transition 14); other commands follow
    the CiA 402 transition table; a command with no transition from ``state`` leaves it
    unchanged.  (The option codes 0x605A-0x605C decide *when* a transition out of
    OPERATION ENABLED completes; that is the drive's business, not this table's.)
    """
    rising_reset = bool(controlword & 0x80) and not previous_controlword & 0x80
    if state is S.FAULT:
        return S.SWITCH_ON_DISABLED if rising_reset else S.FAULT
    if state is S.FAULT_REACTION_ACTIVE:
        return state
    return _TRANSITIONS.get((state, _command(controlword)), state)


def _var(
    name: str, index: int, data_type: int, default: int, access: str = "rw",
    subindex: int = 0, mappable: bool = False,
) -> ODVariable:
    v = ODVariable(name, index, subindex)
    v.data_type = data_type
    v.default = default
    v.access_type = access
    v.pdo_mappable = mappable
    return v


def _pdo_records(
    d: ObjectDictionary, com: int, mapping: int, n: int, kind: str, cob_base: int,
    node_id: int, tpdo: bool,
) -> None:
    for i in range(n):
        rec = ODRecord(f"{kind}{i + 1} communication parameter", com + i)
        rec.add_member(_var("Highest sub-index supported", com + i, od.UNSIGNED8, 5,
                            "const"))
        cob = cob_base + 0x100 * i + node_id
        rec.add_member(_var("COB-ID", com + i, od.UNSIGNED32, cob | 0x8000_0000, subindex=1))
        rec.add_member(_var("Transmission type", com + i, od.UNSIGNED8, 255, subindex=2))
        if tpdo:
            rec.add_member(_var("Inhibit time", com + i, od.UNSIGNED16, 0, subindex=3))
        # TPDO: transmission period; RPDO: deadline (CiA 301), 0 = off [ms]
        rec.add_member(_var("Event timer", com + i, od.UNSIGNED16, 0,
                            subindex=EVENT_TIMER_SUBINDEX))
        d.add_object(rec)
        m = ODRecord(f"{kind}{i + 1} mapping parameter", mapping + i)
        m.add_member(_var("Number of mapped objects", mapping + i, od.UNSIGNED8, 0))
        for sub in range(1, 9):
            m.add_member(_var(f"Mapped object {sub}", mapping + i, od.UNSIGNED32, 0,
                              subindex=sub))
        d.add_object(m)


def build_object_dictionary(node_id: int) -> ObjectDictionary:
    """The drive's object dictionary: CiA 301 communication objects (2 RPDOs, 2 TPDOs,
    heartbeat producer and consumer) and the CiA 402 profile-velocity, option-code and
    watchdog objects listed in the module doc, with the defaults a drive comes up with
    (every watchdog off, shutdown option 0: coast)."""
    d = ObjectDictionary()
    d.node_id = node_id
    d.add_object(_var("Device type", DEVICE_TYPE, od.UNSIGNED32, DEVICE_TYPE_402, "ro"))
    d.add_object(_var("Error register", ERROR_REGISTER, od.UNSIGNED8, 0, "ro"))
    consumer = ODArray("Consumer heartbeat time", CONSUMER_HEARTBEAT_TIME)
    consumer.add_member(_var("Highest sub-index supported", CONSUMER_HEARTBEAT_TIME,
                             od.UNSIGNED8, 1, "const"))
    consumer.add_member(_var("Consumer heartbeat time 1", CONSUMER_HEARTBEAT_TIME,
                             od.UNSIGNED32, 0, subindex=1))
    d.add_object(consumer)
    d.add_object(_var("Producer heartbeat time", PRODUCER_HEARTBEAT_TIME, od.UNSIGNED16, 0))
    _pdo_records(d, 0x1400, 0x1600, 2, "RPDO", 0x200, node_id, tpdo=False)
    _pdo_records(d, 0x1800, 0x1A00, 2, "TPDO", 0x180, node_id, tpdo=True)
    d.add_object(_var("Abort connection option code", ABORT_CONNECTION_OPTION, od.INTEGER16,
                      ABORT_NO_ACTION))
    d.add_object(_var("Error code", ERROR_CODE, od.UNSIGNED16, 0, "ro", mappable=True))
    d.add_object(_var("Controlword", CONTROLWORD, od.UNSIGNED16, 0, mappable=True))
    d.add_object(_var("Statusword", STATUSWORD, od.UNSIGNED16, 0, "ro", mappable=True))
    d.add_object(_var("Quick stop option code", QUICK_STOP_OPTION, od.INTEGER16,
                      QUICK_STOP_QUICK_STOP_RAMP))
    d.add_object(_var("Shutdown option code", SHUTDOWN_OPTION, od.INTEGER16, STOP_OPTION_COAST))
    d.add_object(_var("Disable operation option code", DISABLE_OPERATION_OPTION, od.INTEGER16,
                      STOP_OPTION_SLOW_DOWN_RAMP))
    d.add_object(_var("Fault reaction option code", FAULT_REACTION_OPTION, od.INTEGER16,
                      FAULT_REACTION_QUICK_STOP_RAMP))
    d.add_object(_var("Modes of operation", MODES_OF_OPERATION, od.INTEGER8, 0, mappable=True))
    d.add_object(_var("Modes of operation display", MODES_OF_OPERATION_DISPLAY, od.INTEGER8, 0,
                      "ro", mappable=True))
    d.add_object(_var("Position actual value", POSITION_ACTUAL, od.INTEGER32, 0, "ro",
                      mappable=True))
    d.add_object(_var("Velocity actual value", VELOCITY_ACTUAL, od.INTEGER32, 0, "ro",
                      mappable=True))
    d.add_object(_var("Profile acceleration", PROFILE_ACCELERATION, od.UNSIGNED32, 10_000))
    d.add_object(_var("Profile deceleration", PROFILE_DECELERATION, od.UNSIGNED32, 10_000))
    d.add_object(_var("Quick stop deceleration", QUICK_STOP_DECELERATION, od.UNSIGNED32,
                      10_000))
    d.add_object(_var("Target velocity", TARGET_VELOCITY, od.INTEGER32, 0, mappable=True))
    d.add_object(_var("Supported drive modes", SUPPORTED_DRIVE_MODES, od.UNSIGNED32,
                      1 << (MODE_PROFILE_VELOCITY - 1), "ro"))
    return d
