"""Optional dependencies (pyarrow, kiss-icp, rerun-sdk): imported lazily, with one clear message."""

from __future__ import annotations

import importlib


class MissingDependencyError(ImportError):
    """An optional package needed for this feature is not installed (the message says how to get it)."""


def require(module: str, extra: str, pip_name: str, feature: str):
    """Import ``module`` or raise MissingDependencyError naming the extra and the pip package."""
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise MissingDependencyError(
            f"{feature} needs the optional package '{pip_name}', which is not installed ({e}); "
            f"install it with: pip install 'floxels_ext[{extra}]'  (or: pip install {pip_name})") from None
