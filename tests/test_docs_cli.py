"""docs/cli.md, the command-line reference, against the real parser (``cli.build_parser``):
every command has its section (``## `floxels SUB` ``) and every option of the command is named
there (as ``--option``, in backquotes), and the page names no option the command lacks. A new
option fails here until the page says what it does."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from floxels_ext import cli

ROOT = Path(__file__).resolve().parents[1]
CLI_MD = ROOT / "docs" / "cli.md"
COMMON = {"-h", "--help", "-q", "--quiet", "-v", "--verbose"}  # every command's, in "Conventions"


def _subparsers() -> dict:
    parser = cli.build_parser()
    [action] = [a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict)]
    return action.choices


def _sections(text: str) -> dict[str, str]:
    """Body of each ``## `floxels SUB` `` section, by SUB."""
    out = {}
    parts = re.split(r"^## ", text, flags=re.M)
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        m = re.fullmatch(r"`floxels (\S+)`", head.strip())
        if m:
            out[m.group(1)] = body
    return out


def _named_options(body: str) -> set[str]:
    """Options named in code spans of a section (``--opt``, ``--opt VALUE``, ``--opt {a,b}``)."""
    names = set()
    for span in re.findall(r"`([^`]*)`", body):
        names |= set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", span))
    return names


SUBS = _subparsers()
SECTIONS = _sections(CLI_MD.read_text(encoding="utf-8"))


@pytest.mark.parametrize("sub", sorted(SUBS))
def test_every_option_is_documented(sub):
    assert sub in SECTIONS, f"docs/cli.md has no section '## `floxels {sub}`'"
    options = {o for a in SUBS[sub]._actions for o in a.option_strings if o.startswith("--")} - COMMON
    named = _named_options(SECTIONS[sub])
    assert not options - named, f"docs/cli.md, floxels {sub}: options not described: {sorted(options - named)}"
    stray = named - options - COMMON
    assert not stray, f"docs/cli.md, floxels {sub}: names options the command does not have: {sorted(stray)}"


def test_no_section_for_a_missing_command():
    assert not set(SECTIONS) - set(SUBS), f"docs/cli.md documents commands floxels lacks: {sorted(set(SECTIONS) - set(SUBS))}"


def test_the_check_catches_a_missing_option():
    body = "| `--a X` | ... |\n| `--b {x,y}` | also `--c`, not --d |\n"
    assert _named_options(body) == {"--a", "--b", "--c"}
    assert _sections("# T\n## `floxels run`\nx\n## Other\ny\n## `floxels show`\nz\n") == {"run": "x\n", "show": "z\n"}
