"""One client connection to the fake's RTDE port (30004): handshake, recipes, packages.

A session turns the bytes a client sends into replies (protocol version, controller
version, output/input recipe setup, start/pause) and register writes, and packs the
output packages it streams once started.  It owns no socket: the server feeds it bytes
and sends what :meth:`RtdeSession.feed` and :meth:`RtdeSession.data_package` return.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

import structlog

from mmctl.sim.fake_ur.model import ControllerModel
from mmctl.sim.fake_ur.rtde_types import (
    HEADER,
    INPUT_TYPES,
    NOT_FOUND,
    OUTPUT_TYPES,
    TYPE_WIDTH,
    MsgType,
    frame,
    recipe_struct,
    register_index,
)

log = structlog.get_logger("mmctl.fake_ur.rtde")

CONTROLLER_RATE = 500.0
"""[Hz] the fake's controller frequency (e-Series)."""
_VERSION = struct.Struct(">IIII")
_U16 = struct.Struct(">H")
_DOUBLE = struct.Struct(">d")


@dataclass
class OutputRecipe:
    """An ``O`` recipe: what to send, how often (every ``every`` controller periods)."""

    recipe_id: int
    every: int
    packer: struct.Struct
    getters: list[tuple[Callable[[], object], bool]]


@dataclass
class InputRecipe:
    """An ``I`` recipe: how to unpack a client's data package into registers."""

    recipe_id: int
    unpacker: struct.Struct
    targets: list[tuple[str, int]]  # ("int" | "double" | "other", register index)
    int_registers: list[int]


class RtdeSession:
    """The state of one RTDE client connection."""

    def __init__(self, model: ControllerModel, peer: str):
        self.model = model
        self.peer = peer
        self.protocol_version = 1
        self.started = False
        self.outputs: list[OutputRecipe] = []
        self.inputs: dict[int, InputRecipe] = {}
        self._next_input_id = 1
        self._buf = bytearray()

    # -- client -> controller --------------------------------------------------------------

    def feed(self, data: bytes) -> bytes:
        """Consume received bytes; return the replies to send."""
        self._buf += data
        out = bytearray()
        buf = self._buf
        while len(buf) >= HEADER.size:
            size, msg_type = HEADER.unpack_from(buf)
            if size < HEADER.size:
                raise ValueError(f"RTDE package size {size} < header")
            if len(buf) < size:
                break
            payload = bytes(buf[HEADER.size:size])
            del buf[:size]
            out += self._handle(msg_type, payload)
        return bytes(out)

    def _handle(self, msg_type: int, payload: bytes) -> bytes:
        if msg_type == MsgType.DATA_PACKAGE:
            self._data(payload)
            return b""
        if msg_type == MsgType.REQUEST_PROTOCOL_VERSION:
            version = _U16.unpack_from(payload)[0] if len(payload) >= 2 else 0
            ok = version in (1, 2)
            if ok:
                self.protocol_version = version
            return frame(msg_type, bytes([1 if ok else 0]))
        if msg_type == MsgType.GET_URCONTROL_VERSION:
            return frame(msg_type, _VERSION.pack(*self.model.version))
        if msg_type == MsgType.CONTROL_PACKAGE_SETUP_OUTPUTS:
            return frame(msg_type, self._setup_outputs(payload))
        if msg_type == MsgType.CONTROL_PACKAGE_SETUP_INPUTS:
            return frame(msg_type, self._setup_inputs(payload))
        if msg_type == MsgType.CONTROL_PACKAGE_START:
            self.started = True
            return frame(msg_type, b"\x01")
        if msg_type == MsgType.CONTROL_PACKAGE_PAUSE:
            self.started = False
            return frame(msg_type, b"\x01")
        log.warning("rtde_unknown_package", peer=self.peer, type=msg_type, size=len(payload))
        return b""

    def _setup_outputs(self, payload: bytes) -> bytes:
        frequency = CONTROLLER_RATE
        if self.protocol_version >= 2:
            frequency = _DOUBLE.unpack_from(payload)[0]
            payload = payload[_DOUBLE.size:]
        names = _names(payload)
        types = [OUTPUT_TYPES.get(n, NOT_FOUND) for n in names]
        if NOT_FOUND in types or not names or not 0.0 < frequency <= CONTROLLER_RATE:
            log.warning("rtde_output_setup_refused", peer=self.peer, frequency=frequency,
                        missing=[n for n, t in zip(names, types) if t == NOT_FOUND])
            return b"\x00" + ",".join(types).encode()
        recipe_id = len(self.outputs) + 1
        getters = []
        for name, rtde_type in zip(names, types):
            width = TYPE_WIDTH[rtde_type]
            getter = self.model.getter(name)
            if getter is None:
                zero: object = [0] * width if width > 1 else 0
                getter = _constant(zero)
            getters.append((getter, width > 1))
        self.outputs.append(OutputRecipe(
            recipe_id, max(1, round(CONTROLLER_RATE / frequency)), recipe_struct(types), getters))
        return bytes([recipe_id]) + ",".join(types).encode()

    def _setup_inputs(self, payload: bytes) -> bytes:
        names = _names(payload)
        types = [INPUT_TYPES.get(n, NOT_FOUND) for n in names]
        if NOT_FOUND in types or not names or self._next_input_id > 255:
            log.warning("rtde_input_setup_refused", peer=self.peer,
                        missing=[n for n, t in zip(names, types) if t == NOT_FOUND])
            return b"\x00" + ",".join(types).encode()
        targets: list[tuple[str, int]] = []
        int_registers: list[int] = []
        for name, rtde_type in zip(names, types):
            i = register_index(name, "input_int_register_")
            d = register_index(name, "input_double_register_")
            if i is not None:
                targets.append(("int", i))
                int_registers.append(i)
            elif d is not None:
                targets.append(("double", d))
            else:
                targets.append(("other", TYPE_WIDTH[rtde_type]))
        recipe_id = self._next_input_id
        self._next_input_id += 1
        self.inputs[recipe_id] = InputRecipe(recipe_id, recipe_struct(types), targets, int_registers)
        return bytes([recipe_id]) + ",".join(types).encode()

    def _data(self, payload: bytes) -> None:
        recipe = self.inputs.get(payload[0]) if payload else None
        if recipe is None or len(payload) != recipe.unpacker.size:
            log.warning("rtde_bad_data_package", peer=self.peer, size=len(payload),
                        recipe=payload[0] if payload else None)
            return
        values = recipe.unpacker.unpack(payload)
        regs = self.model.regs
        k = 1
        for kind, index in recipe.targets:
            if kind == "int":
                regs.in_int[index] = values[k]
                k += 1
            elif kind == "double":
                regs.in_double[index] = values[k]
                k += 1
            else:
                k += index
        for index in recipe.int_registers:
            self.model.input_written(index)

    # -- controller -> client --------------------------------------------------------------

    def data_packages(self, tick: int) -> bytes:
        """The output packages due at controller period ``tick`` (empty unless started)."""
        if not self.started:
            return b""
        out = b""
        for recipe in self.outputs:
            if tick % recipe.every:
                continue
            values: list[object] = [recipe.recipe_id]
            for getter, vector in recipe.getters:
                v = getter()
                if vector:
                    values.extend(v)  # type: ignore[arg-type]
                else:
                    values.append(v)
            out += frame(MsgType.DATA_PACKAGE, recipe.packer.pack(*values))
        return out


def _names(payload: bytes) -> list[str]:
    return [n.strip() for n in payload.decode("ascii", errors="replace").split(",") if n.strip()]


def _constant(value: object) -> Callable[[], object]:
    return lambda: value
