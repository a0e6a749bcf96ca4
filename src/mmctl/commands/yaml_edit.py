"""Writing recorded values into a YAML config file in place, for the commands that
measure something the configuration should hold (`mmctl pose record --write`,
`mmctl calibrate tool --write`).

Only the entries named change: each is replaced where it stands (a value on its line,
or a block list below it), or added at the top of its section, which is added when
missing; every other line, comment and blank line stays.  :func:`write_checked` then
loads the whole new file and checks it before it replaces the old one.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from mmctl.errors import MmctlError

if TYPE_CHECKING:
    from mmctl.config import Config


def _meaningful(line: str) -> bool:
    """Neither blank nor a comment."""
    s = line.strip()
    return bool(s) and not s.startswith("#")


def _indent(line: str) -> str:
    m = re.match(r"[ \t]*", line)
    return m.group(0) if m else ""


def _block_end(lines: list[str], start: int, end: int, indent: str) -> int:
    """The first line after ``start`` (before ``end``) of a key at ``indent`` or less."""
    for i in range(start + 1, end):
        if _meaningful(lines[i]) and len(_indent(lines[i])) <= len(indent):
            return i
    return end


def _child_indent(lines: list[str], start: int, end: int, parent: str) -> str:
    """The indentation of the entries of the block ``lines[start + 1:end]``."""
    for i in range(start + 1, end):
        if _meaningful(lines[i]):
            return _indent(lines[i])
    return parent + "  "


def set_entries(text: str, path: Sequence[str], entries: Mapping[str, str],
                note: str = "") -> str:
    """``text`` (a YAML config) with each ``entries`` key (a value already written as
    YAML, e.g. ``"[0.1, 0.2]"``) set in the mapping at ``path`` (section names, e.g.
    ``("sensor", "wrench")``), each followed by ``# note``; everything else unchanged.
    MmctlError when a section on the path is written inline (``wrench: {...}``)."""
    lines = text.splitlines(keepends=True)
    comment = f"  # {note}" if note else ""
    lo, hi, indent = 0, len(lines), ""
    for depth, name in enumerate(path):
        at = None
        for i in range(lo, hi):
            m = re.match(rf"({re.escape(indent)}){re.escape(name)}:(.*)$", lines[i].rstrip("\n"))
            if m and _indent(lines[i]) == indent:
                rest = m.group(2).strip()
                if rest and not rest.startswith("#"):
                    raise MmctlError(f"{'.'.join(path[:depth + 1])} is written inline "
                                     f"({lines[i].strip()!r}): edit it by hand")
                at = i
                break
        if at is None:  # add the rest of the path (and the entries) here
            block = []
            for k, missing in enumerate(path[depth:]):
                block.append(f"{indent}{'  ' * k}{missing}:\n")
            inner = indent + "  " * (len(path) - depth)
            block += [f"{inner}{key}: {value}{comment}\n" for key, value in entries.items()]
            if depth == 0:
                sep = "" if not text or text.endswith("\n") else "\n"
                return text + sep + "".join(block)
            return "".join(lines[:lo] + block + lines[lo:])
        hi = _block_end(lines, at, hi, indent)
        indent = _child_indent(lines, at, hi, indent)
        lo = at + 1
    for key, value in entries.items():
        new = f"{indent}{key}: {value}{comment}\n"
        for i in range(lo, hi):
            if re.match(rf"{re.escape(indent)}{re.escape(key)}:", lines[i]) \
                    and _indent(lines[i]) == indent:
                j = i + 1  # a block list's items follow, deeper or at the same indent
                while j < hi and re.match(rf"{re.escape(indent)}(\s+|)- ", lines[j]):
                    j += 1
                lines[i:j] = [new]
                hi -= j - i - 1
                break
        else:
            lines.insert(lo, new)
            hi += 1
    return "".join(lines)


def write_checked(target: Path, text: str, check: Callable[[Config], None]) -> None:
    """Replace ``target`` by ``text`` once the new file loads as a configuration and
    ``check(config)`` passes (it raises MmctlError otherwise); the file's mode is kept."""
    from mmctl.config import load_config

    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", dir=str(target.parent or "."))
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        check(load_config(Path(tmp)))  # the whole file must still load
        if target.exists():
            os.chmod(tmp, target.stat().st_mode & 0o7777)
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
