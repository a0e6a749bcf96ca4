"""Shut the daemon down: stop commands to arm and base, devices closed, process exits."""

from __future__ import annotations

import argparse

from mmctl.runtime.client import add_client_arguments, call


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    call(args, "stop")
    print("stopping")
    return 0
