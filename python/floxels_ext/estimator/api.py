"""The Floxels estimator: public API and the optimisation loop on top of torch.ops.floxels.

One frame:
1. an exact distance transform (0.1 m samples) of every support scan, cached per scan so
   sliding windows (:func:`estimate_sequence`) build each one once;
2. DBSCAN clusters of the target scan (our exact op: labels identical to scikit-learn);
3. Adam over the flow-grid vertices touched by the target points (see
   ``floxels_ext.ops.corners``: exactly dense Adam, at a fraction of the cost), each
   iteration being: compact gather of the point flow, fused multi-scan DT loss +
   gradient, fused cluster-consistency loss + gradient, flow-norm term, compact scatter;
4. early stopping; the result is the flow of the lowest loss seen.
"""

from __future__ import annotations

import collections.abc
import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.distance import DistanceTransform, EarlyDts
from floxels_ext.estimator.group import fit_group
from floxels_ext.estimator.poses import resolve_sensors
from floxels_ext.estimator.result import HOST_PARTS, FloxelsResult
from floxels_ext.estimator.scans import check_ground, check_scan_container, check_sensors, check_times, frame_period_of, prepare_scans, resolve_device, warn_if_no_sensors
from floxels_ext.estimator.schedule import serial_stages
from floxels_ext.estimator.windows import RAMP_START, Window, solve_windows, window_for
from floxels_ext.ops.solver import MAX_PROBLEMS
from floxels_ext.switches import flag

__all__ = ["Floxels", "FloxelsResult", "DistanceTransform", "estimate_flow", "estimate_sequence", "window_for",
           "MAX_FRAME_PERIOD_S"]

#: With ``flow_unit="m/s"``, a frame period above this (s) is refused: lidars turn at 1-20 Hz,
#: so such times are not seconds (nanosecond timestamps give ~1e8, milliseconds ~100).
MAX_FRAME_PERIOD_S = 10.0


class Floxels:
    """Floxels scene-flow estimator.

    >>> est = Floxels(FloxelsConfig(max_iters=300), device="cpu")
    >>> res = est.fit(scans, target=2)      # res.flow, res.losses, res.labels, res.grid, res.timings
    """

    def __init__(self, config: FloxelsConfig | None = None, device=None, *, preset: str | None = None) -> None:
        self.config = _config_of(config, preset)
        self.device = device

    # -- public -----------------------------------------------------------------------
    def fit(self, scans: Sequence, target: int | None = None,
            dt_cache: dict[int, DistanceTransform | None] | None = None, *,
            times: Sequence[float] | None = None, frame_period: float | None = None,
            sensor_origins: Sequence | None = None, ground_points: Sequence | None = None,
            poses: Sequence | None = None) -> FloxelsResult:
        """Estimate the flow of ``scans[target]`` (default: the middle scan), per frame period.

        ``dt_cache`` maps scan index -> distance transform and is filled in place, so that
        callers optimising several targets over the same scans build each DT once.
        ``times``/``frame_period``/``sensor_origins``/``ground_points``/``poses``: see
        :func:`estimate_flow`.
        """
        t0 = time.perf_counter()
        sensor_origins = _sensors(scans, sensor_origins, poses)
        cache = dt_cache if dt_cache is not None else {}
        early = EarlyDts(self.config, cache)
        warn_if_no_sensors(self.config, sensor_origins)
        prep = prepare_scans(scans, target, self.device, on_ready=early, times=times, period=frame_period,
                             sensors=sensor_origins, grounds=ground_points)
        res = fit_group(self.config, [(prep, cache)], early.streams)[0]
        warn_diverged(self.config, [("the target", res)])
        res.timings.update(prep.timings)
        whole = time.perf_counter() - t0
        # the host's time of the whole call, and what no named part holds (HOST_PARTS)
        res.timings["whole"] = whole
        res.timings["other"] = whole - sum(res.timings.get(k, 0.0) for k in HOST_PARTS)
        return res

    def fit_many(self, windows: Sequence[tuple[Sequence, int | None]]) -> list[FloxelsResult]:
        """Estimate several target frames in one optimisation: ``windows`` is a list of
        ``(scans, target)``. The problems stay independent (each has its own loss, early
        stopping and lowest-loss flow, as when fitted alone) but share every kernel
        launch, which keeps a GPU busy. For sliding windows over one sequence use
        :func:`estimate_sequence`, which also shares the distance transforms."""
        if isinstance(windows, (str, bytes)) or not isinstance(windows, Sequence):
            raise TypeError(f"windows must be a list of (scans, target) pairs, got {type(windows).__name__}")
        if not windows:
            raise ValueError("fit_many needs at least one (scans, target) window")
        for k, w in enumerate(windows):
            # (a list of scans passed as one window has arrays where the scans should be)
            if not (isinstance(w, (tuple, list)) and len(w) == 2 and hasattr(w[0], "__len__")
                    and not hasattr(w[0], "shape") and not isinstance(w[0], str)):
                raise TypeError(f"windows[{k}] must be a (scans, target) pair, e.g. fit_many([(scans, 2)]); "
                                f"got {type(w).__name__}" + (f" of length {len(w)}" if hasattr(w, "__len__") else ""))
        preps = [prepare_scans(scans, target, self.device) for scans, target in windows]
        results = fit_group(self.config, [(p, {}) for p in preps])
        warn_diverged(self.config, [(f"window {k}", r) for k, r in enumerate(results)])
        return results


def warn_diverged(cfg: FloxelsConfig, results: list[tuple[str, FloxelsResult]], total: int | None = None) -> None:
    """One ``DivergedWarning`` naming the results (``(label, result)``, of ``total``, default
    their number) whose optimisation diverged (:attr:`FloxelsResult.diverged`), if any."""
    bad = [(label, r.diverged) for label, r in results if r.diverged]
    if bad:
        from floxels_ext.estimator.result import DivergedWarning
        from floxels_ext.estimator.user_warnings import warn_user

        which = ", ".join(label for label, _ in bad[:3]) + (" ..." if len(bad) > 3 else "")
        warn_user(f"{len(bad)} of {total or len(results)} optimisation(s) diverged ({which}): {bad[0][1]}; lower lr "
                  f"(lr={cfg.lr:g})",
                  DivergedWarning)


def _sensors(scans, sensor_origins, poses):
    """The sensor positions of ``sensor_origins=`` or ``poses=`` (estimator/poses.py)."""
    if poses is None:
        return sensor_origins
    if not hasattr(scans, "__len__"):
        raise TypeError(f"scans must be a sequence of (N_i, 3) arrays, got {type(scans).__name__}")
    return resolve_sensors(sensor_origins, poses, len(scans))


def _config_of(config: FloxelsConfig | None, preset: str | None) -> FloxelsConfig:
    """The configuration of ``config=`` or ``preset=`` (one of them; neither: the paper's)."""
    if config is not None and not isinstance(config, FloxelsConfig):
        raise TypeError(f"config must be a FloxelsConfig, got {type(config).__name__}")
    if preset is None:
        return config or FloxelsConfig()
    if config is not None:
        raise ValueError("give config= or preset=, not both (FloxelsConfig.preset(name, **changes) "
                         "combines a preset with changes)")
    if not isinstance(preset, str):
        raise TypeError(f"preset must be a name (str), got {type(preset).__name__}")
    return FloxelsConfig.preset(preset)


def estimate_flow(scans: Sequence, target: int | None = None, config: FloxelsConfig | None = None, device=None,
                  *, times: Sequence[float] | None = None, frame_period: float | None = None,
                  flow_unit: str = "frame", preset: str | None = None, sensor_origins: Sequence | None = None,
                  ground_points: Sequence | None = None, poses: Sequence | None = None):
    """Flow of every point of ``scans[target]``.

    ``scans``: 2 to 13 (N_i, 3) float arrays/tensors in one ego-motion-compensated frame;
    ``target`` defaults to the middle scan (negative indices count from the end). Without
    ``times`` the scans are taken as consecutive at the sensor rate: support scan ``i`` is at
    time offset ``i - target``. ``times``: the scans' timestamps in seconds (one per scan,
    finite, strictly increasing; e.g. a dropped frame leaves a gap): offsets are then
    ``(t_i - t_target) / period`` with ``period = frame_period`` or, by default, the median
    step of ``times``. ``flow_unit``: ``"frame"`` (default: metres per frame period) or
    ``"m/s"`` (needs ``times`` or ``frame_period``). Returns (N_target, 3): numpy float32 for
    numpy input, else a tensor of the input's dtype on the input's device. Rows with NaN/inf
    coordinates are dropped (with a warning) and get NaN flow. ``preset``: ``"paper"`` (the
    default configuration) or ``"accurate"`` (docs/accurate.md), instead of ``config``.
    ``poses``: each scan's pose, the (4, 4) world-from-sensor matrix that brought it into the
    scans' frame (an (n, 4, 4) array; None for an unknown one); ``"accurate"`` derives from them
    what it needs (the sensor positions, their translations). Or ``sensor_origins``: each scan's
    sensor position (x, y, z) in the scans' frame (an (n, 3) array). Both only where they agree.
    Used by ``range_mask`` and ``visibility`` (both on in ``"accurate"``), which without them are
    skipped with a warning. ``ground_points``: each scan's ground returns that preprocessing removed
    (one (m, 3) array or None per scan, in the scans' frame): ``visibility``'s range images
    count them as returns (a road return behind a place shows it empty); ignored without
    ``visibility`` or without the scan's sensor.
    """
    config = _config_of(config, preset)
    if flow_unit not in ("frame", "m/s"):  # argument mistakes before any work
        raise ValueError(f"flow_unit must be 'frame' or 'm/s', got {flow_unit!r}")
    if flow_unit == "m/s" and times is None and frame_period is None:
        raise ValueError("flow_unit='m/s' needs the scans' times= (seconds) or frame_period= (seconds)")
    frame_period_of(None, frame_period)  # checks it
    to_unit = _unit_factor(flow_unit, None if times is None else check_times(times, len(scans)), frame_period)
    flow = Floxels(config, device).fit(scans, target, times=times, frame_period=frame_period,
                                       sensor_origins=sensor_origins, ground_points=ground_points, poses=poses).flow
    return flow if to_unit == 1.0 else flow * to_unit


def _unit_factor(flow_unit: str, times, frame_period) -> float:
    """Factor from metres per frame period to ``flow_unit``; ``times`` already checked."""
    if flow_unit not in ("frame", "m/s"):
        raise ValueError(f"flow_unit must be 'frame' or 'm/s', got {flow_unit!r}")
    if flow_unit == "frame":
        return 1.0
    if times is None and frame_period is None:
        raise ValueError("flow_unit='m/s' needs the scans' times= (seconds) or frame_period= (seconds)")
    period = frame_period_of(times, frame_period)
    if period > MAX_FRAME_PERIOD_S:  # nanosecond stamps gave velocities 1e9 times too small
        unit, scale = ((("nanoseconds", "1e-9"), ("microseconds", "1e-6"), ("milliseconds", "1e-3"))
                       [0 if period > 1e6 else 1 if period > 1e3 else 2])
        raise ValueError(f"flow_unit='m/s' with a frame period of {period:.6g} s: times= and frame_period= are "
                         f"seconds, and these look like {unit} (multiply them by {scale})")
    return 1.0 / period


def _batches(frames: list[int], size: int, ramp: bool) -> list[list[int]]:
    """Consecutive batches of at most ``size`` frames. ``ramp`` (pipelined sequences): the
    first batches are smaller (4, 8, ... frames) so the GPU starts optimising after a short
    first preparation, and each later batch is prepared while a batch about half its size is
    optimised; results do not depend on the batching."""
    out, k, cur = [], 0, min(size, RAMP_START) if ramp else size
    while k < len(frames):
        out.append(frames[k:k + cur])
        k += cur
        cur = min(size, 2 * cur)
    return out


def estimate_sequence(scans: Sequence, config: FloxelsConfig | None = None, device=None,
                      frames: Sequence[int] | None = None,
                      callback: Callable[[int, FloxelsResult], None] | None = None,
                      batch_size: int | None = None, *, times: Sequence[float] | None = None,
                      frame_period: float | None = None, flow_unit: str = "frame",
                      preset: str | None = None, sensor_origins: Sequence | None = None,
                      ground_points: Sequence | None = None, poses: Sequence | None = None) -> list:
    """Flow of every frame of a sequence (or of ``frames``) with a sliding window of
    ``config.num_scans`` scans. Each scan's distance transform is built once and reused by
    every window that needs it (and freed once no later window does).

    ``batch_size`` target frames are optimised together (default: 16 on CUDA, where
    sharing kernel launches raises throughput, 1 on the CPU); each frame's result is the
    same as optimising it alone. On CUDA the next batch is prepared (distance transforms,
    DBSCAN, sorting) while the GPU optimises the current one; the first batches are then
    smaller (4, 8, ... up to ``batch_size``) so that the GPU starts early.

    ``frames``: indices into ``scans``; negative ones count from the end, like ``target``.
    ``times``/``frame_period``/``flow_unit``: scans not equally spaced and the unit of the
    flow, as in :func:`estimate_flow` (the period is the median step of the whole sequence's
    times; each window's offsets come from its scans' times).

    Returns a list with one flow per requested frame (numpy float32 for numpy input).
    ``callback(frame, result)`` is called after each frame (e.g. to write it to disk), with
    ``result.flow`` in ``flow_unit``. ``preset``: a named configuration instead of ``config``
    (:meth:`FloxelsConfig.preset`; ``"accurate"`` uses 11-scan windows). ``poses`` (or
    ``sensor_origins``), ``ground_points``: each scan's pose (or sensor position) and removed
    ground, as in :func:`estimate_flow`.
    """
    cfg = _config_of(config, preset)
    if getattr(scans, "ndim", None) == 2:
        raise TypeError(f"scans must be a sequence of (N_i, 3) arrays, not a single {tuple(scans.shape)} array")
    check_scan_container(scans)  # (before list(): a dict would give its keys)
    if not isinstance(scans, collections.abc.Sequence):
        scans = list(scans)  # an iterator or a stacked array: materialise it
    # a Sequence is read lazily, window by window (``floxels run`` passes scans that are still
    # being read and preprocessed; the first batch starts as soon as its windows are ready)
    n = len(scans)
    if n < 2:
        raise ValueError(f"a sequence needs at least 2 scans, got {n}")
    if times is not None:
        times = check_times(times, n)
    sensor_origins = resolve_sensors(sensor_origins, poses, n)
    if sensor_origins is not None and len(sensor_origins) != n:
        check_sensors(sensor_origins, n)  # raises, naming the counts
    if ground_points is not None and len(ground_points) != n:
        check_ground(ground_points, n)  # raises, naming the counts
    warn_if_no_sensors(cfg, sensor_origins)
    period = frame_period_of(times, frame_period)
    to_unit = _unit_factor(flow_unit, times, frame_period)
    if callback is not None and not callable(callback):  # else it fails after the first frame's work
        raise TypeError(f"callback must be a function callback(frame, result), got {type(callback).__name__}")
    if frames is None:
        frames = list(range(n))
    else:
        if isinstance(frames, (int, np.integer, str, bytes)) or not hasattr(frames, "__iter__"):
            raise TypeError(f"frames must be a sequence of integer indices (e.g. [{frames!r}]), got "
                            f"{type(frames).__name__}")
        given = list(frames)
        for f in given:
            if isinstance(f, bool) or not isinstance(f, (int, np.integer)):
                raise TypeError(f"frames must hold integer indices, got {f!r}")
        frames = [int(f) + n if int(f) < 0 else int(f) for f in given]
        for f, g in zip(frames, given):
            if not 0 <= f < n:
                raise IndexError(f"frame {g} is out of range for {n} scans (valid: {-n} .. {n - 1})")
    dev = resolve_device(device, scans[0])
    if batch_size is None:
        batch_size = MAX_PROBLEMS if dev.type == "cuda" else 1
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    # On CUDA, the next batch is prepared (scans, distance transforms, DBSCAN, sorting: mostly
    # host-bound work) on a side stream while the GPU optimises this one.
    # FLOXELS_PIPELINE=0 turns this off, FLOXELS_RAMP=0 the smaller first batches (measurements).
    pipelined = (dev.type == "cuda" and len(frames) > batch_size and not serial_stages(dev)
                 and flag("FLOXELS_PIPELINE"))
    batches = []
    for b in _batches(frames, batch_size, ramp=pipelined and flag("FLOXELS_RAMP")):
        batches.append([])
        for f in b:
            start, stop = window_for(f, n, cfg.num_scans, cfg.max_offset)
            batches[-1].append(Window(f, start, stop, None if times is None else times[start:stop], period))
    # the lowest scan a later window reads (frames may come in any order): DTs below it are freed
    low = [math.inf] * (len(batches) + 1)
    for k in range(len(batches) - 1, -1, -1):
        low[k] = min([low[k + 1]] + [w.start for w in batches[k]])
    batch_no = {id(b): k for k, b in enumerate(batches)}
    out = []
    diverged: list = []

    def deliver(f, res):
        if res.diverged:
            diverged.append((f"frame {f}", res))
        if to_unit != 1.0:
            res.flow = res.flow * to_unit
        out.append(res.flow)
        if callback is not None:
            callback(f, res)

    solve_windows(scans, cfg, device, batches, deliver, pipelined=dev if pipelined else None,
                  horizon=lambda nxt: math.inf if not nxt else low[batch_no[id(nxt)]], sensors=sensor_origins,
                  grounds=ground_points)
    if diverged:  # one warning for the call (the results themselves say it: ``res.diverged``)
        warn_diverged(cfg, diverged, total=len(out))
    return out
