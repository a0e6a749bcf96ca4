"""The configuration: every key with its default, range and meaning; checking a file.

  mmctl config reference              every key: default, allowed values, unit, meaning
  mmctl config reference --markdown   the same as docs/configuration.md's table
  mmctl config check FILE [--dump]    = mmctl check-config FILE
"""

from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=("reference", "check"),
                   help="reference: every key; check: validate FILE")
    p.add_argument("file", nargs="?", help="check: the YAML config file")
    p.add_argument("--markdown", action="store_true",
                   help="reference: as a markdown document (docs/configuration.md)")
    p.add_argument("--dump", action="store_true",
                   help="check: print the full config with defaults as JSON")


def run(args: argparse.Namespace) -> int:
    from mmctl.errors import MmctlError

    if args.action == "check":
        if not args.file:
            raise MmctlError("config check needs a FILE")
        from mmctl.commands import check_config

        return check_config.run(args)
    if args.file:
        raise MmctlError("config reference takes no FILE")
    from mmctl.config import Config, reference
    from mmctl.config.schema import keys

    if args.markdown:
        print(reference(), end="")
        return 0
    for key, default, allowed, unit, meaning in keys(Config):
        u = f" [{unit}]" if unit else ""
        print(f"{key} = {default}{u}\n    allowed: {allowed}")
        if meaning:
            print(f"    {meaning}")
    return 0
