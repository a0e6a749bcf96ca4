"""Change the IDK strategy at run time (blended: no jump in commanded velocity).

min-energy (the paper's), locomotion (eq. 7 benchmark), switch (toggle with
`mmctl switch` or the handle button), manipulation (arm only), constrained-min-energy.
"""

from __future__ import annotations

import argparse

from mmctl.config.control import STRATEGIES
from mmctl.runtime.client import add_client_arguments, call, summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("mode", choices=STRATEGIES, help="the IDK strategy")
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    print(summary(call(args, "mode", mode=args.mode)))
    return 0
