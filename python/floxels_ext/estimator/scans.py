"""Validation and normalisation of the scans handed to the estimators.

Policy for bad input (documented in docs/bad-input.md):
* fewer than 2 scans, a target index out of range, scans of different dtypes or kinds
  (numpy vs tensor), or arrays that are not (N, 3) floats: ``ValueError``/``TypeError``;
* ``times`` (seconds, one per scan, finite, strictly increasing): the scans need not be
  equally spaced; time offsets are ``(t_k - t_target) / period`` frame periods;
* rows with NaN/inf coordinates are dropped with a ``UserWarning``; in the target scan
  their flow is returned as NaN so the output keeps one row per input point;
* an empty target scan gives an empty (0, 3) flow; an empty support scan contributes no loss;
* scans far from the origin (a map frame) are re-centred in float64 before any float32 work
  (``recentre.py``); the flow does not change.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from floxels_ext.estimator.recentre import Recentring
from floxels_ext.estimator.schedule import HostCopy, staged_uploads
from floxels_ext.estimator.user_warnings import warn_user


@dataclass
class PreparedScans:
    points: list[torch.Tensor]     # finite rows only, float32, on the compute device
    finite_masks: list[torch.Tensor]  # (N_i,) bool on the compute device: which input rows were kept
    target: int
    offsets: list[float]           # time offset of every support scan in frame periods (index - target)
    supports: list[int]            # indices of the support scans
    was_numpy: bool
    in_dtype: torch.dtype | np.dtype
    in_device: torch.device
    num_target_points: int
    # (min xyz, max xyz) of each scan's kept points where known without a device
    # synchronisation (host scans uploaded to CUDA), else None
    bounds: list[tuple[list[float], list[float]] | None] | None = None
    # the shift subtracted (in float64) from every scan before it became float32 (recentre.py)
    recentring: Recentring | None = None
    # each scan's sensor position (float64 xyz, re-centred like the scans), when given
    sensors: list[np.ndarray] | None = None
    # each scan's removed ground returns (checked (m, 3) tensors, not re-centred),
    # when given: only the range images of ``visibility`` read them
    grounds: list[torch.Tensor | None] | None = None
    # host seconds of this window's preparation: "checks" (validation and conversion), "recentre"
    # (choosing the float64 shift), "stage" (staging, uploads, the early EDT launches)
    timings: dict | None = None

    def sensor(self, i: int) -> np.ndarray | None:
        """Sensor position of scan ``i`` of the window, or None when not given."""
        return None if self.sensors is None else self.sensors[i]

    def ground_of(self, i: int):
        """None without ground returns, else a call giving scan ``i``'s (see :func:`ground_of`)."""
        return ground_of(self.grounds, i, self.recentring)


def ground_of(grounds, i: int, recentring: Recentring | None):
    """None where no scan's ground was given, else a call giving ``grounds[i]`` (checked; None
    for that scan) re-centred like the scans: made only when a range image needs it."""
    if grounds is None:
        return None

    def get():
        g = grounds[i]
        return g if g is None or recentring is None else recentring.apply(g)
    return get


def check_times(times, n: int) -> list[float]:
    """``times`` as floats after checking: one per scan, finite, strictly increasing."""
    if isinstance(times, (str, bytes)) or not hasattr(times, "__len__"):
        raise TypeError(f"times must be a sequence of {n} numbers (seconds), got {type(times).__name__}")
    vals = []
    for k, t in enumerate(times):
        if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) and not (
                isinstance(t, (np.ndarray, torch.Tensor)) and t.ndim == 0):
            raise TypeError(f"times[{k}] must be a number (seconds), got {t!r}")
        vals.append(float(t))
    if len(vals) != n:
        raise ValueError(f"times has {len(vals)} entries but there are {n} scans (one time per scan)")
    bad = [k for k, t in enumerate(vals) if not math.isfinite(t)]
    if bad:
        raise ValueError(f"times[{bad[0]}] is {vals[bad[0]]}; times must be finite")
    for k in range(1, n):
        if not vals[k] > vals[k - 1]:
            raise ValueError(f"times must be strictly increasing: times[{k - 1}] = {vals[k - 1]} and "
                             f"times[{k}] = {vals[k]}")
    return vals


def frame_period_of(times: list[float] | None, frame_period=None) -> float | None:
    """The frame period (s): ``frame_period`` if given, else the median step of ``times``."""
    if frame_period is not None:
        if isinstance(frame_period, bool) or not isinstance(frame_period, (int, float, np.integer, np.floating)):
            raise TypeError(f"frame_period must be a number of seconds, got {frame_period!r}")
        if not (math.isfinite(frame_period) and frame_period > 0):
            raise ValueError(f"frame_period must be a positive finite number of seconds, got {frame_period}")
        return float(frame_period)
    if times is None:
        return None
    return float(np.median(np.diff(np.asarray(times, np.float64))))


def offsets_from_times(times: list[float], target: int, supports: list[int], period: float) -> list[float]:
    """Time offsets (frame periods) of the support scans; values within 1e-6 of an integer
    are snapped to it, so equally spaced times give exactly the offsets of no times."""
    out = []
    for i in supports:
        t = (times[i] - times[target]) / period
        r = round(t)
        out.append(float(r) if abs(t - r) <= 1e-6 * max(1.0, abs(t)) else t)
    return out


def _as_tensor(scan, i: int) -> torch.Tensor:
    if isinstance(scan, np.ndarray):
        if scan.dtype.kind not in "fiub":  # from_numpy refuses strings, objects, ...
            raise TypeError(f"scan {i} must hold floating-point coordinates (float32 or float64; float16 and "
                            f"bfloat16 are widened), got {scan.dtype}")
        if not scan.dtype.isnative:  # e.g. big-endian data read from a file
            scan = scan.astype(scan.dtype.newbyteorder("="))
        t = torch.from_numpy(np.ascontiguousarray(scan))
    elif isinstance(scan, torch.Tensor):
        t = scan
    else:
        raise TypeError(f"scan {i} must be a numpy array or torch tensor of shape (N, 3), got {type(scan).__name__}")
    if t.dim() != 2 or t.shape[1] != 3:
        raise ValueError(f"scan {i} must have shape (N, 3), got {tuple(t.shape)}")
    if not t.dtype.is_floating_point:
        raise TypeError(f"scan {i} must hold floating-point coordinates (float32 or float64; float16 and "
                        f"bfloat16 are widened), got {scan.dtype}")
    return t


def resolve_device(device, first: torch.Tensor | np.ndarray) -> torch.device:
    if device is not None:
        try:
            dev = torch.device(device)
        except (RuntimeError, TypeError, ValueError):
            raise ValueError(f"unknown device {device!r}; use 'cpu' or 'cuda' (or 'cuda:N')") from None
    elif isinstance(first, torch.Tensor):
        dev = first.device
    else:
        dev = torch.device("cpu")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={str(dev)!r} requested but no CUDA device is available (torch "
                         f"{torch.__version__}{'' if torch.version.cuda else ', a CPU-only build'}); use device='cpu'")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ValueError(f"device {str(dev)!r}: there are only {torch.cuda.device_count()} CUDA device(s)")
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"unsupported device {dev}; use 'cpu' or 'cuda'")
    return dev


def prepare_scans(scans: Sequence, target: int | None, device, converted: dict | None = None,
                  first_index: int = 0, on_ready=None, times: Sequence[float] | None = None,
                  period: float | None = None, recentring: Recentring | None = None,
                  sensors: Sequence | None = None, grounds: Sequence | None = None) -> PreparedScans:
    """Validate a window of scans and move them to the compute device.

    ``converted`` (sequence index -> (points, finite mask, bounds)) lets sliding windows over one
    sequence convert, copy and NaN-check each scan once; ``first_index`` is the sequence
    index of ``scans[0]`` (also used in warnings). ``on_ready(i, points, bounds, is_target)``
    is called as soon as a host scan staged for the GPU has its upload queued (support scans
    first, the target last), so the caller can queue work on it while later scans are
    still being copied. ``times`` (seconds, one per scan of the window, checked) with
    ``period`` (default: their median step) give the time offsets; else ``index - target``.
    ``recentring``: the shift shared by the windows of one call (default: one for this
    window); scans far from the origin are moved near it in float64 first. ``sensors``: each
    scan's sensor position (xyz, in the scans' frame; checked, see :func:`check_sensors`).
    ``grounds``: each scan's removed ground returns (see :func:`check_ground`)."""
    t_start = time.perf_counter()
    if isinstance(scans, (np.ndarray, torch.Tensor)):
        raise TypeError("scans must be a sequence of (N_i, 3) arrays, not a single array")
    check_scan_container(scans)
    scans = list(scans)
    if len(scans) < 2:
        raise ValueError(f"Floxels needs at least 2 scans (a target and a support scan), got {len(scans)}")
    if len(scans) > 13:
        raise ValueError(f"at most 13 scans are supported per window, got {len(scans)}")
    for i, s in enumerate(scans):
        if not isinstance(s, (np.ndarray, torch.Tensor)):
            raise TypeError(f"scan {first_index + i} must be a numpy array or torch tensor of shape (N, 3), "
                            f"got {type(s).__name__}")
    kinds = {isinstance(s, np.ndarray) for s in scans}
    if len(kinds) > 1:
        raise TypeError("scans mix numpy arrays and torch tensors; pass one kind")
    tensors = [_as_tensor(s, first_index + i) for i, s in enumerate(scans)]
    dtypes = {t.dtype for t in tensors}
    if len(dtypes) > 1:
        raise TypeError(f"scans have different dtypes {sorted(str(d) for d in dtypes)}; convert them to one dtype")
    devices = {t.device for t in tensors}
    if len(devices) > 1:
        raise ValueError(f"scans are on different devices {sorted(str(d) for d in devices)}")
    n = len(tensors)
    if target is None:
        target = n // 2
    if not isinstance(target, (int, np.integer)) or isinstance(target, bool):
        raise TypeError(f"target must be an integer index, got {type(target).__name__}")
    given = target = int(target)
    if target < 0:
        target += n
    if not 0 <= target < n:
        raise IndexError(f"target index {given} is out of range for {n} scans (valid: {-n} .. {n - 1})")
    if times is not None:
        times = check_times(times, n)
        period = frame_period_of(times, period)
    dev = resolve_device(device, scans[0])
    if sensors is not None:
        sensors = check_sensors(sensors, n, first_index)
    if grounds is not None:
        grounds = check_ground(grounds, n, first_index)

    todo = [i for i in range(n) if converted is None or first_index + i not in converted]
    todo.sort(key=lambda i: i == target)  # support scans first (their EDTs are the longest work)
    if recentring is None:
        recentring = Recentring()
    t_checked = time.perf_counter()
    recentring.decide(tensors)
    t_recentred = time.perf_counter()
    if sensors is not None:
        sensors = [None if s is None else s - recentring.shift for s in sensors]
    ready = None if on_ready is None else (
        lambda k, t, b: on_ready(todo[k], t, b, todo[k] == target, None if sensors is None else sensors[todo[k]],
                                 ground_of(grounds, todo[k], recentring)))
    fresh = dict(zip(todo, _finite_rows([recentring.apply(tensors[i]) for i in todo], dev,
                                        [first_index + i for i in todo],
                                        [i == target for i in todo], ready)))
    points, masks, bounds = [], [], []
    for i in range(n):
        if i in fresh:
            t, finite, b = fresh[i]
            if converted is not None:
                converted[first_index + i] = (t, finite, b)
        else:
            t, finite, b = converted[first_index + i]
        points.append(t)
        masks.append(finite)
        bounds.append(b)
    supports = [i for i in range(n) if i != target]
    offsets = ([float(i - target) for i in supports] if times is None
               else offsets_from_times(times, target, supports, period))
    return PreparedScans(points=points, finite_masks=masks, target=target,
                         offsets=offsets, supports=supports,
                         was_numpy=isinstance(scans[0], np.ndarray), in_dtype=scans[0].dtype,
                         in_device=tensors[0].device, num_target_points=tensors[target].shape[0], bounds=bounds,
                         recentring=recentring, sensors=sensors, grounds=grounds,
                         timings={"checks": t_checked - t_start, "recentre": t_recentred - t_checked,
                                  "stage": time.perf_counter() - t_recentred})


def check_scan_container(scans) -> None:
    """TypeError for a container that ``list()`` would not turn into the scans in time order (a
    dict gives its keys: "scan 0 ... got int"; a set has no order; a string its characters)."""
    if isinstance(scans, (dict, set, frozenset, str, bytes)):
        raise TypeError(f"scans must be a sequence (list or tuple) of (N_i, 3) arrays in time order, got "
                        f"{type(scans).__name__}" + (" (pass list(d.values()) in time order)" if isinstance(scans, dict) else ""))


def check_sensors(sensors, n: int, first_index: int = 0) -> list[np.ndarray | None]:
    """``sensors`` (one xyz sensor position per scan: an (n, 3) array or a sequence of (3,)
    arrays, None for a scan whose sensor is unknown) as float64 (3,) arrays (or None);
    ValueError/TypeError naming the problem."""
    if isinstance(sensors, (str, bytes)) or not hasattr(sensors, "__len__"):
        raise TypeError(f"sensor_origins must be one (x, y, z) position per scan, got {type(sensors).__name__}")
    if len(sensors) != n:
        raise ValueError(f"sensor_origins must hold one (x, y, z) position per scan: got {len(sensors)} "
                         f"for {n} scans")
    out = []
    for i, s in enumerate(sensors):
        if s is None:
            out.append(None)
            continue
        if isinstance(s, torch.Tensor):
            s = s.detach().cpu().numpy()
        try:
            a = np.asarray(s, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"sensor_origins[{first_index + i}] must be 3 numbers (x, y, z), got {s!r}") from None
        if a.shape != (3,):
            raise ValueError(f"sensor_origins[{first_index + i}] must be 3 numbers (x, y, z), got shape {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"sensor_origins[{first_index + i}] is not finite: {a.tolist()}")
        out.append(a)
    return out


def check_ground(grounds, n: int, first_index: int = 0) -> list[torch.Tensor | None]:
    """``grounds`` (per scan, its ground returns that preprocessing removed: an (m, 3) numpy array
    or tensor in the scans' frame, or None) as tensors; ValueError/TypeError naming the problem.
    Non-finite rows are allowed: the range image skips them (estimator/sight.py)."""
    if isinstance(grounds, (str, bytes, np.ndarray, torch.Tensor)) or not hasattr(grounds, "__len__"):
        raise TypeError(f"ground_points must be one (m, 3) array (or None) per scan, got {type(grounds).__name__}")
    if len(grounds) != n:
        raise ValueError(f"ground_points must hold one (m, 3) array (or None) per scan: got {len(grounds)} for {n} scans")
    out = []
    for i, g in enumerate(grounds):
        if g is None:
            out.append(None)
            continue
        if not isinstance(g, (np.ndarray, torch.Tensor)):
            raise TypeError(f"ground_points[{first_index + i}] must be a numpy array or torch tensor of shape (m, 3), "
                            f"got {type(g).__name__}")
        t = torch.from_numpy(g) if isinstance(g, np.ndarray) else g.detach()
        if not (t.dtype.is_floating_point and not t.is_complex()):
            raise TypeError(f"ground_points[{first_index + i}] must hold floating-point coordinates, got {t.dtype}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"ground_points[{first_index + i}] must have shape (m, 3), got {tuple(t.shape)}")
        out.append(t)
    return out


def warn_if_no_sensors(cfg, sensors) -> None:
    """The warning that ``range_mask``/``visibility`` are skipped: no ``sensor_origins``."""
    if (cfg.range_mask or cfg.visibility) and sensors is None:
        warn_user("range_mask and visibility (on in the 'accurate' preset) need sensor_origins= (each scan's "
                  "sensor position) or poses= (each scan's (4, 4) world-from-sensor pose); without them every "
                  "support scan counts everywhere in the evidence test, as without these options")


def _finite_rows(scans: list[torch.Tensor], dev: torch.device, indices: list[int], is_target: list[bool],
                 on_ready=None):
    """Per scan: (a float32 contiguous copy on ``dev`` without the NaN/inf rows (warned
    about), the mask of kept rows, (min xyz, max xyz) or None).

    Host scans bound for a GPU go through page-locked staging (``schedule.staged_uploads``): one
    pass on the host copies them and finds their bounds and whether all is finite, and the
    upload runs asynchronously, so the estimator can size and start the distance transforms
    without waiting for the GPU. Other scans (and staged scans with bad rows) are checked
    on their device; the numbers of bad rows of all of them come back in one host
    synchronisation. ``on_ready(k, points, bounds)``: called for each staged scan as soon as
    its upload is queued."""
    out: list = [None] * len(scans)
    staged = [k for k, t in enumerate(scans) if dev.type == "cuda" and t.device.type == "cpu" and t.shape[0] > 0]
    for j, moved, (lo, hi), finite in staged_uploads([scans[k] for k in staged], dev):
        k = staged[j]
        if finite:
            out[k] = (moved, torch.ones(moved.shape[0], dtype=torch.bool, device=dev), (lo, hi))
            if on_ready is not None:
                on_ready(k, moved, (lo, hi))
        else:
            scans[k] = moved
    checked = [k for k in range(len(scans)) if out[k] is None]  # checked on the device
    if not checked:
        return out
    moved = [scans[k].to(device=dev, dtype=torch.float32, non_blocking=True) for k in checked]
    finite = [torch.isfinite(t).all(dim=1) for t in moved]
    bad = torch.stack([(~f).sum() for f in finite]).tolist()
    for k, t, f, b in zip(checked, moved, finite, bad):
        if b:
            warn_user(f"scan {indices[k]}: dropping {b} point(s) with NaN/inf coordinates"
                      + (" (their flow is NaN)" if is_target[k] else ""))
            t = t[f]
        out[k] = (t.contiguous(), f, None)
    return out


def restore_output(flow_kept: torch.Tensor, prep: PreparedScans):
    """Scatter the flow of the kept target rows back to all input rows (NaN for dropped ones)
    and convert to what the caller passed in: numpy float32, or a tensor of the input's
    dtype on the input's device."""
    return restore_outputs([flow_kept], [prep])[0][0]


def restore_outputs(flows_kept: list[torch.Tensor], preps: list[PreparedScans], evidence: list | None = None,
                    wait: bool = True):
    """:func:`restore_output` of several frames; the numpy outputs of CUDA flows come back in
    one copy through page-locked memory (per-frame copies from pageable memory cost a host
    synchronisation and ~0.3 ms per 100k points each).

    ``evidence``: per frame, the kept rows' (N_kept, 2) float32 (motion-evidence score,
    explained as 0/1), or None. Returns (flows, None) or (flows, [(score, explained)]) with
    the score in the flow's kind (numpy float32 / the input's dtype and device; NaN on dropped
    rows) and explained bool (False on dropped rows); everything in the same one transfer.
    ``wait=False``: the transfer is only queued; returns a function that waits for it (for that
    copy alone, schedule.HostCopy) and returns the same."""
    def full_rows(kept, prep, width):
        if kept.shape[0] == prep.num_target_points:
            return kept.detach()
        full = torch.full((prep.num_target_points, width), float("nan"), dtype=kept.dtype, device=kept.device)
        full[prep.finite_masks[prep.target]] = kept
        return full.detach()

    fulls = [full_rows(f, prep, 3) for f, prep in zip(flows_kept, preps)]
    evs = [full_rows(e, prep, 2) for e, prep in zip(evidence, preps)] if evidence is not None else []
    nf = len(fulls)
    every = fulls + evs
    out: list = [None] * len(every)
    to_host = [k for k in range(len(every)) if preps[k % nf].was_numpy]
    copy = HostCopy([every[k] for k in to_host])
    for k in range(len(every)):
        prep = preps[k % nf]
        if not prep.was_numpy:
            out[k] = every[k].to(device=prep.in_device, dtype=prep.in_dtype)

    def outputs():
        for k, arr in zip(to_host, copy.arrays()):
            out[k] = arr
        if evidence is None:
            return out, None
        pairs = []
        for e in out[nf:]:
            score, flag = e[:, 0], e[:, 1]
            if isinstance(e, np.ndarray):
                pairs.append((np.ascontiguousarray(score), flag == 1.0))
            else:
                pairs.append((score.contiguous(), flag == 1.0))
        return out[:nf], pairs

    return outputs() if wait else outputs
