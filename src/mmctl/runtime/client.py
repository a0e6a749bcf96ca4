"""What the client commands (`mmctl status`, `enable`, ...) share: finding the config
and the control socket, and one request with a one-line error."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

from mmctl.config import Config, load_config, sim_profile
from mmctl.runtime.ipc import ControlClient, resolve_socket_path

#: Where the systemd service puts its socket (RuntimeDirectory=mmctl).
SERVICE_SOCKET = Path("/run/mmctl/mmctl.sock")


def default_config_path() -> Path:
    """$MMCTL_CONFIG, else ./config/sim.yaml when it exists, else the simulated robot's
    profile installed with the package (:func:`mmctl.config.sim_profile`): without a
    configuration named, every command means the simulated robot.  (The built-in
    defaults are the real robot's: an empty file does not start a simulation.)"""
    env = os.environ.get("MMCTL_CONFIG")
    if env:
        return Path(env)
    local = Path("config") / "sim.yaml"
    return local if local.is_file() else sim_profile()


def load(path: str | None) -> Config:
    """The config named on the command line, or the default one."""
    return load_config(Path(path) if path else default_config_path())


def add_client_arguments(p: argparse.ArgumentParser) -> None:
    """--socket and --config, common to every command that talks to the daemon."""
    p.add_argument("--socket", metavar="PATH", help="control socket (default: from the config)")
    p.add_argument("--config", metavar="FILE", help="config file whose daemon.socket_path to use")
    p.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="how long to wait for the daemon's answer [s] (default 10)")


def socket_for(args: argparse.Namespace) -> Path:
    """--socket, else the config's socket, else the service's socket if only that exists."""
    if getattr(args, "socket", None):
        return Path(args.socket)
    path = resolve_socket_path(load(getattr(args, "config", None)).daemon.socket_path)
    if not path.exists() and not getattr(args, "config", None) and SERVICE_SOCKET.exists():
        return SERVICE_SOCKET
    return path


def call(args: argparse.Namespace, cmd: str, **params: object) -> Any:
    """One request to the daemon; IpcError (one line) when there is none or it refuses."""
    with ControlClient(socket_for(args), getattr(args, "timeout", 10.0)) as client:
        return client.call(cmd, **params)


def summary(st: dict[str, object]) -> str:
    """One line: state, mode, fault."""
    mode = st.get("mode", "?")
    if mode == "switch" and st.get("switch"):
        mode = f"switch/{st['switch']}"
    line = f"state={st.get('state')} mode={mode}"
    if st.get("profile") == "reduced":
        line += " profile=reduced"
    if st.get("enabling"):
        line += f" enabling={st['enabling']}"
    if st.get("fault"):
        line += f" fault={st['fault']}"
    conditions = st.get("conditions")
    if isinstance(conditions, list) and conditions:
        line += f" conditions={','.join(map(str, conditions))}"
    return line
