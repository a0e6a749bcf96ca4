"""RTDE wire facts: message types, the variable type table and how each type is packed.

RTDE (Universal Robots' Real-Time Data Exchange, port 30004) frames every message as
``uint16 size`` (header included, big-endian) + ``uint8 type`` + payload.  Protocol
version 2 is what ur_rtde speaks.  Types and names below follow UR's published RTDE
guide for PolyScope 5.x; the vector lengths are those ur_rtde unpacks (3 for the
accelerometer, elbow and payload COG, 6 otherwise).
"""

from __future__ import annotations

import struct
from enum import IntEnum

HEADER = struct.Struct(">HB")
"""size (uint16, header included), type (uint8)."""


class MsgType(IntEnum):
    """RTDE package types (the ASCII letter of each)."""

    REQUEST_PROTOCOL_VERSION = 86  # 'V'
    GET_URCONTROL_VERSION = 118  # 'v'
    TEXT_MESSAGE = 77  # 'M'
    DATA_PACKAGE = 85  # 'U'
    CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
    CONTROL_PACKAGE_SETUP_INPUTS = 73  # 'I'
    CONTROL_PACKAGE_START = 83  # 'S'
    CONTROL_PACKAGE_PAUSE = 80  # 'P'


#: RTDE type name -> struct format (big-endian, without the byte-order prefix).
TYPE_FORMATS: dict[str, str] = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

#: Number of scalars a value of each type flattens to.
TYPE_WIDTH: dict[str, int] = {
    "BOOL": 1, "UINT8": 1, "UINT32": 1, "UINT64": 1, "INT32": 1, "DOUBLE": 1,
    "VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6,
}

NOT_FOUND = "NOT_FOUND"
REGISTER_COUNT = 48
"""Integer and double registers 0..47 in each direction (24..47 are the upper range)."""


def _output_table() -> dict[str, str]:
    v6 = "VECTOR6D"
    table = {
        "timestamp": "DOUBLE",
        "target_q": v6, "target_qd": v6, "target_qdd": v6, "target_current": v6,
        "target_moment": v6, "actual_q": v6, "actual_qd": v6, "actual_qdd": v6,
        "actual_current": v6, "actual_current_window": v6, "actual_current_as_torque": v6,
        "actual_moment": v6, "joint_control_output": v6, "actual_TCP_pose": v6,
        "actual_TCP_speed": v6, "actual_TCP_force": v6, "target_TCP_pose": v6,
        "target_TCP_speed": v6, "joint_temperatures": v6, "actual_joint_voltage": v6,
        "ft_raw_wrench": v6, "payload_inertia": v6, "joint_position_deviation_ratio": "DOUBLE",
        "actual_digital_input_bits": "UINT64", "actual_digital_output_bits": "UINT64",
        "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
        "safety_mode": "INT32", "safety_status": "INT32",
        "actual_tool_accelerometer": "VECTOR3D", "elbow_position": "VECTOR3D",
        "elbow_velocity": "VECTOR3D", "payload_cog": "VECTOR3D",
        "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
        "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE",
        "actual_robot_current": "DOUBLE", "runtime_state": "UINT32",
        "robot_status_bits": "UINT32", "safety_status_bits": "UINT32",
        "analog_io_types": "UINT32", "standard_analog_input0": "DOUBLE",
        "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
        "standard_analog_output1": "DOUBLE", "io_current": "DOUBLE",
        "euromap67_input_bits": "UINT32", "euromap67_output_bits": "UINT32",
        "euromap67_24V_voltage": "DOUBLE", "euromap67_24V_current": "DOUBLE",
        "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
        "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
        "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE",
        "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE",
        "tool_output_mode": "UINT8", "tool_digital_output0_mode": "UINT8",
        "tool_digital_output1_mode": "UINT8", "payload": "DOUBLE",
        "script_control_line": "UINT32", "collision_detection_ratio": "DOUBLE",
        "time_scale_source": "UINT32",
        "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    }
    for i in range(64, 128):
        table[f"output_bit_register_{i}"] = "BOOL"
        table[f"input_bit_register_{i}"] = "BOOL"
    for i in range(REGISTER_COUNT):
        table[f"output_int_register_{i}"] = "INT32"
        table[f"output_double_register_{i}"] = "DOUBLE"
        table[f"input_int_register_{i}"] = "INT32"
        table[f"input_double_register_{i}"] = "DOUBLE"
    return table


def _input_table() -> dict[str, str]:
    table = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(64, 128):
        table[f"input_bit_register_{i}"] = "BOOL"
    for i in range(REGISTER_COUNT):
        table[f"input_int_register_{i}"] = "INT32"
        table[f"input_double_register_{i}"] = "DOUBLE"
    return table


OUTPUT_TYPES: dict[str, str] = _output_table()
"""Every variable a client may ask the controller to send (``O`` recipes)."""

INPUT_TYPES: dict[str, str] = _input_table()
"""Every variable a client may write (``I`` recipes)."""


def recipe_struct(types: list[str]) -> struct.Struct:
    """The struct of one data package body (recipe id first) for a list of RTDE types."""
    return struct.Struct(">B" + "".join(TYPE_FORMATS[t] for t in types))


def frame(msg_type: int, payload: bytes = b"") -> bytes:
    """One RTDE message: header + payload."""
    return HEADER.pack(HEADER.size + len(payload), msg_type) + payload


def register_index(name: str, prefix: str) -> int | None:
    """``input_int_register_7`` with prefix ``input_int_register_`` -> 7; otherwise None."""
    if name.startswith(prefix):
        tail = name[len(prefix):]
        if tail.isdigit():
            return int(tail)
    return None
