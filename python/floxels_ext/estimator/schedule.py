"""The estimator's device schedule: on which CUDA stream each step of a group runs, what waits
for what, and how host data crosses to the device and back. ``group.py`` and ``windows.py``
say what is computed, in the order it is; this module says where it runs.

On a GPU, for one group of targets:

1. **uploads** (``scans.prepare_scans``): host scans go through reused page-locked buffers
   (:func:`staged_uploads`, :func:`upload`; ``floxels::stage_points`` fills them), their copies
   queued on the current stream, so the host waits for nothing;
2. **distance transforms** (``group.prepare_group``, ``distance.EarlyDts``): a single frame's
   EDTs each on a stream of their own (:class:`EdtStreams`), started as soon as each support
   scan's upload is queued; a pipelined batch's on one "dt" stream; timed by two events;
3. **DBSCAN and the problems' set-up**: on a high-priority side stream while the EDTs run (a
   pipelined batch: on the preparing stream itself);
4. **hand-over** (:meth:`PrepareSchedule.hand_over`, :func:`receive`): the stream that solves
   waits for the others, and the caching allocator learns of every tensor used on a stream
   other than the one it was made on (``record_stream``);
5. **solver**: on the current stream (``solver_run.SolverRun``), a pipelined run's next batch
   prepared meanwhile on the side stream (:class:`Pipeline`);
6. **read-back** (:class:`HostCopy`): every output in one page-locked
   copy and one wait for it; in a stream of groups (``windows.solve_windows``) the next group's
   optimisation is queued behind this copy before the host waits for it, so the device goes on
   while the host builds and hands over the results.

On the CPU, or with ``FLOXELS_SERIAL_STAGES=1``, every step runs in order on the current
stream (with a synchronisation after the EDTs, so stage timings are wall times).
"""

from __future__ import annotations

import contextlib
import math
import sys

import torch

from floxels_ext.ops.setup import stage_points
from floxels_ext.switches import flag

__all__ = ["serial_stages", "sync_device", "side_stream", "EdtStreams", "PrepareSchedule", "receive", "Pipeline",
           "staged_uploads", "upload", "HostCopy", "GpuMarks"]

_SIDE_STREAMS: dict = {}


def serial_stages(device: torch.device) -> bool:
    """Whether the steps of a group run in order on the current stream (CPU, or
    ``FLOXELS_SERIAL_STAGES=1``)."""
    return device.type != "cuda" or flag("FLOXELS_SERIAL_STAGES")


def sync_device(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def side_stream(device: torch.device, kind: str = "side"):
    """Persistent side streams per device (a new stream per frame would strand cached
    allocator blocks on streams never used again). "side" (DBSCAN, sorting: short kernels
    whose results the host waits for) has high priority, so that its kernels are scheduled
    ahead of the optimiser's queued blocks; the others ("dt": the EDTs of pipelined batches,
    "dt0".."dt3": those of single frames; long and memory bound) have normal priority."""
    key = (device.index if device.index is not None else torch.cuda.current_device(), kind)
    if key not in _SIDE_STREAMS:
        # (a priority beyond the device's range maps to its highest)
        _SIDE_STREAMS[key] = torch.cuda.Stream(device=torch.device("cuda", key[0]),
                                               priority=-8 if kind == "side" else 0)
    return _SIDE_STREAMS[key]


def _timing_event() -> torch.cuda.Event:
    return torch.cuda.Event(enable_timing=True)


class EdtStreams:
    """The EDTs of a single frame on a GPU, each on a stream of its own (they overlap each
    other's tails); ``start``: an event on the main stream before the first one."""

    def __init__(self) -> None:
        self.start: torch.cuda.Event | None = None
        self.streams: list = []  # the streams used, for the main stream to wait for

    @staticmethod
    def early(device: torch.device) -> bool:
        """Whether EDTs start as the scans are uploaded (``FLOXELS_EARLY_DT=0``: not; they are
        then left to ``prepare_group``, for measurements)."""
        return device.type == "cuda" and not serial_stages(device) and flag("FLOXELS_EARLY_DT")

    @contextlib.contextmanager
    def launching(self, device: torch.device):
        """Work queued inside runs on a new EDT stream, after the current stream's work (the upload)."""
        main = torch.cuda.current_stream(device)
        if self.start is None:
            self.start = _timing_event()
            self.start.record(main)
        st = side_stream(device, f"dt{len(self.streams) % 4}")
        st.wait_stream(main)  # the upload
        with torch.cuda.stream(st):
            yield
        self.streams.append(st)


class PrepareSchedule:
    """The streams of one group's preparation (``group.prepare_group``), made when it starts:
    ``pipelined``: the current stream is the caller's side stream (the device still optimises
    the batch before), the EDTs go on the "dt" stream; else DBSCAN and the set-up go on the
    side stream and the EDTs each on their own (``early``: those already started with the
    uploads)."""

    def __init__(self, device: torch.device, pipelined: bool, early: EdtStreams | None = None) -> None:
        self.device, self.pipelined = device, pipelined
        self.serial = serial_stages(device)
        self.main = torch.cuda.current_stream(device) if device.type == "cuda" else None
        self.side = self.edt = None
        if not self.serial:
            self.side = None if pipelined else side_stream(device)
            self.edt = side_stream(device, "dt") if pipelined else self.main
            (self.side or self.edt).wait_stream(self.main)  # the scans are ready
        self.streams = None if self.serial or pipelined else (early if early is not None else EdtStreams())
        self.dt_events: tuple | None = None  # around the EDTs: their GPU time

    def begin_dts(self, count: int) -> None:
        """``count`` EDTs are about to be queued."""
        if self.streams is None and self.edt is not None and count:
            self.dt_events = (_timing_event(), _timing_event())
            self.dt_events[0].record(self.edt)

    def dt(self):
        """The context in which one EDT is queued."""
        if self.streams is not None:
            return self.streams.launching(self.device)
        return torch.cuda.stream(self.edt) if self.edt is not None else contextlib.nullcontext()

    def end_dts(self) -> None:
        """Every EDT is queued: the main stream waits for a single frame's EDT streams; serial:
        the device finishes them (the stage's wall time)."""
        if self.streams is not None and self.streams.start is not None:
            for st in self.streams.streams:
                self.main.wait_stream(st)
            self.dt_events = (self.streams.start, _timing_event())
        if self.dt_events is not None:
            self.dt_events[1].record(self.edt)
        if self.serial:
            sync_device(self.device)

    def targets(self):
        """The context of DBSCAN and the problems' set-up."""
        return torch.cuda.stream(self.side) if self.side is not None else contextlib.nullcontext()

    def hand_over(self, items, problems, orders, labels) -> None:
        """The preparation is queued: a pipelined batch's preparing stream waits for its EDTs
        (and the allocator learns that their DTs are used there); else the main stream waits
        for the side stream."""
        work = self.side if self.side is not None else (torch.cuda.current_stream(self.device)
                                                         if self.pipelined else None)
        if self.pipelined and self.edt is not None:
            work.wait_stream(self.edt)
            for d in {id(t): t for pr in problems if pr is not None
                      for t in [*pr.dts, *(x for s in (pr.sights or []) if s is not None for x in s.tensors())]}.values():
                d.record_stream(work)
        if self.side is not None:
            used_on(self.main, items, problems, orders, labels)
            self.main.wait_stream(self.side)


def receive(prepared, packs, wait_for) -> None:
    """The current stream solves a group prepared on ``wait_for`` (a pipelined batch's side
    stream; None: prepared on this one): it waits for it, and the allocator learns that the
    group's tensors are used here."""
    if wait_for is None:
        return
    main = torch.cuda.current_stream()
    used_on(main, prepared.items, prepared.problems, prepared.orders, prepared.labels)
    for _, packed in packs:
        packed.record_stream(main)
    main.wait_stream(wait_for)


def used_on(stream, items, problems, orders, labels) -> None:
    """Tensors made on another stream and used on ``stream``: keep the caching allocator
    from handing their memory out again while ``stream`` may still use it."""
    for pr, order in zip(problems, orders):
        if pr is not None:
            for t in (pr.points, pr.corners.corner_idx, pr.corners.corner_w, pr.corners.vertices, order, pr.labels,
                      *pr.dts, *(pr.segments or ())):
                if t is not None:
                    t.record_stream(stream)
    for lab in labels:
        if lab is not None:
            lab.record_stream(stream)
    for prep, _ in items:
        prep.finite_masks[prep.target].record_stream(stream)


class Pipeline:
    """A sequence's batches (``windows.solve_windows``): with ``device`` (a CUDA device), the
    next batch is prepared (and packed) on the side stream while the current stream optimises
    this one; None: one after the other on the current stream."""

    def __init__(self, device: torch.device | None) -> None:
        self.side = side_stream(device) if device is not None else None

    @property
    def on(self) -> bool:
        return self.side is not None

    def preparing(self):
        """The context in which a batch is prepared."""
        return torch.cuda.stream(self.side) if self.side is not None else contextlib.nullcontext()


class GpuMarks:
    """Timing events recorded on the current stream at named points of a group's solve
    (``mark``), read once the stream has passed them (``spans``: seconds from each mark to
    the next, keyed ``<name>_gpu``); nothing on the CPU. No synchronisation of their own."""

    def __init__(self, device: torch.device) -> None:
        self.on = device.type == "cuda"
        self.events: list = []

    def mark(self, name: str) -> None:
        if self.on:
            ev = _timing_event()
            ev.record()
            self.events.append((name, ev))

    def spans(self) -> dict[str, float]:
        return {f"{a}_gpu": 1e-3 * ea.elapsed_time(eb) for (a, ea), (_, eb) in zip(self.events, self.events[1:])}


# ----------------------------------------------------------------------------- staging
class _Stager:
    """Page-locked host buffers for uploads, reused once their copy has run (an event per
    buffer): allocating page-locked memory per frame would cost more than the copy."""

    def __init__(self) -> None:
        self.free: dict = {}  # device index -> [(buffer, event after its last upload)]

    def take(self, dev: torch.device, numel: int) -> torch.Tensor:
        """A free buffer of at least ``numel`` floats: the smallest that fits (a large one taken
        by a small scan would leave the next large upload none), else a new one of the next
        power of two (the next scan, a little larger, fits it too). Without both, uploads larger
        than the smallest buffer (ground returns: 110k points a 128-beam scan) allocated and
        first-touched fresh page-locked memory per scan: ~3-4 ms a frame of the run's
        optimiser thread (bench/RESULTS.md)."""
        pool = self.free.setdefault(_index(dev), [])
        best = None
        for k, (buf, ev) in enumerate(pool):
            if buf.numel() >= numel and (best is None or buf.numel() < pool[best][0].numel()) and ev.query():
                best = k
        if best is not None:
            return pool.pop(best)[0][:numel]
        size = max(1 << 18, 1 << max(numel - 1, 0).bit_length())
        return torch.empty(size, dtype=torch.float32, pin_memory=True)[:numel]

    def used(self, view: torch.Tensor, dev: torch.device) -> None:
        """``view`` (from take) has its upload to ``dev`` queued on dev's current stream."""
        ev = torch.cuda.Event()
        ev.record(torch.cuda.current_stream(dev))
        base = view._base if view._base is not None else view
        pool = self.free.setdefault(_index(dev), [])
        pool.append((base, ev))
        if len(pool) > 64:  # a burst of scans in flight: forget the oldest buffer
            pool.pop(0)


def _index(dev: torch.device) -> int:
    return dev.index if dev.index is not None else torch.cuda.current_device()


_STAGER = _Stager()


def staged_uploads(scans: list[torch.Tensor], dev: torch.device):
    """Host scans (non-empty) to ``dev`` through the page-locked buffers: one pass on the host
    (``floxels::stage_points``, a thread per scan) copies them and finds their bounds and
    whether all is finite; then yields ``(k, points on dev, (min xyz, max xyz), finite)`` as
    each upload is queued (asynchronous), so the caller can queue work on a scan while later
    ones are still being copied."""
    bufs = [_STAGER.take(dev, s.shape[0] * 3) for s in scans]
    for k, (buf, (lo, hi, finite)) in enumerate(zip(bufs, stage_points(scans, bufs))):
        moved = buf.view(-1, 3).to(dev, non_blocking=True)
        _STAGER.used(buf, dev)
        yield k, moved, (lo, hi), finite


def upload(t: torch.Tensor, dev: torch.device) -> torch.Tensor:
    """``t`` (m, 3) as float32 on ``dev``; a host tensor bound for a GPU through the page-locked
    staging buffers, its copy queued on the current stream (the host waits for nothing)."""
    if dev.type != "cuda" or t.device.type != "cpu" or t.shape[0] == 0:
        return t.to(device=dev, dtype=torch.float32)
    buf = _STAGER.take(dev, t.shape[0] * 3)
    buf.view(-1, 3).copy_(t)
    out = buf.view(-1, 3).to(dev, non_blocking=True)
    _STAGER.used(buf, dev)
    return out


class _ReadBack:
    """Page-locked host buffers for read-backs, reused once every array handed out from one is
    gone. The arrays are views of one numpy array per buffer (``arr``), so ``arr``'s reference
    count says whether any is still held (a writer thread, a caller's list); a fresh
    page-locked allocation per group cost ~1 ms a frame of idle GPU in ``floxels run``
    (tools/run_gaps.py: ``torch.empty`` under the read-back, bench/RESULTS.md). At most
    ``KEEP`` buffers are kept; beyond them (a caller keeping every result) new ones are not
    pooled and go with their arrays."""

    KEEP = 4

    def __init__(self) -> None:
        self.pool: list = []  # [(page-locked tensor, its numpy view)]

    def take(self, numel: int):
        """(tensor, numpy view) of at least ``numel`` floats that nothing else holds."""
        best = None
        for k, (t, arr) in enumerate(self.pool):
            # 3 = this list's tuple, the loop's name, getrefcount's argument
            if t.numel() >= numel and sys.getrefcount(arr) <= 3 and (best is None or t.numel() < self.pool[best][0].numel()):
                best = k
        if best is not None:
            return self.pool[best]
        keep = len(self.pool) < self.KEEP
        # a pooled buffer rounded up (later groups, a little larger, fit it); one that is not
        # pooled (its arrays are kept) of the size asked, as a plain page-locked allocation
        size = max(1 << 20, 1 << max(numel - 1, 0).bit_length()) if keep else numel
        t = torch.empty(size, dtype=torch.float32, pin_memory=True)
        entry = (t, t.numpy())
        if keep:
            self.pool.append(entry)
        return entry


_READBACK = _ReadBack()


class HostCopy:
    """float32 numpy copies of (N_i, k) tensors in two steps: the constructor queues CUDA ones
    as one page-locked copy on the current stream (the arrays are views of one reused buffer,
    :class:`_ReadBack`; per-tensor copies from pageable memory cost a synchronisation and ~0.3 ms
    per 100k points each) and records an event behind it; :meth:`arrays` waits for that event
    only, not for the stream, so work queued on the stream after the copy (the next group's
    optimisation) does not hold the arrays back."""

    def __init__(self, tensors: list[torch.Tensor]) -> None:
        import numpy as np

        self.shapes = [t.shape for t in tensors]
        self.event = self.arr = None
        if not tensors or not any(t.is_cuda for t in tensors):
            self.out = [t.cpu().numpy().astype(np.float32, copy=False) for t in tensors]
            return
        flat = torch.cat([t.reshape(-1).to(torch.float32) for t in tensors])
        host, self.arr = _READBACK.take(flat.numel())  # held here: the pool does not hand it out again
        host[:flat.numel()].copy_(flat, non_blocking=True)
        self.event = torch.cuda.Event()
        self.event.record(torch.cuda.current_stream(flat.device))
        self.out = None

    def arrays(self) -> list:
        if self.out is None:
            self.event.synchronize()
            out, at = [], 0
            for shape in self.shapes:
                n = math.prod(shape)
                out.append(self.arr[at:at + n].reshape(shape))
                at += n
            self.out, self.arr = out, None
        return self.out
