"""``tools/update_cost.py``: the instructions-per-update figure under callgrind.

The workload runs in-process (every mode commands motion without a fault); the tool
itself runs under valgrind with a tiny ``--n`` when valgrind is installed (about 20 s,
most of it valgrind starting Python).  Only that a positive figure comes out is checked,
never its size.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import pytest

from mmctl.config import load_config

_TOOL = Path(__file__).resolve().parent.parent / "tools" / "update_cost.py"
_spec = importlib.util.spec_from_file_location("mmctl_update_cost_tool", _TOOL)
assert _spec is not None and _spec.loader is not None
update_cost = importlib.util.module_from_spec(_spec)
sys.modules["mmctl_update_cost_tool"] = update_cost
_spec.loader.exec_module(update_cost)


@pytest.mark.parametrize("mode", update_cost.MODES)
def test_the_scripted_cycle_moves_in_every_mode(mode: str) -> None:
    w = update_cost.TARGETS["cycle"](load_config(update_cost.DEFAULT_CONFIG), mode)
    assert w.check() == "no update ran"
    w.run(w.make(5))
    items = w.make(3)
    assert items[0][1] < items[-1][1]  # the clock runs on across calls
    w.run(items)
    assert w.check() is None


def test_totals_from_a_callgrind_dump(tmp_path: Path) -> None:
    dump = tmp_path / "callgrind.out.1"
    dump.write_text("version: 1\nevents: Ir\nfl=x\nfn=y\n0 5\nsummary: 1234\n"
                    "totals: 1234\n")
    assert update_cost._totals(dump) == 1234


@pytest.mark.skipif(shutil.which("valgrind") is None or shutil.which("callgrind_control")
                    is None, reason="valgrind (callgrind) is not installed")
def test_the_tool_prints_instructions_per_update(capsys: pytest.CaptureFixture[str]) -> None:
    assert update_cost.main(["--n", "3", "--warmup", "2", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["target"] == "cycle" and data["n"] == 3
    assert data["ir_per_update"]["min-energy"] > 0
    assert data["ir_total"]["min-energy"] > 0


def test_bad_arguments_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        update_cost.main(["--n", "0"])
    assert e.value.code == 2
    assert "--n must be >= 1" in capsys.readouterr().err
