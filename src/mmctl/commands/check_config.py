"""Validate a YAML configuration file.

Prints "ok" when the file is valid, otherwise one line naming the key path, the
offending value and what is allowed, and exits with status 2.
"""

from __future__ import annotations

import argparse
import json

from mmctl.config import load_config, to_dict


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="YAML config file, e.g. config/sim.yaml")
    p.add_argument("--dump", action="store_true", help="print the full config with defaults as JSON")


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.file)
    if args.dump:
        print(json.dumps(to_dict(cfg), indent=2))
    else:
        print("ok")
    return 0
