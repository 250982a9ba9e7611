"""``nsfp`` and ``fastnsf`` entries of the method registry (``floxels run --method``).

Both are two-scan methods: frame ``i`` is estimated towards scan ``i + 1``. The last frame of
a sequence has no next scan; its flow is estimated towards the previous scan (time offset -1)
and negated, i.e. it assumes constant velocity over the last two frames.

With ``times`` (seconds, one per scan) a pair need not be one frame period apart (a dropped
frame): the pair's flow is scaled to one period, ``flow * period / (t_other - t_frame)``
(period: the median step of ``times``; this also does the negation above), i.e. constant
velocity across the gap.
"""

from __future__ import annotations

import dataclasses
import time

from floxels_ext import methods
from floxels_ext.baselines.config import FastNSFConfig, NSFPConfig


def _config(cls, name: str, options):
    options = dict(options or {})
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(options) - known)
    if unknown:
        raise ValueError(f"{name}: unknown option(s) {unknown}; known: {', '.join(sorted(known))}")
    if "adam_betas" in options:
        options["adam_betas"] = tuple(options["adam_betas"])
    return cls(**options)


def pair_for_frame(frame: int, num_scans: int) -> tuple[int, float]:
    """(index of the scan the flow of ``frame`` is estimated towards, sign to apply)."""
    if num_scans < 2:
        raise ValueError(f"a sequence needs at least 2 scans, got {num_scans}")
    if not 0 <= frame < num_scans:
        raise IndexError(f"frame {frame} is out of range for {num_scans} scans")
    return (frame + 1, 1.0) if frame + 1 < num_scans else (frame - 1, -1.0)


def run_sequence(fit, cfg, scans, frames, device, callback=None, timings=None, times=None) -> list:
    """Flow of each frame in ``frames`` (default all) with the two-scan method ``fit``;
    ``callback(frame, flow)`` after each. ``timings`` (a list), when given, receives the
    seconds spent per frame. ``times``: scan timestamps (s); flows are scaled to per period."""
    from floxels_ext.estimator.scans import check_times, frame_period_of

    scans = list(scans)
    if times is not None:
        times = check_times(times, len(scans))
        period = frame_period_of(times)
    frames = list(range(len(scans))) if frames is None else [int(f) for f in frames]
    for f in frames:  # validate all before spending time on any
        pair_for_frame(f, len(scans))
    out = []
    for f in frames:
        other, sign = pair_for_frame(f, len(scans))
        t0 = time.perf_counter()
        flow = fit(scans[f], scans[other], cfg, device).flow
        if times is not None:
            scale = period / (times[other] - times[f])
            if scale != 1.0:
                flow = flow * scale
        elif sign < 0:
            flow = -flow
        if timings is not None:
            timings.append(time.perf_counter() - t0)
        out.append(flow)
        if callback is not None:
            callback(f, flow)
    return out


def _nsfp_sequence(scans, frames, device, options, callback, times=None) -> None:
    from floxels_ext.baselines.nsfp import fit_nsfp

    run_sequence(fit_nsfp, _config(NSFPConfig, "nsfp", options), scans, frames, device, callback, times=times)


def _fastnsf_sequence(scans, frames, device, options, callback, times=None) -> None:
    from floxels_ext.baselines.fastnsf import fit_fastnsf

    run_sequence(fit_fastnsf, _config(FastNSFConfig, "fastnsf", options), scans, frames, device, callback,
                 times=times)


def _pair_support(i: int, n: int, options: dict) -> list[int]:
    return [pair_for_frame(i, n)[0]]


methods.register(methods.Method(
    "nsfp", "Neural Scene Flow Prior (8x128 MLP, truncated Chamfer, forward + backward flow)", _nsfp_sequence,
    NSFPConfig, support_frames=_pair_support))
methods.register(methods.Method(
    "fastnsf", "Fast Neural Scene Flow (8x128 MLP, distance-transform loss on our EDT/dt_loss ops)",
    _fastnsf_sequence, FastNSFConfig, support_frames=_pair_support))
