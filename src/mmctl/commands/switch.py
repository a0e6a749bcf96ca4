"""In switch mode, toggle between manipulation (base locked, arm only) and locomotion.

The change is blended over idk.switch.blend_time: no jump in commanded velocity.
"""

from __future__ import annotations

import argparse

from mmctl.runtime.client import add_client_arguments, call, summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("to", choices=("manipulation", "locomotion"), help="the sub-mode")
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    print(summary(call(args, "switch", to=args.to)))
    return 0
