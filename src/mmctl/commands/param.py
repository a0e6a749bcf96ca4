"""Change or read a control parameter while the daemon runs: `mmctl set KEY VALUE`,
`mmctl get KEY`.

Settable at run time: the admittance's virtual mass and damping, the whole-body caps
(limits.energy, base_speed, ee_speed, reduced_ee_speed, body_region), the null-space
gain idk.null_gain and the IDK's weights (idk.locomotion.w_alpha / w_beta,
idk.constrained.task_weight).  VALUE is YAML: ``60``, ``[4, 4, 4, 4, 4, 4]``, ``null``
(a derived cap), ``chest``; a single number sets every entry of a list.  The value is
checked as the configuration file is (the same one-line error), applied without a jump
in the commanded velocity (a lower cap is reached on the acceleration limits), logged
(``param_set``) and shown by `mmctl status` (``changed``).  The change lasts until the
daemon restarts: write it into the configuration file to keep it.  `mmctl get` reads any
key of the running configuration.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import yaml

from mmctl.errors import MmctlError
from mmctl.runtime.client import add_client_arguments, call


def add_set_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("key", help="dotted key, e.g. admittance.damping (see `mmctl config "
                   "reference`)")
    p.add_argument("value", help="YAML value: 60, [4, 4, 4, 4, 4, 4], null, chest")
    p.add_argument("--json", action="store_true", help="print the reply as JSON")
    add_client_arguments(p)


def add_get_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("key", help="dotted key, e.g. limits.energy")
    p.add_argument("--json", action="store_true", help="print the reply as JSON")
    add_client_arguments(p)


def parse_value(text: str) -> Any:
    """VALUE as YAML (one line); MmctlError for what YAML cannot read."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0]
        raise MmctlError(f"cannot read {text!r} as a YAML value ({first})") from None


def _text(value: Any) -> str:
    return json.dumps(value)


def run_set(args: argparse.Namespace) -> int:
    res = call(args, "set", key=args.key, value=parse_value(args.value))
    if args.json:
        print(json.dumps({k: v for k, v in res.items() if k != "status"}))
        return 0
    print(f"{res['key']}: {_text(res['old'])} -> {_text(res['value'])}")
    return 0


def run_get(args: argparse.Namespace) -> int:
    res = call(args, "get", key=args.key)
    if args.json:
        print(json.dumps(res))
        return 0
    note = " (changed at run time)" if res.get("changed") else ""
    print(f"{res['key']}: {_text(res['value'])}{note}")
    return 0
