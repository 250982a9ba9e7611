"""Output file paths of the ``floxels`` commands, checked before any work starts (an existing
directory or a missing parent directory given as ``--png``/``--json``/``--out``/``--summary``
used to surface as a traceback after the work, leaving a hidden temporary file behind), and
the atomic replace that removes its temporary file whatever happens."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["check_output_file", "replace_atomically"]


def check_output_file(path, option: str, example: str = "out") -> Path:
    """``path`` as a Path if a file can be written there: not an existing directory, in an
    existing directory. Raises ``CLIError`` naming ``option`` otherwise. ``example``: a file
    name suggested inside a directory given by mistake."""
    from floxels_ext.errors import CLIError

    p = Path(path)
    if p.is_dir():
        raise CLIError(f"{option} {p} is an existing directory; give a file name, e.g. {p / example}")
    parent = p.parent
    if not parent.is_dir():
        raise CLIError(f"{option} {p}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CLIError(f"{option} {p}: directory {parent} is not writable")
    return p


def replace_atomically(tmp: Path, path: Path, write) -> Path:
    """``write(tmp)``, then rename ``tmp`` to ``path``; ``tmp`` is removed if either fails."""
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
