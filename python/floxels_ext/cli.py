"""``floxels`` command line: ``floxels simulate ...``, ``floxels eval ...`` and more.

This module only dispatches: each subcommand lives with its concern (``floxels run`` in
``lidar.run``, ``floxels eval`` in ``evaluation.eval_cli``, ...).

Subcommands come from a registry so other modules can add theirs without touching this
file's logic: list the module in ``SUBCOMMAND_MODULES`` (or call ``register``). A subcommand
module exposes ``add_parser(subparsers)``, which creates its parser with
``subparsers.add_parser(name, help=...)`` and sets ``func`` via ``set_defaults(func=run)``;
``run(args)`` returns an exit code (or None for 0). Keep such modules' top-level imports light
and import heavy things inside ``run``: ``floxels --help`` imports every one of them and loads
neither torch nor numpy (tests/test_cli_startup.py). User mistakes (missing files, bad
arguments, malformed data) should raise ``CLIError`` (``floxels_ext.errors``) or
``seqio.SequenceFormatError``: ``main`` prints ``floxels: error: <message>`` to stderr and
exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings
from typing import Callable

from floxels_ext.errors import CLIError

__all__ = ["CLIError", "SUBCOMMAND_MODULES", "register", "build_parser", "main"]

# Modules with an ``add_parser(subparsers)`` function, added after the built-in commands.
# The order is the order of ``floxels --help``.
SUBCOMMAND_MODULES: list[str] = ["floxels_ext.evaluation.simulate_cli", "floxels_ext.evaluation.eval_cli",
                                 "floxels_ext.evaluation.demo", "floxels_ext.lidar.run",
                                 "floxels_ext.lidar.viz.accumulate", "floxels_ext.lidar.viz.show",
                                 "floxels_ext.lidar.export.command"]
_EXTRA: list[Callable] = []


def register(add_parser: Callable | str) -> None:
    """Register a subcommand: an ``add_parser(subparsers)`` callable or a module path having one."""
    if isinstance(add_parser, str):
        if add_parser not in SUBCOMMAND_MODULES:
            SUBCOMMAND_MODULES.append(add_parser)
    elif add_parser not in _EXTRA:
        _EXTRA.append(add_parser)


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



class _Parser(argparse.ArgumentParser):
    """argparse with every usage error reported as ``floxels: error: ...`` (exit 2), also
    those of subcommands (argparse would say ``floxels demo: error: ...``)."""

    def error(self, message: str):
        self.print_usage(sys.stderr)
        self.exit(2, f"floxels: error: {message}\n")

    def format_help(self) -> str:
        # a subcommand's description may be a function: text that needs heavy imports (numpy)
        # is built only when this help is printed, so that `floxels --help` stays fast
        if callable(self.description):
            self.description = self.description()
        return super().format_help()


def _version() -> str:
    try:
        from importlib.metadata import PackageNotFoundError, version

        return version("floxels_ext")
    except (ImportError, PackageNotFoundError):  # running from a source tree
        from floxels_ext import __version__

        return __version__


class _PrintVersion(argparse.Action):
    """``--version``: the version is looked up when asked for (importlib.metadata costs ~40 ms of
    every ``floxels`` start otherwise)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest, nargs=0, default=default,
                         help=help or "show program's version number and exit")

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"floxels_ext {_version()}")  # to stdout, as argparse's own version action does
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser. Global options: ``--version``; ``-q/--quiet`` and ``-v/--verbose``
    (also after the subcommand), stored as ``args.verbosity`` = -1, 0 or 1, which
    subcommands read with ``getattr(args, "verbosity", 0)``."""
    parser = _Parser(prog="floxels", description="Floxels scene flow tools.")
    parser.add_argument("--version", action=_PrintVersion)
    _add_verbosity(parser, 0)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)
    sub.add_parser = _with_verbosity(sub.add_parser)
    for add in _EXTRA:
        add(sub)
    for mod in SUBCOMMAND_MODULES:
        importlib.import_module(mod).add_parser(sub)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning met while a command runs (the estimator's, numpy's, ...), printed as the
    commands print theirs: ``floxels: warning: ...``, without the source line it was raised at
    (for a command's user that line is inside the package, not theirs)."""
    print(f"floxels: warning: {message}", file=sys.stderr if file is None else file, flush=True)


def _slice_values(argv: list[str]) -> list[str]:
    """``--frames -1:`` as ``--frames=-1:``: argparse reads a value that starts with "-" and is no
    plain number as the next option ("expected one argument"), so a slice from the end needed
    the "=" form."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        a = argv[i]
        if a == "--frames" and i + 1 < len(argv) and argv[i + 1][:1] == "-" and ":" in argv[i + 1] \
                and all(c in "-0123456789:" for c in argv[i + 1]):
            out.append(f"--frames={argv[i + 1]}")
            i += 2
            continue
        out.append(a)
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = _slice_values([str(a) for a in (sys.argv[1:] if argv is None else argv)])
    args = parser.parse_args(argv)  # argparse itself exits 2 on bad usage (and --help exits 0)
    # imported after parsing: they load numpy, which `floxels --help` does not need
    from floxels_ext.lidar.io import LidarFormatError, MissingDependencyError
    from floxels_ext.evaluation.seqio import SequenceFormatError

    try:
        with warnings.catch_warnings():  # restores the display on the way out
            warnings.showwarning = _show_warning
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
    except OSError as e:  # the place, not the program: a read-only file system, a full disk, ...
        print(f"floxels: error: {e}", file=sys.stderr)
        return 2
    return 0 if rc is None else int(rc)


if __name__ == "__main__":
    sys.exit(main())
