"""The daemon's process holds what it holds on the robot: `mmctl.runtime` (and the
transports it loads) import nothing from the simulation (`mmctl.sim`) or the study
(`mmctl.study`), at any depth of the module, lazily or not."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "mmctl"
FORBIDDEN = ("mmctl.sim", "mmctl.study")


def _imports(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.append((node.lineno, node.module))
    return out


@pytest.mark.parametrize("package", ["runtime", "transports", "control", "model", "config"])
def test_daemon_side_packages_never_import_the_simulation(package: str) -> None:
    bad = [f"{p.relative_to(SRC)}:{line}: {name}"
           for p in sorted((SRC / package).rglob("*.py"))
           for line, name in _imports(p)
           if name == FORBIDDEN[0] or name.startswith(tuple(f + "." for f in FORBIDDEN))
           or name in FORBIDDEN]
    assert bad == []


def test_the_check_sees_an_import() -> None:
    """The walk finds lazy imports inside functions (what the rule is about)."""
    found = _imports(SRC / "commands" / "sim.py")
    assert any(name == "mmctl.sim.service" for _line, name in found)
