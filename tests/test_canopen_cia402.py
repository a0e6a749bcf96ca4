"""CiA 402 words and state machine (pure)."""

from __future__ import annotations

import pytest

from mmctl.transports.base import cia402 as ds
from mmctl.transports.base.cia402 import Cia402State as S
from mmctl.transports.base.cia402 import Controlword as CW


@pytest.mark.parametrize("state", [s for s in S if s is not S.UNKNOWN])
def test_statusword_round_trip(state: S) -> None:
    for reached in (False, True):
        assert ds.decode_statusword(ds.encode_statusword(state, target_reached=reached)) is state


@pytest.mark.parametrize(
    ("word", "state"),
    [(0x0000, S.NOT_READY_TO_SWITCH_ON), (0x0250, S.SWITCH_ON_DISABLED),
     (0x0231, S.READY_TO_SWITCH_ON), (0x0233, S.SWITCHED_ON),
     (0x0637, S.OPERATION_ENABLED), (0x0217, S.QUICK_STOP_ACTIVE),
     (0x021F, S.FAULT_REACTION_ACTIVE), (0x0218, S.FAULT), (0x0208, S.FAULT)],
)
def test_decode_known_statuswords(word: int, state: S) -> None:
    assert ds.decode_statusword(word) is state


def test_enable_sequence_and_back() -> None:
    s = S.SWITCH_ON_DISABLED
    prev = 0
    for cw, want in ((CW.SHUTDOWN, S.READY_TO_SWITCH_ON), (CW.SWITCH_ON, S.SWITCHED_ON),
                     (CW.ENABLE_OPERATION, S.OPERATION_ENABLED), (CW.SWITCH_ON, S.SWITCHED_ON),
                     (CW.ENABLE_OPERATION, S.OPERATION_ENABLED),
                     (CW.QUICK_STOP, S.QUICK_STOP_ACTIVE),
                     (CW.DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED)):
        s = ds.next_state(s, cw, prev)
        prev = cw
        assert s is want


def test_commands_without_a_transition_keep_the_state() -> None:
    assert ds.next_state(S.SWITCH_ON_DISABLED, CW.ENABLE_OPERATION, 0) is S.SWITCH_ON_DISABLED
    assert ds.next_state(S.SWITCH_ON_DISABLED, CW.SWITCH_ON, 0) is S.SWITCH_ON_DISABLED


def test_fault_reset_needs_a_rising_edge() -> None:
    assert ds.next_state(S.FAULT, CW.ENABLE_OPERATION, 0) is S.FAULT
    assert ds.next_state(S.FAULT, CW.FAULT_RESET, CW.FAULT_RESET) is S.FAULT
    assert ds.next_state(S.FAULT, CW.FAULT_RESET, 0) is S.SWITCH_ON_DISABLED


def test_object_dictionary_has_the_profile_objects() -> None:
    od = ds.build_object_dictionary(3)
    for index in (ds.CONTROLWORD, ds.STATUSWORD, ds.MODES_OF_OPERATION, ds.TARGET_VELOCITY,
                  ds.VELOCITY_ACTUAL, ds.POSITION_ACTUAL, ds.PRODUCER_HEARTBEAT_TIME,
                  0x1400, 0x1600, 0x1800, 0x1801, 0x1A00, 0x1A01):
        assert index in od
    assert od[ds.TARGET_VELOCITY].pdo_mappable
    assert od[0x1800][1].default == 0x8000_0183  # TPDO1 COB-ID, not valid until configured


def test_fault_reaction_active_ignores_every_command_including_the_reset_edge() -> None:
    for cw in (CW.FAULT_RESET, CW.DISABLE_VOLTAGE, CW.SHUTDOWN, CW.ENABLE_OPERATION):
        assert ds.next_state(S.FAULT_REACTION_ACTIVE, cw, 0) is S.FAULT_REACTION_ACTIVE


def test_object_dictionary_has_the_watchdog_and_option_code_objects_off_by_default() -> None:
    od = ds.build_object_dictionary(2)
    assert od[ds.CONSUMER_HEARTBEAT_TIME][1].default == 0  # no consumer heartbeat
    assert od[ds.RPDO1_COMMUNICATION][ds.EVENT_TIMER_SUBINDEX].default == 0  # no deadline
    assert od[ds.RPDO1_COMMUNICATION][0].default == 5
    assert od[ds.ABORT_CONNECTION_OPTION].default == ds.ABORT_NO_ACTION
    assert od[ds.SHUTDOWN_OPTION].default == ds.STOP_OPTION_COAST  # CiA 402's default
    for index in (ds.QUICK_STOP_OPTION, ds.DISABLE_OPERATION_OPTION, ds.FAULT_REACTION_OPTION,
                  ds.QUICK_STOP_DECELERATION):
        assert index in od
