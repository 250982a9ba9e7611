"""Output file paths of the ``floxels`` commands, checked before any work starts (an existing
directory or a missing parent directory given as ``--png``/``--json``/``--out``/``--summary``
used to surface as a traceback after the work, leaving a hidden temporary file behind), output
directories tried with a write before the work (a read-only place used to end in a
traceback, or to be found only after every frame was computed), and the atomic replace that
removes its temporary file whatever happens."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["check_output_file", "check_writable_dir", "replace_atomically"]


def check_output_file(path, option: str, example: str = "out", suffix: str | None = None) -> Path:
    """``path`` as a Path if a file can be written there: not an existing directory, in an
    existing directory. Raises ``CLIError`` naming ``option`` otherwise. ``example``: a file
    name suggested inside a directory given by mistake. ``suffix``: the only file name ending
    accepted (e.g. ".png": PNG bytes under another name mislead every viewer)."""
    from floxels_ext.errors import CLIError

    if not str(path).strip():
        raise CLIError(f"{option} is empty; give a file name, e.g. {example}")
    p = Path(path)
    if suffix is not None and p.suffix.lower() != suffix and not p.is_dir():
        raise CLIError(f"{option} {p}: writes a {suffix} file; give a name ending in {suffix}, e.g. "
                       f"{p.with_suffix(suffix).name if p.name else example}")
    if p.is_dir():
        raise CLIError(f"{option} {p} is an existing directory; give a file name, e.g. {p / example}")
    parent = Path(os.path.realpath(p)).parent if p.is_symlink() else p.parent  # a link is written through
    if not parent.is_dir():
        raise CLIError(f"{option} {p}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CLIError(f"{option} {p}: directory {parent} is not writable")
    return p


def check_writable_dir(path, option: str) -> Path:
    """``path`` as a Path to a directory that takes new files: when it exists, tried with a
    write (a hidden file created and removed, which sees read-only file systems, missing
    permissions and ACLs alike); else its nearest existing parent is tried the same way (it
    must take the new directory; nothing is created here). Raises ``CLIError`` naming
    ``option`` otherwise."""
    from floxels_ext.errors import CLIError

    if not str(path).strip():
        raise CLIError(f"{option} is empty; give a directory")
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise CLIError(f"{option} {p} exists and is not a directory")
    place = p.absolute()
    while not place.exists():
        place = place.parent
    if not place.is_dir():
        raise CLIError(f"{option} {p}: {place} is not a directory")
    why = _write_test(place)
    if why is not None:
        raise CLIError(f"{option} {p}: cannot write " + ("there" if place == p.absolute() else
                                                          f"in {place} to create it") + f": {why}")
    return p


def _write_test(d: Path) -> str | None:
    """None when a file can be created in directory ``d``, else why not."""
    probe = d / f".floxels-write-test.{os.getpid()}"
    try:
        os.close(os.open(probe, os.O_CREAT | os.O_WRONLY, 0o600))
    except OSError as e:
        return e.strerror or str(e)
    try:
        os.unlink(probe)
    except OSError:
        pass
    return None


def replace_atomically(tmp: Path, path: Path, write) -> Path:
    """``write(tmp)``, then rename ``tmp`` to ``path``; ``tmp`` is removed if either fails. A
    ``path`` that is a symbolic link is written through (its target replaced, in the target's
    directory), not replaced by a file."""
    path, tmp = Path(path), Path(tmp)
    if path.is_symlink():
        path = Path(os.path.realpath(path))
        tmp = path.with_name(tmp.name)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
