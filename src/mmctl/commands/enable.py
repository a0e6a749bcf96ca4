"""Arm the robot: the daemon starts sending motion commands.

Refused (exit 2, one line naming the causes) while any fault condition is present or a
device is unhealthy; after a fault the cause must be gone before re-enabling.
"""

from __future__ import annotations

import argparse

from mmctl.runtime.client import add_client_arguments, call, summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    print(summary(call(args, "enable")))
    return 0
