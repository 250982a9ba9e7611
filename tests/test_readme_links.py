"""The README's promises that a newcomer tries first: every relative link resolves (files, and
``#anchors`` to a heading of the file they point into; also those of docs/*.md), and every
command of its quick start exists.

The quick start is the README section whose heading says "Quick start" (any level), with its
sub-sections; its commands are the lines of its fenced code blocks (``\\`` continuations joined,
``#`` comments dropped). Checked per command:

* ``floxels SUB ...`` / ``python -m floxels_ext SUB ...``: SUB is a command of ``floxels`` and
  every ``--option`` (also inside ``[...]``, the README's mark of an optional part) is one of
  SUB's options (the real parser: ``cli.build_parser``);
* ``pip install``: ``.`` is this repository (pyproject.toml), ``'floxels_ext[a,b]'`` names
  extras that pyproject.toml defines;
* ``python path.py`` / ``bash path.sh`` / ``./path``: the script exists; ``python -m pytest``:
  its path arguments exist.

Paths given to ``floxels`` itself are the user's data (``flow/00``), not checked.

Also: CI (``.ci/run``) runs the quick start's set-up and test commands, the README links every
file of docs/, stays a ten-minute read (at most 300 lines), and no heading of the README or of
docs/ names an issue number (a reader does not know them).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from floxels_ext import cli

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
_FENCE = re.compile(r"^\s*(```|~~~)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REF_LINK = re.compile(r"^\s*\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
_HTML_LINK = re.compile(r"<(?:img|a)\b[^>]*?\b(?:src|href)=\"([^\"]+)\"", re.I)


def _markdown_lines(path: Path):
    """(line, inside a fenced block) for each line of a markdown file."""
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if _FENCE.match(line):
            fenced = not fenced
            yield line, True
            continue
        yield line, fenced


def _slug(text: str) -> str:
    """GitHub's anchor of a heading: links reduced to their text, lower case, punctuation
    dropped (letters, digits, '_', '-' and spaces kept), spaces to '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", text)
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line, fenced in _markdown_lines(path):
        m = None if fenced else _HEADING.match(line)
        if m:
            s = _slug(m.group(2))
            out.add(s if s not in seen else f"{s}-{seen[s]}")
            seen[s] = seen.get(s, 0) + 1
    return out


def _links(path: Path) -> list[str]:
    out = []
    for line, fenced in _markdown_lines(path):
        if fenced:
            continue
        line = re.sub(r"`[^`]*`", "", line)  # code spans are not links
        out += _LINK.findall(line) + _HTML_LINK.findall(line)
        m = _REF_LINK.match(line)
        if m:
            out.append(m.group(1))
    return out


def _markdown_files() -> list[Path]:
    return [README] + sorted((ROOT / "docs").glob("*.md"))


@pytest.mark.parametrize("doc", _markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(doc):
    broken = []
    for target in _links(doc):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto: ...
            continue
        file_part, _, anchor = target.partition("#")
        dest = (doc.parent / file_part).resolve() if file_part else doc
        if not dest.exists():
            broken.append(f"{target}: no such file {dest}")
        elif anchor and dest.suffix == ".md" and anchor.lower() not in _anchors(dest):
            broken.append(f"{target}: no heading with the anchor #{anchor} in {dest.name}")
    assert not broken, f"{doc.name}: broken relative links:\n" + "\n".join(broken)


# ----------------------------------------------------------------------------- quick start
def quick_start_commands(path: Path = README) -> list[str]:
    """The command lines of the quick start's fenced code blocks (module docstring)."""
    level = None
    block: list[str] = []
    commands: list[str] = []
    in_code = False
    for line, fenced in _markdown_lines(path):
        m = None if fenced else _HEADING.match(line)
        if m:
            if level is not None and len(m.group(1)) <= level:
                break
            if level is None and "quick start" in m.group(2).lower():
                level = len(m.group(1))
            continue
        if level is None:
            continue
        if _FENCE.match(line):
            in_code = not in_code
            continue
        if in_code:
            block.append(line)
    pending = ""
    heredoc = None  # the end word of a here-document whose body is not a command
    for line in block:
        if heredoc is not None:
            heredoc = None if line.strip() == heredoc else heredoc
            continue
        m = re.search(r"<<-?\s*['\"]?(\w+)['\"]?", line)
        if m:
            heredoc = m.group(1)
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        text = (pending + line).strip()
        pending = ""
        words = shlex.split(text, comments=True) if text else []
        if words:
            commands.append(shlex.join(words))
    return commands


def _extras() -> set[str]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        tomli = pytest.importorskip("tomli")
        tomllib = tomli
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return set(tomllib.load(fh)["project"].get("optional-dependencies", {}))


def _subparsers() -> dict:
    parser = cli.build_parser()
    [action] = [a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict)]
    return parser, action.choices


def _check_floxels(words: list[str]) -> list[str]:
    parser, subs = _subparsers()
    words = [w.strip("[]") for w in words]
    words = [w for w in words if w]
    k = 0
    while k < len(words) and words[k].startswith("-"):
        if words[k] not in parser._option_string_actions:
            return [f"unknown option {words[k]} of floxels"]
        k += 1
    if k == len(words):
        return [] if words else ["no subcommand"]
    sub = words[k]
    if sub not in subs:
        return [f"floxels has no command {sub!r} (commands: {', '.join(subs)})"]
    known = subs[sub]._option_string_actions
    return [f"floxels {sub} has no option {w.split('=')[0]}" for w in words[k + 1:]
            if w.startswith("-") and not re.match(r"^-\d", w) and w.split("=")[0] not in known]


def _check_command(cmd: str) -> list[str]:
    words = shlex.split(cmd)
    if words[0] == "floxels":
        return _check_floxels(words[1:])
    if words[0] in ("python", "python3"):
        if words[1:3] == ["-m", "floxels_ext"]:
            return _check_floxels(words[3:])
        if words[1:3] == ["-m", "pytest"]:
            return [f"pytest path {w} does not exist" for w in words[3:]
                    if not w.startswith("-") and not (ROOT / w.split("::")[0]).exists()]
        if len(words) > 1 and words[1].endswith(".py"):
            return [] if (ROOT / words[1]).is_file() else [f"script {words[1]} does not exist"]
        return []
    if words[0] in ("bash", "sh") and len(words) > 1:
        return [] if (ROOT / words[1]).is_file() else [f"script {words[1]} does not exist"]
    if words[0].startswith("./"):
        return [] if (ROOT / words[0]).is_file() else [f"script {words[0]} does not exist"]
    if words[0] == "pip" and words[1:2] == ["install"]:
        problems = []
        for w in words[2:]:
            if w == "." and not (ROOT / "pyproject.toml").is_file():
                problems.append("pip install . but no pyproject.toml")
            m = re.match(r"^floxels_ext\[([^\]]*)\]$", w)
            if m:
                missing = {e.strip() for e in m.group(1).split(",")} - _extras()
                if missing:
                    problems.append(f"pyproject.toml defines no extra(s) {sorted(missing)}")
        return problems
    return []


def test_quick_start_commands_exist():
    commands = quick_start_commands()
    assert commands, "README.md has no 'Quick start' section with commands in fenced code blocks"
    assert any(shlex.split(c)[0] == "floxels" for c in commands), "the quick start runs no floxels command"
    problems = [f"{c}\n    -> {p}" for c in commands for p in _check_command(c)]
    assert not problems, "README quick start:\n" + "\n".join(problems)


def test_the_checks_catch_mistakes(tmp_path):
    """The checker itself: a wrong command, option, extra, script or link is reported."""
    assert _check_command("floxels run in --out o --scans 5") == []
    assert _check_command("floxels show flow --frame 1 --png a.png [--rerun a.rrd]") == []
    assert _check_command("floxels runn in") and _check_command("floxels run in --outt o")
    assert _check_command("floxels show flow [--rerunn a.rrd]")
    assert _check_command("pip install 'floxels_ext[av2,nope]'") and not _check_command("pip install 'floxels_ext[av2]'")
    assert _check_command("python tools/no_such_tool.py") and _check_command("python -m pytest -q no_such_dir")
    md = tmp_path / "x.md"
    md.write_text("# Quick start\n```bash\nfloxels demo  # comment\nfloxels run a \\\n  --out b\n```\n"
                  "## Sub\n```\npip install .\n```\n# Next\n```\nfloxels nothing\n```\n"
                  "[ok](#quick-start) [bad](#nowhere) [file](missing.md) `[code](missing2.md)`\n")
    assert quick_start_commands(md) == ["floxels demo", "floxels run a --out b", "pip install ."]
    assert _links(md) == ["#quick-start", "#nowhere", "missing.md"]
    assert _anchors(md) == {"quick-start", "sub", "next"}
    assert _slug("Beyond the paper: the `accurate` preset (v2)") == "beyond-the-paper-the-accurate-preset-v2"
    heredoc = tmp_path / "h.md"  # a here-document's body is not a command
    heredoc.write_text("# Quick start\n```\npython - <<'PY'\nimport os\nPY\nfloxels demo\n```\n")
    assert quick_start_commands(heredoc) == ["python - '<<PY'", "floxels demo"]


# ----------------------------------------------------------------------------- the rest
def _ci_commands() -> list[str]:
    """The commands .ci/run runs after its "README" markers, as the README writes them: without
    pip's ``-q`` and without leading ``VAR=value`` assignments."""
    commands, on = [], False
    for line in (ROOT / ".ci" / "run").read_text().splitlines():
        if line.startswith("# --- README"):
            on = True
            continue
        if not on or not line.strip() or line.lstrip().startswith("#"):
            continue
        words = shlex.split(line, comments=True)
        while words and re.match(r"^[A-Z_][A-Z0-9_]*=", words[0]):
            words = words[1:]
        if words[:2] == ["pip", "install"]:
            words = [w for w in words if w != "-q"]
        elif words[:3] == ["python", "-m", "pytest"]:
            pass
        else:
            continue
        commands.append(shlex.join(words))
    return commands


def test_ci_runs_the_readme_commands():
    ci = _ci_commands()
    assert len(ci) >= 3, f".ci/run: expected the set-up (pip) and test (pytest) commands after its README markers, got {ci}"
    readme = quick_start_commands()
    missing = [c for c in ci if c not in readme]
    assert not missing, f".ci/run runs commands the README's quick start does not show: {missing}"


def test_readme_links_every_doc():
    linked = {(README.parent / t.partition("#")[0]).resolve() for t in _links(README) if t.partition("#")[0]}
    missing = [p.name for p in sorted((ROOT / "docs").glob("*.md")) if p.resolve() not in linked]
    assert not missing, f"README.md does not link docs/{missing}"


def test_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= 300, f"README.md has {n} lines; move detail into docs/ (at most 300)"


@pytest.mark.parametrize("doc", _markdown_files(), ids=lambda p: p.relative_to(ROOT).as_posix())
def test_no_heading_names_an_issue(doc):
    bad = [line for line, fenced in _markdown_lines(doc)
           if not fenced and _HEADING.match(line) and re.search(r"\bissues?\s*#?\d", line, re.I)]
    assert not bad, f"{doc.name}: headings that name an issue number: {bad}"
