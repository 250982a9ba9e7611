"""Sliding windows: each target's window of scans, and the batch loop that optimises them
(:func:`solve_windows`), over one sequence (``api.estimate_sequence``) or a stream of
segments (:func:`estimate_stream`: many sequences through one optimiser pipeline).

:func:`estimate_sequence` (``api.py``) optimises the windows of one sequence, preparing the
next batch while the device optimises the current one; each call starts that pipeline (a first
batch prepared with the device idle, smaller first batches) and drains it (the last batch
optimised with nothing prepared beside it). A dataset of many short sequences paid that once
per sequence. :func:`estimate_stream` takes the targets of many *segments* (independent
sequences, or chunks of one, laid end to end in one index space) from an iterator, possibly
endless while it runs, and batches them across segment ends: the pipeline starts once and
drains once. A window never leaves its segment (:func:`segment_window`), so a target's flow is
the one ``estimate_sequence`` gives over its segment alone; only the batching differs, which
does not change results.

Both share :func:`solve_windows`, the batch loop.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass

import torch

from floxels_ext.estimator.config import FloxelsConfig
from floxels_ext.estimator.distance import WindowCache
from floxels_ext.estimator.recentre import Recentring
from floxels_ext.estimator.group import pack, prepare_group, solve_group
from floxels_ext.estimator.scans import check_times, frame_period_of, prepare_scans, resolve_device, warn_if_no_sensors
from floxels_ext.estimator.schedule import Pipeline, serial_stages
from floxels_ext.ops.solver import MAX_PROBLEMS
from floxels_ext.switches import flag

__all__ = ["Segment", "Window", "segment_window", "solve_windows", "estimate_stream", "RAMP_START"]

RAMP_START = 4  # first batch of a pipelined run: the device starts after a short preparation


@dataclass(frozen=True)
class Segment:
    """Scans ``[lo, hi)`` of the stream: one sequence (or chunk) whose windows stay inside it.
    ``times``: its scans' times in seconds (``hi - lo`` of them, strictly increasing) or None."""

    lo: int
    hi: int
    times: tuple | None = None

    def __post_init__(self) -> None:
        if self.hi - self.lo < 2:
            raise ValueError(f"a segment needs at least 2 scans, got [{self.lo}, {self.hi})")
        if self.times is not None:
            object.__setattr__(self, "times", tuple(check_times(self.times, self.hi - self.lo)))


@dataclass(frozen=True)
class Window:
    """One target's window: scans ``[start, stop)`` of the stream, their times and period."""

    frame: int
    start: int
    stop: int
    times: list | None = None
    period: float | None = None
    segment: int = 0  # windows of one segment share one re-centring shift (its first scan index)


def window_for(frame: int, num_frames: int, num_scans: int, max_offset: int = 0) -> tuple[int, int]:
    """[start, stop) of the window of ``num_scans`` scans used for ``frame``: centred on it,
    shifted inwards at the ends of the sequence (so the target may be the first/last scan);
    ``max_offset`` > 0: cut to the scans at most that many frames from ``frame``."""
    w = min(num_scans, num_frames)
    start = min(max(frame - w // 2, 0), num_frames - w)
    if max_offset > 0:
        return max(start, frame - max_offset), min(start + w, frame + max_offset + 1)
    return start, start + w


def segment_window(frame: int, seg: Segment, num_scans: int, period: float | None = None,
                   max_offset: int = 0) -> Window:
    """The window of stream index ``frame`` within its segment (as over the segment alone)."""
    if not seg.lo <= frame < seg.hi:
        raise IndexError(f"target {frame} is outside its segment [{seg.lo}, {seg.hi})")
    s, e = window_for(frame - seg.lo, seg.hi - seg.lo, num_scans, max_offset)
    times = None if seg.times is None else list(seg.times[s:e])
    if times is not None and period is None:
        period = frame_period_of(list(seg.times))
    return Window(frame, seg.lo + s, seg.lo + e, times, period, seg.lo)


def solve_windows(scans: Sequence, cfg: FloxelsConfig, device, batches: Iterable[list[Window]],
                  deliver: Callable[[int, object], None], *, pipelined: torch.device | None = None,
                  horizon: Callable[[list[Window] | None], float] | None = None,
                  sensors: Sequence | None = None, grounds: Sequence | None = None) -> None:
    """Optimise the windows of ``batches`` (lists of :class:`Window`), one batch at a time;
    ``deliver(frame, result)`` per target in order. Each scan's distance transform is built
    once and shared by the windows that use it. ``pipelined`` (a CUDA device): the next batch
    is prepared on a side stream of it while the device optimises this one (``schedule.Pipeline``). ``horizon(next_batch)``:
    the lowest scan index a later window uses (default: the next batch's lowest start, right
    when window starts never decrease); DTs and device scans below it are freed. ``sensors``:
    each scan's sensor position (indexed like ``scans``; ``FloxelsConfig.range_mask``);
    ``grounds``: each scan's removed ground returns (indexed like ``scans``; ``visibility``)."""
    cache: dict = {}
    converted: dict = {}  # stream index -> scan on the device (converted and NaN-checked once)
    # one float64 shift per segment (scans far from the origin), chosen at its first window and
    # kept, so the windows of a segment share scans and distance transforms in one frame
    recentrings: dict[int, Recentring] = {}
    pipe = Pipeline(pipelined)
    if horizon is None:
        def horizon(nxt):
            return min(w.start for w in nxt) if nxt else math.inf

    def prepare(batch, poll=None):
        def items():
            return [(prepare_scans(scans[w.start:w.stop], w.frame - w.start, device, converted, w.start,
                                   times=w.times, period=w.period,
                                   recentring=recentrings.setdefault(w.segment, Recentring()),
                                   sensors=None if sensors is None else [sensors[j] for j in range(w.start, w.stop)],
                                   grounds=None if grounds is None else [grounds[j] for j in range(w.start, w.stop)]),
                     WindowCache(cache, w.start)) for w in batch]
        if not pipe.on:
            return prepare_group(cfg, items())
        with pipe.preparing():
            prepared = prepare_group(cfg, items(), pipelined=True, poll=poll)
            prepared.packs = pack(cfg, prepared)  # packing, too, before the current batch ends
            return prepared

    it = iter(batches)
    batch = next(it, None)
    if not batch:
        return
    solving = solve_group(cfg, prepare(batch), wait_for=pipe.side)
    while batch:
        error, nxt, prepared = None, None, None
        try:
            nxt = next(it, None)  # a stream's source may wait for its next segment here: the device is busy
            if nxt:
                prepared = prepare(nxt, poll=solving.poll)
        except BaseException as e:  # deliver this batch's flows first, then raise
            error = e
        # this batch's results queued, then the next batch's optimisation behind them: the
        # device goes on with it while the host waits for this batch's read-back and builds and
        # delivers its results (which, with the motion evidence, left the GPU idle ~1 ms a frame)
        finishing = solving.queue_results()
        solving = solve_group(cfg, prepared, wait_for=pipe.side) if prepared is not None else None
        results = finishing.results()
        del finishing
        low = horizon(nxt if error is None else None)
        for d in (cache, converted):  # free the DTs and device scans that no later window will use
            for i in [i for i in d if i < low]:
                del d[i]
        for w, res in zip(batch, results):
            deliver(w.frame, res)
        if error is not None:
            raise error
        batch = nxt


def _stream_batches(windows: Iterator[Window], size: int, ramp: bool) -> Iterator[list[Window]]:
    cur = min(size, RAMP_START) if ramp else size
    while True:
        batch = []
        for w in windows:
            batch.append(w)
            if len(batch) == cur:
                break
        if not batch:
            return
        yield batch
        cur = min(size, 2 * cur)


def estimate_stream(scans: Sequence, targets: Iterable[tuple[int, Segment]], config: FloxelsConfig | None = None,
                    device=None, callback: Callable[[int, object], None] | None = None,
                    batch_size: int | None = None, sensors: Sequence | None = None,
                    grounds: Sequence | None = None) -> None:
    """Flow of every target of ``targets`` (an iterable of ``(stream index, Segment)``, indices
    increasing; it may be a generator that waits for the next segment): ``callback(index,
    result)`` as each is done, nothing kept (a stream may be a whole dataset). ``scans[a:b]``
    gives stream scans ``a..b-1`` (read lazily; a scan is asked for when a window first needs
    it, and never again once no later window does). Results equal ``estimate_sequence`` over
    each segment alone (per frame period; ``times`` per segment). ``sensors``: each stream
    scan's sensor position (indexed like ``scans``), for ``range_mask`` and ``visibility``;
    ``grounds``: each stream scan's removed ground returns (indexed like ``scans``), for
    ``visibility``'s range images."""
    if config is not None and not isinstance(config, FloxelsConfig):
        raise TypeError(f"config must be a FloxelsConfig, got {type(config).__name__}")
    cfg = config or FloxelsConfig()
    dev = resolve_device(device, None)
    if batch_size is None:
        batch_size = MAX_PROBLEMS if dev.type == "cuda" else 1
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
    pipelined = dev.type == "cuda" and not serial_stages(dev) and flag("FLOXELS_PIPELINE")
    periods: dict = {}

    def windows() -> Iterator[Window]:
        last = -1
        for frame, seg in targets:
            frame = int(frame)
            if frame <= last:
                raise ValueError(f"stream targets must increase: {frame} after {last}")
            last = frame
            if seg.times is not None and seg not in periods:
                periods.clear()  # one segment at a time: its period computed once
                periods[seg] = frame_period_of(list(seg.times))
            yield segment_window(frame, seg, cfg.num_scans, periods.get(seg), cfg.max_offset)

    batches = _stream_batches(windows(), batch_size, ramp=pipelined and flag("FLOXELS_RAMP"))
    warn_if_no_sensors(cfg, sensors)
    solve_windows(scans, cfg, device, batches, callback or (lambda f, r: None), pipelined=dev if pipelined else None,
                  sensors=sensors, grounds=grounds)
