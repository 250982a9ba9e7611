"""``floxels`` command line: ``floxels simulate ...``, ``floxels eval ...`` and more.

Subcommands come from a registry so other modules can add theirs without touching this
file's logic: list the module in ``SUBCOMMAND_MODULES`` (or call ``register``). A subcommand
module exposes ``add_parser(subparsers)``, which creates its parser with
``subparsers.add_parser(name, help=...)`` and sets ``func`` via ``set_defaults(func=run)``;
``run(args)`` returns an exit code (or None for 0). Keep such modules' top-level imports light
and import heavy things inside ``run``. User mistakes (missing files, bad arguments, malformed
data) should raise ``CLIError`` or ``seqio.SequenceFormatError``: ``main`` prints
``floxels: error: <message>`` to stderr and exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from pathlib import Path
from typing import Callable

__all__ = ["CLIError", "SUBCOMMAND_MODULES", "register", "build_parser", "main"]

# Modules with an ``add_parser(subparsers)`` function, added after the built-in commands.
SUBCOMMAND_MODULES: list[str] = ["floxels_ext.eval_cli", "floxels_ext.demo", "floxels_ext.run", "floxels_ext.accumulate", "floxels_ext.show"]
_EXTRA: list[Callable] = []


class CLIError(Exception):
    """A user error: reported as ``floxels: error: ...`` with exit status 2."""


def register(add_parser: Callable | str) -> None:
    """Register a subcommand: an ``add_parser(subparsers)`` callable or a module path having one."""
    if isinstance(add_parser, str):
        if add_parser not in SUBCOMMAND_MODULES:
            SUBCOMMAND_MODULES.append(add_parser)
    elif add_parser not in _EXTRA:
        _EXTRA.append(add_parser)


# ----------------------------------------------------------------------------- simulate
def _add_simulate(sub) -> None:
    from .sim.scenes import SCENES  # light: numpy only

    p = sub.add_parser("simulate", help="write a synthetic lidar sequence with ground-truth flow",
                       description="Simulate a spinning lidar in a synthetic scene and write one .npz per frame "
                                   "(points, pose, flow, classes, instance, ground, dynamic).")
    p.add_argument("out_dir", metavar="OUT_DIR", help="output sequence directory")
    p.add_argument("--scene", choices=sorted(SCENES), default="urban")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--frames", type=int, default=13, help="number of frames (default 13)")
    p.add_argument("--small", action="store_true", help="32 beams x 512 azimuth steps (fast)")
    p.add_argument("--beams", type=int, help="number of lidar beams (default 64)")
    p.add_argument("--azimuth-steps", type=int, help="firings per revolution (default 2048)")
    p.add_argument("--max-range", type=float, help="metres (default 70)")
    p.add_argument("--range-noise", type=float, help="range noise std-dev in metres (default 0.02; 0.015 with --boxes)")
    p.add_argument("--dropout", type=float, help="probability of losing a return (default 0.05)")
    p.add_argument("--boxes", "--no-vehicle-detail", dest="vehicle_detail", action="store_false",
                   help="vehicles as plain boxes, as the simulator made them before vehicle detail "
                        "(reproduces earlier output)")
    p.add_argument("--force", action="store_true", help="replace frames already in OUT_DIR")
    p.set_defaults(func=_run_simulate)


def _run_simulate(args) -> int:
    from . import seqio
    from .sim import simulate_sequence

    if args.frames < 1:
        raise CLIError("--frames must be >= 1")
    out = Path(args.out_dir)
    if out.exists() and not out.is_dir():
        raise CLIError(f"{out} exists and is not a directory")
    old = sorted(out.glob("[0-9][0-9][0-9][0-9][0-9][0-9].npz")) if out.is_dir() else []
    if old and not args.force:
        raise CLIError(f"{out} already holds {len(old)} frame file(s); use --force to replace them")
    opts = {k: v for k, v in (("beams", args.beams), ("azimuth_steps", args.azimuth_steps),
                              ("max_range", args.max_range), ("range_noise", args.range_noise),
                              ("dropout", args.dropout)) if v is not None}
    t0 = time.perf_counter()
    try:
        seq = simulate_sequence(args.scene, args.frames, args.seed, small=args.small,
                                vehicle_detail=args.vehicle_detail, **opts)
    except ValueError as e:  # invalid lidar settings
        raise CLIError(str(e)) from None
    for p in old:
        p.unlink()
    seqio.save_sequence(out, seq)
    n = [len(f) for f in seq.frames]
    dyn = sum(int(f.dynamic.sum()) for f in seq.frames)
    print(f"wrote {len(n)} frames of scene '{args.scene}' (seed {args.seed}) to {out}: "
          f"{min(n)}-{max(n)} points/frame, {dyn} dynamic points, {time.perf_counter() - t0:.1f} s")
    return 0


# ----------------------------------------------------------------------------- main
def _add_verbosity(parser: argparse.ArgumentParser, default) -> None:
    g = parser.add_mutually_exclusive_group()
    g.add_argument("-q", "--quiet", dest="verbosity", action="store_const", const=-1, default=default,
                   help="print errors and the final summary only (no progress)")
    g.add_argument("-v", "--verbose", dest="verbosity", action="store_const", const=1, default=default,
                   help="print more detail")


def _with_verbosity(add_parser):
    """Subcommand parsers accept -q/-v too (``floxels run -q ...``); their default is
    SUPPRESS so that a -q/-v given before the subcommand is not reset."""
    def add(name, **kw):
        p = add_parser(name, **kw)
        _add_verbosity(p, argparse.SUPPRESS)
        return p
    return add



_BUILTIN = [_add_simulate]


class _Parser(argparse.ArgumentParser):
    """argparse with every usage error reported as ``floxels: error: ...`` (exit 2), also
    those of subcommands (argparse would say ``floxels demo: error: ...``)."""

    def error(self, message: str):
        self.print_usage(sys.stderr)
        self.exit(2, f"floxels: error: {message}\n")


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("floxels_ext")
    except (ImportError, PackageNotFoundError):  # running from a source tree
        from . import __version__

        return __version__


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser. Global options: ``--version``; ``-q/--quiet`` and ``-v/--verbose``
    (also after the subcommand), stored as ``args.verbosity`` = -1, 0 or 1, which
    subcommands read with ``getattr(args, "verbosity", 0)``."""
    parser = _Parser(prog="floxels", description="Floxels scene flow tools.")
    parser.add_argument("--version", action="version", version=f"floxels_ext {_version()}")
    _add_verbosity(parser, 0)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)
    sub.add_parser = _with_verbosity(sub.add_parser)
    for add in _BUILTIN + _EXTRA:
        add(sub)
    for mod in SUBCOMMAND_MODULES:
        importlib.import_module(mod).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from .io import LidarFormatError, MissingDependencyError
    from .seqio import SequenceFormatError

    parser = build_parser()
    args = parser.parse_args(argv)  # argparse itself exits 2 on bad usage
    try:
        rc = args.func(args)
    except (CLIError, SequenceFormatError, LidarFormatError, MissingDependencyError, FileNotFoundError,
            NotADirectoryError, PermissionError) as e:
        print(f"floxels: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("floxels: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into e.g. `head`, which exited: not an error of ours
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return 0 if rc is None else int(rc)


if __name__ == "__main__":  # python -m floxels_ext.cli: run the imported module's main, so that its
    # CLIError is the class the subcommands raise (this file as __main__ would define a second one)
    from floxels_ext.cli import main as _main

    sys.exit(_main())
