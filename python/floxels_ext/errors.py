"""The error type of the ``floxels`` commands, in a module of its own so that every command module
can raise it without importing the command line (``cli.py``), and so that ``python -m
floxels_ext.cli`` and the subcommands it runs share one class."""

from __future__ import annotations

__all__ = ["CLIError"]


class CLIError(Exception):
    """A user error: reported as ``floxels: error: ...`` with exit status 2."""
