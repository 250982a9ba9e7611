"""What the Ray fault tests read of processes and outputs (Linux /proc): a process's command
name, its descendants, and each output file's inode and mtime (a file written twice gets a new
inode: outputs are written under a temporary name and renamed)."""

import os
from pathlib import Path


def cmdline(pid) -> str:
    """The process's first command-line word ("ray::FloxelsWorker..." for a Ray actor)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().split(b"\0", 1)[0].decode(errors="replace")
    except OSError:
        return ""


def process_tree(pid: int) -> list[int]:
    """``pid`` and every descendant, parents before their children."""
    todo, seen = [pid], []
    while todo:
        p = todo.pop(0)
        seen.append(p)
        try:
            for tid in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{tid}/children") as f:
                    todo += [int(x) for x in f.read().split()]
        except OSError:
            pass
    return seen


def output_stamps(out: Path) -> dict:
    """{output file: (inode, mtime ns)} of every frame output under ``out``."""
    stamps = {}
    for p in out.rglob("*.npz"):
        try:
            st = p.stat()
        except OSError:  # replaced while listed
            continue
        stamps[p] = (st.st_ino, st.st_mtime_ns)
    return stamps


def run_beside(watcher, argv: list[str], capsys) -> tuple[int, str]:
    """``floxels`` ``argv`` with ``watcher`` (a thread with a ``stop`` flag: a killer) running
    beside it; (exit code, stderr)."""
    from floxels_ext import cli

    watcher.start()
    try:
        rc = cli.main(argv)
    finally:
        watcher.stop = True
        watcher.join()
    return rc, capsys.readouterr().err
