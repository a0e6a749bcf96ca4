"""Re-zero the force/torque sensor (software bias over sensor.wrench.tare_samples samples).

Refused while armed: a tare must not absorb the operator's push.
"""

from __future__ import annotations

import argparse

from mmctl.runtime.client import add_client_arguments, call


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    res = call(args, "tare")
    print(f"taring over {res.get('samples')} samples")
    return 0
