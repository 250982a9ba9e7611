"""One place for the runtime switches: every FLOXELS_* name used anywhere in the sources is
listed in floxels_ext.switches and in the table of docs/switches.md, and nothing is listed that
no source uses any more."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from floxels_ext.switches import SWITCHES, flag

ROOT = Path(__file__).resolve().parents[1]
NAME = re.compile(r"\bFLOXELS_[A-Z0-9_]*[A-Z0-9]\b")
# compile-time macros set by CMake (not environment variables a user sets)
MACROS = {"FLOXELS_WITH_CUDA"}


def _source_names() -> set[str]:
    files = [ROOT / "CMakeLists.txt", ROOT / ".ci" / "run"]
    for d, pats in (("python", ("*.py",)), ("csrc", ("*.cpp", "*.h", "*.cu", "*.cuh")), ("tests", ("*.py",)),
                    ("bench", ("*.py", "*.sh")), ("tools", ("*.py", "*.sh"))):
        for pat in pats:
            files += list((ROOT / d).rglob(pat))
    names = set()
    for f in files:
        if f.is_file() and f.name != "test_switches.py" and f.name != "switches.py":
            names |= set(NAME.findall(f.read_text(errors="replace")))
    return names - MACROS


def test_every_switch_is_listed():
    listed = {s.name for s in SWITCHES}
    used = _source_names()
    assert not used - listed, f"FLOXELS_* names used but not listed in floxels_ext/switches.py: {sorted(used - listed)}"
    assert not listed - used, f"listed in floxels_ext/switches.py but used nowhere: {sorted(listed - used)}"


def _table_names() -> list[str]:
    """The variables of docs/switches.md's table: its rows' first cells."""
    text = (ROOT / "docs" / "switches.md").read_text(encoding="utf-8")
    return re.findall(r"^\|\s*`(FLOXELS_[A-Z0-9_]+)`\s*\|", text, flags=re.M)


def test_docs_table_lists_every_switch():
    rows = _table_names()
    listed = [s.name for s in SWITCHES]
    missing = [n for n in listed if n not in rows]
    assert not missing, f"docs/switches.md's table lacks {missing}"
    extra = [n for n in rows if n not in listed]
    assert not extra, f"docs/switches.md's table lists {extra}, which floxels_ext/switches.py does not"
    assert len(rows) == len(set(rows)), "docs/switches.md's table lists a variable twice"


@pytest.mark.parametrize("value,default_on,expected", [(None, True, True), ("0", True, False), ("1", True, True),
                                                       (None, False, False), ("1", False, True), ("0", False, False)])
def test_flag(monkeypatch, value, default_on, expected):
    name = "FLOXELS_PIPELINE" if default_on else "FLOXELS_SERIAL_STAGES"
    if value is None:
        monkeypatch.delenv(name, raising=False)
    else:
        monkeypatch.setenv(name, value)
    assert flag(name) is expected
