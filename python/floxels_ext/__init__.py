"""floxels_ext: fast unsupervised voxel-based scene flow (Floxels, CVPR 2025).

Layout (docs/architecture.md): ``ops`` (the compiled ops and their Python registration),
``estimator`` (the Floxels optimiser), ``lidar`` (files to flow files: ``floxels run``),
``evaluation`` (simulator, metrics, protocols), ``baselines`` (NSFP, FastNSF), ``reference``
(pure-PyTorch oracles), ``methods`` (the registry ``floxels run`` picks methods from) and
``cli`` (the ``floxels`` command, which only dispatches).

Importing the package does not import torch (it costs ~1-2 s, and ``floxels --help`` needs
none of it): the public names below load their module on first use (PEP 562). The compiled ops
(``torch.ops.floxels.*``) are registered as soon as torch is there: at once when torch was
imported before this package, else right after ``import torch`` finishes (a one-shot import
hook), so ``import floxels_ext`` followed by ``torch.ops.floxels.edt(...)`` works in either
order of imports.
"""

from __future__ import annotations

import importlib
import sys

__version__ = "0.1.0"

# public name -> module that defines it (loaded on first attribute access)
_LAZY = {
    "FloxelsConfig": "floxels_ext.estimator",
    "Floxels": "floxels_ext.estimator",
    "FloxelsResult": "floxels_ext.estimator",
    "DistanceTransform": "floxels_ext.estimator",
    "estimate_flow": "floxels_ext.estimator",
    "estimate_sequence": "floxels_ext.estimator",
}
_SUBMODULES = ("ops", "reference")

__all__ = ["FloxelsConfig", "Floxels", "FloxelsResult", "DistanceTransform", "estimate_flow",
           "estimate_sequence", "ops", "reference"]


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBMODULES or (not name.startswith("__") and _is_submodule(name)):
        value = importlib.import_module(f"{__name__}.{name}")  # floxels_ext.estimator etc., as before
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later lookups skip this function
    return value


def _is_submodule(name: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(f"{__name__}.{name}") is not None


def __dir__():
    return sorted(set(globals()) | set(__all__))


def _register_ops() -> None:
    importlib.import_module("floxels_ext.ops")  # loads _C: registers torch.ops.floxels.*


class _RegisterOpsAfterTorch:
    """A ``sys.meta_path`` finder that acts once, for the module ``torch``: it lets the other
    finders find it and runs :func:`_register_ops` right after torch's own module code. A
    failure there (a broken build of ``_C``) becomes a warning, never a failed ``import torch``;
    the same error is raised again when the ops are used (``floxels_ext.ops``)."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname != "torch":
            return None
        self.remove()
        import importlib.util

        spec = importlib.util.find_spec("torch")
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run_module = spec.loader.exec_module

        def exec_module(module):
            run_module(module)
            try:
                _register_ops()
            except Exception as e:  # noqa: BLE001 - see the class docstring
                import warnings

                warnings.warn(f"floxels_ext: torch.ops.floxels could not be registered: {e}", stacklevel=2)

        spec.loader.exec_module = exec_module  # this spec's own loader instance
        return spec

    def remove(self) -> None:
        if self in sys.meta_path:
            sys.meta_path.remove(self)


if "torch" in sys.modules:
    _register_ops()
elif not any(isinstance(f, _RegisterOpsAfterTorch) for f in sys.meta_path):
    sys.meta_path.insert(0, _RegisterOpsAfterTorch())
