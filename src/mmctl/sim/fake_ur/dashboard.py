"""The dashboard server (port 29999): one text line in, one text line out.

Answers follow UR's dashboard server for PolyScope 5.x; only what ur_rtde and an
operator's bring-up use is modelled, anything else gets the server's
"could not understand" answer.
"""

from __future__ import annotations

from mmctl.sim.fake_ur.model import ControllerModel

WELCOME = "Connected: Universal Robots Dashboard Server"


def answer(model: ControllerModel, line: str) -> tuple[str, bool]:
    """The reply to one command line, and whether the server closes the connection."""
    cmd = line.strip()
    low = cmd.lower()
    playing = model.program is not None
    if low == "polyscopeversion":
        return f"URSoftware {model.version_text} (Apr 30 2021)", False
    if low == "version":
        return model.version_text, False
    if low == "get serial number":
        return model.serial, False
    if low == "get robot model":
        return "UR10", False
    if low == "is in remote control":
        return ("true" if model.remote_control else "false"), False
    if low == "robotmode":
        return "Robotmode: RUNNING", False
    if low == "safetystatus":
        return f"Safetystatus: {model.safety_status_name}", False
    if low == "safetymode":
        return f"Safetymode: {model.safety_status_name}", False
    if low == "programstate":
        return f"{'PLAYING' if playing else 'STOPPED'} {model.program_name}", False
    if low == "running":
        return f"Program running: {'true' if playing else 'false'}", False
    if low == "get loaded program":
        return "No program loaded", False
    if low == "isprogramsaved":
        return f"false {model.program_name}", False
    if low == "quit":
        return "Disconnected", True
    if low.startswith("addtolog"):
        return "Added log message", False
    if low.startswith("popup"):
        return "showing popup", False
    if low == "close popup":
        return "closing popup", False
    if low == "close safety popup":
        return "closing safety popup", False
    if low.startswith("setuserrole"):
        return f"Setting user role: {cmd[len('setUserRole'):].strip()}", False
    control = _control(model, low, cmd)
    if control is not None:
        return control, False
    return f"could not understand: '{cmd}'", False


def _control(model: ControllerModel, low: str, cmd: str) -> str | None:
    """Commands that act on the robot (refused in local control)."""
    replies = {
        "stop": "Stopped", "pause": "Pausing program", "play": "Failed to execute: play",
        "power on": "Powering on", "power off": "Powering off",
        "brake release": "Brake releasing", "unlock protective stop": "Protective stop releasing",
        "restart safety": "Restarting safety", "shutdown": "Shutting down",
    }
    if low.startswith("load "):
        reply = f"File not found: {cmd[5:].strip()}"
    elif low in replies:
        reply = replies[low]
    else:
        return None
    if not model.remote_control:
        return "Command is not allowed due to local control"
    if low == "stop":
        model.stop_program("dashboard stop")
    elif low == "unlock protective stop":
        model.set_protective_stop(False)
    return reply
