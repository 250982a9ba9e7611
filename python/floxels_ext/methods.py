"""Registry of scene-flow methods that ``floxels run --method NAME`` (and ``bench/compare``) can use.

A method is a :class:`Method`: a name, a one-line description, and

* ``estimate_sequence(scans, frames, device, options, callback, times=None)``: estimate the
  flow of each frame index in ``frames`` of ``scans`` (a list of (N_i, 3) float32 numpy arrays
  in one ego-motion-compensated frame, consecutive at the sensor rate or, with ``times``, at
  those timestamps in seconds: one per scan, strictly increasing), calling
  ``callback(frame, flow)`` with a (N_frame, 3) float32 numpy array as soon as each frame is
  done (so that callers can write it and stay resumable); a method may pass a third argument,
  a dict of per-point fields of the frame (Floxels with ``evidence`` "score" or "zero": its
  ``evidence`` and ``explained``, :mod:`floxels_ext.estimator.evidence`), only when its
  options ask for them, so two-argument callbacks keep working. ``options`` is a dict of
  method-specific settings (e.g. ``{"num_scans": 5}``); unknown keys raise ``ValueError``.
  The flow is always per frame period (the median step of ``times`` when given), so
  unequally spaced scans (a dropped frame) give flows comparable with the others. A method
  may also take ``sensors=`` (each scan's sensor position in the scans' frame, or None per
  scan where unknown; Floxels' ``range_mask`` uses them); callers pass it (like ``times``)
  only to methods whose function names it. Likewise ``ground=`` (each scan's ground returns
  that preprocessing removed, an (m, 3) float32 array in the scans' frame, or None): callers
  pass it only where ``Method.uses_ground(options)`` says the options read it (keeping the
  ground costs the reader a copy per frame).

``estimate_stream(scans, targets, device, options, callback)`` (optional): the same for many
sequences laid end to end in one index space (``floxels run DATASET``): ``targets`` yields
``(index, segment)`` pairs (``floxels_ext.estimator.windows.Segment``: the scans ``[lo, hi)``
the window of ``index`` stays in, and their times), possibly waiting for the next sequence;
one call serves them all, so the method's own pipeline neither restarts nor drains between
sequences. Without it, ``floxels run`` calls ``estimate_sequence`` once per segment.

``config`` (optional) is the dataclass whose fields the options are; the CLI then parses
``--option KEY=VALUE`` text by each field's type (``cluster_loss=no`` is False).

``support_frames(i, n, options)`` (optional): the frames (of ``n``) whose scans the estimate
of frame ``i`` reads besides its own; ``floxels run`` fails a frame none of whose support scans
could be read, instead of writing the method's answer without them (issue 45). A method that
got no estimate for a frame passes ``{"failure": reason}`` as its per-point fields (to a
callback that takes them); the frame then fails with that reason (Floxels: an optimisation that
diverged).

Modules register their methods lazily: list the module in ``METHOD_MODULES``; it must call
:func:`register` at import time. Keeping heavy imports inside the functions keeps
``floxels --help`` fast.
"""

from __future__ import annotations

import contextlib
import importlib
import inspect
from collections.abc import Callable, Sequence
from dataclasses import dataclass

__all__ = ["Method", "METHOD_MODULES", "register", "get_method", "available_methods", "accepts"]

# Modules that register methods when imported (floxels' own is below).
METHOD_MODULES: list[str] = ["floxels_ext.baselines"]


@dataclass(frozen=True)
class Method:
    name: str
    description: str
    estimate_sequence: Callable[[list, Sequence[int], object, dict, Callable], None]
    config: type | None = None
    estimate_stream: Callable | None = None
    # options -> whether the method reads the scans' removed ground (``ground=``) with them
    uses_ground: Callable[[dict], bool] | None = None
    # (frame, frames in the sequence, options) -> the frames whose scans its estimate reads
    support_frames: Callable[[int, int, dict], list[int]] | None = None

    def wants_ground(self, options: dict) -> bool:
        """Whether to keep and pass each scan's removed ground for ``options`` (bad options:
        False; the method reports them itself)."""
        if self.uses_ground is None or not accepts(self.estimate_sequence, "ground"):
            return False
        try:
            return bool(self.uses_ground(dict(options or {})))
        except (TypeError, ValueError):
            return False


_REGISTRY: dict[str, Method] = {}


def register(method: Method) -> None:
    """Add (or replace) a method under ``method.name``."""
    _REGISTRY[method.name] = method


def accepts(fn, name: str) -> bool:
    """Whether method function ``fn`` takes the keyword ``name`` (``times``, ``sensors``: callers
    pass them only to methods that name them, so older methods keep working)."""
    try:
        return name in inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return False


def _load_all() -> None:
    for mod in METHOD_MODULES:
        importlib.import_module(mod)


def available_methods() -> list[str]:
    _load_all()
    return sorted(_REGISTRY)


def get_method(name: str) -> Method:
    _load_all()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; available: {', '.join(sorted(_REGISTRY))}") from None


# ----------------------------------------------------------------------------- floxels
def _floxels_deliver(cfg, callback):
    """The estimator's callback ``(frame, result)`` as the method's: the flow, with the
    motion evidence's fields (``evidence`` on) and ``failure`` where the optimisation diverged
    (to a callback that takes fields; others get the flow, and the estimator's warning)."""
    fields_ok = cfg.evidence != "off" or _takes_fields(callback)

    def deliver(f, res):
        fields = {} if cfg.evidence == "off" else {"evidence": res.evidence, "explained": res.explained}
        if res.diverged and fields_ok:
            fields["failure"] = f"the optimisation diverged: {res.diverged}; lower lr (lr={cfg.lr:g})"
        if fields:
            callback(f, res.flow, fields)
        else:
            callback(f, res.flow)
    return deliver, fields_ok


def _takes_fields(callback) -> bool:
    try:
        params = list(inspect.signature(callback).parameters.values())
    except (TypeError, ValueError):
        return False
    return len(params) >= 3 or any(p.kind == p.VAR_POSITIONAL for p in params)


@contextlib.contextmanager
def _quiet_divergence(handled: bool):
    """Where the failures reach the callback, the estimator's DivergedWarning would say it twice."""
    if not handled:
        yield
        return
    import warnings

    from floxels_ext.estimator.result import DivergedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DivergedWarning)
        yield


def _floxels_sequence(scans, frames, device, options, callback, times=None, sensors=None, ground=None) -> None:
    from floxels_ext.estimator.config import FloxelsConfig
    from floxels_ext.estimator.api import estimate_sequence

    options = dict(options or {})
    try:
        cfg = FloxelsConfig(**options)
    except TypeError as e:  # unknown field name
        raise ValueError(f"floxels: bad option: {e}") from None
    deliver, handled = _floxels_deliver(cfg, callback)
    with _quiet_divergence(handled):
        estimate_sequence(scans, cfg, device=device, frames=list(frames), times=times, sensor_origins=sensors,
                          ground_points=ground, callback=deliver)


def _floxels_stream(scans, targets, device, options, callback, sensors=None, ground=None) -> None:
    from floxels_ext.estimator.config import FloxelsConfig
    from floxels_ext.estimator.windows import estimate_stream

    try:
        cfg = FloxelsConfig(**dict(options or {}))
    except TypeError as e:  # unknown field name
        raise ValueError(f"floxels: bad option: {e}") from None
    deliver, handled = _floxels_deliver(cfg, callback)  # the same per-point fields as _floxels_sequence
    with _quiet_divergence(handled):
        estimate_stream(scans, targets, cfg, device=device, sensors=sensors, grounds=ground, callback=deliver)


def _floxels_support(i: int, n: int, options: dict) -> list[int]:
    from floxels_ext.estimator.api import window_for
    from floxels_ext.estimator.config import FloxelsConfig

    lo, hi = window_for(i, n, int(options.get("num_scans", FloxelsConfig.num_scans)))
    return [j for j in range(lo, hi) if j != i]


def _register_floxels() -> None:
    from floxels_ext.estimator.config import FloxelsConfig

    register(Method("floxels", "Floxels (voxel flow grid, multi-scan DT loss; this project)", _floxels_sequence,
                    FloxelsConfig, estimate_stream=_floxels_stream,
                    uses_ground=lambda options: FloxelsConfig(**options).visibility, support_frames=_floxels_support))


_register_floxels()
