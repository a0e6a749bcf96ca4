"""Select the limits' profile at run time: normal, or reduced for first runs.

reduced caps the end-effector at ``limits.reduced_ee_speed`` (0.25 m/s, ISO 10218-1's
reduced speed for hand guiding) on top of the whole-body caps (kinetic energy, base
and end-effector speed from ISO/TS 15066, ``limits.body_region``).  A lower cap is
reached on the acceleration limits, never by a jump.  `mmctl status` shows the
profile, the caps in force and which limit bound the last command.
"""

from __future__ import annotations

import argparse

from mmctl.runtime.client import add_client_arguments, call, summary


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("profile", choices=("normal", "reduced"), help="the limits' profile")
    add_client_arguments(p)


def run(args: argparse.Namespace) -> int:
    st = call(args, "profile", profile=args.profile)
    caps = st.get("caps") or {}
    print(f"{summary(st)} caps: E_K <= {caps.get('energy_J')} J, base <= "
          f"{caps.get('base_speed_m_s')} m/s, end-effector <= {caps.get('ee_speed_m_s')} m/s")
    return 0
