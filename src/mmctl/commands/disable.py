"""Disarm the robot: speedStop the arm, zero and disable the base; the loop keeps running."""

from __future__ import annotations

import argparse

from mmctl.runtime.client import add_client_arguments, call, summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    print(summary(call(args, "disable")))
    return 0
