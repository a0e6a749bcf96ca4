"""Run a recorded inputs log (`mmctl run --record-inputs DIR`) through the pure update
again and compare its commands with the recorded ones, cycle by cycle.

Prints how many cycles were replayed and the first cycle whose commands differ (none
for a log of the same version: the update is a function of its inputs).  Exits 0 when
they are identical, 1 at the first difference, 2 when the folder is not a log.  How a
field incident is debugged: replay the robot's own log on a desk, with prints or a
debugger in the update.
"""

from __future__ import annotations

import argparse
import sys


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", metavar="DIR", help="the folder `mmctl run --record-inputs` wrote")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args: argparse.Namespace) -> int:
    import json

    from mmctl.runtime.inputlog import LogError, replay

    def progress(done: int, total: int) -> None:
        print(f"\rreplaying: {done}/{total} cycles", end="", file=sys.stderr, flush=True)

    try:
        result = replay(args.log, progress=progress if sys.stderr.isatty() else None)
    except LogError as exc:
        print(f"mmctl replay: {exc}", file=sys.stderr)
        return 2
    if sys.stderr.isatty():
        print(file=sys.stderr)
    if args.json:
        print(json.dumps(result._asdict()))
    elif result.first_difference is None:
        print(f"replayed {result.cycles} cycles: every command identical to the recording")
    else:
        print(f"replayed {result.cycles} cycles: cycle {result.first_difference} differs: "
              f"{result.detail}")
    return 0 if result.first_difference is None else 1
