"""The daemon's process holds what it holds on the robot: `mmctl.runtime` (and the
transports, control chain and telemetry it loads) import nothing from the simulation
(`mmctl.sim`), the study (`mmctl.study`) or the benchmarks (`mmctl.bench`), at any depth
of the module, lazily or not."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "mmctl"
FORBIDDEN = ("mmctl.sim", "mmctl.study", "mmctl.bench")


def _imports(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.append((node.lineno, node.module))
    return out


@pytest.mark.parametrize("package", ["runtime", "transports", "control", "model", "config",
                                     "telemetry"])
def test_daemon_side_packages_never_import_the_simulation(package: str) -> None:
    bad = [f"{p.relative_to(SRC)}:{line}: {name}"
           for p in sorted((SRC / package).rglob("*.py"))
           for line, name in _imports(p)
           if name in FORBIDDEN or name.startswith(tuple(f + "." for f in FORBIDDEN))]
    assert bad == []


def test_the_check_sees_an_import() -> None:
    """The walk finds lazy imports inside functions (what the rule is about)."""
    found = _imports(SRC / "commands" / "sim.py")
    assert any(name == "mmctl.sim.service" for _line, name in found)


def test_the_daemon_loads_no_optional_extra() -> None:
    """`pip install mmctl` (no extras) runs the daemon: building it and its command
    loads none of the telemetry, study or bench extras' modules (telemetry off)."""
    import json
    import subprocess
    import sys

    from mmctl.extras import EXTRAS

    code = (
        "import json, sys\n"
        "import mmctl.cli, mmctl.commands.run\n"
        "from mmctl.config import default_config\n"
        "from mmctl.runtime.factory import create_daemon\n"
        "create_daemon(default_config(), None)\n"
        "print(json.dumps(sorted({m.split('.')[0] for m in sys.modules})))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120).stdout
    loaded = set(json.loads(out))
    optional = {m for mods in EXTRAS.values() for m in mods}
    assert loaded & optional == set()
    assert {"numpy", "pinocchio", "can", "canopen"} <= loaded  # the check sees imports


def test_a_missing_extra_is_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from mmctl import extras
    from mmctl.errors import MmctlError

    monkeypatch.setitem(extras.EXTRAS, "telemetry", ("rerun", "mmctl_no_such_module"))
    with pytest.raises(MmctlError, match=r"telemetry \(--viewer\) needs the 'telemetry' extra "
                                         r"\(missing: mmctl_no_such_module\): "
                                         r"pip install 'mmctl\[telemetry\]'"):
        extras.require("telemetry", "telemetry (--viewer)")
    extras.require("study", "the study's figures")  # installed here: no error


def test_mode_names_come_from_one_enum() -> None:
    """The config's choices, the controller, the CLI and the telemetry codes all use
    :class:`mmctl.config.control.Mode`."""
    from typing import get_args

    from mmctl.cli import build_parser
    from mmctl.config.control import STRATEGIES, Mode, Strategy, SwitchMode
    from mmctl.control import step
    from mmctl.telemetry import ring

    assert STRATEGIES == get_args(Strategy) == tuple(m.value for m in Mode)
    assert step.Mode is Mode and step.SwitchMode is SwitchMode
    assert set(step.SOLVERS) == set(STRATEGIES) - {Mode.SWITCH.value}
    modes = [m for m in ring.MODES if m != "idle"]
    assert [m.split("/")[0] for m in modes] == [
        s for s in STRATEGIES for _ in (SwitchMode if s == Mode.SWITCH.value else (s,))]
    sub = build_parser()._subparsers._group_actions[0].choices  # type: ignore[union-attr]
    mode_cmd = sub["mode"]
    assert any(tuple(a.choices or ()) == STRATEGIES for a in mode_cmd._actions)


def test_the_runtime_has_no_import_cycle_and_no_mixin() -> None:
    """The daemon's runtime is layered: no module of mmctl.runtime imports (even for the
    type checker only) one that imports it back, and the daemon composes its parts
    (the loop's runtime, the operator, the calibration) instead of inheriting them."""
    import ast
    from pathlib import Path

    import mmctl.runtime
    from mmctl.runtime.daemon import Daemon

    root = Path(mmctl.runtime.__file__).parent
    graph: dict[str, set[str]] = {}
    for path in root.glob("*.py"):
        name = f"mmctl.runtime.{path.stem}"
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                mods = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
                deps |= {m for m in mods if m.startswith("mmctl.runtime.")}
            elif isinstance(node, ast.Import):
                deps |= {a.name for a in node.names if a.name.startswith("mmctl.runtime.")}
        graph[name] = deps - {name}
    seen: dict[str, int] = {}  # 1: on the path, 2: done

    def visit(mod: str, path: tuple[str, ...]) -> None:
        if seen.get(mod) == 1:
            raise AssertionError(f"import cycle: {' -> '.join(path + (mod,))}")
        if seen.get(mod) == 2 or mod not in graph:
            return
        seen[mod] = 1
        for dep in sorted(graph[mod]):
            visit(dep, path + (mod,))
        seen[mod] = 2

    for mod in sorted(graph):
        visit(mod, ())
    assert Daemon.__bases__ == (object,)
