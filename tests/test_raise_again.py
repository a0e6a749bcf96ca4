"""A stored exception raised again and again keeps one raise's traceback.

Found on a daemon whose arm process had ended: every cycle's watchdog kick re-raised the
stored ``arm_disconnected`` fault, each raise appended its frames to that one
instance's ``__traceback__``, and the daemon grew to 7.5 GB resident in 86 minutes."""

from __future__ import annotations

from types import TracebackType

import pytest

from mmctl.config import config_from_dict
from mmctl.errors import FaultCause, SafetyFault, again
from mmctl.transports.ur_rtde_process import UrRtdeProcessArm


def _depth(tb: TracebackType | None) -> int:
    n = 0
    while tb is not None:
        n, tb = n + 1, tb.tb_next
    return n


def test_a_plain_reraise_grows_and_again_does_not() -> None:
    stored = ValueError("gone")

    def plain() -> None:
        raise stored

    def fresh() -> None:
        raise again(stored)

    for raiser, bound in ((plain, None), (fresh, 2)):
        stored.__traceback__ = None
        for _ in range(1000):
            with pytest.raises(ValueError):
                raiser()
        depth = _depth(stored.__traceback__)
        if bound is None:
            assert depth >= 1000  # the Python behaviour the helper exists for
        else:
            assert depth <= bound, depth


def test_a_lost_arm_link_raised_every_cycle_holds_one_traceback() -> None:
    cfg = config_from_dict({})
    arm = UrRtdeProcessArm(cfg.arm, cfg.limits)
    gone = SafetyFault(FaultCause.ARM_DISCONNECTED, host=cfg.arm.host,
                       why="the arm process ended (exit code 0)")
    arm._cmd = memoryview(bytearray(8)).cast("d")  # (a staging record: no child needed)
    arm._gone = gone
    for _ in range(5000):  # ten seconds of cycles
        with pytest.raises(SafetyFault) as info:
            arm.kick_watchdog()
        assert info.value is gone
    assert _depth(gone.__traceback__) <= 4, _depth(gone.__traceback__)
